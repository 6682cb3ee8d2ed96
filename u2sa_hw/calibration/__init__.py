"""Sensor calibration: magnetometer hard/soft iron (ellipsoid fit) and accelerometer offsets and
scales (six still poses), with the checks that say whether a result can be trusted."""
