"""What a driver declares about its device for the rest of the system, read by service kind.

Nothing outside a driver reads a driver's setting names (DESIGN.md section 4): the mock
catalog, replay and ``u2sa check`` (its probe, its "no mock" fix) ask the driver class,
found by service kind through the registry (:func:`u2sa_hw.registry.resolve_kind`), and
get values in their own vocabulary. Besides ``used_devices`` (see
:mod:`u2sa_hw.ports.device_link`) a driver class declares::

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("nmea_gps",)   # the mocks that stand in for its
                                                            # device (the usual one first)
    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> Mapping[str, Any]:
        # what a mock of *device* must mirror of the driver's wiring (lines, ids, pulse range);
        # a ValueError (ConfigError) names the setting and the fix
    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> Mapping[str, Any]:
        # what ``u2sa check --probe`` expects at the device (a protocol, a chip, node ids)
    @classmethod
    def replay_options(cls, device: str, config: Mapping[str, Any]) -> Mapping[str, Any]:
        # how a replay feeds the device (a serial device's burst gap)

Each is called with the service's config with the class's declared defaults under it (what
the service runs with, :func:`with_defaults`), so a profile that leaves a setting at its
default gets the driver's default, never a guess of the caller's. The keys each mapping may
hold are listed in docs/ports.md ("Driver declarations"). A mock wiring may give, under
:data:`SOURCES`, the setting each value comes from, for the caller's messages only
(``{"protocol": "format"}``). A class that declares nothing gets empty mappings and no mock
kinds.
"""

from __future__ import annotations

from typing import Any, Mapping

SOURCES = "sources"   # mock wiring key: value key -> the setting it comes from (for messages only)


def declared_class(kind: str) -> type:
    """The service class of *kind* (LookupError lists the known kinds; a real ImportError is not hidden)."""
    from u2sa_hw.registry import resolve_kind   # the registry imports drivers lazily, only here

    return resolve_kind(kind)


def with_defaults(cls: type, config: Mapping[str, Any]) -> dict[str, Any]:
    """*config* over the defaults of the fields *cls* declares (a config file may leave any out)."""
    fields = getattr(cls, "config_fields", None)
    defaults = {f.name: f.default for f in fields()} if fields is not None else {}
    return {**defaults, **config}


def mock_kinds(cls: type) -> tuple[str, ...]:
    """The mock kinds that stand in for the device of a service of class *cls* (the usual one first)."""
    return tuple(getattr(cls, "MOCK_KINDS", ()))


def mock_wiring(cls: type, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
    """What a mock of *device* (of *service*, class *cls*) mirrors of the driver's wiring; ValueError
    (the driver's ConfigError) names the setting and the fix."""
    declare = getattr(cls, "mock_wiring", None)
    return dict(declare(service, device, with_defaults(cls, config))) if declare is not None else {}


def probe_expectation(cls: type, config: Mapping[str, Any]) -> dict[str, Any]:
    """What the driver of class *cls* expects at its device (``u2sa check --probe``)."""
    declare = getattr(cls, "probe_expectation", None)
    return dict(declare(with_defaults(cls, config))) if declare is not None else {}


def replay_options(cls: type, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
    """How a replay feeds *device* of a service of class *cls* (e.g. ``burst_gap_s``)."""
    declare = getattr(cls, "replay_options", None)
    return dict(declare(device, with_defaults(cls, config))) if declare is not None else {}


def source_of(wiring: Mapping[str, Any], key: str) -> str:
    """The setting a mock wiring's *key* comes from (for a message), else *key* itself."""
    sources = wiring.get(SOURCES)
    return str(sources.get(key, key)) if isinstance(sources, Mapping) else key
