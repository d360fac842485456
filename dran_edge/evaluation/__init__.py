"""Scoring against OptiTrack: association and alignment, the paper's metrics (Sec. 6.2),
the evaluation of a run and its report.
"""
