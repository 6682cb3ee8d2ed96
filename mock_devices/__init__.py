"""Mock devices: test doubles that speak the real device protocols byte for byte.

They stand in for hardware in CI, simulation and replay, and meet the drivers only at a
device address (a pty symlink, a CAN channel, a Unix socket, a sysfs-shaped directory),
exactly as real hardware does: this package never imports ``drivers``. Every mock sensor
samples one :class:`~u2sa_hw.mocks.vehicle_sim.SimVehicle` so the sensors agree, and every
mock actuator drives it. Each device is built with keyword options, has ``start()``,
``stop()``, an ``address``, a ``history`` and fault-scripting methods.

Serial mocks: ``pty_serial`` (the pty link), ``nmea_gps``, ``serial_compass``; see
docs/mock-devices-serial.md.
"""

# One module, one name: this folder installs as u2sa_hw.mocks (setup.py). Imported as a top-level
# 'mock_devices' (a script run from the source tree) it would load a second copy of every module.
if __name__ != "u2sa_hw.mocks":
    raise ImportError(f"import this package as u2sa_hw.mocks, not {__name__}: the mock_devices/ folder is "
                      "installed inside u2sa_hw (make venv, or pip install -e . in the source tree)")
