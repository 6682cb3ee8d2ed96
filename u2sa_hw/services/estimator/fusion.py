"""Sensor fusion for the State Estimator: State Information messages in, one estimate out.

Pure logic (no bus, no clock; the caller passes ``now`` in seconds of a monotonic clock):
sensors are registered by name on their first message; each message is split into
measurement groups by its presence vector and reference frame and folded into the
:class:`~u2sa_hw.services.estimator.ekf.NavigationEkf`.

How fields are read, by ``reference_frame`` (case-insensitive):

=================  =====================================================================
``NED``, ``LOCAL``  x, y, z: north, east, down (m) about the origin; x_dot, y_dot, z_dot:
or empty            NED velocity (m/s)
``GEODETIC``        x = latitude, y = longitude (deg; both needed), z = altitude (m up);
                    converted with :mod:`u2sa_hw.geo` about the profile origin. Position
                    sigmas are metres. x_dot, y_dot, z_dot: NED velocity (m/s)
``FRD``, ``BODY``   x_dot = forward speed, y_dot = right, z_dot = down (m/s), e.g. wheel
                    odometry; x, y, z are meaningless here and counted as unusable
any frame           psi: heading (rad, clockwise from north); psi_dot: yaw rate (rad/s)
=================  =====================================================================

A sigma that is absent, not finite or not positive is replaced by the configured default.
A non-finite value is unusable (counted, never fused). Attitude fields the filter does not
model (phi, theta, their rates, psi_ddot and the fluid fields) are passed through from the
latest message carrying them. A group rejected by the gate ``reinit_after`` times in a row
from the same sensor is accepted anyway (position/heading are reset to it), so one bad
estimate cannot lock out every sensor forever.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, field

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import GeoOrigin, geodetic_to_ned
from u2sa_hw.messages import STATE_FIELDS  # also installs the presence setters
from u2sa_hw.services.estimator.ekf import Measurement, NavigationEkf, UpdateResult

NED_FRAMES = frozenset({"", "NED", "LOCAL"})
GEODETIC_FRAMES = frozenset({"GEODETIC", "GLOBAL"})
BODY_FRAMES = frozenset({"FRD", "BODY"})
_PASSTHROUGH_VALUES = ("phi", "theta", "phi_dot", "theta_dot", "phi_ddot", "theta_ddot", "psi_ddot",
                       "fluid_x_dot", "fluid_y_dot", "fluid_z_dot", "fluid_x_ddot", "fluid_y_ddot", "fluid_z_ddot")
PASSTHROUGH_FIELDS = (*_PASSTHROUGH_VALUES, *(f"{n}_sigma" for n in _PASSTHROUGH_VALUES))
# estimate field <- filter state
_OUTPUT = (("x", "north"), ("y", "east"), ("z", "down"), ("x_dot", "v_north"), ("y_dot", "v_east"),
           ("z_dot", "v_down"), ("psi", "psi"), ("psi_dot", "yaw_rate"))
_BIT = {name: 1 << i for i, name in enumerate(STATE_FIELDS)}
_PASSTHROUGH = tuple((name, _BIT[name]) for name in PASSTHROUGH_FIELDS)
_PASSTHROUGH_MASK = sum(bit for _, bit in _PASSTHROUGH)
_OUTPUT_BITS = tuple((state, out, _BIT[out], f"{out}_sigma", _BIT[f"{out}_sigma"]) for out, state in _OUTPUT)


# (kind, filter components, message fields, (sigma field, its presence bit, default sigma) per field)
_Group = tuple[str, tuple[str, ...], tuple[str, ...], tuple[tuple[str, int, float], ...]]


def _sigma(msg: t.StateInformation, bit: int, name: str, default: float) -> float:
    """The sigma field *name* when present, finite and > 0, else *default*."""
    if msg.presence_vector & bit:
        sigma = getattr(msg, name)
        if math.isfinite(sigma) and sigma > 0:
            return sigma
    return default


@functools.lru_cache(maxsize=256)
def _value_fields(presence_vector: int) -> tuple[str, ...]:
    """The value (not sigma) fields a presence vector marks (a sensor sends a handful of vectors)."""
    return tuple(n for n in STATE_FIELDS if presence_vector & _BIT[n] and not n.endswith("_sigma"))


@dataclass(frozen=True)
class FusionSettings:
    """Default sigmas for absent ones, the filter's process noise and its outlier gate."""

    default_position_sigma: float = 3.0     # m (horizontal)
    default_altitude_sigma: float = 5.0     # m
    default_velocity_sigma: float = 0.5     # m/s
    default_heading_sigma: float = 0.1      # rad
    default_yaw_rate_sigma: float = 0.05    # rad/s
    accel_noise: float = 0.5                # m/s^2/sqrt(Hz), horizontal
    vertical_accel_noise: float = 0.2       # m/s^2/sqrt(Hz)
    yaw_accel_noise: float = 2.0            # rad/s^2/sqrt(Hz): wheels and thrusters turn briskly
    gate_probability: float = 0.999         # chi-square probability of the gate; >= 1 disables it
    reinit_after: int = 10                  # consecutive rejections before a sensor is trusted again


