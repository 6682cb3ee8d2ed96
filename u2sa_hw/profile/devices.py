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

API (stable; drivers, ``u2sa check``, install, udev generation, the mock launcher and replay
build on it). One resolver reads every profile's devices, for every user:

- :func:`resolve_devices` ``(profile, *, configs, strict, skip_old_form) -> ResolvedDevices``:
  every device of a :class:`~u2sa_hw.profile.vehicle.VehicleProfile` or of a profile's raw TOML
  data (a log's recorded profile), as :class:`DeviceEntry` with its typed address and the
  service that uses it. Strict (the default), a mistake is one ProfileError or AddressError
  naming the table and the fix; lenient (``strict=False``, ``u2sa check`` and replay), the
  devices whose address does not parse are left out (``bad``), the services that use them too,
  and what still stops the rest is kept as ``error`` instead of raised.
- :func:`profile_devices` ``(profile) -> dict[str, DeviceEntry]``: the strict resolution's entries.
- :func:`device_address` ``(profile, device)``: one device's address, the one a driver opens
  (``DeviceLink.resolve``).
- :class:`DeviceEntry`: ``name``, ``address``, ``service``, ``mock``, ``options``, ``sides``,
  ``drives``, ``used`` (False for an address no enabled service opens: ``u2sa check`` warns
  about it).
- :func:`service_devices` ``(kind_class, service, config)``: the devices one service uses.
- :func:`effective_config` ``(profile, service)``: the config a service will run with.

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
from typing import Any, Mapping, Union

from u2sa_hw.ports.address import AddressError, DeviceAddress, parse_address
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

DEVICE_KEYS = ("address", "mock", "service", "options", "sides", "drives")
DEVICE_KEY_TYPES: dict[str, type] = {"address": str, "mock": str, "service": str, "options": dict, "sides": list,
                                     "drives": dict}
Source = Union[VehicleProfile, Mapping[str, Any]]   # a loaded profile, or a profile's raw TOML data


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
    for key, kind in DEVICE_KEY_TYPES.items():
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


@dataclass(frozen=True)
class ResolvedDevices:
    """What :func:`resolve_devices` found.

    ``entries``: device -> its :class:`DeviceEntry`. ``users``: device -> every service that uses it (raw
    data: a recorded profile's claims, two users included). Lenient only: ``bad``, the devices whose
    address does not parse (left out); ``profile``, the profile read past them (their users disabled);
    ``error``, what stopped the resolution of the rest (``entries`` is then empty).
    """

    entries: dict[str, DeviceEntry]
    users: dict[str, tuple[str, ...]] = field(default_factory=dict)
    bad: frozenset[str] = frozenset()
    profile: VehicleProfile | None = None
    error: ValueError | None = None


def resolve_devices(profile: Source, *, configs: Mapping[str, Mapping[str, Any]] | None = None,
                    strict: bool = True, skip_old_form: bool = False) -> ResolvedDevices:
    """Every device of *profile*, a loaded :class:`VehicleProfile` or a profile's raw TOML data.

    *configs* (service -> effective config) saves reading each service's config again; lenient,
    pass ``u2sa_hw.check.lenient.readable_configs`` so a service with a wrong setting still names its
    devices. *strict*: a mistake raises (ProfileError, AddressError, a service's ConfigError), each
    naming the table and the fix. Lenient: see :class:`ResolvedDevices`; the services still given an
    address setting of the old form (``port``, ``bus``...: the services check names the new form)
    are left out, as *skip_old_form* leaves them out of a strict resolution (install's).

    Raw data is a recorded profile (a log's ``vehicle.toml``, with *configs* for every service
    table): every service of it counts, enabled or not, and a service claims its own name too (and,
    without a kind to ask, the names its ``device``/``device_name`` settings and channel lists give);
    ``users`` lists each device's claimants, and an address that does not parse is left out (lenient)
    or an AddressError (strict).
    """
    if not isinstance(profile, VehicleProfile):
        return _recorded(profile, configs or {}, strict=strict)
    if strict:
        source = _without_old_form(profile) if skip_old_form else profile
        entries = profile_devices(source, configs=configs)
        return ResolvedDevices(entries, users={n: (e.service,) for n, e in entries.items() if e.service})
    return _lenient(profile, configs or {})


def _lenient(profile: VehicleProfile, configs: Mapping[str, Mapping[str, Any]]) -> ResolvedDevices:
    """The lenient resolution of a loaded profile (see :func:`resolve_devices`)."""
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
            services[name] = replace(spec, enabled=False)
    kept = {name: table for name, table in tables.items() if name not in bad}
    readable = replace(profile, devices=kept, services=services)
    try:
        entries = profile_devices(readable, configs=configs)
    except ValueError as exc:   # ProfileError, or a service's ConfigError while reading its devices
        return ResolvedDevices({}, bad=frozenset(bad), profile=readable, error=exc)
    return ResolvedDevices(entries, users={n: (e.service,) for n, e in entries.items() if e.service},
                           bad=frozenset(bad), profile=readable)


def _recorded(data: Mapping[str, Any], configs: Mapping[str, Mapping[str, Any]], *, strict: bool) -> ResolvedDevices:
    """The devices of a recorded profile's raw TOML *data* (see :func:`resolve_devices`)."""
    services = data.get("services") if isinstance(data.get("services"), dict) else {}
    kinds = {n: t["kind"] for n, t in services.items() if isinstance(t, dict) and isinstance(t.get("kind"), str)}
    users: dict[str, list[str]] = {}
    for service, config in configs.items():
        for device in sorted(_claims(service, kinds.get(service), config)):
            users.setdefault(device, []).append(service)
    entries: dict[str, DeviceEntry] = {}
    bad: set[str] = set()
    for name, table in _tables(data).items():
        if not isinstance(table, dict) or not table.get("address"):
            continue
        try:
            address = device_address(data, name)
        except AddressError:
            if strict:
                raise
            bad.add(name)
            continue
        owners = users.get(name, [])
        entries[name] = _entry(name, address, owners[0] if len(owners) == 1 else "", table)
    return ResolvedDevices(entries, users={d: tuple(sorted(s)) for d, s in users.items()}, bad=frozenset(bad))


def _claims(service: str, kind: str | None, config: Mapping[str, Any]) -> set[str]:
    """The device names a recorded *service* (of *kind*) with *config* taps under: its own name and what
    its driver declares; without a kind to ask, the names its settings give."""
    from u2sa_hw.registry import resolve_kind

    names = {service}
    if kind:
        try:
            names.update(service_devices(resolve_kind(kind), service, config))
        except (LookupError, ImportError):
            pass
    else:
        device = config.get("device") or config.get("device_name")
        if isinstance(device, str) and device.strip():
            names.add(device.strip())
        for value in config.values():
            if isinstance(value, list):
                names.update(str(v.get("device") or v["name"]) for v in value
                             if isinstance(v, dict) and isinstance(v.get("name"), str))
    return names


def clean_device_tables(tables: Any, *, services: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Each ``[devices.NAME]`` table with only the keys a device table takes, of the right type, and a
    ``service`` that is one of *services* (``u2sa check`` reports the rest)."""
    kept: dict[str, dict[str, Any]] = {}
    for name, table in (tables.items() if isinstance(tables, dict) else ()):
        if not isinstance(table, dict):
            continue
        kept[name] = {k: v for k, v in table.items() if k in DEVICE_KEY_TYPES and isinstance(v, DEVICE_KEY_TYPES[k])}
        if kept[name].get("service") is not None and kept[name]["service"] not in services:
            del kept[name]["service"]
    return kept


def _without_old_form(profile: VehicleProfile) -> VehicleProfile:
    """*profile* with the services still given an old-form address setting disabled."""
    from u2sa_hw.registry import resolve_kind

    services = dict(profile.services)
    for name, spec in profile.services.items():
        try:
            old = spec.enabled and _old_form(spec, resolve_kind(spec.kind))
        except (LookupError, ImportError, AttributeError):
            continue
        if old:
            services[name] = replace(spec, enabled=False)
    return replace(profile, services=services)


def _old_form(spec: Any, cls: type) -> bool:
    """True when service *spec* (of class *cls*) is still given an address setting of the old form, in its
    profile settings or its config file (a file that does not read gives none)."""
    from u2sa_hw.config.keys import old_form_keys
    from u2sa_hw.service.base_config import BASE_CONFIG

    fields = [f.name for f in (*BASE_CONFIG, *cls.config_fields())]
    return any(old_form_keys(values, fields) for values in (dict(spec.settings), spec.file_settings()))


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


def _tables(profile: Source) -> Mapping[str, Any]:
    """The ``[devices]`` tables of a loaded profile or of raw TOML data."""
    if isinstance(profile, VehicleProfile):
        return profile.devices or {}
    tables = profile.get("devices")
    return tables if isinstance(tables, dict) else {}


def device_address(profile: Source, device: str) -> DeviceAddress:
    """The address a driver opens for *device*: ``[devices.DEVICE] address`` of *profile* (loaded, or raw
    TOML data).

    Raises AddressError (a ValueError naming the device and the fix) when it is not given or
    the text is wrong.
    """
    tables = _tables(profile)
    table = tables.get(device)
    text = table.get("address") if isinstance(table, dict) else None
    if not text:
        raise AddressError(device, "", f"no address: add [devices.{device}] address = \"...\" to the vehicle "
                           f"profile{_did_you_mean(device, tables)}")
    return parse_address(text, device=device)
