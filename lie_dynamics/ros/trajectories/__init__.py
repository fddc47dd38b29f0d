"""Trajectories from a planner, read and written serialized, with their efforts filled, in plain
Python (no rclpy import)."""
