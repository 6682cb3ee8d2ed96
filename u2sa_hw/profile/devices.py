"""The devices of a vehicle profile: one ``[devices.NAME]`` table, one address, per device.

```toml
[devices.gps]
address = "serial:///dev/u2sa/gps?baud=9600&usb=1546:01a7"   # docs/ports.md has the grammar
mock = "nmea_gps"            # what stands in for it in simulation (u2sa mock --list-kinds)
options = { rate_hz = 5 }    # the mock's own keyword options
service = "gps"              # optional: the service that uses it (default: found from the services)

[services.gps]
kind = "gps_nmea"
device = "gps"               # default: the service's name (a setting like any other)
```

API (stable; ``u2sa check``, install, udev generation, the simulation and replay build on it):

- :func:`profile_devices` ``(profile) -> dict[str, DeviceEntry]``: every device, with its
  parsed :class:`~u2sa_hw.ports.address.DeviceAddress`, the service that uses it, its mock.
- :class:`DeviceEntry`: ``name``, ``address``, ``service``, ``mock``, ``options``, ``sides``,
  ``drives``, ``legacy`` (True when the address came from old-form service settings), ``used``
  (False for an address no enabled service opens: ``u2sa check`` warns about it).
- :func:`service_devices` ``(kind_class, service, config)``: the devices one service uses.
- :func:`effective_config` ``(profile, service)``: the config a service will run with.

Which devices a service uses, and (for old-form profiles) their address, is declared by the
driver: a service class with a ``used_devices(service, config) -> {device: legacy address
or None}`` classmethod (:class:`u2sa_hw.ports.device_link.DeviceLink` documents it). Nothing
here knows a driver's setting names. An old-form profile (the address in the service's
``port``/``bus``/``interface``/``chip``/``channels`` settings) keeps loading: the address is
derived from those and one warning per device shows the new form. A ``[devices.NAME]`` table
of the old form that names a service using several devices (a ``pwm_servo`` with channels)
lends its ``mock`` to each of them.
"""

from __future__ import annotations

import difflib
import logging
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

from u2sa_hw.ports.address import AddressError, DeviceAddress, parse_address
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

log = logging.getLogger(__name__)

DEVICE_KEYS = ("address", "mock", "service", "options", "sides", "drives")
LEGACY_DEVICE_KEYS = ("usb", "can")   # udev identity and CAN bitrate of the old form (now address parameters)
# old-form tables naming one of several devices of a service: which address kind a mock kind stands in for
_GROUP_MOCK_KINDS = {"pca9685": "pca9685", "sysfs_pwm": "pwm"}


@dataclass(frozen=True)
class DeviceEntry:
    """One device of the profile."""

    name: str
    address: DeviceAddress
    service: str = ""                      # the service that uses it ("" when none does)
    mock: str | None = None                # the mock kind that stands in for it in simulation
    options: dict[str, Any] = field(default_factory=dict)
    sides: tuple[str, ...] = ()            # CAN motor mocks: the side each controller drives
    drives: dict[str, str] = field(default_factory=dict)   # actuator -> vehicle model input
    legacy: bool = False                   # the address came from old-form service settings
    table: str = ""                        # the [devices.X] table it was read from ("" when none)
    used: bool = True                      # an enabled service opens it (False: an address nothing opens)


def effective_config(profile: VehicleProfile, name: str) -> dict[str, Any]:
    """What service *name* will run with: its kind's defaults, the profile settings, its config file."""
    from u2sa_hw.config.configurator import Configurator
    from u2sa_hw.registry import resolve_kind
    from u2sa_hw.service.base_config import BASE_CONFIG

    spec = profile.service(name)
    try:
        cls = resolve_kind(spec.kind)
    except LookupError as exc:
        raise ProfileError(f"{profile.path} [services.{name}]: {exc}") from None
    quiet = logging.getLogger("u2sa_hw.profile.devices.config")
    quiet.addHandler(logging.NullHandler())
    quiet.propagate = False
    config = Configurator(spec.config_path, (*BASE_CONFIG, *cls.config_fields()), logger=quiet,
                          initial=spec.settings)
    return {field_name: value for field_name, _type, value in config.enumerate()}


def service_devices(cls: type, service: str, config: Mapping[str, Any]) -> dict[str, str | None]:
    """The devices service *service* of class *cls* uses: name -> old-form address text (or None)."""
    used = getattr(cls, "used_devices", None)
    return dict(used(service, config)) if used is not None else {}


