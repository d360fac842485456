"""Neighbour communication (``dran_edge.comms``): wire codec, transports, local ingest socket."""
