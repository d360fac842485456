"""ROS 2 integration: the rclpy bridge node (docs/ros2.md)."""
