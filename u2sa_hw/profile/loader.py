"""Reading the vehicle profile (``vehicle.toml``): one file says what runs on this vehicle.

```toml
[vehicle]
name = "rover"
system_id = 1
lcm_url = "udpm://239.255.76.67:7667?ttl=0"   # optional; else $U2SA_LCM_URL, else this default
bus_security = "signed"  # optional; "open" only for a bench: nothing signed or verified (docs/security.md)
bus_key = "/etc/u2sa/bus.key"   # optional; $U2SA_BUS_KEY_FILE overrides it; a path, never the key itself
bus_interface = "eth0"   # optional, for ttl >= 1: the one interface the bus uses (ttl=0 uses lo only)
config_dir = "config"    # per-service TOML files: <config_dir>/<service>.toml
log_dir = "logs"         # one log file per service
data_dir = "data"        # recordings, state
log_level = "info"
origin = { lat = 29.1895, lon = -81.0483, alt = 10.0 }   # local NED frame origin

[services.gps]           # one table per service; the table name is the service name
kind = "gps_nmea"        # the service registry name (u2sa service --list-kinds)
config = "config/gps.toml"   # optional; default <config_dir>/<name>.toml
device = "gps"           # optional; the device it uses (default: its own name)
settings = { uere_m = 4.0 }   # optional initial values

[devices.gps]            # one address per device (docs/ports.md); mock: its stand-in in simulation
address = "serial:///dev/u2sa/gps?baud=9600"
mock = "nmea_gps"
```

Relative paths are relative to the profile's directory. The parsed form is
:class:`~u2sa_hw.profile.vehicle.VehicleProfile`; each table other than ``[vehicle]`` and
``[services]`` is checked by its own parser, imported here.
"""


from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any

from u2sa_hw.config.keys import unknown_key_problems
from u2sa_hw.service.validate import kind_problem
from u2sa_hw.geofence_parse import profile_fence
from u2sa_hw.profile.numbers import checked
from u2sa_hw.profile.vehicle import Origin, ProfileError, ServiceSpec, VehicleProfile
from u2sa_hw.safety.config import parse_safety
from u2sa_hw.service.log import level_number
from u2sa_hw.services.hsm.rules import SUPERVISION_KEYS

# Every key a table of the profile may hold; any other is an error with a did-you-mean (a typo
# must not leave a setting silently at its default). [safety] and [devices.*] are checked by
# their own modules (u2sa_hw.safety.config, u2sa_hw.profile.devices), supervision by the HSM's rules.
TOP_TABLES = ("vehicle", "services", "devices", "safety", "geofence", "simulation")
VEHICLE_KEYS = ("name", "system_id", "lcm_url", "bus_security", "bus_key", "bus_interface", "config_dir",
                "log_dir", "data_dir", "log_level", "origin")
ORIGIN_KEYS = ("lat", "lon", "alt")
SERVICE_KEYS = ("kind", "config", "settings", "enabled", "required", "supervision", "device")
# The mock launcher's SimulationSettings (mock_devices/launcher.py) reads these; a test keeps them equal.
SIMULATION_KEYS = ("model", "track_width", "wheel_base", "max_speed", "start", "rate_hz", "can_udp_port", "seed",
                   "timeout_s")
SIMULATION_START_KEYS = ("north", "east", "heading_deg")

VEHICLE_ENV = "U2SA_VEHICLE"
SYSTEM_PROFILE = Path("/etc/u2sa/vehicle.toml")


def _typed(table: dict[str, Any], key: str, kind: type, default: Any, where: str) -> Any:
    value = table.get(key, default)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if value is not None and not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ProfileError(f"{where}: '{key}' must be {kind.__name__}, got {type(value).__name__} {value!r}")
    return value


def _looks_like_a_key(value: str) -> bool:
    """True when *value* is a bus key itself (64 hex digits), pasted where the path of its file belongs."""
    digits = value.strip()
    return len(digits) == 64 and all(c in "0123456789abcdefABCDEF" for c in digits)


def key_problems(path: Path, data: dict[str, Any]) -> list[str]:
    """Unknown keys and service kinds of the profile *data* read from *path*, one line each with a did-you-mean."""
    problems = unknown_key_problems(data, TOP_TABLES, where=str(path), what="table")
    v = data.get("vehicle")
    if isinstance(v, dict):
        problems += unknown_key_problems(v, VEHICLE_KEYS, where=f"{path} [vehicle]")
        if isinstance(v.get("origin"), dict):
            problems += unknown_key_problems(v["origin"], ORIGIN_KEYS, where=f"{path} [vehicle] origin")
    services = data.get("services")
    for name, s in (services.items() if isinstance(services, dict) else ()):
        if not isinstance(s, dict):
            continue
        where = f"{path} [services.{name}]"
        problems += unknown_key_problems(s, SERVICE_KEYS, where=where)
        if isinstance(s.get("kind"), str) and s["kind"] and s.get("enabled", True) is not False:
            problem = kind_problem(s["kind"], where=f"{where} kind")
            if problem:
                problems.append(problem)
        if isinstance(s.get("supervision"), dict):
            problems += unknown_key_problems(s["supervision"], list(SUPERVISION_KEYS),
                                             where=f"{path} [services.{name}.supervision]")
    sim = data.get("simulation")
    if isinstance(sim, dict):
        problems += unknown_key_problems(sim, SIMULATION_KEYS, where=f"{path} [simulation]")
        if isinstance(sim.get("start"), dict):
            problems += unknown_key_problems(sim["start"], SIMULATION_START_KEYS, where=f"{path} [simulation] start")
    return problems


