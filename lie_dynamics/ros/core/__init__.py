"""The decision core of the dynamics node, in plain Python (no rclpy import)."""
