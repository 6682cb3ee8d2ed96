"""The offline check: a vehicle profile against what the code declares, every problem at once.

:func:`check_profile` reads the profile itself (so a table ``load_profile`` would stop at
does not hide the others), then checks in turn: the top-level tables and ``[vehicle]``
(unknown keys with a did-you-mean, types, choices, ranges, the directories and files it
names), then loads the profile (past those mistakes, :mod:`u2sa_hw.check.lenient`), every
service (:mod:`u2sa_hw.check.services`: kind, settings, config file, referenced files,
supervision), the device tables and addresses (:mod:`u2sa_hw.check.device_checks`),
``[simulation]``, and ``[safety]`` key by key and against the services
(:mod:`u2sa_hw.check.safety_checks`). A reason ``load_profile`` gives that none of these
names is reported as it says it. Nothing is opened but files: ``u2sa check --probe`` looks
at the devices.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from u2sa_hw.check.bus_checks import check_bus, check_security_env
from u2sa_hw.check.device_checks import check_devices, check_simulation
from u2sa_hw.check.lenient import ORIGIN_RANGES, VEHICLE_KEYS, lenient_profile
from u2sa_hw.check.problem import Collector, Problem, did_you_mean, type_name
from u2sa_hw.profile.loader import TOP_TABLES


def read_profile_table(path: Path, out: Collector) -> dict[str, Any] | None:
    """The profile's TOML as a dict, or None with the reason added to *out*."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        out.error("", "vehicle profile not found", "pass --vehicle with the path of your vehicle.toml "
                  "(examples/ has complete ones)")
        return None
    except OSError as exc:
        out.error("", f"cannot read the profile ({exc.strerror or exc})", "check the path and its permissions")
        return None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        out.error("", f"not UTF-8 text (byte {raw[exc.start]:#04x} at offset {exc.start})",
                  "save the profile as UTF-8 text; binary bytes do not belong in a TOML file")
        return None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        out.error("", f"not valid TOML: {exc}", "fix the syntax at that line")
        return None


def check_profile(path: Path, *, for_sim: bool = False) -> list[Problem]:
    """Every problem of the vehicle profile at *path*, errors and warnings, in file order.

    *for_sim*: the profile is about to run on mock devices (``u2sa sim``): a device without a
    mock is an error and host device nodes (udev rules, ``/dev`` paths) are not looked at.
    """
    path = Path(path)
    out = Collector(path)
    data = read_profile_table(path, out)
    if data is None:
        return out.problems
    for key in data:
        if key not in TOP_TABLES:
            out.error(key, f"unknown table '{key}'{did_you_mean(key, TOP_TABLES)}",
                      f"a profile has the tables {', '.join(TOP_TABLES)}; rename or remove '{key}'")
    for key in TOP_TABLES:
        if key in data and not isinstance(data[key], dict):
            out.error(key, f"'{key}' must be a table, got {type_name(data[key])}", f"write it as [{key}]")
    vehicle = data.get("vehicle", {}) if isinstance(data.get("vehicle", {}), dict) else {}
    _check_vehicle(path, vehicle, out)
    check_bus(vehicle, out)   # where the bus listens: u2sa_hw/check/bus_checks.py
    check_security_env(vehicle, out)   # $U2SA_BUS_SECURITY, which the installed units ignore
    profile, load_error = _load(path)
    if profile is None:
        profile = lenient_profile(path, data)   # past the mistakes load_profile stops at: the rest is checked too
    from u2sa_hw.check.services import check_services

    services = data.get("services", {}) if isinstance(data.get("services"), dict) else {}
    check_services(path, data, services, out, profile=profile)
    check_devices(path, data, out, profile=profile, for_sim=for_sim)
    if "simulation" in data or for_sim:
        check_simulation(path, data, out)
    if profile is not None:
        from u2sa_hw.check.safety_checks import check_safety

        check_safety(profile, data.get("safety"), out)
    if load_error and not any(p.is_error for p in out.problems):
        # load_profile refused the profile for a reason none of the checks above names: say it as it said it
        for line in load_error.splitlines():
            out.from_text(line, key="", fix="see the example profiles in examples/")
    return _unique(out.problems)


