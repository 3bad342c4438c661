"""Thin rclpy adapters over the ROS-free core. Importing this package needs rclpy."""
