"""Calibration on the robot's own data: recorded joint signals made ready for identification
(signals), recordings read from rosbag2 folders and trajectory CSVs (recordings), the calibration
regressor and its base parameters (regressor), the physically consistent fit (fit), the
excitation design (excitation), the result and its file (result), and `identify_dynamics`
(identify), which joins them."""
from .fit import UnidentifiableWarning
from .identify import identify_dynamics, write_report
from .result import CalibrationResult, load_calibration, rewrite_urdf, with_calibration

__all__ = ['CalibrationResult', 'UnidentifiableWarning', 'identify_dynamics', 'load_calibration', 'rewrite_urdf',
           'with_calibration', 'write_report']
