"""Calibration on the robot's own data: recorded joint signals made ready for identification
(signals), recordings read from rosbag2 folders and trajectory CSVs (recordings)."""
