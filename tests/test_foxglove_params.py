"""The Foxglove parameter bridge reads the configs of every live service: the ones that answer discovery and
the ones whose health the bridge has heard (a discovery answer can come after the wait on a busy machine)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from u2sa_hw.foxglove.params import ParameterBridge

pytest.importorskip("foxglove")


class FakeBus:
    """Discovery answered by *answering* only; every service answers a config request."""

    def __init__(self, answering: list[str]) -> None:
        self.answering = answering
        self.transport = SimpleNamespace(auth=object())
        self.asked: list[str] = []

    def discover(self, *, timeout: float) -> list[Any]:
        return [SimpleNamespace(name=n) for n in self.answering]

    def get_config(self, service: str, *, timeout: float) -> Any:
        self.asked.append(service)
        return SimpleNamespace(ok=True, fields=[SimpleNamespace(name="rate_hz", value="5.0")])


def test_services_heard_but_late_to_discovery_are_read_too() -> None:
    bus = FakeBus(answering=["world"])
    params = ParameterBridge(bus, allow_writes=False, heard=lambda: ["foxglove", "world"])
    got = {p.name: p.get_value() for p in params.on_get_parameters(None, [])}
    assert got == {"foxglove.rate_hz": 5.0, "world.rate_hz": 5.0}
    assert bus.asked == ["foxglove", "world"]   # each once


def test_named_parameters_ask_only_their_services() -> None:
    bus = FakeBus(answering=["world", "gps"])
    params = ParameterBridge(bus, allow_writes=False, heard=lambda: ["foxglove"])
    assert [p.name for p in params.on_get_parameters(None, ["gps.rate_hz"])] == ["gps.rate_hz"]
    assert bus.asked == ["gps"]
