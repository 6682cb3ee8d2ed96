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
from collections.abc import Callable
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import GeoOrigin, geodetic_to_ned
from u2sa_hw.messages import STATE_FIELDS  # also installs the presence setters
from u2sa_hw.services.estimator.ekf import STATE_NAMES, Measurement, NavigationEkf

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
_OUTPUT_BITS = tuple((state, out, _BIT[out], f"{out}_sigma", _BIT[f"{out}_sigma"]) for out, state in _OUTPUT)
# filter state index -> (estimate field, its bit | its sigma's bit, the sigma field)
_OUTPUT_BY_STATE = {STATE_NAMES.index(state): (out, bit | sigma_bit, out_sigma)
                    for state, out, bit, out_sigma, sigma_bit in _OUTPUT_BITS}


# (kind, filter components, message fields, (sigma field, its presence bit, default sigma) per field)
_Group = tuple[str, tuple[str, ...], tuple[str, ...], tuple[tuple[str, int, float], ...]]
_Getter = Callable[[Any], tuple[float, ...]]


def _getter(names: tuple[str, ...]) -> _Getter:
    """A function of a message returning the fields *names* as a tuple (attrgetter returns one field bare)."""
    if len(names) == 1:
        one = attrgetter(names[0])
        return lambda msg: (one(msg),)
    return attrgetter(*names)


def _some_fields(names: tuple[str, ...], msg: Any) -> tuple[float, ...]:
    """The fields *names* of *msg*, 0.0 for an empty name."""
    return tuple(getattr(msg, n) if n else 0.0 for n in names)


@dataclass(frozen=True)
class _MessagePlan:
    """How a message with one presence vector and frame is read, when all its values are finite."""

    values: _Getter                   # every present value field (to check that all are finite)
    fields: frozenset[str]            # their names
    frame: str                        # the frame as a sensor record lists it
    # per group: kind, components, fields, its values, its sigmas (absent ones 0, i.e. the default), defaults
    groups: tuple[tuple[str, tuple[str, ...], tuple[str, ...], _Getter, _Getter, tuple[float, ...]], ...]
    unusable: tuple[str, ...]         # present fields no group reads (a position in a body frame)
    passthrough: tuple[tuple[str, int], ...]   # present attitude fields copied into the estimate


def _sigma(msg: t.StateInformation, bit: int, name: str, default: float) -> float:
    """The sigma field *name* when present, finite and > 0, else *default*."""
    if msg.presence_vector & bit:
        sigma = getattr(msg, name)
        if math.isfinite(sigma) and sigma > 0:
            return sigma
    return default


