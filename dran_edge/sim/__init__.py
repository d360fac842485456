"""Simulation: missions of Dingo-like robots, VIO event streams, synthetic pose graphs, and
the writer of simulated runs.
"""
