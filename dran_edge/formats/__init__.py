"""File formats read and written: g2o, TUM, OptiTrack Motive CSV, the run directory and
replay outputs (docs/run-format.md).
"""
