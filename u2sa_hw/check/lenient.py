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

The devices themselves are read past their mistakes by the one resolver of a profile's
devices, :func:`u2sa_hw.profile.devices.resolve_devices` with ``strict=False`` (given
:func:`readable_configs`): the devices whose address does not parse are left out, the
services that use them too, and so are the services still given an address setting of the
old form (the services check names the new form).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path
from typing import Any, Mapping

import tomli_w

from u2sa_hw.profile.devices import clean_device_tables
from u2sa_hw.profile.loader import VEHICLE_KEYS as VEHICLE_KEY_NAMES
from u2sa_hw.profile.numbers import PROFILE_NUMBERS

PATH_KEYS = ("config_dir", "log_dir", "data_dir", "bus_key")
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
    for source in (spec.settings, spec.file_settings()):   # the file wins, as in the service
        for key, value in source.items():
            if key in fields:
                try:
                    values[key] = coerce(fields[key], value)
                except ConfigError:
                    continue
    return values
