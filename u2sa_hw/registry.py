"""Service registry: kind name -> ``"module:Class"``, imported only when used.

This is python-can's ``BACKENDS`` pattern: ``u2sa_hw`` never imports drivers at import
time; a service kind is resolved when a service of that kind is started. Packages may
add kinds through the ``u2sa_hw.services`` entry-point group.

Beside the services, the same pattern names the mock devices (:data:`MOCK_DEVICES`: mock kind
-> its class, built by :mod:`u2sa_hw.mocks.catalog`) and the CAN motor protocols the probe
recognises (:data:`CAN_PROTOCOLS`), so a new device is its own modules plus lines here
(docs/adding-a-device.md).
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any, NamedTuple

RECORDER_KIND = "recorder"   # started first by the launcher and systemd, so its log holds everyone's start-up

SERVICE_KINDS: dict[str, str] = {
    # core services
    "state_estimator": "u2sa_hw.services.estimator.service:StateEstimator",
    "mission_manager": "u2sa_hw.services.mission.service:MissionManagerService",
    "world_modeler": "u2sa_hw.services.world.service:WorldModeler",
    "path_planner": "u2sa_hw.services.planner.service:PathPlannerService",
    "control": "u2sa_hw.services.control.service:ControlSystem",
    "hsm": "u2sa_hw.services.hsm.service:HealthStatusMonitor",
    "recorder": "u2sa_hw.services.recorder.service:Recorder",
    "foxglove_bridge": "u2sa_hw.foxglove.service:FoxgloveBridgeService",
    "gps_nmea": "u2sa_hw.drivers.gps_nmea.driver:GpsNmeaDriver",
    "compass_serial": "u2sa_hw.drivers.compass.driver:SerialCompassDriver",
    "gpio_output": "u2sa_hw.drivers.gpio.driver:GpioOutputDriver",
    "gpio_input": "u2sa_hw.drivers.gpio.driver:GpioInputDriver",
    "rc_mux": "u2sa_hw.drivers.rc_mux.driver:RcMuxDriver",
    "imu_mpu9250": "u2sa_hw.drivers.imu.mpu9250:Mpu9250ImuDriver",
    "imu_bno055": "u2sa_hw.drivers.imu.bno055:Bno055ImuDriver",
    "pwm_servo": "u2sa_hw.drivers.pwm.servo:PwmServoDriver",
    "odrive_can": "u2sa_hw.drivers.can_motor.odrive.driver:OdriveCanMotor",
    "vesc_can": "u2sa_hw.drivers.can_motor.vesc.driver:VescCanMotor",
}


# Built-in kinds that are not actuators: the RC mux reads the profile's actuators at start and
# skips these without importing them (the estimator's numpy, the GPS's pyserial would otherwise
# sit in the mux's memory). tests/test_registry.py checks this table against the classes.
NOT_ACTUATOR_KINDS = frozenset({
    "state_estimator", "mission_manager", "world_modeler", "path_planner", "control", "hsm", "recorder",
    "foxglove_bridge", "gps_nmea", "compass_serial", "gpio_input", "imu_mpu9250", "imu_bno055",
})


ACTUATOR_KINDS = frozenset(SERVICE_KINDS) - NOT_ACTUATOR_KINDS
"""Built-in kinds whose service moves actuators (the actuator drivers and the RC mux): the safety chain runs
them real-time (:mod:`u2sa_hw.realtime`) and their units' watchdog kills (:mod:`u2sa_hw.install.units`), so a
new actuator driver gets both from its one ``SERVICE_KINDS`` line."""

COMMAND_SOURCE_KINDS = ACTUATOR_KINDS | {"control"}
"""Kinds whose process publishes or executes actuator commands: their watchdog sends SIGKILL."""

def known_kinds() -> dict[str, str]:
    """Every registered kind, built-in ones and those from entry points."""
    from importlib.metadata import entry_points   # scanning installed packages costs ~15 ms: only when needed

    kinds = dict(SERVICE_KINDS)
    for ep in entry_points(group="u2sa_hw.services"):
        kinds.setdefault(ep.name, ep.value)
    return kinds


def resolve_kind(kind: str) -> type:
    """Import and return the service class of *kind*; LookupError lists the known kinds."""
    target = SERVICE_KINDS.get(kind)
    if target is None:
        kinds = known_kinds()
        target = kinds.get(kind)
    if target is None:
        raise LookupError(f"unknown service kind '{kind}'; known kinds: {', '.join(sorted(kinds))}")
    return _load(target)


# ---- mock kinds -------------------------------------------------------------------------------
class MockEntry(NamedTuple):
    """One mock kind: the class that stands in for the device (``"module:Class"``, imported only when
    built), the catalog builder that wires it (:data:`u2sa_hw.mocks.catalog.BUILDERS`) and what it is."""

    target: str
    build: str
    what: str


MOCK_DEVICES: dict[str, MockEntry] = {
    "nmea_gps": MockEntry("u2sa_hw.mocks.nmea_gps:NmeaGpsDevice", "serial",
                          "NMEA 0183 GNSS receiver on a pty (serial:// address)"),
    "nmea_compass": MockEntry("u2sa_hw.mocks.serial_compass:NmeaCompassDevice", "serial",
                              "NMEA HDG/HDM/HDT compass on a pty (serial:// address)"),
    "os5000_compass": MockEntry("u2sa_hw.mocks.serial_compass:Os5000CompassDevice", "serial",
                                "OceanServer OS5000 compass on a pty (serial:// address)"),
    "mpu9250": MockEntry("u2sa_hw.mocks.mpu9250_chip:Mpu9250Chip", "i2c_chip",
                         "MPU-9250 + AK8963 on the mock I2C bus (i2c:// address)"),
    "mpu6500": MockEntry("u2sa_hw.mocks.mpu9250_chip:Mpu9250Chip", "i2c_chip",
                         "MPU-6500 on the mock I2C bus (i2c:// address)"),
    "mpu6050": MockEntry("u2sa_hw.mocks.mpu9250_chip:Mpu9250Chip", "i2c_chip",
                         "MPU-6050 on the mock I2C bus (i2c:// address)"),
    "bno055": MockEntry("u2sa_hw.mocks.bno055_chip:Bno055Chip", "i2c_chip",
                        "BNO055 on the mock I2C bus (i2c:// address)"),
    "pca9685": MockEntry("u2sa_hw.mocks.pca9685_chip:Pca9685Chip", "pca9685",
                         "a PCA9685 output of a pwm_servo channel (pca9685:// address)"),
    "sysfs_pwm": MockEntry("u2sa_hw.mocks.sysfs_pwm:SysfsPwmChip", "sysfs_pwm",
                           "a sysfs-shaped PWM chip directory standing in for /sys/class/pwm/pwmchipN, "
                           "for a pwm_servo channel (pwm:// address)"),
    "rc_receiver": MockEntry("u2sa_hw.mocks.rc_receiver:RcReceiverMock", "rc_receiver",
                             "RC receiver pulse trains and the RC mux on a mock GPIO chip "
                             "(gpio:// address; the rc_mux service's channel, enable and select lines)"),
    "gpio_chip": MockEntry("u2sa_hw.mocks.gpio_chip:MockGpioChip", "gpio_chip",
                           "a mock GPIO chip (gpio:// address; a gpio_output service's outputs)"),
    "odrive": MockEntry("u2sa_hw.mocks.odrive_node:OdriveCanNode", "can_motor",
                        "ODrive CANSimple nodes, one per controller (can:// address; the service's "
                        "actuators, node ids, directions, wheel radii, firmware)"),
    "vesc": MockEntry("u2sa_hw.mocks.vesc_node:VescCanNode", "can_motor",
                      "VESC nodes, one per controller (can:// address; the service's actuators, "
                      "controller ids, directions, ERPM scale)"),
}
"""Mock kind (a ``[devices.NAME] mock``, a driver's ``MOCK_KINDS``) -> its class, builder and description.
A new mock is its module in ``mock_devices/`` and one line here (docs/adding-a-device.md)."""


def resolve_mock(kind: str) -> type:
    """Import and return the mock class of mock kind *kind*; LookupError lists the known kinds."""
    entry = MOCK_DEVICES.get(kind)
    if entry is None:
        raise LookupError(f"unknown mock kind '{kind}'; known: {', '.join(sorted(MOCK_DEVICES))}")
    return _load(entry.target)


# ---- CAN protocols ----------------------------------------------------------------------------
CAN_PROTOCOLS: dict[str, str] = {
    "odrive": "u2sa_hw.protocols.odrive_cansimple",
    "vesc": "u2sa_hw.protocols.vesc_can",
}
"""A CAN motor driver's declared ``probe_expectation`` protocol -> the module that speaks it. Each module
gives ``probe_node(frame) -> int | None`` (the node id of a frame only a live node of that family sends,
else None) and ``PROBE_SEEN`` (what those frames are called), which ``u2sa check --probe`` uses
(:mod:`u2sa_hw.ports.can.probe`), and ``probe_frame(node_id)``, one such frame (the contract test,
``tests/test_can_probe_table.py``)."""


def can_protocol(protocol: str) -> ModuleType:
    """The protocol module of CAN protocol *protocol*; LookupError lists the known ones."""
    name = CAN_PROTOCOLS.get(protocol)
    if name is None:
        raise LookupError(f"unknown CAN protocol '{protocol}'; known: {', '.join(sorted(CAN_PROTOCOLS))}")
    return importlib.import_module(name)


def _load(target: str) -> Any:
    """The object a ``"module:Name"`` string names (a real ImportError is not hidden)."""
    module_name, _, name = target.partition(":")
    return getattr(importlib.import_module(module_name), name)
