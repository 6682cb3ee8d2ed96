"""Every number the vehicle profile holds outside a service's ``settings``, with its range.

A service's settings are its declared config fields (:mod:`u2sa_hw.config.fields`); the rest of
``vehicle.toml`` -- ``[vehicle]``, ``[safety]`` and its ``manual_mixer`` and ``prearm``
tables, each service's ``supervision`` table, ``[simulation]`` -- is read by its own parser,
and each parser checks its numbers against this one table, so every number of the profile has
a finite range (a rate at most :data:`~u2sa_hw.config.fields.MAX_RATE_HZ`, a timeout at most
:data:`~u2sa_hw.config.fields.MAX_TIMEOUT_S`) and a test walks the table and the parsers' dataclasses
(tests/test_config_bounds.py). A key is its dotted place in the profile; ``*`` stands for any
service's name.

:func:`range_problem` ``(key, value) -> str | None``: ``"'rate_hz' = 1000000000.0 is out of range;
give a value > 0 and <= 1000"`` when *value* is out of *key*'s range (None when in range or not
a number: the parsers report a wrong type in their own words).
"""

from __future__ import annotations

import math
from typing import Any

from u2sa_hw.config.fields import MAX_RATE_HZ, MAX_TIMEOUT_S, ConfigError, ConfigField, coerce, field, to_text

SUPERVISION = "services.*.supervision"
MAX_DISTANCE_M = 1_000_000.0   # a simulated start this far from the origin is still on the map
DEFAULT_RC_MODE_TIMEOUT_MS = 250.0   # [safety] rc_mode_timeout_ms (u2sa_hw/safety/config.py reads it)
MAX_RC_MODE_TIMEOUT_MS = 1000.0

PROFILE_NUMBERS: dict[str, ConfigField] = {f.name: f for f in (
    # [vehicle]
    field("vehicle.system_id", 1, "the vehicle's id on the bus", ge=0, le=255),
    field("vehicle.origin.lat", 0.0, "degrees", ge=-90.0, le=90.0),
    field("vehicle.origin.lon", 0.0, "degrees", ge=-180.0, le=180.0),
    field("vehicle.origin.alt", 0.0, "metres", ge=-1000.0, le=10000.0),
    # [safety] (u2sa_hw/safety/config.py)
    field("safety.rc_mode_timeout_ms", DEFAULT_RC_MODE_TIMEOUT_MS, "actuators go neutral when the newest RC_MODE is "
          "older", gt=0.0, le=MAX_RC_MODE_TIMEOUT_MS),
    field("safety.manual_mixer.center_us", 1500.0, "stick centre pulse", gt=800.0, le=2200.0),
    field("safety.manual_mixer.span_us", 500.0, "full deflection pulse offset", gt=50.0, le=1000.0),
    field("safety.manual_mixer.deadband_us", 25.0, "no command inside +-this (also at most span_us / 2)", ge=0.0,
          le=500.0),
    # [safety.prearm] (u2sa_hw/safety/prearm_table.py)
    field("safety.prearm.health_timeout_s", 3.0, "a service's health older than this fails its check", gt=0.0,
          le=MAX_TIMEOUT_S),
    field("safety.prearm.gps.max_sigma_m", 5.0, "horizontal sigma of a fix", gt=0.0, le=10000.0),
    field("safety.prearm.estimator.max_position_sigma_m", 5.0, "the estimate's position sigma", gt=0.0, le=10000.0),
    field("safety.prearm.estimator.max_heading_sigma_deg", 10.0, "the estimate's heading sigma", gt=0.0, le=180.0),
    field("safety.prearm.estimator.max_estimate_age_s", 0.5, "0: not judged", ge=0.0, le=MAX_TIMEOUT_S),
    field("safety.prearm.geofence.max_position_age_s", 1.0, "an older position fails the geofence check", gt=0.0,
          le=MAX_TIMEOUT_S),
    # [geofence] (u2sa_hw/geofence_parse.py)
    field("geofence.margin_m", 1.0, "the path planner keeps this far inside every fence line", ge=0.0, le=100.0),
    field("geofence.circles.radius_m", 10.0, "m", gt=0.0, le=10000.0),
    # [services.NAME.supervision] (u2sa_hw/services/hsm/rules.py)
    field(f"{SUPERVISION}.heartbeat_timeout_s", 3.0, "no health for this long -> missing", ge=0.0, le=MAX_TIMEOUT_S),
    field(f"{SUPERVISION}.startup_grace_s", 10.0, "time to the first heartbeat", ge=0.0, le=MAX_TIMEOUT_S),
    field(f"{SUPERVISION}.stale_after_s", 0.0, "no data for this long -> stale (0: not checked)", ge=0.0,
          le=MAX_TIMEOUT_S),
    field(f"{SUPERVISION}.require_grace_s", 30.0, "required details must hold within this long", ge=0.0,
          le=MAX_TIMEOUT_S),
    field(f"{SUPERVISION}.degraded_restart_s", 0.0, "restart after degraded this long (0: never)", ge=0.0,
          le=MAX_TIMEOUT_S),
    # [simulation] (mock_devices/launcher.py)
    field("simulation.track_width", 0.5, "m", gt=0.0, le=100.0),
    field("simulation.wheel_base", 0.6, "m", gt=0.0, le=100.0),
    field("simulation.max_speed", 2.0, "m/s", gt=0.0, le=100.0),
    field("simulation.rate_hz", 100.0, "simulation steps per second", gt=0.0, le=MAX_RATE_HZ),
    field("simulation.timeout_s", 120.0, "u2sa sim gives up after this long (--timeout overrides)", gt=0.0,
          le=MAX_TIMEOUT_S),
    field("simulation.can_udp_port", 43113, "UDP port of the first simulated CAN bus", ge=1024, le=65000),
    field("simulation.seed", 1, "base of every mock's noise seed", le=2**32 - 1),
    field("simulation.start.north", 0.0, "m from the origin", ge=-MAX_DISTANCE_M, le=MAX_DISTANCE_M),
    field("simulation.start.east", 0.0, "m from the origin", ge=-MAX_DISTANCE_M, le=MAX_DISTANCE_M),
    field("simulation.start.heading_deg", 0.0, "clockwise from north", ge=-360.0, le=360.0),
)}


def range_problem(key: str, value: Any) -> str | None:
    """``"'NAME' = VALUE is out of range; give a value RANGE"`` when the number *value* is outside *key*'s range.

    *key* is a key of :data:`PROFILE_NUMBERS`; NAME is its last part. None when *value* is in
    range, or not a number (or a bool): the parsers report a wrong type in their own words.
    """
    f = PROFILE_NUMBERS[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (f.type is int and isinstance(value, float)):
        return None
    try:
        coerce(f, float(value) if f.type is float else value)
    except ConfigError:
        finite = "" if math.isfinite(value) else "finite "
        return (f"'{key.rsplit('.', 1)[-1]}' = {to_text(value)} is out of range; give a {finite}value "
                f"{f.range_text()}")
    return None


def checked(key: str, value: Any, where: str, error: type[Exception]) -> None:
    """Raise *error* ``"{where}: 'NAME' = VALUE is out of range; give a value RANGE"`` when it is."""
    problem = range_problem(key, value)
    if problem:
        raise error(f"{where}: {problem}")
