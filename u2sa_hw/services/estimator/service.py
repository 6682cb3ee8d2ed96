"""State Estimator (requirement S1; thesis 3.2.3.1, 4.5.2.2).

Two modes, chosen by the config field ``mode``:

``ekf`` (default)
    An extended Kalman filter (:mod:`.ekf`) fed by every sensor on ``STATE_INFO``
    (:mod:`.fusion` says how each field and frame is read). ``STATE_ESTIMATE`` (NED, with
    sigmas) goes out at once after a message whose update moved a kind listed in
    ``publish_on`` (position and heading: what the planner steers by), and the run loop
    predicts and publishes whenever nothing went out for ``1 / publish_rate_hz``, so the
    rate is the least the consumers get. Nothing is published before the first usable
    measurement.
``passthrough``
    The thesis's FlightGear estimator: each State Information has its present fields
    copied into the running estimate, which is published at once.

Sensors are registered by name on their first message; a sensor silent for longer than
``sensor_timeout_s`` is listed in health (status ``degraded``, ``silent_sensors``, and in words
with how long each has been silent in ``degraded_reason``), as are the outliers the gate
rejected per sensor. Changing a filter field over the bus restarts the filter.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import MAX_RATE_HZ, MAX_TIMEOUT_S, ConfigError, field
from u2sa_hw.messages import STATE_FIELDS
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.services.estimator.fusion import FusionSettings, StateFusion

MODES = ("ekf", "passthrough")
_FILTER_FIELDS = tuple(FusionSettings.__dataclass_fields__)
# publish_on names -> the filter's measurement kinds
PUBLISH_KINDS = {"position": ("position",), "velocity": ("velocity_ned", "velocity_body"), "heading": ("heading",),
                 "yaw_rate": ("yaw_rate",)}


class StateEstimator(U2SAService):
    """Fuses State Information from any number of sensors into STATE_ESTIMATE."""

    SERVICE_TYPE: ClassVar[str] = "state_estimator"
    # the clock of sensor arrival and publication times (a bench or test may set a simulated one)
    clock: Callable[[], float] = staticmethod(time.monotonic)
    _D = FusionSettings()
    CONFIG = (
        field("mode", "ekf", "ekf: extended Kalman filter; passthrough: copy present fields of each message", choices=MODES),
        field("sensor_timeout_s", 2.0, "a sensor silent for this long is reported in health", gt=0, le=MAX_TIMEOUT_S),
        field("publish_rate_hz", 50.0, "ekf: the least STATE_ESTIMATE publications per second (a prediction "
                                        "goes out when nothing did for 1/rate)", gt=0, le=MAX_RATE_HZ),
        field("publish_on", "position,heading", "ekf: measurement kinds whose update is published at once "
                                                 "(position, velocity, heading, yaw_rate; comma separated, may be empty)"),
        field("default_position_sigma", _D.default_position_sigma, "m, for a position without x_sigma/y_sigma", gt=0, le=10000.0),
        field("default_altitude_sigma", _D.default_altitude_sigma, "m, for a z without z_sigma", gt=0, le=10000.0),
        field("default_velocity_sigma", _D.default_velocity_sigma, "m/s, for a velocity without its sigma", gt=0, le=100.0),
        field("default_heading_sigma", _D.default_heading_sigma, "rad, for a psi without psi_sigma", gt=0, le=math.pi),
        field("default_yaw_rate_sigma", _D.default_yaw_rate_sigma, "rad/s, for a psi_dot without its sigma", gt=0, le=10.0),
        field("accel_noise", _D.accel_noise, "process noise, horizontal acceleration m/s^2/sqrt(Hz)", gt=0, le=100.0),
        field("vertical_accel_noise", _D.vertical_accel_noise, "process noise, vertical acceleration", gt=0, le=100.0),
        field("yaw_accel_noise", _D.yaw_accel_noise, "process noise, yaw acceleration rad/s^2/sqrt(Hz)", gt=0, le=100.0),
        field("gate_probability", _D.gate_probability, "chi-square probability of the outlier gate (1 disables)", gt=0, le=1),
        field("reinit_after", _D.reinit_after, "consecutive rejections of one sensor before it is trusted again", ge=1, le=10000),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._lock = threading.Lock()
        self.check_config()
        self.mode = self.config.get("mode")
        self.estimate = t.StateInformation()
        self.estimate.sensor_name = name
        self.estimate.reference_frame = "NED"
        self.sensors: dict[str, float] = {}
        self.fusion = self._new_fusion()
        self.publish_kinds = self._checked_publish_on(self.config.get("publish_on"))
        self._last_publish = -float("inf")   # monotonic time of the latest STATE_ESTIMATE
        self.published_on_update = 0
        self.published_on_rate = 0
        self.register_subscriber(ch.STATE_INFO, t.StateInformation)
        self.register_publisher(ch.STATE_ESTIMATE, t.StateInformation)

    def _checked_mode(self, mode: str) -> str:
        if mode not in MODES:
            where = f"{self.config.path} or " if self.config.path else ""
            raise ConfigError(f"{self.name}: config field 'mode' must be one of {', '.join(MODES)}, got {mode!r} "
                              f"(fix it in {where}the vehicle profile's settings)")
        return mode

    def _checked_publish_on(self, text: str) -> frozenset[str]:
        names = [n.strip().lower() for n in str(text).split(",") if n.strip()]
        unknown = [n for n in names if n not in PUBLISH_KINDS]
        if unknown:
            where = f"{self.config.path} or " if self.config.path else ""
            raise ConfigError(f"{self.name}: config field 'publish_on' names {', '.join(unknown)}; use any of "
                              f"{', '.join(PUBLISH_KINDS)} (fix it in {where}the vehicle profile's settings)")
        return frozenset(kind for n in names for kind in PUBLISH_KINDS[n])

    def check_config(self) -> None:
        """Refuse an unknown mode or publish_on kind, or a rate that is not > 0."""
        self._checked_mode(self.config.get("mode"))
        self._checked_publish_on(self.config.get("publish_on"))
        if not float(self.config.get("publish_rate_hz")) > 0:
            raise ConfigError(f"{self.name}: publish_rate_hz must be > 0, got {self.config.get('publish_rate_hz')!r}")

    def _new_fusion(self) -> StateFusion:
        settings = FusionSettings(**{k: self.config.get(k) for k in _FILTER_FIELDS})
        return StateFusion(origin=self.profile.origin, settings=settings, logger=self.logger)

    # -- input ------------------------------------------------------------------------------
    def callback(self, data: Any) -> None:
        """Register the sensor and fold its State Information into the estimate."""
        if not isinstance(data, t.StateInformation):
            super().callback(data)
            return
        now = self.clock()
        name = data.sensor_name
        with self._lock:
            if name not in self.sensors:
                self.logger.info("new sensor '%s' (frame %s, fields: %s)", name, data.reference_frame or "NED",
                                 ", ".join(data.present_fields()))
            self.sensors[name] = now
            if self.mode == "ekf":
                if self.publish_kinds.isdisjoint(self.fusion.ingest(data, now=now)):
                    return
                msg = self.fusion.estimate(name=self.name)
                if msg is None:
                    return
                self._last_publish = now
                self.published_on_update += 1
                self.publish(ch.STATE_ESTIMATE, msg)
                return
            self.copy_present(data, self.estimate)
            self.estimate.header.timestamp_us = data.header.timestamp_us
            if data.reference_frame:
                self.estimate.reference_frame = data.reference_frame
            self.publish(ch.STATE_ESTIMATE, self.estimate)
            self.estimate.header.timestamp_us = 0

    @staticmethod
    def copy_present(src: t.StateInformation, dst: t.StateInformation) -> None:
        """Copy every field present in *src* into *dst* (marking it present there)."""
        pv = src.presence_vector
        for bit, name in enumerate(STATE_FIELDS):
            if pv >> bit & 1:
                setattr(dst, name, getattr(src, name))
        dst.presence_vector |= pv

    # -- output -----------------------------------------------------------------------------
    def run(self) -> None:
        """In ekf mode: predict and publish when nothing went out for ``1 / publish_rate_hz``."""
        while True:
            due = self.publish_if_due(self.clock())
            if not self.wait(max(0.0, due - self.clock())):
                return

    def publish_if_due(self, now: float) -> float:
        """In ekf mode, predict to *now* and publish if nothing went out for a period; the next due time."""
        period = 1.0 / float(self.config.get("publish_rate_hz"))
        with self._lock:
            if self.mode == "ekf" and now - self._last_publish >= period:
                self.fusion.predict_to(now)
                msg = self.fusion.estimate(name=self.name)
                if msg is not None:
                    self._last_publish = now
                    self.published_on_rate += 1
                    self.publish(ch.STATE_ESTIMATE, msg)
            since = now - self._last_publish
            return now + (period - since if since < period else period)

    def on_config_change(self, name: str, value: Any) -> None:
        """Apply a new mode or filter setting live (a filter setting restarts the filter)."""
        if name == "mode":
            try:
                mode = self._checked_mode(value)
            except ConfigError as exc:
                self.error(f"{exc}; staying in {self.mode} mode")
                return
            with self._lock:
                self.mode = mode
                self.fusion = self._new_fusion()
            self.logger.info("mode is now %s", mode)
        elif name in _FILTER_FIELDS:
            with self._lock:
                self.fusion = self._new_fusion()
            self.logger.info("%s changed to %s: filter restarted", name, value)
        elif name == "publish_on":
            self.publish_kinds = self._checked_publish_on(value)

    def health_details(self) -> dict[str, Any]:
        """Mode, known and silent sensors, and per-sensor outliers (ekf)."""
        now = self.clock()
        timeout = float(self.config.get("sensor_timeout_s"))
        with self._lock:
            silent_for = {n: now - seen for n, seen in sorted(self.sensors.items()) if now - seen > timeout}
            silent = list(silent_for)
            records = list(self.fusion.sensors.values())
            current = self.fusion.estimate(name=self.name) if self.mode == "ekf" else self.estimate
            sigmas = estimate_sigmas(current)
        if silent and self.status == "ok":
            self.status = "degraded"
        elif not silent and self.status == "degraded":
            self.status = "ok"
        details: dict[str, Any] = {"mode": self.mode, "sensors": ",".join(sorted(self.sensors)),
                                   "silent_sensors": ",".join(silent), **sigmas,
                                   # In words, for `u2sa health` and the pre-arm checks: which sensor, how long.
                                   "degraded_reason": silent_reason(silent_for, timeout)}
        if self.mode == "ekf":
            details["published_on_update"] = self.published_on_update
            details["published_on_rate"] = self.published_on_rate
            details["outliers"] = ",".join(f"{r.name}:{r.outliers}" for r in records)
            details["unusable_fields"] = ",".join(f"{r.name}:{r.unusable}" for r in records if r.unusable)
            details["waiting_for_heading"] = ",".join(f"{r.name}:{r.deferred}" for r in records if r.deferred)
        return details


def silent_reason(silent_for: dict[str, float], timeout: float) -> str:
    """``silent sensor gps: no message for 3.1 s (sensor_timeout_s 2)``, one part per sensor; "" when none is silent."""
    if not silent_for:
        return ""
    parts = [f"{name or '(no source)'}: no message for {age:.1f} s" for name, age in silent_for.items()]
    noun = "sensor" if len(parts) == 1 else "sensors"
    return f"silent {noun} {', '.join(parts)} (sensor_timeout_s {timeout:g})"


def estimate_sigmas(msg: t.StateInformation | None) -> dict[str, str]:
    """``position_sigma_m`` (horizontal, the root of the north and east variances) and ``heading_sigma_deg``
    of an estimate, as health details: empty while that part is not estimated, ``unknown`` without a sigma."""
    out = {"position_sigma_m": "", "heading_sigma_deg": ""}
    if msg is None:
        return out
    if msg.has("x") and msg.has("y"):
        sx, sy = msg.get("x_sigma"), msg.get("y_sigma")
        out["position_sigma_m"] = "unknown" if sx is None or sy is None else f"{math.hypot(sx, sy):.2f}"
    if msg.has("psi"):
        sp = msg.get("psi_sigma")
        out["heading_sigma_deg"] = "unknown" if sp is None else f"{math.degrees(sp):.2f}"
    return out
