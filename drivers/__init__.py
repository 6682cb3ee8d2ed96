"""Device drivers (the interaction layer): one folder per device family, each driver a U2SA Sensor or
Actuator service; shared parts (serial line sensors, value ranges, NMEA fields) beside them."""

# One module, one name: this folder installs as u2sa_hw.drivers (setup.py). Imported as a top-level
# 'drivers' (a script run from the source tree) it would load a second copy of every module.
if __name__ != "u2sa_hw.drivers":
    raise ImportError(f"import this package as u2sa_hw.drivers, not {__name__}: the drivers/ folder is "
                      "installed inside u2sa_hw (make venv, or pip install -e . in the source tree)")