@functools.lru_cache(maxsize=64)
def _passthrough_fields(presence_vector: int) -> tuple[str, ...]:
    """The pass-through fields a presence vector marks."""
    return tuple(name for name, bit in _PASSTHROUGH if presence_vector & bit)


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
        self._plans: dict[tuple[int, str], _MessagePlan] = {}

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

    def _message_plan(self, present: int, frame_text: str) -> _MessagePlan:
        """The :class:`_MessagePlan` of messages with the fields *present* in *frame_text*."""
        fields = _value_fields(present)
        groups, unusable = self._layout(present, frame_text)
        plans = []
        for kind, components, names, sigmas in groups:
            sigma_names = tuple(name if present & bit else "" for name, bit, _ in sigmas)
            if all(sigma_names):
                get_sigmas = _getter(sigma_names)
            else:
                get_sigmas = functools.partial(_some_fields, sigma_names)
            plans.append((kind, components, names, _getter(names), get_sigmas, tuple(d for _, _, d in sigmas)))
        return _MessagePlan(_getter(fields) if fields else lambda msg: (), frozenset(fields),
                            frame_text.strip().upper() or "NED", tuple(plans), tuple(unusable),
                            tuple((n, bit) for n, bit in _PASSTHROUGH if present & bit))

    def _groups(self, msg: t.StateInformation, plan: _MessagePlan
                ) -> tuple[list[tuple[str, tuple[str, ...], tuple[float, ...], tuple[float, ...]]], list[str]]:
        """(kind, components, values, sigmas) of each measurement group in *msg*, and the unusable fields."""
        values = plan.values(msg)
        if not math.isfinite(sum(values)):   # a NaN or an infinity somewhere (or a huge sum): field by field
            found, unusable = self.measurements(msg)
            return [(m.kind, m.components, m.values, m.sigmas) for m in found], unusable
        out = []
        for kind, components, names, get_values, get_sigmas, defaults in plan.groups:
            values = get_values(msg)
            if kind == "geodetic":   # x = lat, y = lon (deg), z = altitude up (m)
                kind, values = "position", self._geodetic_to_ned(names, values)
            sigmas = get_sigmas(msg)
            if not (min(sigmas) > 0.0 and math.isfinite(sum(sigmas))):   # one absent, not finite or not > 0
                sigmas = tuple(x if 0.0 < x < math.inf else d for x, d in zip(sigmas, defaults))
            out.append((kind, components, values, sigmas))
        return out, list(plan.unusable)

    # -- ingest -----------------------------------------------------------------------------
    def register(self, name: str, *, now: float) -> SensorRecord:
        """The record of sensor *name*, created (and logged) on its first message."""
        rec = self.sensors.get(name)
        if rec is None:
            rec = self.sensors[name] = SensorRecord(name=name, first_seen=now, last_seen=now)
            self.logger.debug("new sensor '%s'", name)
        return rec

    def ingest(self, msg: t.StateInformation, *, now: float) -> list[str]:
        """Fold one message into the estimate at time *now*; return the kinds of the groups folded in
        (accepted, or initialised a component)."""
        name = msg.sensor_name or "(unnamed)"
        rec = self.sensors.get(name) or self.register(name, now=now)
        rec.messages += 1
        rec.last_seen = now
        key = (msg.presence_vector, msg.reference_frame)
        plan = self._plans.get(key)
        if plan is None:
            plan = self._plans[key] = self._message_plan(*key)
        rec.frames.add(plan.frame)
        if not rec.fields.issuperset(plan.fields):
            rec.fields |= plan.fields
        groups, unusable = self._groups(msg, plan)
        if unusable:
            rec.unusable += len(unusable)
            self._warn_once(name, f"fields {', '.join(unusable)} in frame '{msg.reference_frame}'",
                            "unusable (non-finite, half a geodetic position, or a position in a body/unknown "
                            "frame); they are ignored")
        if plan.passthrough:
            self._copy_passthrough(msg, plan.passthrough)
        ekf = self.ekf
        ekf.predict_to(now)
        folded = []
        for kind, components, values, sigmas in groups:
            outcome = ekf.update_values(kind, components, values, sigmas)
            if outcome == "rejected":
                outcome = self._rejected(rec, Measurement(kind, components, values, sigmas))
            else:
                rec.consecutive_rejects[kind] = 0
            if outcome == "deferred":
                rec.deferred += 1
                self._warn_once(name, f"{kind} before any heading", "waits for a heading measurement (psi)")
            elif outcome != "rejected":
                rec.accepted += 1
                folded.append(kind)
        return folded

    def _rejected(self, rec: SensorRecord, m: Measurement) -> str:
        """Count a group the gate rejected; after ``reinit_after`` in a row, fold it in anyway. The outcome."""
        rec.outliers += 1
        count = rec.consecutive_rejects.get(m.kind, 0) + 1
        rec.consecutive_rejects[m.kind] = count
        self.logger.debug("sensor '%s': %s rejected (d2 %.1f > %.1f)", rec.name, m.kind,
                          self.ekf.mahalanobis2, self.ekf.threshold)
        if count < self.settings.reinit_after:
            return "rejected"
        self.logger.warning("sensor '%s': %d %s measurements in a row beyond the gate; trusting it "
                            "again (the estimate had diverged or the sensor jumped)", rec.name, count, m.kind)
        rec.consecutive_rejects[m.kind] = 0
        if m.kind in ("position", "heading"):
            self.ekf.reset_to(m)
            return "initialised"
        return self.ekf.update_values(m.kind, m.components, m.values, m.sigmas, gate=False)

    def _copy_passthrough(self, msg: t.StateInformation, present: tuple[tuple[str, int], ...]) -> None:
        kept = self.passthrough
        for name, bit in present:
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
        ekf, kept = self.ekf, self.passthrough
        observed, present = ekf.observed, kept.presence_vector
        if not observed and not present:
            return None
        msg = t.StateInformation()
        msg.sensor_name = name
        msg.reference_frame = "NED"
        x, var = ekf.x.tolist(), ekf.P.diagonal().tolist()
        for i in observed:
            out, bits, out_sigma = _OUTPUT_BY_STATE[i]
            setattr(msg, out, x[i])
            setattr(msg, out_sigma, math.sqrt(max(var[i], 0.0)))
            present |= bits
        for name_ in _passthrough_fields(kept.presence_vector):
            setattr(msg, name_, getattr(kept, name_))
        msg.presence_vector = present
        return msg

    def silent_sensors(self, *, now: float, timeout: float) -> list[str]:
        """Sensors not heard from for more than *timeout* seconds."""
        return sorted(n for n, rec in self.sensors.items() if now - rec.last_seen > timeout)
