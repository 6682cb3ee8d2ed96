"""Failsafe scenarios for ``u2sa sim --scenario FILE``: events scripted at times.

A scenario file is TOML::

    name = "rc_loss"                       # default: the file's stem
    description = "the pilot's RC link drops for 2 s mid-mission, then comes back"
    engage = true                          # the pilot hands over to autonomy first (default true)
    end_s = 14.0                           # the run ends this long after t0 (default: last event + 4 s)

    [[event]]
    at_s = 5.0                             # seconds after t0: when autonomy engaged (engage = false: when ready)
    action = "rc_loss"

    [[event]]
    at_s = 7.0
    action = "rc_return"

Actions and their keys (every key but ``at_s``/``action``/``label`` belongs to the action):

==================  ==========================================================================
``rc_loss``         the RC receiver stops its pulses (the pilot's link is gone)
``rc_return``       the pulses come back
``mode``            ``value = "manual"`` or ``"autonomous"``: the pilot's mode switch
``reengage``        the safety pilot's procedure: switch to manual, wait for RC_MODE manual, back
                    to autonomous, wait for autonomy (a re-arm after a loss or failsafe)
``sticks``          RC channel = position -1..1, e.g. ``throttle = 0.6, steering = -0.3``
``centre``          every stick back to the centre
``gps_fix``         ``fix = false``: every GPS mock stops reporting a fix; ``true``: it is back
``push``            ``north_mps = 0.0, east_mps = -2.0``: the world moves the simulated vehicle this
                    fast whatever it commands (a slope, mud, a current); 0, 0 ends it
``signal``          ``service = "wheels", signal = "KILL" | "STOP" | "CONT" | "TERM"``
``forge``           ``actuator = "left_wheel", percent = 60``: an ACTUATOR_CMD published by the
                    scenario runner, ``count`` times (default 20) every ``every_s`` (0.05)
``failsafe``        ``active = true|false, reason = "...", source = "operator", target = ""``
                    (a Failsafe on FAILSAFE; an operator clear names its target in ``target``,
                    "*" for all, see u2sa_hw/failsafe.py)
==================  ==========================================================================

Errors are one line naming the file, the event and the key.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

SIGNALS = ("KILL", "STOP", "CONT", "TERM")
SETTLE_S = 4.0
MAX_PUSH_MPS = 20.0

# action -> {key: (type, required)}
ACTIONS: dict[str, dict[str, tuple[type | tuple[type, ...], bool]]] = {
    "rc_loss": {},
    "rc_return": {},
    "mode": {"value": (str, True)},
    "reengage": {},
    "sticks": {},   # any RC channel name -> float, checked against the receiver at run time
    "centre": {},
    "gps_fix": {"fix": (bool, True)},
    "push": {"north_mps": ((int, float), False), "east_mps": ((int, float), False)},
    "signal": {"service": (str, True), "signal": (str, True)},
    "forge": {"actuator": (str, True), "percent": ((int, float), True), "count": (int, False),
              "every_s": ((int, float), False)},
    "failsafe": {"active": (bool, True), "reason": (str, False), "source": (str, False), "target": (str, False)},
}


class ScenarioError(ValueError):
    """A scenario file cannot be used; the message names the file, the event and the key."""


@dataclass(frozen=True)
class ScenarioEvent:
    """One scripted event: when (s after t0), what, with which parameters."""

    at_s: float
    action: str
    params: dict[str, Any] = field(default_factory=dict)
    label: str = ""

    def describe(self) -> str:
        """``rc_loss`` or ``signal service=wheels signal=KILL``."""
        args = " ".join(f"{k}={v}" for k, v in self.params.items())
        return self.label or (f"{self.action} {args}" if args else self.action)


@dataclass(frozen=True)
class Scenario:
    """A scenario file: its name, whether the pilot engages first, the events in time order, the end."""

    name: str
    path: Path
    description: str
    engage: bool
    end_s: float
    events: tuple[ScenarioEvent, ...]


def _event(raw: Any, index: int, where: str) -> ScenarioEvent:
    at = f"{where} event[{index}]"
    if not isinstance(raw, dict):
        raise ScenarioError(f"{at}: must be a table ([[event]] with at_s and action)")
    raw = dict(raw)
    at_s, action, label = raw.pop("at_s", None), raw.pop("action", None), raw.pop("label", "")
    if isinstance(at_s, bool) or not isinstance(at_s, (int, float)) or at_s < 0:
        raise ScenarioError(f"{at}: at_s must be a number of seconds >= 0 after t0, got {at_s!r}")
    if action not in ACTIONS:
        raise ScenarioError(f"{at}: action {action!r} is not one of {', '.join(ACTIONS)}")
    keys = ACTIONS[action]
    if action == "sticks":
        if not raw:
            raise ScenarioError(f"{at}: sticks needs at least one channel = position, e.g. throttle = 0.5")
        for name, value in raw.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not -1 <= value <= 1:
                raise ScenarioError(f"{at}: sticks {name} must be a position -1..1, got {value!r}")
    else:
        unknown = sorted(set(raw) - set(keys))
        if unknown:
            raise ScenarioError(f"{at}: unknown key(s) {', '.join(unknown)} for {action}; "
                                f"its keys: {', '.join(keys) or 'none'}")
        for key, (kind, required) in keys.items():
            if key not in raw:
                if required:
                    raise ScenarioError(f"{at}: {action} needs {key}")
                continue
            if isinstance(raw[key], bool) and kind is not bool or not isinstance(raw[key], kind):
                raise ScenarioError(f"{at}: {key} has the wrong type ({raw[key]!r})")
    if action == "mode" and raw["value"] not in ("manual", "autonomous"):
        raise ScenarioError(f"{at}: mode value must be \"manual\" or \"autonomous\", got {raw['value']!r}")
    if action == "push" and any(abs(raw.get(k, 0.0)) > MAX_PUSH_MPS for k in ("north_mps", "east_mps")):
        raise ScenarioError(f"{at}: push speeds must be within -{MAX_PUSH_MPS:g}..{MAX_PUSH_MPS:g} m/s")
    if action == "signal":
        raw["signal"] = raw["signal"].upper().removeprefix("SIG")
        if raw["signal"] not in SIGNALS:
            raise ScenarioError(f"{at}: signal must be one of {', '.join(SIGNALS)}, got {raw['signal']!r}")
    return ScenarioEvent(float(at_s), action, raw, str(label))


def load_scenario_file(path: Path) -> Scenario:
    """Read and check a scenario file; ScenarioError names the file and the key."""
    where = str(path)
    try:
        data = tomllib.loads(Path(path).read_text())
    except OSError as exc:
        raise ScenarioError(f"{where}: cannot read the scenario file: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{where}: not valid TOML: {exc}") from None
    unknown = sorted(set(data) - {"name", "description", "engage", "end_s", "event"})
    if unknown:
        raise ScenarioError(f"{where}: unknown key(s) {', '.join(unknown)}; a scenario has name, description, "
                            "engage, end_s and [[event]] tables")
    raw_events = data.get("event", [])
    if not isinstance(raw_events, list) or not raw_events:
        raise ScenarioError(f"{where}: no [[event]] tables; add at least one (at_s, action)")
    events = sorted((_event(e, i, where) for i, e in enumerate(raw_events)), key=lambda e: e.at_s)
    engage = data.get("engage", True)
    if not isinstance(engage, bool):
        raise ScenarioError(f"{where}: engage must be true or false")
    end_s = data.get("end_s", events[-1].at_s + SETTLE_S)
    if isinstance(end_s, bool) or not isinstance(end_s, (int, float)) or end_s < events[-1].at_s:
        raise ScenarioError(f"{where}: end_s must be a number >= the last event's at_s ({events[-1].at_s:g})")
    return Scenario(name=str(data.get("name", Path(path).stem)), path=Path(path),
                    description=str(data.get("description", "")), engage=engage, end_s=float(end_s),
                    events=tuple(events))
