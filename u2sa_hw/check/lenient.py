"""A profile read past its mistakes, so the checks that need a loaded profile still run.

``load_profile`` stops at the first kind of mistake (unknown keys, a wrong type, an unknown
log level, a ``[safety]`` typo), and ``profile_devices`` at the first bad device table.
``u2sa check`` has already reported those one by one; to check the device addresses and the
``[safety]`` wiring too, in the same run, it reads a copy of the profile with the reported
mistakes left out:

- :func:`lenient_profile`: unknown tables and keys, values of the wrong type or outside their
  choices, services whose kind is unknown, and the ``[safety]`` table (checked from the raw
  table by :mod:`u2sa_hw.check.safety_checks`) are left out; a device table keeps only the
  keys it may have. Relative paths are made absolute first, so the copy (written to a
  temporary directory) names the same files; the result carries the real path, so every
  message names the real profile.
- :func:`readable_configs`: each service's config, a wrong setting or config-file value left
  at its default, so the devices of a service with a bad ``baudrate`` are still known.
- :func:`lenient_devices`: the device tables without bad keys and without the devices whose
  address does not parse; the services that use those are left out too, and so are the
  services still given an address setting of the old form (``port``, ``bus``...; the
  services check names the new form), whose devices have no address to read.
- :func:`without_old_form`: only the latter, for install's own reading of the devices.
"""

from __future__ import annotations

import dataclasses
import tempfile
import tomllib
from pathlib import Path
from typing import Any, Mapping

import tomli_w

from u2sa_hw.profile.loader import VEHICLE_KEYS as VEHICLE_KEY_NAMES
from u2sa_hw.profile.numbers import PROFILE_NUMBERS

PATH_KEYS = ("config_dir", "log_dir", "data_dir", "bus_key")
DEVICE_KEY_TYPES: dict[str, type] = {"address": str, "mock": str, "service": str, "options": dict, "sides": list,
                                     "drives": dict}   # u2sa_hw.profile.devices.check_table's types
VEHICLE_KEYS: dict[str, type] = {   # the loader's keys (u2sa_hw.profile.loader), with the type each takes
    name: {"system_id": int, "origin": dict}.get(name, str) for name in VEHICLE_KEY_NAMES}
ORIGIN_RANGES = {key: (f.ge, f.le) for key in ("lat", "lon", "alt")   # u2sa_hw/profile/numbers.py, as the loader
                 for f in (PROFILE_NUMBERS[f"vehicle.origin.{key}"],)}


def _vehicle(table: Mapping[str, Any], base: Path) -> dict[str, Any]:
    from u2sa_hw.service.log import LEVEL_NAMES

    kept: dict[str, Any] = {}
    for key, value in table.items():
        want = VEHICLE_KEYS.get(key)
        if want is None or not isinstance(value, want) or isinstance(value, bool):
            continue
        if key in PATH_KEYS:
            value = str(base / Path(value).expanduser())
        kept[key] = value
    if kept.get("log_level") not in (None, *LEVEL_NAMES):
        del kept["log_level"]
    if kept.get("bus_security") not in (None, "signed", "open"):
        del kept["bus_security"]
    if "origin" in kept:
        kept["origin"] = {k: v for k, v in kept["origin"].items()
                          if k in ORIGIN_RANGES and isinstance(v, (int, float)) and not isinstance(v, bool)
                          and ORIGIN_RANGES[k][0] <= v <= ORIGIN_RANGES[k][1]}   # reported by _check_vehicle
    if not (isinstance(kept.get("system_id"), int) and 0 <= kept["system_id"] <= 255):
        kept.pop("system_id", None)
    return kept


def _services(table: Mapping[str, Any], base: Path) -> dict[str, Any]:
    from u2sa_hw.check.services import SERVICE_KEY_TYPES
    from u2sa_hw.registry import known_kinds
    from u2sa_hw.services.hsm.rules import _KEYS as SUPERVISION_KEYS

    kinds = known_kinds()
    kept: dict[str, Any] = {}
    for name, service in table.items():
        if not isinstance(service, dict) or service.get("kind") not in kinds:
            continue
        clean = {k: v for k, v in service.items() if k in SERVICE_KEY_TYPES and isinstance(v, SERVICE_KEY_TYPES[k])}
        if isinstance(clean.get("config"), str):
            clean["config"] = str(base / clean["config"])
        if isinstance(clean.get("supervision"), dict):
            clean["supervision"] = {k: v for k, v in clean["supervision"].items() if k in SUPERVISION_KEYS}
        kept[name] = clean
    return kept


def lenient_profile(path: Path, data: Mapping[str, Any]) -> Any:
    """The profile at *path* (parsed as *data*) without its reported mistakes; None when even that cannot load."""
    from u2sa_hw.profile.vehicle import ProfileError
    from u2sa_hw.profile.loader import TOP_TABLES, load_profile

    base = path.resolve().parent
    clean: dict[str, Any] = {k: v for k, v in data.items() if k in TOP_TABLES and isinstance(v, dict)}
    clean["vehicle"] = _vehicle(clean.get("vehicle", {}), base)
    clean["services"] = _services(clean.get("services", {}), base)
    clean["devices"] = clean_device_tables(clean.get("devices", {}), services=clean["services"])
    clean.pop("simulation", None)   # the mock launcher's table: checked on its own, not needed here
    clean.pop("safety", None)       # checked from the raw table, key by key (check.safety_checks)
    with tempfile.TemporaryDirectory(prefix="u2sa-check-") as tmp:
        copy = Path(tmp) / path.name
        copy.write_bytes(tomli_w.dumps(clean).encode())
        try:
            profile = load_profile(copy)
        except (ProfileError, ValueError):
            return None
    return dataclasses.replace(profile, path=path)