@dataclass
class SensorRecord:
    """What the estimator knows about one sensor."""

    name: str
    first_seen: float
    last_seen: float
    messages: int = 0
    accepted: int = 0
    outliers: int = 0
    unusable: int = 0
    deferred: int = 0
    fields: set[str] = field(default_factory=set)
    frames: set[str] = field(default_factory=set)
    consecutive_rejects: dict[str, int] = field(default_factory=dict)


class StateFusion:
    """Registers sensors, converts their messages to measurements and keeps the filter."""

    def __init__(self, *, origin: GeoOrigin, settings: FusionSettings = FusionSettings(),
                 logger: logging.Logger | None = None) -> None:
        self.origin = origin
        self.settings = settings
        self.logger = logger or logging.getLogger("u2sa.estimator.fusion")
        self.ekf = NavigationEkf(accel_noise=settings.accel_noise, vertical_accel_noise=settings.vertical_accel_noise,
                                 yaw_accel_noise=settings.yaw_accel_noise, gate_probability=settings.gate_probability)
        self.sensors: dict[str, SensorRecord] = {}
        self.passthrough = t.StateInformation()
        self._warned: set[tuple[str, str]] = set()
        self._layouts: dict[tuple[int, str], tuple[list[_Group], list[str]]] = {}

    # -- messages -> measurements ---------------------------------------------------------
    def measurements(self, msg: t.StateInformation) -> tuple[list[Measurement], list[str]]:
        """The measurement groups in *msg*, and the present fields that cannot be used."""
        present = msg.presence_vector
        bad = [n for n in _value_fields(present) if not math.isfinite(getattr(msg, n))]
        usable = present & ~sum(_BIT[n] for n in bad)
        layout = self._layouts.get((usable, msg.reference_frame))
        if layout is None:
            layout = self._layouts[(usable, msg.reference_frame)] = self._layout(usable, msg.reference_frame)
        groups, unusable = layout
        out = []
        for kind, components, fields, sigmas in groups:
            values = tuple(getattr(msg, f) for f in fields)
            if kind == "geodetic":   # x = lat, y = lon (deg), z = altitude up (m)
                kind, values = "position", self._geodetic_to_ned(fields, values)
            out.append(Measurement(kind, components, values,
                                   tuple(_sigma(msg, bit, name, default) for name, bit, default in sigmas)))
        return out, [*bad, *unusable]

    def _geodetic_to_ned(self, fields: tuple[str, ...], values: tuple[float, ...]) -> tuple[float, ...]:
        by_field = dict(zip(fields, values))
        out: list[float] = []
        if "x" in by_field:
            north, east, _ = geodetic_to_ned(by_field["x"], by_field["y"], None, origin=self.origin)
            out += [north, east]
        if "z" in by_field:
            out.append(self.origin.alt - by_field["z"])
        return tuple(out)

    def _layout(self, usable: int, frame_text: str) -> tuple[list[_Group], list[str]]:
        """Which groups a message with the finite fields *usable* in *frame_text* makes, and what is unusable.

        Computed once per presence vector and frame: a sensor sends the same few every time.
        """
        s = self.settings
        frame = frame_text.strip().upper()
        ok = {n for n in STATE_FIELDS if usable & _BIT[n] and not n.endswith("_sigma")}
        defaults = {"x": s.default_position_sigma, "y": s.default_position_sigma, "z": s.default_altitude_sigma,
                    "x_dot": s.default_velocity_sigma, "y_dot": s.default_velocity_sigma,
                    "z_dot": s.default_velocity_sigma, "psi": s.default_heading_sigma,
                    "psi_dot": s.default_yaw_rate_sigma}
        groups: list[_Group] = []
        unusable: list[str] = []

        def group(kind: str, pairs: tuple[tuple[str, str], ...]) -> None:
            parts = [(n, c) for n, c in pairs if n in ok]
            if parts:
                groups.append((kind, tuple(c for _, c in parts), tuple(n for n, _ in parts),
                               tuple((f"{n}_sigma", _BIT[f"{n}_sigma"], defaults[n]) for n, _ in parts)))

        position = (("x", "north"), ("y", "east"), ("z", "down"))
        if frame in NED_FRAMES:
            group("position", position)
        elif frame in GEODETIC_FRAMES:
            if not ("x" in ok and "y" in ok):
                unusable += [n for n in ("x", "y") if n in ok]   # latitude without longitude or vice versa
                ok -= {"x", "y"}
            group("geodetic", position)
        else:
            unusable += [n for n in ("x", "y", "z") if n in ok]
        if frame in NED_FRAMES or frame in GEODETIC_FRAMES:
            group("velocity_ned", (("x_dot", "v_north"), ("y_dot", "v_east"), ("z_dot", "v_down")))
        elif frame in BODY_FRAMES:
            group("velocity_body", (("x_dot", "forward"), ("y_dot", "right"), ("z_dot", "down")))
        else:
            unusable += [n for n in ("x_dot", "y_dot", "z_dot") if n in ok]
        group("heading", (("psi", "psi"),))
        group("yaw_rate", (("psi_dot", "yaw_rate"),))
        return groups, unusable

    # -- ingest -----------------------------------------------------------------------------
    def register(self, name: str, *, now: float) -> SensorRecord:
        """The record of sensor *name*, created (and logged) on its first message."""
        rec = self.sensors.get(name)
        if rec is None:
            rec = self.sensors[name] = SensorRecord(name=name, first_seen=now, last_seen=now)
            self.logger.debug("new sensor '%s'", name)
        return rec

    def ingest(self, msg: t.StateInformation, *, now: float) -> list[tuple[Measurement, UpdateResult]]:
        """Fold one message into the estimate at time *now*; return what happened to each group."""
        name = msg.sensor_name or "(unnamed)"
        rec = self.register(name, now=now)
        rec.messages += 1
        rec.last_seen = now
        rec.frames.add(msg.reference_frame.strip().upper() or "NED")
        rec.fields.update(_value_fields(msg.presence_vector))
        groups, unusable = self.measurements(msg)
        if unusable:
            rec.unusable += len(unusable)
            self._warn_once(name, f"fields {', '.join(unusable)} in frame '{msg.reference_frame}'",
                            "unusable (non-finite, half a geodetic position, or a position in a body/unknown "
                            "frame); they are ignored")
        self._copy_passthrough(msg)
        self.ekf.predict_to(now)
        results = []
        for m in groups:
            res = self.ekf.update(m)
            if res.outcome == "rejected":
                rec.outliers += 1
                count = rec.consecutive_rejects.get(m.kind, 0) + 1
                rec.consecutive_rejects[m.kind] = count
                self.logger.debug("sensor '%s': %s rejected (d2 %.1f > %.1f)", name, m.kind,
                                  res.mahalanobis2, res.threshold)
                if count >= self.settings.reinit_after:
                    self.logger.warning("sensor '%s': %d %s measurements in a row beyond the gate; trusting it "
                                        "again (the estimate had diverged or the sensor jumped)", name, count, m.kind)
                    if m.kind in ("position", "heading"):
                        self.ekf.reset_to(m)
                        res = UpdateResult("initialised", res.mahalanobis2, res.threshold)
                    else:
                        res = self.ekf.update(m, gate=False)
                    rec.consecutive_rejects[m.kind] = 0
            else:
                rec.consecutive_rejects[m.kind] = 0
            if res.outcome == "deferred":
                rec.deferred += 1
                self._warn_once(name, f"{m.kind} before any heading", "waits for a heading measurement (psi)")
            elif res.outcome != "rejected":
                rec.accepted += 1
            results.append((m, res))
        return results

    def _copy_passthrough(self, msg: t.StateInformation) -> None:
        present = msg.presence_vector & _PASSTHROUGH_MASK
        if not present:
            return
        kept = self.passthrough
        for name, bit in _PASSTHROUGH:
            if present & bit:
                value = getattr(msg, name)
                if math.isfinite(value):
                    setattr(kept, name, value)
                    kept.presence_vector |= bit

    def _warn_once(self, sensor: str, what: str, why: str) -> None:
        if (sensor, what) not in self._warned:
            self._warned.add((sensor, what))
            self.logger.warning("sensor '%s': %s %s", sensor, what, why)

    # -- output -------------------------------------------------------------------------------
    def predict_to(self, now: float) -> None:
        """Propagate the filter to *now*."""
        self.ekf.predict_to(now)

    def estimate(self, *, name: str = "state_estimator") -> t.StateInformation | None:
        """The current estimate (NED, with sigmas), or None before any usable measurement."""
        state = self.ekf.state()
        kept = self.passthrough
        if not state and not kept.presence_vector:
            return None
        msg = t.StateInformation()
        msg.sensor_name = name
        msg.reference_frame = "NED"
        present = kept.presence_vector
        for state_name, out, bit, out_sigma, sigma_bit in _OUTPUT_BITS:
            if state_name in state:
                value, sigma = state[state_name]
                setattr(msg, out, value)
                setattr(msg, out_sigma, sigma)
                present |= bit | sigma_bit
        if kept.presence_vector:
            for name_, bit in _PASSTHROUGH:
                if kept.presence_vector & bit:
                    setattr(msg, name_, getattr(kept, name_))
        msg.presence_vector = present
        return msg

    def silent_sensors(self, *, now: float, timeout: float) -> list[str]:
        """Sensors not heard from for more than *timeout* seconds."""
        return sorted(n for n, rec in self.sensors.items() if now - rec.last_seen > timeout)
