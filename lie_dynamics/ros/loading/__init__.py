"""Robot descriptions: where they come from, which may replace the running model, and their
build off the control path, in plain Python (no rclpy import)."""
