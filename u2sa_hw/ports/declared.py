"""What a driver declares about its device for the rest of the system: a typed base, read by service kind.

Nothing outside a driver reads a driver's setting names (DESIGN.md section 4): the mock
catalog, replay, install and ``u2sa check`` (its probe, its "no mock" fix) ask the driver
class, found by service kind through the registry (:func:`u2sa_hw.registry.resolve_kind`),
and get values in their own vocabulary. Every hardware driver class derives from
:class:`DeviceDeclarations` and overrides what applies to it::

    class GpsNmeaDriver(SerialLineSensor):           # SerialLineSensor derives from DeviceDeclarations
        MOCK_KINDS = ("nmea_gps",)                   # the mocks that stand in for its device, usual first
        @classmethod
        def used_devices(cls, service, config) -> tuple[str, ...]: ...    # the devices it opens
        @classmethod
        def mock_wiring(cls, service, device, config) -> Mapping[str, Any]: ...
        @classmethod
        def probe_expectation(cls, config) -> Mapping[str, Any]: ...
        @classmethod
        def replay_options(cls, device, config) -> Mapping[str, Any]: ...

The base's defaults declare nothing (no devices, no mocks, empty mappings), so a service that
is not a driver (``control``, a mission) is read the same way and gives nothing. The module
functions below call the declarations with the service's config with the class's field
defaults under it (what the service runs with, :func:`with_defaults`), so a profile that
leaves a setting at its default gets the driver's default, never a guess of the caller's.
The keys each mapping may hold are listed in docs/ports.md ("Driver declarations"). A mock
wiring may give, under :data:`SOURCES`, the setting each value comes from, for the caller's
messages only (``{"protocol": "format"}``). ``tests/test_driver_declarations_typed.py`` checks
that every registered driver derives from the base and declares its devices and mocks.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

SOURCES = "sources"   # mock wiring key: value key -> the setting it comes from (for messages only)


class DeviceDeclarations:
    """The typed declarations of a driver class; each default declares nothing (see the module docstring)."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ()
    """The ``CATALOG`` mock kinds that stand in for the driver's device, the usual one first."""

    IDENTITY_REGISTER: ClassVar[int | None] = None
    """An I2C driver's chip identity register, the first register it reads when it sets its chip up: a log
    holds that set-up (and a replay can identify the chip) only when its device's first record reads it."""

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        """The names of the devices service *service* opens (their ``[devices.NAME]`` tables), in order."""
        return ()

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> Mapping[str, Any]:
        """What a mock of *device* must mirror of the driver's wiring (lines, ids, pulse range), in the mocks'
        vocabulary; a ConfigError (a ValueError) names the setting and the fix."""
        return {}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> Mapping[str, Any]:
        """What ``u2sa check --probe`` expects at the device (a protocol, a chip and variant, node ids)."""
        return {}

    @classmethod
    def replay_options(cls, device: str, config: Mapping[str, Any]) -> Mapping[str, Any]:
        """How a replay feeds *device* (a serial device's ``burst_gap_s``)."""
        return {}


def declares_devices(cls: object) -> bool:
    """True when *cls* is a class deriving from :class:`DeviceDeclarations` (a driver)."""
    return isinstance(cls, type) and issubclass(cls, DeviceDeclarations)


def declarations(cls: type) -> type[DeviceDeclarations]:
    """*cls* when it is a driver, else the base (a service that is not a driver declares nothing)."""
    return cls if declares_devices(cls) else DeviceDeclarations


def declared_class(kind: str) -> type:
    """The service class of *kind* (LookupError lists the known kinds; a real ImportError is not hidden)."""
    from u2sa_hw.registry import resolve_kind   # the registry imports drivers lazily, only here

    return resolve_kind(kind)


def with_defaults(cls: type, config: Mapping[str, Any]) -> dict[str, Any]:
    """*config* over the defaults of the fields *cls* declares (a config file may leave any out)."""
    fields = getattr(cls, "config_fields", None)   # the service contract's, not a declaration
    defaults = {f.name: f.default for f in fields()} if fields is not None else {}
    return {**defaults, **config}


def used_devices(cls: type, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
    """The devices service *service* of class *cls* opens (*config* as given: the caller's is the effective one)."""
    return tuple(declarations(cls).used_devices(service, config))


def mock_kinds(cls: type) -> tuple[str, ...]:
    """The mock kinds that stand in for the device of a service of class *cls* (the usual one first)."""
    return tuple(declarations(cls).MOCK_KINDS)


def mock_wiring(cls: type, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
    """What a mock of *device* (of *service*, class *cls*) mirrors of the driver's wiring; ValueError
    (the driver's ConfigError) names the setting and the fix."""
    return dict(declarations(cls).mock_wiring(service, device, with_defaults(cls, config)))


def probe_expectation(cls: type, config: Mapping[str, Any]) -> dict[str, Any]:
    """What the driver of class *cls* expects at its device (``u2sa check --probe``)."""
    return dict(declarations(cls).probe_expectation(with_defaults(cls, config)))


def replay_options(cls: type, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
    """How a replay feeds *device* of a service of class *cls* (e.g. ``burst_gap_s``)."""
    return dict(declarations(cls).replay_options(device, with_defaults(cls, config)))


def source_of(wiring: Mapping[str, Any], key: str) -> str:
    """The setting a mock wiring's *key* comes from (for a message), else *key* itself."""
    sources = wiring.get(SOURCES)
    return str(sources.get(key, key)) if isinstance(sources, Mapping) else key