def _check_vehicle(path: Path, vehicle: dict[str, Any], out: Collector) -> None:
    from u2sa_hw.service.log import LEVEL_NAMES

    for key, value in vehicle.items():
        want = VEHICLE_KEYS.get(key)
        if want is None:
            out.error(f"vehicle.{key}", f"unknown key '{key}'{did_you_mean(key, VEHICLE_KEYS)}",
                      f"known keys: {', '.join(VEHICLE_KEYS)}")
        elif not isinstance(value, want) or isinstance(value, bool) and want is not bool:
            out.error(f"vehicle.{key}", f"must be {want.__name__}, got {type_name(value)} {value!r}",
                      f"write {key} = {_example(want)}")
    level = vehicle.get("log_level")
    if isinstance(level, str) and level not in LEVEL_NAMES:
        out.error("vehicle.log_level", f"unknown log level '{level}'{did_you_mean(level, LEVEL_NAMES)}",
                  f"use one of {', '.join(LEVEL_NAMES)}")
    security = vehicle.get("bus_security")
    if isinstance(security, str) and security not in ("signed", "open"):
        out.error("vehicle.bus_security", f"'{security}' is not a bus security mode",
                  "use \"signed\" (the default) or \"open\" (a bench only; docs/security.md)")
    system_id = vehicle.get("system_id")
    if isinstance(system_id, int) and not isinstance(system_id, bool) and not 0 <= system_id <= 255:
        out.error("vehicle.system_id", f"{system_id} is outside 0..255", "give the vehicle an id in 0..255")
    origin = vehicle.get("origin")
    if isinstance(origin, dict):
        for key, value in origin.items():
            bounds = ORIGIN_RANGES.get(key)
            if bounds is None:
                out.error(f"vehicle.origin.{key}", f"unknown key '{key}'{did_you_mean(key, ORIGIN_RANGES)}",
                          "origin = { lat = 29.19, lon = -81.05, alt = 10.0 }")
            elif isinstance(value, bool) or not isinstance(value, (int, float)):
                out.error(f"vehicle.origin.{key}", f"must be a number, got {type_name(value)} {value!r}",
                          "origin = { lat = 29.19, lon = -81.05, alt = 10.0 } (degrees, metres)")
            elif not bounds[0] <= value <= bounds[1]:
                out.error(f"vehicle.origin.{key}", f"{value} is outside {bounds[0]:g}..{bounds[1]:g}",
                          "give the local frame's origin in degrees (lat, lon) and metres (alt)")
    base = path.resolve().parent
    config_dir = vehicle.get("config_dir")
    if isinstance(config_dir, str) and not (base / Path(config_dir).expanduser()).is_dir():
        out.warning("vehicle.config_dir", f"directory {base / config_dir} does not exist: every service runs "
                    "with its defaults and the profile's settings",
                    "create it, or correct the path (relative to the profile's directory)")
    bus_key = vehicle.get("bus_key")
    if isinstance(bus_key, str) and bus_key.strip():
        key_path = base / Path(bus_key).expanduser()
        if not key_path.exists():
            out.warning("vehicle.bus_key", f"bus key {key_path} does not exist (u2sa run refuses to start without "
                        "it; u2sa sim signs with a key of its own)",
                        f"u2sa key rotate --file {key_path} makes one there, or copy the vehicle's with "
                        f"u2sa key import FILE --file {key_path}")


def _example(kind: type) -> str:
    return {str: '"text"', int: "1", float: "1.0", bool: "true", dict: "{ ... }"}.get(kind, "...")


def _load(path: Path) -> tuple[Any, str]:
    """(the parsed profile, "") or (None, load_profile's error): the checks report its reasons one by one."""
    from u2sa_hw.profile.vehicle import ProfileError
    from u2sa_hw.profile.loader import load_profile

    try:
        return load_profile(path), ""
    except ProfileError as exc:
        return None, str(exc)


def _unique(problems: list[Problem]) -> list[Problem]:
    seen, result = set(), []
    for p in problems:
        if p not in seen:
            seen.add(p)
            result.append(p)
    return result
