"""Readers and writers of file formats: bags, ROS messages, trajectories."""
