"""What the HSM watches: one :class:`WatchRule` per expected service, from the vehicle profile.

Each enabled service of the profile (other than HSMs) is expected. Its optional
``[services.NAME.supervision]`` table says how it is judged::

    [services.gps]
    kind = "gps_nmea"
    required = true                 # its failure raises the failsafe (profile key, default true)

    [services.gps.supervision]
    heartbeat_timeout_s = 3.0       # default: missed_heartbeats x the service's health_interval_s
    startup_grace_s = 10.0          # time to the first heartbeat after a (re)start
    data_channel = "STATE_INFO"     # its data: messages on this channel whose header.source is the service
    stale_after_s = 2.0             # no data for this long while alive -> stale (0: not checked)
    require_details = ["fix"]       # health details that must be true ("1", "true", "yes", a non-zero number)
    require_grace_s = 30.0          # ...within this long of starting and after turning false
    degraded_restart_s = 0.0        # restart after reporting "degraded" this long (0: never)
    restart = true                  # false: never restarted, a problem marks it failed at once

A wrong key or type is refused with the file, the table and the fix.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, fields
from typing import Any

from u2sa_hw.profile.numbers import SUPERVISION, checked
from u2sa_hw.profile.vehicle import ProfileError, ServiceSpec, VehicleProfile

SUPERVISION_TABLE = "supervision"
HSM_KIND = "hsm"
DEFAULT_HEALTH_INTERVAL_S = 1.0


@dataclass(frozen=True)
class WatchRule:
    """How one expected service is judged."""

    name: str
    required: bool = True
    heartbeat_timeout_s: float = 3.0
    startup_grace_s: float = 10.0
    data_channel: str = ""
    stale_after_s: float = 0.0
    require_details: tuple[str, ...] = ()
    require_grace_s: float = 30.0
    degraded_restart_s: float = 0.0
    restart: bool = True


@dataclass(frozen=True)
class MonitorPolicy:
    """Restart backoff and escalation, the same for every service."""

    max_restarts: int = 3
    restart_backoff_s: float = 2.0
    max_backoff_s: float = 30.0
    recovery_s: float = 30.0
    failsafe_latch: bool = True
    confirm_s: float = 0.5       # a problem must last this long, undisproved, before it is acted on
    stall_s: float = 1.0         # a gap between judgements longer than this: the HSM itself stalled

    def backoff(self, attempt: int) -> float:
        """Seconds after restart number *attempt* (1-based) before the next may follow."""
        return min(self.max_backoff_s, self.restart_backoff_s * 2 ** max(0, attempt - 1))


_KEYS = {f.name: f for f in fields(WatchRule) if f.name not in ("name", "required")}
SUPERVISION_KEYS = tuple(_KEYS)   # the keys of [services.NAME.supervision] (the profile loader checks them)


def health_interval_of(spec: ServiceSpec) -> float:
    """The service's ``health_interval_s``: its config file, else the profile's settings, else 1 s."""
    value: Any = spec.settings.get("health_interval_s", DEFAULT_HEALTH_INTERVAL_S)
    try:
        value = tomllib.loads(spec.config_path.read_text()).get("health_interval_s", value)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        pass   # no file yet or a broken (or binary) one: the service itself reports the broken file
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
        return DEFAULT_HEALTH_INTERVAL_S
    return float(value)


def _checked(where: str, key: str, value: Any, default: Any) -> Any:
    if isinstance(default, tuple):
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ProfileError(f"{where}: '{key}' must be a list of strings like [\"fix\"], got {value!r}")
        return tuple(value)
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if type(value) is not type(default):
        raise ProfileError(f"{where}: '{key}' must be {type(default).__name__}, got {type(value).__name__} {value!r}")
    if isinstance(value, float) and value < 0:
        raise ProfileError(f"{where}: '{key}' must be >= 0, got {value}")
    if isinstance(value, float):
        checked(f"{SUPERVISION}.{key}", value, where, ProfileError)
    return value


def rule_for(profile: VehicleProfile, spec: ServiceSpec, *, missed_heartbeats: int,
             startup_grace_s: float) -> WatchRule:
    """The WatchRule of *spec* from its supervision table (ProfileError on a bad key or type)."""
    where = f"{profile.path} [services.{spec.name}.{SUPERVISION_TABLE}]"
    table = profile.raw.get("services", {}).get(spec.name, {}).get(SUPERVISION_TABLE, {})
    if not isinstance(table, dict):
        raise ProfileError(f"{where}: must be a table (see docs/supervision.md)")
    values: dict[str, Any] = {
        "heartbeat_timeout_s": missed_heartbeats * health_interval_of(spec),
        "startup_grace_s": startup_grace_s,
    }
    for key, value in table.items():
        f = _KEYS.get(key)
        if f is None:
            raise ProfileError(f"{where}: unknown key '{key}' (known: {', '.join(sorted(_KEYS))})")
        values[key] = _checked(where, key, value, f.default)
    if values.get("stale_after_s", 0.0) > 0 and not values.get("data_channel"):
        raise ProfileError(f"{where}: stale_after_s needs data_channel (the channel the service's data goes out on)")
    return WatchRule(name=spec.name, required=spec.required, **values)


def rules_from_profile(profile: VehicleProfile, *, own_name: str, missed_heartbeats: int = 3,
                       startup_grace_s: float = 10.0) -> list[WatchRule]:
    """A rule for every enabled service of *profile* except HSMs (*own_name* and kind ``hsm``)."""
    return [rule_for(profile, spec, missed_heartbeats=missed_heartbeats, startup_grace_s=startup_grace_s)
            for spec in profile.services.values()
            if spec.enabled and spec.name != own_name and spec.kind != HSM_KIND]
