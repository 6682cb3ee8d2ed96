"""The profile's ``[safety.prearm]`` table: which pre-arm checks run, on which services, with which bounds.

```toml
[safety.prearm]
gps = { service = "gps", max_sigma_m = 5.0 }
estimator = { service = "estimator", max_position_sigma_m = 5.0, max_heading_sigma_deg = 10.0,
              max_estimate_age_s = 0.5 }
imu = { services = ["imu"] }
geofence = { service = "estimator", max_position_age_s = 1.0 }   # on whenever the profile has a [geofence]
required_services = { ignore = [], allow_degraded = [] }
rc_link = true
no_failsafe = true
health_timeout_s = 3.0
```

Every key is optional: a team writes nothing and gets every check its profile's services
allow, with the defaults above. A check is ``true`` (on, defaults), ``false`` (off) or a
table (on, with some keys changed). The services a check judges default from the kinds:
``gps`` the first enabled ``gps_nmea`` service, ``estimator`` the first enabled
``state_estimator``, ``imu`` every enabled ``imu_*`` service; a check whose kind the profile
lacks is off unless named, and then it is an error. :func:`parse_prearm` refuses an unknown
key, a wrong type, a service that is not in the profile, disabled or of the wrong kind, with
one line naming the file, the key and the fix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from u2sa_hw.config.keys import did_you_mean
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

TABLE = "prearm"
GPS_KINDS = frozenset({"gps_nmea"})
ESTIMATOR_KINDS = frozenset({"state_estimator"})
IMU_KIND_PREFIX = "imu_"
MONITOR_KINDS = frozenset({"hsm"})   # degraded when others are: allowed degraded by default
RC_KINDS = frozenset({"rc_mux"})   # the RC link check judges the RC service; it is never a "required service"
# The order checks are evaluated and reported in: the first failure is the one a pilot reads.
CHECK_ORDER = ("no_failsafe", "rc_link", "gps", "imu", "estimator", "geofence", "required_services")
_TOP_KEYS = frozenset(CHECK_ORDER) | {"health_timeout_s"}
DEFAULT_HEALTH_TIMEOUT_S = 3.0


@dataclass(frozen=True)
class GpsCheck:
    """Fresh data and a 3D fix with its horizontal sigma under ``max_sigma_m``."""

    service: str
    max_sigma_m: float = 5.0


@dataclass(frozen=True)
class EstimatorCheck:
    """Healthy, publishing (STATE_ESTIMATE younger than ``max_estimate_age_s``; 0: not judged), converged."""

    service: str
    max_position_sigma_m: float = 5.0
    max_heading_sigma_deg: float = 10.0
    max_estimate_age_s: float = 0.5


@dataclass(frozen=True)
class GeofenceCheck:
    """The estimator's newest position (younger than ``max_position_age_s``) inside the profile's fence."""

    service: str
    fence: Any = None   # u2sa_hw.geofence.Fence
    max_position_age_s: float = 1.0


@dataclass(frozen=True)
class ImuCheck:
    """Every IMU service healthy and calibrated."""

    services: tuple[str, ...]


@dataclass(frozen=True)
class RequiredServicesCheck:
    """Every service in ``services`` healthy (status ok, or degraded for those in ``allow_degraded``)."""

    services: tuple[str, ...]
    allow_degraded: tuple[str, ...] = ()


@dataclass(frozen=True)
class PrearmTable:
    """The parsed ``[safety.prearm]`` table (None: the check is off)."""

    gps: GpsCheck | None
    estimator: EstimatorCheck | None
    imu: ImuCheck | None
    required_services: RequiredServicesCheck | None
    geofence: GeofenceCheck | None = None
    rc_link: bool = True
    no_failsafe: bool = True
    health_timeout_s: float = DEFAULT_HEALTH_TIMEOUT_S

    def enabled(self) -> tuple[str, ...]:
        """The names of the checks that run, in evaluation order."""
        return tuple(name for name in CHECK_ORDER if getattr(self, name) not in (None, False))


class _Reader:
    """Typed reads from the table; every error names the file, the key and the fix."""

    def __init__(self, profile: VehicleProfile) -> None:
        self.profile = profile
        self.where = f"{profile.path or 'the vehicle profile'} [safety.{TABLE}]"

    def error(self, key: str, text: str) -> ProfileError:
        return ProfileError(f"{self.where}: '{key}' {text}")

    def number(self, table: Mapping[str, Any], check: str | None, key: str, default: float, *, unit: str,
               allow_zero: bool = False) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0 or (value == 0 and not allow_zero):
            bound = ">= 0" if allow_zero else "> 0"
            example = f"{check} = {{ {key} = {default!r} }}" if check else f"{key} = {default!r}"
            raise self.error(f"{check}.{key}" if check else key,
                             f"must be a number {bound} ({unit}), got {value!r}; e.g. {example}")
        from u2sa_hw.profile.numbers import range_problem

        dotted = f"{check}.{key}" if check else key
        problem = range_problem(f"safety.{TABLE}.{dotted}", value)
        if problem:
            raise ProfileError(f"{self.where}: {problem.replace(repr(key), repr(dotted), 1)} ({unit})")
        return float(value)

    def names(self, table: Mapping[str, Any], check: str, key: str) -> tuple[str, ...]:
        value = table.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self.error(f"{check}.{key}", f"must be a list of service names like [\"imu\"], got {value!r}")
        for name in value:
            self.service(check, key, name, kinds=None)
        return tuple(value)

    def service(self, check: str, key: str, name: Any, *, kinds: frozenset[str] | None,
                prefix: str = "") -> str:
        """*name* checked: a string naming an enabled service of the profile of one of *kinds*."""
        services = self.profile.services
        if not isinstance(name, str):
            raise self.error(f"{check}.{key}", f"must be a service name (a string), got {name!r}")
        if name not in services:
            raise self.error(f"{check}.{key}", f"names service '{name}', which is not in the profile (services: "
                                               f"{', '.join(services) or 'none'}); name one of them or set "
                                               f"{check} = false")
        spec = services[name]
        if not spec.enabled:
            raise self.error(f"{check}.{key}", f"names service '{name}', which is disabled (enabled = false): the "
                                               f"check could never pass; enable it or set {check} = false")
        if (kinds is not None or prefix) and not (spec.kind in (kinds or ()) or (prefix and spec.kind.startswith(prefix))):
            want = " or ".join(sorted(kinds or ())) or f"{prefix}*"
            raise self.error(f"{check}.{key}", f"names service '{name}' of kind {spec.kind}; the {check} check "
                                               f"reads a {want} service's health")
        return name

    def check_table(self, data: Mapping[str, Any], check: str, keys: frozenset[str]) -> dict[str, Any] | None:
        """The check's table: {} for true or absent, None for false; ProfileError on anything else."""
        value = data.get(check, True)
        if value is False:
            return None
        if value is True:
            return {}
        if not isinstance(value, dict):
            raise self.error(check, f"must be true, false or a table like {check} = {{ {sorted(keys)[0]} = ... }}, "
                                    f"got {value!r}")
        unknown = sorted(set(value) - keys)
        if unknown:
            hint = did_you_mean(unknown[0], keys)
            raise self.error(f"{check}.{unknown[0]}", f"is not a key of the {check} check{'; ' + hint if hint else ''} "
                                                       f"(known: {', '.join(sorted(keys))})")
        return dict(value)

    def default_service(self, check: str, data: Mapping[str, Any], table: dict[str, Any],
                        kinds: frozenset[str]) -> str | None:
        """The named service, else the first enabled one of *kinds*; None when absent and not asked for."""
        if "service" in table:
            return self.service(check, "service", table["service"], kinds=kinds)
        found = next((s.name for s in self.profile.services.values() if s.enabled and s.kind in kinds), None)
        if found is None and check in data:
            raise self.error(check, f"is on, but the profile has no enabled {' or '.join(sorted(kinds))} service; "
                                    f"add one, name it with {check} = {{ service = \"...\" }}, or set {check} = false")
        return found


