"""The profile's ``[safety]`` table: which outputs the hardware RC mux switches, the software
mux's timings, the pilot's manual mixer.

```toml
[safety]
hardware_mux = { steering = "steering" }  # actuator -> the RC channel the mux passes to it in manual
rc_mode_timeout_ms = 250                   # actuators go neutral when the newest RC_MODE is older
on_check_lost = "neutral"                  # a pre-arm check lost while autonomous: neutral | hold

[safety.manual_mixer]                      # the pilot's sticks -> MANUAL_CMD for the software-muxed actuators
kind = "differential"                      # differential | twin_thruster | ackermann (control's mixers)
left = "left_wheel"                        # ackermann: steering = "...", throttle = "..."
right = "right_wheel"
throttle_channel = "throttle"              # RC receiver channels (the rc_mux service's `channels`)
steering_channel = "steering"
center_us = 1500                           # stick centre, full deflection +-span_us, no command inside +-deadband_us
span_us = 500
deadband_us = 25

[safety.prearm]                            # pre-arm checks (u2sa_hw/safety/prearm.py)
```

Every actuator NOT named in ``hardware_mux`` is switched in software (the fail-safe
default: an output nobody declared as wired through the mux still obeys the pilot's
switch). This module checks the table's syntax at profile load; :func:`check_wiring`
checks the names against the services' actuators and RC channels (it imports the
services' kinds, so commands call it once before anything starts).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Mapping

from u2sa_hw.config.keys import unknown_key_problems
from u2sa_hw.profile.numbers import DEFAULT_RC_MODE_TIMEOUT_MS, MAX_RC_MODE_TIMEOUT_MS, PROFILE_NUMBERS
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

if TYPE_CHECKING:
    from u2sa_hw.services.control.mixers import Mixer

TABLE = "safety"
ON_CHECK_LOST = ("neutral", "hold")
MIXER_OUTPUTS = {"differential": ("left", "right"), "twin_thruster": ("left", "right"),
                 "ackermann": ("steering", "throttle")}
_TOP_KEYS = {"hardware_mux", "rc_mode_timeout_ms", "on_check_lost", "manual_mixer", "prearm"}
_MIXER_KEYS = {"kind", "left", "right", "steering", "throttle", "throttle_channel", "steering_channel",
               "center_us", "span_us", "deadband_us"}


def _error(where: str, text: str) -> Exception:
    return ProfileError(f"{where}: {text}")


def _error_lines(lines: list[str]) -> Exception:
    """One ProfileError of whole lines (an unknown key each, with a did-you-mean)."""
    return ProfileError("\n".join(lines))


@dataclass(frozen=True)
class ManualMixerSpec:
    """The pilot's manual mixer: which actuators, which stick channels, the stick calibration."""

    kind: str
    outputs: Mapping[str, str]          # mixer role (left/right or steering/throttle) -> actuator name
    throttle_channel: str
    steering_channel: str
    center_us: float = 1500.0
    span_us: float = 500.0
    deadband_us: float = 25.0

    @property
    def actuators(self) -> tuple[str, ...]:
        """The actuator names the mixer drives."""
        return tuple(self.outputs.values())

    def build(self) -> Mixer:
        """The control system's mixer of this kind, driving these actuators."""
        from u2sa_hw.services.control.mixers import build_mixer
        return build_mixer(self.kind, **self.outputs)

    def stick_percent(self, pulse_us: float) -> float:
        """A stick's pulse width as -100..100 % (0 inside the deadband; 0 for no pulse)."""
        if pulse_us <= 0:
            return 0.0
        offset = pulse_us - self.center_us
        if abs(offset) <= self.deadband_us:
            return 0.0
        usable = self.span_us - self.deadband_us
        pct = (abs(offset) - self.deadband_us) / usable * 100.0
        return max(-100.0, min(100.0, pct if offset > 0 else -pct))


@dataclass(frozen=True)
class SafetyConfig:
    """The parsed ``[safety]`` table (defaults when the profile has none)."""

    hardware_mux: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}))
    rc_mode_timeout_s: float = DEFAULT_RC_MODE_TIMEOUT_MS / 1000.0
    on_check_lost: str = "neutral"
    manual_mixer: ManualMixerSpec | None = None
    prearm: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))

    def behind_hardware_mux(self, actuator: str) -> bool:
        """True when *actuator*'s output is wired through the hardware RC mux."""
        return actuator in self.hardware_mux


def _number(table: Mapping[str, Any], key: str, default: float, where: str, *, low: float, high: float) -> float:
    value = table.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _error(where, f"'{key}' must be a number, got {type(value).__name__} {value!r}")
    if not low < float(value) <= high:
        raise _error(where, f"'{key}' = {value} is out of range; use a value in ({low:g}, {high:g}]")
    return float(value)


