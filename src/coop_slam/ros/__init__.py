"""Thin ROS 1 layer: message conversion and node classes. Everything else in coop_slam is
ROS-free."""