def parse_prearm(profile: VehicleProfile) -> PrearmTable:
    """The profile's ``[safety.prearm]`` table with its defaults; ProfileError names the file, key and fix."""
    r = _Reader(profile)
    safety = profile.raw.get("safety", {})
    data = safety.get(TABLE, {}) if isinstance(safety, dict) else {}
    if not isinstance(data, dict):
        raise ProfileError(f"{r.where}: must be a table of checks (see docs/safety.md)")
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        hint = did_you_mean(unknown[0], _TOP_KEYS)
        raise r.error(unknown[0], f"is not a pre-arm check{'; ' + hint if hint else ''} "
                                  f"(known: {', '.join(sorted(_TOP_KEYS))})")
    flags = {}
    for key in ("rc_link", "no_failsafe"):
        value = data.get(key, True)
        if not isinstance(value, bool):
            raise r.error(key, f"must be true or false, got {value!r}")
        flags[key] = value
    timeout = r.number(data, None, "health_timeout_s", DEFAULT_HEALTH_TIMEOUT_S, unit="s")

    gps = None
    table = r.check_table(data, "gps", frozenset({"service", "max_sigma_m"}))
    if table is not None and (name := r.default_service("gps", data, table, GPS_KINDS)) is not None:
        gps = GpsCheck(service=name, max_sigma_m=r.number(table, "gps", "max_sigma_m", 5.0, unit="m"))

    estimator = None
    table = r.check_table(data, "estimator", frozenset({"service", "max_position_sigma_m", "max_heading_sigma_deg",
                                                        "max_estimate_age_s"}))
    if table is not None and (name := r.default_service("estimator", data, table, ESTIMATOR_KINDS)) is not None:
        estimator = EstimatorCheck(
            service=name, max_position_sigma_m=r.number(table, "estimator", "max_position_sigma_m", 5.0, unit="m"),
            max_heading_sigma_deg=r.number(table, "estimator", "max_heading_sigma_deg", 10.0, unit="deg"),
            max_estimate_age_s=r.number(table, "estimator", "max_estimate_age_s", 0.5, unit="s; 0: not judged",
                                        allow_zero=True))

    imu = None
    table = r.check_table(data, "imu", frozenset({"services"}))
    if table is not None:
        if "services" in table:
            value = table["services"]
            if not isinstance(value, list) or not value:
                raise r.error("imu.services", f"must be a non-empty list of IMU service names like [\"imu\"], "
                                              f"got {value!r}; to turn the check off set imu = false")
            names = tuple(r.service("imu", "services", n, kinds=None, prefix=IMU_KIND_PREFIX) for n in value)
        else:
            names = tuple(s.name for s in profile.services.values()
                          if s.enabled and s.kind.startswith(IMU_KIND_PREFIX))
            if not names and "imu" in data:
                raise r.error("imu", "is on, but the profile has no enabled imu_* service; add one or set imu = false")
        imu = ImuCheck(services=names) if names else None

    required = None
    table = r.check_table(data, "required_services", frozenset({"ignore", "allow_degraded"}))
    if table is not None:
        ignore = set(r.names(table, "required_services", "ignore"))
        # A service judged by its own check is left to it: its reason says more than "degraded".
        judged = {*(c.service for c in (gps, estimator) if c is not None), *(imu.services if imu else ())}
        names = tuple(s.name for s in profile.services.values()
                      if s.enabled and s.required and s.kind not in RC_KINDS and s.name not in ignore | judged)
        # An HSM says "degraded" when ANOTHER service is in trouble: that service is judged by its own
        # entry and a failsafe by no_failsafe, so the HSM's own degraded must not take autonomy away.
        monitors = tuple(s.name for s in profile.services.values() if s.kind in MONITOR_KINDS and s.name in names)
        allowed = r.names(table, "required_services", "allow_degraded")
        required = RequiredServicesCheck(services=names, allow_degraded=(*allowed, *(m for m in monitors
                                                                                     if m not in allowed)))
    return PrearmTable(gps=gps, estimator=estimator, imu=imu, required_services=required,
                       geofence=_geofence(r, data, profile), rc_link=flags["rc_link"], no_failsafe=flags["no_failsafe"], health_timeout_s=timeout)


def _geofence(r: _Reader, data: Mapping[str, Any], profile: VehicleProfile) -> GeofenceCheck | None:
    """The geofence check: on exactly when the profile has a ``[geofence]`` (a fence nobody enforces is worse
    than none, so it cannot be turned off, and without a fence it has nothing to judge)."""
    from u2sa_hw.geofence_parse import profile_fence

    fence = profile_fence(profile)
    if fence is None:
        if "geofence" in data:
            raise r.error("geofence", "is set, but the profile has no [geofence] table to check against; add the "
                                      "fence (docs/geofence.md) or remove the key")
        return None
    table = r.check_table(data, "geofence", frozenset({"service", "max_position_age_s"}))
    if table is None:
        raise r.error("geofence", "cannot be false while the profile has a [geofence]: a fence that is not "
                                  "enforced is worse than none; remove [geofence] to drive without one")
    name = r.default_service("geofence", {**data, "geofence": table}, table, ESTIMATOR_KINDS)
    assert name is not None   # default_service raises when the check is asked for and nothing provides it
    return GeofenceCheck(service=name, fence=fence,
                         max_position_age_s=r.number(table, "geofence", "max_position_age_s", 1.0, unit="s"))
