"""A profile read past its mistakes, so the checks that need a loaded profile still run.

``load_profile`` stops at the first kind of mistake (unknown keys, a wrong type, an unknown
log level). ``u2sa check`` has already reported those one by one; to check the device
addresses and the ``[safety]`` wiring too, in the same run, it loads a copy of the profile
with the reported mistakes left out: unknown tables and keys, values of the wrong type or
outside their choices, services whose kind is unknown. Relative paths are made absolute
first, so the copy (written to a temporary directory) names the same files; the result
carries the real path, so every message names the real profile.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path
from typing import Any, Mapping

import tomli_w

PATH_KEYS = ("config_dir", "log_dir", "data_dir", "bus_key")


def _vehicle(table: Mapping[str, Any], base: Path) -> dict[str, Any]:
    from u2sa_hw.check.offline import ORIGIN_RANGES, VEHICLE_KEYS
    from u2sa_hw.service_log import LEVEL_NAMES

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
                          if k in ORIGIN_RANGES and isinstance(v, (int, float)) and not isinstance(v, bool)}
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
    from u2sa_hw.vehicle import TOP_TABLES, ProfileError, load_profile

    base = path.resolve().parent
    clean: dict[str, Any] = {k: v for k, v in data.items() if k in TOP_TABLES and isinstance(v, dict)}
    clean["vehicle"] = _vehicle(clean.get("vehicle", {}), base)
    clean["services"] = _services(clean.get("services", {}), base)
    if isinstance(clean.get("simulation"), dict):
        clean.pop("simulation")   # the mock launcher's table: checked on its own, not needed here
    with tempfile.TemporaryDirectory(prefix="u2sa-check-") as tmp:
        copy = Path(tmp) / path.name
        copy.write_bytes(tomli_w.dumps(clean).encode())
        try:
            profile = load_profile(copy)
        except (ProfileError, ValueError):
            return None
    return dataclasses.replace(profile, path=path)
