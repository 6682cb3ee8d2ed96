"""docs/adding-a-device.md stays true: the files it names exist, its counts rest on the tables it names, and an
actuator kind gets the safety chain from its one registry line (issue 25)."""

from __future__ import annotations

import re

from conftest import REPO
from u2sa_hw.install.units import COMMAND_SOURCE_KINDS
from u2sa_hw.realtime import SAFETY_CHAIN_PRIORITIES
from u2sa_hw.registry import ACTUATOR_KINDS, NOT_ACTUATOR_KINDS, SERVICE_KINDS

DOC = REPO / "docs" / "adding-a-device.md"
EXAMPLES = ("speed_log", "acme", "foo", "<")   # the walk-throughs' own new files: not in the repository
PATH = re.compile(r"`((?:u2sa_hw|drivers|mock_devices|hil|tests|docs|udev)/[\w./<>-]+)`")


def test_every_file_the_guide_names_exists() -> None:
    text = DOC.read_text()
    named = {p.rstrip("/.") for p in PATH.findall(text) if not any(e in p for e in EXAMPLES)}
    assert len(named) > 20, "the guide names the files to open; the pattern found too few"
    missing = sorted(p for p in named if not (REPO / p).exists())
    assert missing == [], f"docs/adding-a-device.md names files that do not exist: {missing}"


def test_the_guide_is_linked_from_the_docs_index() -> None:
    assert "(adding-a-device.md)" in (REPO / "docs" / "README.md").read_text()


def test_every_actuator_kind_is_in_the_safety_chain() -> None:
    """A kind left out of NOT_ACTUATOR_KINDS runs real-time and its watchdog kills, with no line elsewhere."""
    assert ACTUATOR_KINDS == frozenset(SERVICE_KINDS) - NOT_ACTUATOR_KINDS
    assert {"odrive_can", "vesc_can", "pwm_servo", "gpio_output", "rc_mux"} <= ACTUATOR_KINDS
    for kind in ACTUATOR_KINDS:
        assert SAFETY_CHAIN_PRIORITIES.get(kind, 0) > 0, kind
        assert kind in COMMAND_SOURCE_KINDS, kind
    assert "control" in COMMAND_SOURCE_KINDS and "control" not in SAFETY_CHAIN_PRIORITIES
