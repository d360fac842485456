"""DRAN proper (paper Sec. 3-5): one robot's Algorithm 1 (agent), consensus on public variables
(eqs. 5-6, 12), the two-stage distributed initialisation (Sec. 4.2.1) and graph partitions.
"""
