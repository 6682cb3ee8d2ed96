"""The ``[devices.NAME]`` tables, the device addresses and ``[simulation]`` of a profile.

On the vehicle (the default) every ``/dev/u2sa/NAME`` serial path must be created by something, and
two adapters must be told apart: :mod:`u2sa_hw.check.device_nodes`.

On the vehicle a real SocketCAN address without ``bitrate=`` is a warning: install cannot
set the interface's bitrate, so CAN does not come up at boot unless something else does it.

For ``u2sa sim`` (*for_sim*) every service with a device (a driver) must have a mock: a
``[devices]`` table with ``mock = "..."`` for it; the error names the mock kind to use, the
first of those the driver declares (``MOCK_KINDS``, :mod:`u2sa_hw.ports.declared`).
Mock kinds and ``[simulation]`` are read through :mod:`mock_devices` when it is installed,
behind one lazy boundary (:func:`_mock_support`, imported inside the check, never at module
level: ``u2sa_hw`` imports none of ``mock_devices``, ``hil``, ``drivers``, ``simulation`` at
import time); ``[simulation]``'s keys are checked either way.

Every device table's address is parsed on its own, so each wrong one is its own line; the
checks that need the whole device list (unused addresses, shared PWM outputs, mocks, device
nodes, CAN bitrates) then read it past those mistakes (the one resolver,
:func:`u2sa_hw.profile.devices.resolve_devices`, lenient, with the services' wrong settings at
their defaults), so one bad table or setting does not hide the rest.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.check.device_nodes import check_device_nodes, check_usb_identities
from u2sa_hw.check.lenient import readable_configs
from u2sa_hw.check.problem import Collector, did_you_mean, type_name
from u2sa_hw.profile.devices import ResolvedDevices, resolve_devices

DRIVER_PREFIX = "u2sa_hw.drivers."               # registry targets of hardware drivers: each has a device


def check_devices(path: Path, data: Mapping[str, Any], out: Collector, *, profile: Any, for_sim: bool) -> None:
    """Add the problems of the device tables and addresses of the profile at *path* to *out*."""
    devices = data.get("devices", {})
    services = data.get("services", {}) if isinstance(data.get("services"), dict) else {}
    if not isinstance(devices, dict):
        return
    from u2sa_hw.config.keys import old_device_key_fix
    from u2sa_hw.profile.devices import DEVICE_KEYS

    catalog = _mock_catalog()
    for name, table in devices.items():
        key = f"devices.{name}"
        if not isinstance(table, dict):
            out.error(key, f"must be a table, got {type_name(table)}", f"write [devices.{name}] with address = \"...\"")
            continue
        for k in table:
            if k in DEVICE_KEYS:
                continue
            old = old_device_key_fix(k)   # usb = {...}, can = {...}: the old form
            if old is not None:
                out.error(f"{key}.{k}", f"'{k}' is the old form", old)
            else:
                out.error(f"{key}.{k}", f"unknown key '{k}'{did_you_mean(k, DEVICE_KEYS)}",
                          f"a device table has {', '.join(DEVICE_KEYS)}")
        service = table.get("service")   # default: the service that names the device (profile_devices)
        if service is not None and (not isinstance(service, str) or service not in services):
            out.error(f"{key}.service", f"'{service}' is not a service of the profile"
                      f"{did_you_mean(service, services)}", "name the service that uses this device "
                      f"(services: {', '.join(services) or 'none'})")
        mock = table.get("mock")
        if mock is not None and catalog is not None and mock not in catalog:
            out.error(f"{key}.mock", f"'{mock}' is not a mock kind{did_you_mean(mock, catalog)}",
                      f"use one of {', '.join(sorted(catalog))}")
        for k, want in (("options", dict), ("sides", list), ("drives", dict)):
            if k in table and not isinstance(table[k], want):
                out.error(f"{key}.{k}", f"must be a {'table' if want is dict else 'list'}, got {type_name(table[k])}",
                          "see docs/simulation.md")
        _check_address_text(name, table.get("address"), out)
    if profile is None:   # not even a lenient copy loads: judge the mocks by the tables alone
        if for_sim:
            _check_mocks(None, profile, devices, services, out)
        return
    resolved = resolve_devices(profile, configs=readable_configs(profile), strict=False)
    readable = resolved.profile
    entries = _check_addresses(resolved, out)
    if for_sim:
        _check_mocks(entries, profile, devices, services, out)
    elif entries is not None:
        check_device_nodes(entries, readable, out)
        check_usb_identities(entries, out)
        _check_can_bitrates(entries, readable, out)


def _check_address_text(name: str, text: Any, out: Collector) -> None:
    """The table's own address parses (each wrong one is its own line, with the fix)."""
    from u2sa_hw.ports.address import AddressError, parse_address

    if not isinstance(text, str):
        return   # missing (the device list says whether one is needed) or of the wrong type (above)
    try:
        parse_address(text, device=name)
    except AddressError as exc:
        out.from_text(f"[devices.{name}]: {exc}", key=f"devices.{name}", fix="write the address as docs/ports.md shows")