def clean_device_tables(tables: Any, *, services: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Each ``[devices.NAME]`` table with only the keys a device table takes, of the right type, and a
    ``service`` that is one of *services* (the device check reports the rest)."""
    kept: dict[str, dict[str, Any]] = {}
    for name, table in (tables.items() if isinstance(tables, dict) else ()):
        if not isinstance(table, dict):
            continue
        kept[name] = {k: v for k, v in table.items() if k in DEVICE_KEY_TYPES and isinstance(v, DEVICE_KEY_TYPES[k])}
        if kept[name].get("service") is not None and kept[name]["service"] not in services:
            del kept[name]["service"]
    return kept


def readable_configs(profile: Any) -> dict[str, dict[str, Any]]:
    """service -> the config it runs with, for every enabled service of a known kind; a value that is
    wrong (in the settings or the config file) is left at its default, as if it were not written."""
    from u2sa_hw.profile.devices import effective_config

    configs: dict[str, dict[str, Any]] = {}
    for name, spec in profile.services.items():
        if not spec.enabled:
            continue
        try:
            configs[name] = effective_config(profile, name)
        except ValueError:   # a wrong value (ConfigError), an unknown kind (ProfileError)
            values = _config_past_mistakes(spec)
            if values is not None:
                configs[name] = values
    return configs


def _written_values(spec: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the profile's settings, the config file's values) of *spec* as written (a file that does not read: {})."""
    file_values: dict[str, Any] = {}
    if spec.config_path.is_file():
        try:
            read = tomllib.loads(spec.config_path.read_bytes().decode("utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            read = {}
        file_values = read if isinstance(read, dict) else {}
    return dict(spec.settings), file_values


def _config_past_mistakes(spec: Any) -> dict[str, Any] | None:
    from u2sa_hw.config.fields import ConfigError, coerce
    from u2sa_hw.registry import resolve_kind
    from u2sa_hw.service.base_config import BASE_CONFIG

    try:
        cls = resolve_kind(spec.kind)
    except (LookupError, ImportError, AttributeError):
        return None
    fields = {f.name: f for f in (*BASE_CONFIG, *cls.config_fields())}
    values = {name: f.default for name, f in fields.items()}
    file_values: dict[str, Any] = {}
    if spec.config_path.is_file():
        try:
            file_values = tomllib.loads(spec.config_path.read_bytes().decode("utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            file_values = {}
    for source in (spec.settings, file_values):   # the file wins, as in the service
        for key, value in source.items():
            if key in fields:
                try:
                    values[key] = coerce(fields[key], value)
                except ConfigError:
                    continue
    return values


def lenient_devices(profile: Any, configs: Mapping[str, Mapping[str, Any]]) -> tuple[Any, set[str]]:
    """(*profile* with clean device tables and without the devices whose address does not parse, the names
    of those devices). A service that uses such a device, or is still given an old-form address setting
    (the services check's error), is disabled in the copy, so the other devices are still read; *configs*
    are :func:`readable_configs`."""
    from u2sa_hw.profile.devices import service_devices
    from u2sa_hw.ports.address import AddressError, parse_address
    from u2sa_hw.registry import resolve_kind

    tables = clean_device_tables(profile.devices, services=profile.services)
    bad: set[str] = set()
    for name, table in tables.items():
        if "address" in table:
            try:
                parse_address(table["address"], device=name)
            except AddressError:
                bad.add(name)
    services = dict(profile.services)
    for name, spec in profile.services.items():
        if not spec.enabled or name not in configs:
            continue
        try:
            cls = resolve_kind(spec.kind)
            used = service_devices(cls, name, configs[name])
        except (LookupError, ImportError, AttributeError, ValueError):
            continue
        if bad & set(used) or any(tables[b].get("service") == name for b in bad) or _old_form(spec, cls):
            services[name] = dataclasses.replace(spec, enabled=False)
    kept = {name: table for name, table in tables.items() if name not in bad}
    return dataclasses.replace(profile, devices=kept, services=services), bad


def without_old_form(profile: Any) -> Any:
    """*profile* with the services still given an old-form address setting disabled (the services check's
    error names the new form; their devices have no address to read, so nothing says that too)."""
    from u2sa_hw.registry import resolve_kind

    services = dict(profile.services)
    for name, spec in profile.services.items():
        try:
            old = spec.enabled and _old_form(spec, resolve_kind(spec.kind))
        except (LookupError, ImportError, AttributeError):
            continue
        if old:
            services[name] = dataclasses.replace(spec, enabled=False)
    return dataclasses.replace(profile, services=services)


def _old_form(spec: Any, cls: type) -> bool:
    """True when service *spec* (of class *cls*) is still given an address setting of the old form."""
    from u2sa_hw.config.keys import old_form_keys
    from u2sa_hw.service.base_config import BASE_CONFIG

    fields = [f.name for f in (*BASE_CONFIG, *cls.config_fields())]
    return any(old_form_keys(values, fields) for values in _written_values(spec))
