"""dran-edge: decentralized object-based multi-robot pose-graph SLAM (DRAN) on the edge.

The core (geometry, factors, graph, solver, agent) imports only numpy, scipy and the
standard library; the shells (cli, daemon, replay, simulate, eval) and the
``dran_edge.perception`` / ``dran_edge.comms`` packages may import more, lazily.
"""

__version__ = "0.1.0"