@dataclass(frozen=True)
class _MockSupport:
    """What the checks read from :mod:`mock_devices`: its catalog and how it reads ``[simulation]``."""

    catalog: Mapping[str, Any]          # mock kind -> its catalog entry
    settings: Any                       # u2sa_hw.mocks.launcher.SimulationSettings
    error: type[Exception]              # u2sa_hw.mocks.sim_context.DeviceError


def _mock_support() -> _MockSupport | None:
    """The lazy boundary to :mod:`mock_devices`; None when it is not installed (any other error surfaces)."""
    try:
        from u2sa_hw.mocks.catalog import CATALOG
        from u2sa_hw.mocks.launcher import SimulationSettings
        from u2sa_hw.mocks.sim_context import DeviceError
    except ModuleNotFoundError as exc:
        if exc.name != "u2sa_hw.mocks":
            raise
        return None
    return _MockSupport(catalog=CATALOG, settings=SimulationSettings, error=DeviceError)


def _mock_catalog() -> Mapping[str, Any] | None:
    support = _mock_support()
    return None if support is None else support.catalog


def _check_addresses(resolved: ResolvedDevices, out: Collector) -> dict[str, Any] | None:
    """Every device of the profile (*resolved* past the mistakes reported above); None when even that stops.

    The list's own errors (a service with no address, two services on one device) are reported here.
    """
    from u2sa_hw.profile.vehicle import ProfileError

    exc = resolved.error   # ProfileError, or a service's ConfigError while reading its devices
    if exc is not None:
        stopped_at = "devices." if isinstance(exc, ProfileError) else "services."
        missing = re.search(r"device '([^']+)' of service '[^']+' has no address", str(exc))
        told = f"no address: add [devices.{missing.group(1)}]" if missing else None   # by the driver's own check
        if not any(p.is_error and (p.key.startswith(stopped_at) or (told and told in p.message))
                   for p in out.problems):
            out.from_text(str(exc), key="devices", fix="write the address as docs/ports.md shows")
        return None
    _check_unused(resolved.entries, resolved.profile, out)
    _check_shared_outputs(resolved.entries, out)
    return resolved.entries


def _check_unused(entries: Mapping[str, Any], profile: Any, out: Collector) -> None:
    """A ``[devices.NAME]`` address no enabled service opens: most likely a misspelt ``device`` setting
    (a table named after a disabled service, or naming one, is that service's and no warning)."""
    import difflib

    disabled = {name for name, spec in profile.services.items() if not spec.enabled}
    for name, entry in entries.items():
        if entry.used or name in disabled or entry.service in disabled:
            continue
        users = [f"{e.service} (device '{e.name}')" for e in entries.values() if e.used and e.service]
        close = difflib.get_close_matches(name, [e.name for e in entries.values() if e.used], n=1)
        hint = f"; did a service mean device = \"{name}\" instead of '{close[0]}'?" if close else ""
        out.warning(f"devices.{name}", f"address {entry.address.url} is used by no enabled service{hint}",
                    f"set device = \"{name}\" in the service that drives it, or remove the table "
                    f"(services with devices: {', '.join(users) or 'none'})")


def _check_shared_outputs(entries: Mapping[str, Any], out: Collector) -> None:
    """Two devices (of any services) on one PWM output: sysfs and a PCA9685 have no exclusivity, so two
    drivers would fight over one ESC line."""
    seen: dict[tuple[Any, ...], Any] = {}
    for name, entry in entries.items():
        if entry.address.kind not in ("pwm", "pca9685") or not entry.used:
            continue
        key = entry.address.output_id
        other = seen.setdefault(key, entry)
        if other is not entry:
            out.error(f"devices.{name}", f"device '{name}' (service '{entry.service}') and device '{other.name}' "
                      f"(service '{other.service}') are one output: {entry.address.url} and {other.address.url}",
                      "give each actuator its own channel")


