"""AprilTag perception: frame sources and tag -> object observations (``dran_edge.perception``).

Hardware libraries (pyrealsense2, depthai) are imported lazily by the source that needs them.
"""
