"""Service registry: kind name -> ``"module:Class"``, imported only when used.

This is python-can's ``BACKENDS`` pattern: ``u2sa_hw`` never imports drivers at import
time; a service kind is resolved when a service of that kind is started. Packages may
add kinds through the ``u2sa_hw.services`` entry-point group.
"""

from __future__ import annotations

import importlib

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
    module_name, _, class_name = target.partition(":")
    module = importlib.import_module(module_name)  # a real ImportError is not hidden
    return getattr(module, class_name)
