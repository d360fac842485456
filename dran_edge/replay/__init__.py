"""Replay of recorded or simulated runs through the robot code, faster than real time."""