def _limit(key: str) -> float:
    """The upper bound of profile number *key* (u2sa_hw/profile/numbers.py, the one table of them)."""
    bound = PROFILE_NUMBERS[key].upper_bound
    assert bound is not None
    return float(bound)


def _name(table: Mapping[str, Any], key: str, where: str) -> str:
    value = table.get(key)
    if not isinstance(value, str) or not value.strip():
        raise _error(where, f"'{key}' must name an actuator or RC channel (a non-empty string), got {value!r}")
    return value.strip()


def _parse_mixer(table: Any, where: str) -> ManualMixerSpec:
    if not isinstance(table, dict):
        raise _error(where, "must be a table with kind, the actuator names and the stick channels")
    unknown = unknown_key_problems(table, _MIXER_KEYS, where=where)
    if unknown:
        raise _error_lines(unknown)
    kind = str(table.get("kind", "")).strip().lower()
    if kind not in MIXER_OUTPUTS:
        raise _error(where, f"'kind' = {table.get('kind')!r}; use one of {', '.join(MIXER_OUTPUTS)}")
    roles = MIXER_OUTPUTS[kind]
    outputs = {role: _name(table, role, where) for role in roles}
    if len(set(outputs.values())) != len(outputs):
        raise _error(where, f"the {kind} mixer's {' and '.join(roles)} must be different actuators")
    for key in ("throttle_channel", "steering_channel"):
        if key not in table:
            raise _error(where, f"missing '{key}': the manual mixer needs the RC receiver channel of each stick "
                                "(a name from the rc_mux service's channels, e.g. throttle_channel = \"throttle\")")
    sticks = (_name(table, "throttle_channel", where), _name(table, "steering_channel", where))
    if sticks[0] == sticks[1]:
        raise _error(where, "throttle_channel and steering_channel must be different RC channels")
    center = _number(table, "center_us", 1500.0, where, low=800.0, high=_limit("safety.manual_mixer.center_us"))
    span = _number(table, "span_us", 500.0, where, low=50.0, high=_limit("safety.manual_mixer.span_us"))
    deadband = _number(table, "deadband_us", 25.0, where, low=-1e-9,
                       high=min(span / 2, _limit("safety.manual_mixer.deadband_us")))
    return ManualMixerSpec(kind, MappingProxyType(outputs), *sticks, center_us=center, span_us=span,
                           deadband_us=deadband)


def parse_safety(data: Any, *, where: str) -> SafetyConfig:
    """Parse a ``[safety]`` table (*where* names the file for messages); ProfileError on a bad one."""
    if data is None:
        return SafetyConfig()
    if not isinstance(data, dict):
        raise _error(where, "must be a table")
    unknown = unknown_key_problems(data, _TOP_KEYS, where=where)
    if unknown:
        raise _error_lines(unknown)
    mux = data.get("hardware_mux", {})
    if not isinstance(mux, dict) or not all(isinstance(k, str) and isinstance(v, str) and v.strip()
                                            for k, v in mux.items()):
        raise _error(where, "'hardware_mux' must be a table actuator = \"RC channel\" for each PWM output wired "
                            "through the hardware RC mux, e.g. hardware_mux = { steering = \"steering\" }")
    lost = data.get("on_check_lost", "neutral")
    if lost not in ON_CHECK_LOST:
        raise _error(where, f"'on_check_lost' = {lost!r}; use one of {', '.join(ON_CHECK_LOST)}")
    prearm = data.get("prearm", {})
    if not isinstance(prearm, dict):
        raise _error(f"{where}.prearm", "must be a table of checks")
    mixer = data.get("manual_mixer")
    return SafetyConfig(
        hardware_mux=MappingProxyType({k: v.strip() for k, v in mux.items()}),
        rc_mode_timeout_s=_number(data, "rc_mode_timeout_ms", DEFAULT_RC_MODE_TIMEOUT_MS, where,
                                  low=0.0, high=MAX_RC_MODE_TIMEOUT_MS) / 1000.0,
        on_check_lost=lost,
        manual_mixer=None if mixer is None else _parse_mixer(mixer, f"{where}.manual_mixer"),
        prearm=MappingProxyType(dict(prearm)))


def load_safety(profile: VehicleProfile) -> SafetyConfig:
    """The profile's ``[safety]`` table, parsed; ProfileError names the file and key."""
    return parse_safety(profile.raw.get(TABLE), where=f"{profile.path or 'the vehicle profile'} [{TABLE}]")
