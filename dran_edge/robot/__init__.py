"""One robot's online core: the bounded keyframe graph fed by VIO and perception events, the
odometry segments, and the RobotCore that runs the DRAN agent on top of them.
"""
