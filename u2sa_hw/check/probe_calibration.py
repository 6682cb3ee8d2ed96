"""The probe's calibration warnings: a sensor whose calibration fields still hold the defaults.

A magnetometer or accelerometer whose ``*_offset`` is zero and ``*_matrix`` identity (what
``u2sa calibrate`` replaces) works, but its heading or tilt carries the sensor's and the
vehicle's errors; the probe says so on a ``probe warn`` line (not a failure).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from u2sa_hw.calibration.correction import IDENTITY9, ZERO3

SENSORS = (("mag", "magnetometer", "compass"), ("accel", "accelerometer", "imu"))


def uncalibrated(cfg: dict[str, Any], *, magnetometer: bool) -> list[str]:
    """Warning texts for the sensors of *cfg* that hold the default calibration (``magnetometer``: it has one)."""
    out = []
    for prefix, what, command in SENSORS:
        offset, matrix = cfg.get(f"{prefix}_offset"), cfg.get(f"{prefix}_matrix")
        if offset is None or matrix is None or (prefix == "mag" and not magnetometer):
            continue
        if [float(v) for v in offset] == ZERO3 and [float(v) for v in matrix] == IDENTITY9:
            out.append(f"uncalibrated {what} ({prefix}_offset/{prefix}_matrix are zero/identity): "
                       f"run u2sa calibrate {command} SERVICE with the service running")
    return out


def has_magnetometer(kind: str, cfg: dict[str, Any], text: str) -> bool:
    """Whether the service's device has a magnetometer it calibrates: an MPU-9250 whose AK8963 answered
    or is configured, or a serial compass reporting raw field values."""
    if kind == "imu_mpu9250":
        return "AK8963 WIA 0x48" in text or str(cfg.get("chip", "")) == "mpu9250" or "MPU-9250" in text
    if kind == "compass_serial":
        return str(cfg.get("format", "")).lower() == "os5000" and bool(cfg.get("raw_field", False))
    return False


def with_calibration_warnings(profile: Any, target: Any, result: Any) -> Any:
    """*result* with a warning per uncalibrated sensor of *target*'s service (unchanged when it failed)."""
    from u2sa_hw.profile.devices import effective_config

    spec = profile.services.get(target.service)
    if not result.ok or spec is None:
        return result
    try:
        cfg = effective_config(profile, target.service)
    except Exception:  # noqa: BLE001 - the offline check reports a broken config; no warning here
        return result
    warnings = uncalibrated(cfg, magnetometer=has_magnetometer(spec.kind, cfg, result.text))
    return dataclasses.replace(result, warnings=(*result.warnings, *warnings)) if warnings else result
