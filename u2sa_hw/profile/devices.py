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
  ``drives``, ``used`` (False for an address no enabled service opens: ``u2sa check`` warns
  about it).
- :func:`service_devices` ``(kind_class, service, config)``: the devices one service uses.
- :func:`effective_config` ``(profile, service)``: the config a service will run with.
- :func:`device_address` ``(profile, device)``: the address a driver opens for a device.

Which devices a service uses is declared by the driver: its ``used_devices(service, config)``
declaration (:class:`u2sa_hw.ports.declared.DeviceDeclarations`). Nothing here knows a driver's
setting names. Every device a service uses needs its own table with an address; the old
profile form (the address spread over the service's settings, ``usb``/``can`` tables beside
it) is retired: its keys are errors naming the new form (:mod:`u2sa_hw.config.keys`).
"""

from __future__ import annotations

import difflib
import logging
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

from u2sa_hw.ports.address import AddressError, DeviceAddress, parse_address
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

DEVICE_KEYS = ("address", "mock", "service", "options", "sides", "drives")


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


def service_devices(cls: type, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
    """The names of the devices service *service* of class *cls* uses; a service that is not a driver uses
    none (:mod:`u2sa_hw.ports.declared`)."""
    from u2sa_hw.ports.declared import used_devices

    return used_devices(cls, service, config)


def _where(profile: VehicleProfile, table: str) -> str:
    return f"{profile.path or 'profile'} [devices.{table}]"


def check_table(profile: VehicleProfile, name: str, table: Mapping[str, Any]) -> None:
    """ProfileError for an unknown key (with a did-you-mean; an old-form key: the new form) or a wrong-typed
    value in ``[devices.NAME]``."""
    from u2sa_hw.config.keys import old_device_key_fix

    for key in table:
        if key in DEVICE_KEYS:
            continue
        old = old_device_key_fix(key)
        if old is not None:
            raise ProfileError(f"{_where(profile, name)}: '{key}' is the old form: {old}")
        close = difflib.get_close_matches(key, DEVICE_KEYS, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise ProfileError(f"{_where(profile, name)}: unknown key '{key}'; {hint}a device table takes "
                           f"{', '.join(DEVICE_KEYS)}")
    types = {"address": str, "mock": str, "service": str, "options": dict, "sides": list, "drives": dict}
    for key, kind in types.items():
        if key in table and not isinstance(table[key], kind):
            raise ProfileError(f"{_where(profile, name)}: {key} must be a {kind.__name__}, "
                               f"not {type(table[key]).__name__} ({table[key]!r})")


def _usage(profile: VehicleProfile, configs: Mapping[str, Mapping[str, Any]] | None) -> dict[str, str]:
    """device -> the enabled service that uses it; two users are an error."""
    from u2sa_hw.ports.declared import declares_devices
    from u2sa_hw.registry import resolve_kind

    owners: dict[str, str] = {}
    for service, spec in profile.services.items():
        if not spec.enabled:
            continue
        try:
            cls = resolve_kind(spec.kind)
        except (LookupError, ImportError):
            continue   # an unknown kind is the profile check's error, not a device's
        if not declares_devices(cls):
            continue
        config = configs[service] if configs is not None and service in configs else effective_config(profile, service)
        for device in service_devices(cls, service, config):
            if owners.get(device, service) != service:
                raise ProfileError(f"{profile.path} [services.{service}]: device '{device}' is also used by service "
                                   f"'{owners[device]}'; give each service its own device (device = \"...\")")
            owners[device] = service
    return owners


def profile_devices(profile: VehicleProfile, *,
                    configs: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, DeviceEntry]:
    """Every device of *profile* (see the module docstring); ProfileError names the table and the fix.

    *configs* (service -> effective config) saves reading each service's config again.
    """
    tables = {name: table for name, table in profile.devices.items()}
    for name, table in tables.items():
        check_table(profile, name, table)
        service = table.get("service")
        if service is not None and service not in profile.services:
            raise ProfileError(f"{_where(profile, name)}: service = '{service}' is not a service of the profile "
                               f"(services: {', '.join(profile.services) or 'none'})")
    owners = _usage(profile, configs)
    entries: dict[str, DeviceEntry] = {}
    for device, service in owners.items():
        table = tables.get(device) or {}
        text = table.get("address")
        if not text:
            raise ProfileError(f"{_where(profile, device)}: device '{device}' of service '{service}' has no address; "
                               f"add [devices.{device}] address = \"...\" (docs/ports.md lists the forms: serial://, "
                               f"can://, i2c://, gpio://, pwm://, pca9685://){_did_you_mean(device, tables)}")
        entries[device] = _entry(device, _parsed(profile, device, text), service, table)
    for name, table in tables.items():
        if name in entries:
            continue
        if "address" not in table:
            service = table.get("service", name)
            raise ProfileError(f"{_where(profile, name)}: no address, and service '{service}' uses no device "
                               f"of this name; add address = \"...\" (docs/ports.md) or set service = \"...\" "
                               "to the service that uses it")
        entry = _entry(name, _parsed(profile, name, table["address"]), str(table.get("service", "")), table)
        entries[name] = replace(entry, used=False)
    return entries


def _parsed(profile: VehicleProfile, name: str, text: str) -> DeviceAddress:
    """The address of ``[devices.NAME]``; ProfileError names the table and what is wrong."""
    try:
        return parse_address(text, device=name)
    except AddressError as exc:
        raise ProfileError(f"{_where(profile, name)}: {exc}") from None


def _did_you_mean(device: str, tables: Mapping[str, Any]) -> str:
    """`` or set device = "winch" (a [devices.winch] table exists)`` for a near miss, else ``""``."""
    close = difflib.get_close_matches(device, [n for n, t in tables.items() if isinstance(t, dict)
                                               and t.get("address")], n=1)
    return (f", or name the device that has one (did you mean device = \"{close[0]}\"? [devices.{close[0]}] "
            "has an address)") if close else ""


def _entry(name: str, address: DeviceAddress, service: str, table: Mapping[str, Any]) -> DeviceEntry:
    sides = table.get("sides") or ()
    return DeviceEntry(name=name, address=address, service=service, mock=table.get("mock"),
                       options=dict(table.get("options") or {}), sides=tuple(str(s) for s in sides),
                       drives={str(k): str(v) for k, v in (table.get("drives") or {}).items()}, table=name)


def device_address(profile: VehicleProfile, device: str) -> DeviceAddress:
    """The address a driver opens for *device*: ``[devices.DEVICE] address``.

    Raises AddressError (a ValueError naming the device and the fix) when it is not given or
    the text is wrong.
    """
    table = profile.devices.get(device) if profile.devices else None
    text = table.get("address") if isinstance(table, dict) else None
    if not text:
        raise AddressError(device, "", f"no address: add [devices.{device}] address = \"...\" to the vehicle "
                           f"profile{_did_you_mean(device, profile.devices or {})}")
    return parse_address(text, device=device)
