"""The embedded ROS 2 runtime: rclpy's API on Cyclone DDS (see docs/runtime.md)."""
