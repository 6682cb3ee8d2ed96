"""Every registered driver declares to the rest of the system through the typed base
(:class:`u2sa_hw.ports.declared.DeviceDeclarations`), never by attribute conventions: it derives
from the base, names the devices it opens and the mocks that stand in for them, and the
readers in ``u2sa_hw.ports.declared`` call those declarations directly. A class that does not
derive from the base, or derives but declares nothing, is caught here."""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

import pytest

from u2sa_hw import registry
from u2sa_hw.mocks.catalog import CATALOG
from u2sa_hw.ports import declared
from u2sa_hw.ports.declared import DeviceDeclarations

DRIVER_PREFIX = "u2sa_hw.drivers."
DRIVER_KINDS = sorted(kind for kind, target in registry.SERVICE_KINDS.items() if target.startswith(DRIVER_PREFIX))
OVERRIDDEN = ("used_devices", "mock_wiring", "probe_expectation")   # every driver says these itself


def declaration_problems(cls: object) -> list[str]:
    """What *cls* fails of the driver declaration contract, one line each ([]: it keeps it)."""
    name = getattr(cls, "__name__", repr(cls))
    if not declared.declares_devices(cls):
        return [f"{name} does not derive from DeviceDeclarations (u2sa_hw/ports/declared.py)"]
    assert isinstance(cls, type) and issubclass(cls, DeviceDeclarations)
    problems = [f"{name} does not declare {method} (the base declares nothing)" for method in OVERRIDDEN
                if getattr(cls, method).__func__ is getattr(DeviceDeclarations, method).__func__]
    if not cls.MOCK_KINDS:
        problems.append(f"{name} names no MOCK_KINDS")
    problems += [f"{name}: MOCK_KINDS names {kind!r}, not a CATALOG mock kind" for kind in cls.MOCK_KINDS
                 if kind not in CATALOG]
    return problems


def test_the_registry_has_drivers_to_check() -> None:
    assert {"gps_nmea", "compass_serial", "imu_mpu9250", "imu_bno055", "pwm_servo", "rc_mux", "gpio_output",
            "gpio_input", "odrive_can", "vesc_can"} <= set(DRIVER_KINDS)


@pytest.mark.parametrize("kind", DRIVER_KINDS)
def test_every_registered_driver_keeps_the_declaration_contract(kind: str) -> None:
    assert declaration_problems(registry.resolve_kind(kind)) == []


@pytest.mark.parametrize("kind", DRIVER_KINDS)
def test_every_declaration_answers_in_its_declared_types(kind: str) -> None:
    cls = registry.resolve_kind(kind)
    config = declared.with_defaults(cls, {})
    used = declared.used_devices(cls, "svc", config)
    assert all(isinstance(device, str) and device for device in used)
    assert isinstance(declared.mock_kinds(cls), tuple)
    assert isinstance(declared.probe_expectation(cls, {}), dict)
    assert isinstance(declared.replay_options(cls, "svc", {}), dict)


class NotADriver:
    """A class with the old attribute conventions but not the typed base."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("nmea_gps",)

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        return (service,)


class DeclaresNothing(DeviceDeclarations):
    """Derives from the base and declares nothing of its own."""


class WrongMock(DeviceDeclarations):
    """Declares everything, but a mock kind the catalog does not have."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("no_such_mock",)

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        return (service,)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        return {}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        return {}


def test_a_class_without_the_typed_base_fails_the_contract() -> None:
    assert declaration_problems(NotADriver) == [
        "NotADriver does not derive from DeviceDeclarations (u2sa_hw/ports/declared.py)"]


def test_a_class_that_declares_nothing_fails_the_contract() -> None:
    assert declaration_problems(DeclaresNothing) == [
        "DeclaresNothing does not declare used_devices (the base declares nothing)",
        "DeclaresNothing does not declare mock_wiring (the base declares nothing)",
        "DeclaresNothing does not declare probe_expectation (the base declares nothing)",
        "DeclaresNothing names no MOCK_KINDS"]


def test_a_mock_kind_the_catalog_lacks_fails_the_contract() -> None:
    assert declaration_problems(WrongMock) == ["WrongMock: MOCK_KINDS names 'no_such_mock', not a CATALOG mock kind"]


def test_the_readers_ignore_attribute_conventions_on_a_class_without_the_base() -> None:
    """The old getattr reading would have taken NotADriver's MOCK_KINDS and used_devices; the typed readers
    take only what the base declares, so a service that is not a driver declares nothing."""
    assert declared.mock_kinds(NotADriver) == ()
    assert declared.used_devices(NotADriver, "gps", {}) == ()
    assert declared.mock_wiring(NotADriver, "gps", "gps", {}) == {}
    assert declared.probe_expectation(NotADriver, {}) == {}
    assert declared.replay_options(NotADriver, "gps", {}) == {}


def test_a_service_that_is_not_a_driver_declares_nothing() -> None:
    control = registry.resolve_kind("control")
    assert not declared.declares_devices(control)
    assert declared.mock_kinds(control) == () and declared.used_devices(control, "control", {}) == ()
