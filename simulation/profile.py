"""The simulation's copy of a vehicle profile: the same services, pointed at the mock devices.

A vehicle profile names each device's real address (``[devices.gps] address =
"serial:///dev/u2sa/gps?baud=9600"``). In simulation only that address changes: every
device with a mock gets its mock address (the mock launcher's ``addresses``, e.g.
``mock+serial:///run/sim/dev/gps?baud=9600``). Rather than edit the user's files,
:func:`write_sim_profile` writes a complete copy under the run directory: ``vehicle.toml``
with each device's address replaced (a ``[devices.NAME]`` table is added for a mocked device
that has none), and a copy of each service's config file (with any other setting *overrides*, e.g. ``record_raw``).
Paths the services read relative to the profile (mission and objects files) are made
absolute, so the copy runs from anywhere, and what a ``u2sa param set`` changes during a
simulation stays in the run directory.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any, Mapping

import tomli_w

from u2sa_hw.service.validate import declared_fields
from u2sa_hw.profile.devices import effective_config
from u2sa_hw.registry import RECORDER_KIND
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

SIM_PROFILE_NAME = "vehicle.toml"
__all__ = ["effective_config", "effective_configs", "write_sim_profile"]


def effective_configs(profile: VehicleProfile) -> dict[str, dict[str, Any]]:
    """:func:`effective_config` of every enabled service."""
    return {name: effective_config(profile, name) for name, spec in profile.services.items() if spec.enabled}


def _absolute(value: Any, base: Path) -> Any:
    if isinstance(value, str) and value.strip() and not Path(value).is_absolute():
        return str((base / value).resolve())
    return value


def _read_config(path: Path) -> dict[str, Any]:
    if not path.exists():
        return {}
    try:
        return tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ProfileError(f"{path}: cannot read this service config ({exc}); fix or delete it") from None


def write_sim_profile(profile: VehicleProfile, *, run_dir: Path, addresses: Mapping[str, str],
                      overrides: Mapping[str, Mapping[str, Any]] | None = None,
                      log_dir: Path | None = None, lcm_url: str | None = None, mission: Path | None = None,
                      record_dir: Path | None = None) -> Path:
    """Write the simulation copy of *profile* into *run_dir*; returns the new ``vehicle.toml``.

    *addresses* maps a device to its mock address; *overrides* maps a service to other
    settings to change (e.g. ``record_raw``); *mission*
    replaces every mission manager's ``mission_file``; *record_dir* adds (or enables) a
    recorder service writing there; *lcm_url* isolates the run's bus.
    """
    if profile.path is None:
        raise ProfileError("a simulation needs a vehicle profile file (--vehicle PATH)")
    base = profile.path.resolve().parent
    run_dir = run_dir.resolve()
    config_dir = run_dir / "config"
    config_dir.mkdir(parents=True, exist_ok=True)
    data = copy.deepcopy(profile.raw)
    vehicle = data.setdefault("vehicle", {})
    vehicle.update(config_dir=str(config_dir), data_dir=str(run_dir / "data"),
                   log_dir=str((log_dir or run_dir / "logs").resolve()))
    if lcm_url:
        vehicle["lcm_url"] = lcm_url
    devices = data.setdefault("devices", {})
    for device, address in addresses.items():
        table = devices.setdefault(device, {})
        if not isinstance(table, dict):
            raise ProfileError(f"{profile.path} [devices.{device}]: must be a table")
        table["address"] = str(address)
    if not devices:
        del data["devices"]
    overrides = overrides or {}
    services = data.setdefault("services", {})
    if record_dir is not None:
        recorders = [n for n, s in profile.services.items() if s.kind == RECORDER_KIND]
        for name in recorders or ["recorder"]:
            table = services.setdefault(name, {"kind": "recorder"})
            table["enabled"] = True
            table["required"] = False
            table.setdefault("settings", {})["directory"] = str(record_dir.resolve())
    for name, table in services.items():
        spec = profile.services.get(name)
        changes: dict[str, Any] = dict(overrides.get(name, {}))
        if spec is not None and spec.kind == "mission_manager" and mission is not None:
            changes["mission_file"] = str(mission.resolve())
        settings = dict(table.get("settings", {}))
        original = _read_config(spec.config_path) if spec is not None else {}
        for key in _file_fields(spec.kind if spec is not None else table.get("kind")):
            for values in (settings, original):
                if key in values:
                    values[key] = _absolute(values[key], base)
        settings.update(changes)
        table["settings"] = settings
        copied = config_dir / f"{name}.toml"
        original.update({k: v for k, v in changes.items() if k in original})
        copied.write_text(tomli_w.dumps(original))
        table["config"] = str(copied)
    path = run_dir / SIM_PROFILE_NAME
    header = (f"# Simulation copy of {profile.path.resolve()} written by u2sa sim / u2sa mock.\n"
              "# Device addresses point at the mock devices; edit the original, not this file.\n")
    path.write_text(header + tomli_w.dumps(data))
    return path


def _file_fields(kind: Any) -> list[str]:
    """The settings a service of *kind* declares as files (``field(file=...)``): relative to the profile's directory."""
    try:
        return [name for name, f in declared_fields(str(kind)).items() if f.names_file]
    except LookupError:   # an unknown kind: u2sa check reports it before a simulation starts
        return []