def read_profile_text(path: Path) -> str:
    """The profile's text; ProfileError naming the file when it is missing, unreadable or not UTF-8."""
    try:
        return path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ProfileError(f"{path}: vehicle profile not found; pass --vehicle with the path of your vehicle.toml "
                           "(examples/ has complete ones)") from None
    except UnicodeDecodeError as exc:
        raise ProfileError(f"{path}: not a text file (byte {exc.start} is 0x{exc.object[exc.start]:02x}, not "
                           "UTF-8); pass the vehicle.toml itself, or fix the file") from None
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read the vehicle profile ({exc.strerror or exc})") from None


def load_profile(path: Path | str | None) -> VehicleProfile:
    """Parse the profile at *path* (None: ``$U2SA_VEHICLE``, then /etc/u2sa/vehicle.toml, else defaults)."""
    if path is None:
        env = os.environ.get(VEHICLE_ENV)
        if env:
            path = env
        elif SYSTEM_PROFILE.exists():
            path = SYSTEM_PROFILE
        else:
            return VehicleProfile(path=None)
    path = Path(path)
    try:
        data = tomllib.loads(read_profile_text(path))
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{path}: not valid TOML: {exc}") from None
    problems = key_problems(path, data)
    if problems:
        raise ProfileError("\n".join(problems))
    base = path.resolve().parent
    v = data.get("vehicle", {})
    where = f"{path} [vehicle]"
    if not isinstance(v, dict):
        raise ProfileError(f"{path}: [vehicle] must be a table")

    def rel(key: str, default: str) -> Path:
        p = Path(_typed(v, key, str, default, where))
        return p if p.is_absolute() else base / p

    o = v.get("origin", {})
    if not isinstance(o, dict):
        raise ProfileError(f"{where}: 'origin' must be a table like {{ lat = 29.19, lon = -81.05, alt = 10.0 }}")
    origin = Origin(*(_typed(o, k, float, 0.0, f"{where} origin") for k in ("lat", "lon", "alt")))
    for k in ORIGIN_KEYS:
        checked(f"vehicle.origin.{k}", getattr(origin, k), f"{where} origin", ProfileError)
    checked("vehicle.system_id", v.get("system_id", 1), where, ProfileError)
    config_dir = rel("config_dir", "config")
    services: dict[str, ServiceSpec] = {}
    for name, s in data.get("services", {}).items():
        w = f"{path} [services.{name}]"
        if not isinstance(s, dict):
            raise ProfileError(f"{w}: must be a table with at least kind = \"...\"")
        kind = _typed(s, "kind", str, None, w)
        if not kind:
            raise ProfileError(f"{w}: missing 'kind' (the service type, e.g. kind = \"state_estimator\")")
        cfg = s.get("config")
        cfg_path = (base / cfg) if isinstance(cfg, str) else config_dir / f"{name}.toml"
        settings = _typed(s, "settings", dict, {}, w)
        device = _typed(s, "device", str, None, w)
        if device is not None:   # `device = "gps"` beside kind: the device setting (docs/ports.md)
            settings = {**settings, "device": device}
        services[name] = ServiceSpec(name=name, kind=kind, config_path=cfg_path, settings=settings,
                                     enabled=_typed(s, "enabled", bool, True, w),
                                     required=_typed(s, "required", bool, True, w))
    log_level = _typed(v, "log_level", str, "info", where)
    try:
        level_number(log_level)
    except ValueError as exc:
        raise ProfileError(f"{where}: log_level: {exc}") from None
    bus_security = _typed(v, "bus_security", str, None, where)
    if bus_security not in (None, "signed", "open"):
        raise ProfileError(f"{where}: bus_security must be \"signed\" (the default) or \"open\", not {bus_security!r}")
    bus_key = _typed(v, "bus_key", str, None, where)
    if bus_key is not None and _looks_like_a_key(bus_key):   # never echoed: it is a secret in a world-readable file
        raise ProfileError(f"{where}: bus_key holds a key (64 hex digits), not the path of a key file; a key must "
                           "not be in the profile, which every user of the board may read: store it with 'sudo u2sa "
                           "key import - --file /etc/u2sa/bus.key' (paste it on standard input), then remove bus_key "
                           "or set it to the path of that file")
    parse_safety(data.get("safety"), where=f"{path} [safety]")  # its syntax; check_wiring checks the names
    profile = VehicleProfile(
        path=path,
        name=_typed(v, "name", str, path.stem, where),
        system_id=_typed(v, "system_id", int, 1, where),
        lcm_url=_typed(v, "lcm_url", str, None, where),
        bus_security=bus_security,
        bus_key=(base / Path(bus_key).expanduser()) if bus_key else None,
        bus_interface=_typed(v, "bus_interface", str, None, where) or None,
        config_dir=config_dir,
        log_dir=rel("log_dir", "logs"),
        data_dir=rel("data_dir", "data"),
        log_level=log_level,
        origin=origin,
        services=services,
        devices={k: d for k, d in data.get("devices", {}).items() if isinstance(d, dict)},
        raw=data,
    )
    profile_fence(profile)   # a malformed [geofence] is refused here, before anything runs on it
    return profile
