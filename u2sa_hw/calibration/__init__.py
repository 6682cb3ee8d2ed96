"""Sensor calibration: magnetometer hard/soft iron (ellipsoid fit, ``magnetometer``) and accelerometer
offsets and scales (six still poses, ``accelerometer``), with the checks that say whether a result can be
trusted; ``correction``: how a driver holds and applies a saved result, and the tilt-compensated heading.
``u2sa calibrate`` (u2sa_hw/cli/calibrate_cmd.py) runs them against a live service (docs/calibration.md)."""
