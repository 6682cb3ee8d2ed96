"""The mock table: every mock kind is one line of ``MOCK_DEVICES`` naming a class its catalog builder can build
(issue 25: a new serial or CAN motor mock is its module and one table line, no branch in the catalog).

Walks :data:`u2sa_hw.registry.MOCK_DEVICES` with the catalog's own check (``entry_problems``) and shows
the check and the builders work from what a class declares, never from its kind's name.
"""

from __future__ import annotations

import subprocess
import sys
from typing import Any, Mapping

import pytest

from conftest import REPO
from u2sa_hw.mocks import catalog
from u2sa_hw.mocks.odrive_node import NODE_SPEED_MARGIN, OdriveCanNode
from u2sa_hw.mocks.vesc_node import VescCanNode
from u2sa_hw.registry import MOCK_DEVICES, MockEntry, resolve_mock

KINDS = sorted(MOCK_DEVICES)


@pytest.mark.parametrize("kind", KINDS)
def test_each_entry_imports_a_class_its_builder_can_build(kind: str) -> None:
    assert catalog.entry_problems(kind) == []
    assert isinstance(resolve_mock(kind), type)
    assert MOCK_DEVICES[kind].what.strip()
    assert catalog.CATALOG[kind] == (catalog.BUILDERS[MOCK_DEVICES[kind].build].build, MOCK_DEVICES[kind].what)


def test_the_table_names_each_class_as_module_and_class() -> None:
    for kind, entry in MOCK_DEVICES.items():
        module, sep, name = entry.target.partition(":")
        assert sep and module.startswith("u2sa_hw.mocks.") and name.isidentifier(), kind


class _NotAMock:
    """A class with none of the serial builder's keywords."""

    def __init__(self, *, colour: str = "red") -> None:
        self.colour = colour


class _CanNodeWithoutWiring:
    """A CAN node that does not say how the driver's wiring becomes its keywords."""

    def __init__(self, vehicle: Any, *, side: str, direction: int, wheel_radius_m: float, interface: str,
                 channel: str, bus_options: Mapping[str, Any] | None = None) -> None:
        self.side = side


SNEAKY = 42   # not a class


@pytest.mark.parametrize(("entry", "problem"), [
    (MockEntry(f"{__name__}:_NotAMock", "serial", "x"), "lacks 'link_path'"),
    (MockEntry(f"{__name__}:_CanNodeWithoutWiring", "can_motor", "x"), "lacks 'wiring_options'"),
    (MockEntry(f"{__name__}:SNEAKY", "serial", "x"), "is not a class"),
    (MockEntry("u2sa_hw.mocks.nmea_gps:NmeaGpsDevice", "no_such_builder", "x"), "is not a builder"),
    (MockEntry("u2sa_hw.mocks.nmea_gps:NmeaGpsDevice", "serial", "  "), "no description"),
])
def test_the_check_finds_a_bad_entry(monkeypatch: pytest.MonkeyPatch, entry: MockEntry, problem: str) -> None:
    monkeypatch.setitem(MOCK_DEVICES, "bad", entry)
    problems = catalog.entry_problems("bad")
    assert any(problem in p for p in problems), problems


def test_a_missing_module_is_an_import_error_not_a_silent_skip(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(MOCK_DEVICES, "bad", MockEntry("u2sa_hw.mocks.no_such_module:Thing", "serial", "x"))
    with pytest.raises(ImportError):
        catalog.entry_problems("bad")


@pytest.mark.parametrize(("cls", "wiring", "expected"), [
    (OdriveCanNode, {"firmware": "0.5", "command_limit_turns_per_s": 4.0},
     {"node_id": 3, "firmware": "0.5", "vel_limit": 4.0 * NODE_SPEED_MARGIN}),
    (OdriveCanNode, {}, {"node_id": 3, "firmware": "0.6", "vel_limit": 2.0 * NODE_SPEED_MARGIN}),
    (VescCanNode, {"max_erpm": 9000, "pole_pairs": 5, "gear_ratio": 2},
     {"controller_id": 3, "max_erpm": 9000.0, "pole_pairs": 5, "gear_ratio": 2.0}),
])
def test_a_can_node_turns_the_drivers_wiring_into_its_keywords(cls: Any, wiring: dict[str, Any],
                                                                expected: dict[str, Any]) -> None:
    assert cls.wiring_options(wiring, node_id=3) == expected


def test_the_catalog_holds_no_per_family_branch() -> None:
    """The builders find the class through the table: no mock kind's name and no mock class in the catalog's code."""
    text = (REPO / "mock_devices" / "catalog.py").read_text()
    code = text.split('"""', 2)[2]   # past the module docstring
    for kind in ("odrive", "vesc", "bno055", "nmea_compass", "os5000_compass"):
        assert f'"{kind}"' not in code, kind
    for entry in MOCK_DEVICES.values():
        assert entry.target.partition(":")[2] not in code, entry.target


def test_the_registry_imports_no_mock_until_one_is_resolved() -> None:
    """``u2sa_hw`` may name the mocks in strings, never import them at module level (tests/test_layout.py)."""
    code = ("import sys, u2sa_hw.registry as r; assert not any(m.startswith('u2sa_hw.mocks') for m in sys.modules); "
            "r.resolve_mock('vesc'); assert 'u2sa_hw.mocks.vesc_node' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)

