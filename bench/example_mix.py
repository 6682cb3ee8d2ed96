"""The example ground vehicle's bus traffic, for the benchmarks that replay a load of it
(bench/recorder.py, bench/foxglove.py, bench/replay.py's recorder part).

Rates from examples/ground_vehicle's configs with every driver's record_raw on: gps 5 Hz,
compass 10 Hz, IMU 50 Hz, ODrive encoder estimates 100 Hz per axis, estimator 50 Hz, control
and planner 20 Hz, RC 10 Hz, health 1 Hz per service; raw taps: NMEA lines, I2C burst reads,
CAN frames both ways, PWM writes at the servo's 50 Hz, RC pulse edges (3 channels, 50 Hz).
"""

from __future__ import annotations

# channel -> (messages per second, payload bytes)
EXAMPLE_RATES: dict[str, tuple[float, int]] = {
    "STATE_INFO": (5 + 10 + 50 + 100, 440), "STATE_ESTIMATE": (50, 440), "ACTUATOR_CMD": (40, 80),
    "NAV_POINT": (20, 120), "RC_MODE": (10, 60), "GOALS": (1, 200), "MISSION_STATUS": (1, 120),
    "WORLD": (2, 300), "WORLD_SUMMARY": (2, 100), "U2SA_HEALTH": (12, 600), "U2SA_SYSTEM_HEALTH": (1, 800),
    "RAW.gps": (30, 110), "RAW.compass": (20, 80), "RAW.imu": (100, 70), "RAW.wheels": (460, 70),
    "RAW.pan": (50, 60), "RAW.rc": (300, 60),
}