def _where(profile: VehicleProfile, table: str) -> str:
    return f"{profile.path or 'profile'} [devices.{table}]"


def check_table(profile: VehicleProfile, name: str, table: Mapping[str, Any]) -> None:
    """ProfileError for an unknown key (with a did-you-mean) or a wrong-typed value in ``[devices.NAME]``."""
    for key in table:
        if key in DEVICE_KEYS or key in LEGACY_DEVICE_KEYS:
            continue
        close = difflib.get_close_matches(key, DEVICE_KEYS, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise ProfileError(f"{_where(profile, name)}: unknown key '{key}'; {hint}a device table takes "
                           f"{', '.join(DEVICE_KEYS)}")
    types = {"address": str, "mock": str, "service": str, "options": dict, "sides": list, "drives": dict}
    for key, kind in types.items():
        if key in table and not isinstance(table[key], kind):
            raise ProfileError(f"{_where(profile, name)}: {key} must be a {kind.__name__}, "
                               f"not {type(table[key]).__name__} ({table[key]!r})")


def _fold_legacy_keys(text: str, table: Mapping[str, Any], name: str) -> str:
    """Old-form ``usb = {vendor, product, serial}`` / ``can = {bitrate}`` into address parameters."""
    address = parse_address(text, device=name)
    extra: dict[str, Any] = {}
    usb = table.get("usb")
    if isinstance(usb, dict) and address.kind == "serial":
        if usb.get("vendor") and usb.get("product") and "usb" not in address.params:
            extra["usb"] = f"{str(usb['vendor']).lower()}:{str(usb['product']).lower()}"
        if usb.get("serial") and "serial" not in address.params:
            extra["serial"] = str(usb["serial"])
    can = table.get("can")
    if isinstance(can, dict) and address.kind == "can" and can.get("bitrate") and "bitrate" not in address.params:
        extra["bitrate"] = int(can["bitrate"])
    return address.with_params(**extra).url if extra else text


def _usage(profile: VehicleProfile, configs: Mapping[str, Mapping[str, Any]] | None
           ) -> dict[str, tuple[str, str | None]]:
    """device -> (service, old-form address) over the enabled services; two users are an error."""
    from u2sa_hw.registry import resolve_kind

    owners: dict[str, tuple[str, str | None]] = {}
    for service, spec in profile.services.items():
        if not spec.enabled:
            continue
        try:
            cls = resolve_kind(spec.kind)
        except (LookupError, ImportError):
            continue   # an unknown kind is the profile check's error, not a device's
        if not hasattr(cls, "used_devices"):
            continue
        config = configs[service] if configs is not None and service in configs else effective_config(profile, service)
        for device, legacy in service_devices(cls, service, config).items():
            if device in owners and owners[device][0] != service:
                raise ProfileError(f"{profile.path} [services.{service}]: device '{device}' is also used by service "
                                   f"'{owners[device][0]}'; give each service its own device (device = \"...\")")
            owners[device] = (service, legacy)
    return owners


def profile_devices(profile: VehicleProfile, *, configs: Mapping[str, Mapping[str, Any]] | None = None,
                    warn: Callable[[str], None] | None = None) -> dict[str, DeviceEntry]:
    """Every device of *profile* (see the module docstring); ProfileError names the table and the fix.

    *configs* (service -> effective config) saves reading each service's config again;
    *warn* receives the one-line notice for each device given in the old form (default: log).
    """
    warn = warn or log.warning
    tables = {name: table for name, table in profile.devices.items()}
    for name, table in tables.items():
        check_table(profile, name, table)
        service = table.get("service")
        if service is not None and service not in profile.services:
            raise ProfileError(f"{_where(profile, name)}: service = '{service}' is not a service of the profile "
                               f"(services: {', '.join(profile.services) or 'none'})")
    owners = _usage(profile, configs)
    groups = {name: table for name, table in tables.items() if name not in owners and "address" not in table
              and table.get("service", name) in profile.services}
    entries: dict[str, DeviceEntry] = {}
    for device, (service, legacy) in owners.items():
        table = tables.get(device)
        group_name = ""
        if table is None:
            table, group_name = _group_for(groups, service, legacy, device) or ({}, "")
        text = table.get("address") if group_name == "" else None
        from_legacy = not text
        if not text:
            text = legacy
        where = _where(profile, group_name or device)
        if not text:
            raise ProfileError(f"{where}: device '{device}' of service '{service}' has no address; add "
                               f"[devices.{device}] address = \"...\" (docs/ports.md lists the forms: serial://, "
                               f"can://, i2c://, gpio://, pwm://, pca9685://){_did_you_mean(device, tables)}")
        try:
            if from_legacy:
                text = _fold_legacy_keys(text, table, device)
            address = parse_address(text, device=device)
        except AddressError as exc:
            raise ProfileError(f"{where}: {exc}") from None
        if from_legacy:
            named = ("" if device == service else
                     f" and name it in the service (device = \"{device}\"; a pwm_servo: in its channel's table)")
            warn(f"{profile.path} [services.{service}]: device '{device}' is given in the old form (service "
                 f"settings); write [devices.{device}] address = \"{address.url}\"{named}")
        entries[device] = _entry(device, address, service, table, from_legacy, group_name or
                                 (device if device in tables else ""))
    for name, table in tables.items():
        if name in entries or name in groups and _serves(entries, groups[name].get("service", name)):
            continue   # a device, or an old-form table lending its mock to the devices of its service
        if "address" not in table:
            if "mock" not in table and any(k in table for k in LEGACY_DEVICE_KEYS):
                continue   # an old-form udev/CAN table of a device no service names: nothing to open
            service = table.get("service", name)
            raise ProfileError(f"{_where(profile, name)}: no address, and service '{service}' uses no device "
                               f"of this name; add address = \"...\" (docs/ports.md) or set service = \"...\" "
                               "to the service that uses it")
        try:
            address = parse_address(table["address"], device=name)
        except AddressError as exc:
            raise ProfileError(f"{_where(profile, name)}: {exc}") from None
        entries[name] = replace(_entry(name, address, str(table.get("service", "")), table, False, name), used=False)
    return entries


def _group_for(groups: Mapping[str, Mapping[str, Any]], service: str, legacy: str | None,
               device: str) -> tuple[Mapping[str, Any], str] | None:
    """The old-form table that lends its mock to *device* of *service* (matched by address kind)."""
    candidates = [(n, t) for n, t in groups.items() if t.get("service", n) == service]
    if len(candidates) > 1 and legacy:
        try:
            kind = parse_address(legacy, device=device).kind
        except AddressError:
            kind = ""
        candidates = [(n, t) for n, t in candidates if _GROUP_MOCK_KINDS.get(str(t.get("mock")), kind) == kind]
    if not candidates:
        return None
    name, table = candidates[0]
    return table, name


def _did_you_mean(device: str, tables: Mapping[str, Any]) -> str:
    """`` or set device = "winch" (a [devices.winch] table exists)`` for a near miss, else ``""``."""
    close = difflib.get_close_matches(device, [n for n, t in tables.items() if isinstance(t, dict)
                                               and t.get("address")], n=1)
    return (f", or name the device that has one (did you mean device = \"{close[0]}\"? [devices.{close[0]}] "
            "has an address)") if close else ""


def _serves(entries: Mapping[str, DeviceEntry], service: str) -> bool:
    return any(e.service == service for e in entries.values())


def _entry(name: str, address: DeviceAddress, service: str, table: Mapping[str, Any], legacy: bool,
           table_name: str) -> DeviceEntry:
    sides = table.get("sides") or ()
    return DeviceEntry(name=name, address=address, service=service, mock=table.get("mock"),
                       options=dict(table.get("options") or {}), sides=tuple(str(s) for s in sides),
                       drives={str(k): str(v) for k, v in (table.get("drives") or {}).items()}, legacy=legacy,
                       table=table_name)


def device_address(profile: VehicleProfile, device: str, legacy: str | None) -> DeviceAddress:
    """The address a driver opens for *device*: ``[devices.DEVICE] address``, else the old-form *legacy* one.

    Raises AddressError (a ValueError naming the device and the fix) when neither is given or
    the text is wrong.
    """
    table = profile.devices.get(device) if profile.devices else None
    text = table.get("address") if isinstance(table, dict) else None
    if not text:
        text = legacy
    if not text:
        raise AddressError(device, "", f"no address: add [devices.{device}] address = \"...\" to the vehicle "
                           f"profile{_did_you_mean(device, profile.devices or {})}")
    return parse_address(text, device=device)
