"""Experiment drivers of the paper: N agents in one process (fleet), the DGS baseline,
the loopback node and the object simulation.
"""
