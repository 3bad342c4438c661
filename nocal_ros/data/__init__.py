"""Datasets: rosbag reading and writing, synthetic scenes, cameras and trajectories."""