def _check_mocks(entries: Mapping[str, Any] | None, profile: Any, devices: Any, services: Mapping[str, Any],
                 out: Collector) -> None:
    """Simulation: every device of an enabled service has a mock; the error names the device and the mock kind.

    When the device list cannot be read at all, each driver service is judged by the device tables
    that belong to it (its own name, its ``device``, a table naming it with ``service =``): only a
    service none of whose tables has a mock is said to have none.
    """
    from u2sa_hw.registry import known_kinds

    if entries is None:
        kinds = known_kinds()
        tables = devices if isinstance(devices, dict) else {}
        for service, table in services.items():
            if not isinstance(table, dict) or table.get("enabled", True) is False or \
                    not str(kinds.get(table.get("kind"), "")).startswith(DRIVER_PREFIX):
                continue
            device = table.get("device") if isinstance(table.get("device"), str) else service
            own = [t for n, t in tables.items() if isinstance(t, dict) and (n in (device, service)
                                                                            or t.get("service") == service)]
            if not any(t.get("mock") for t in own):
                _no_mock(out, device, service, table.get("kind"), key=f"devices.{device}" if device in tables
                         else f"services.{service}")
        return
    for device, entry in entries.items():
        spec = profile.services.get(entry.service)
        if spec is None or not spec.enabled or entry.mock or not entry.used:
            continue
        _no_mock(out, device, entry.service, spec.kind,
                 key=f"devices.{device}" if entry.table else f"services.{entry.service}")


def mock_for_kind(kind: Any) -> str:
    """The mock kind that usually stands in for the device of a service of *kind*, as its driver declares
    (``"..."`` when it declares none, or the kind is unknown: the profile check reports that)."""
    from u2sa_hw.ports.declared import declared_class, mock_kinds

    try:
        kinds = mock_kinds(declared_class(str(kind)))
    except LookupError:
        return "..."
    return kinds[0] if kinds else "..."


def _no_mock(out: Collector, device: str, service: str, kind: Any, *, key: str) -> None:
    mock = mock_for_kind(kind)
    out.error(key, f"device '{device}' of service '{service}' ({kind}) has no mock, so in simulation the "
              "service would wait for hardware that is not there",
              f"add mock = \"{mock}\" to [devices.{device}] (u2sa mock --list-kinds), or enabled = false "
              f"in [services.{service}]")


def _check_can_bitrates(entries: Mapping[str, Any], profile: Any, out: Collector) -> None:
    """A real SocketCAN address without ``bitrate=``: install cannot bring the interface up at boot."""
    for name, entry in entries.items():
        address = entry.address
        spec = profile.services.get(entry.service)
        if address.kind != "can" or address.mock or address.can_interface != "socketcan" or address.bitrate \
                or not entry.used or spec is None or not spec.enabled:
            continue
        key = f"devices.{name}.address"
        out.warning(key, f"CAN interface {address.can_channel} has no bitrate: u2sa install cannot set it, so "
                    f"{address.can_channel} does not come up at boot (the service waits for it) unless something "
                    "else configures it",
                    f"add the bus's bit rate to the address, e.g. {address.with_params(bitrate=500000).url} "
                    "(every node on the bus uses the same one; docs/deployment.md)")


def check_simulation(path: Path, data: Mapping[str, Any], out: Collector) -> None:
    """``[simulation]``: each unknown key (with a did-you-mean), then the rest as the mock launcher reads it."""
    from u2sa_hw.profile.loader import SIMULATION_KEYS, SIMULATION_START_KEYS

    table = data.get("simulation")
    if isinstance(table, dict):
        table = _known_keys(table, SIMULATION_KEYS, "simulation", out)
        if isinstance(table.get("start"), dict):
            table["start"] = _known_keys(table["start"], SIMULATION_START_KEYS, "simulation.start", out)
    support = _mock_support()
    if support is None:
        return
    try:
        support.settings.from_table(table, where=str(path))
    except support.error as exc:
        out.from_text(str(exc), key="simulation", fix="see docs/simulation.md")


def _known_keys(table: Mapping[str, Any], known: tuple[str, ...], key: str, out: Collector) -> dict[str, Any]:
    """*table* without its unknown keys, each reported once with a did-you-mean."""
    for name in table:
        if name not in known:
            out.error(f"{key}.{name}", f"unknown key '{name}'{did_you_mean(name, known)}", f"known: {', '.join(known)}")
    return {name: value for name, value in table.items() if name in known}
