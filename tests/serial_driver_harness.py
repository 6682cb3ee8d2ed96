"""Test harness for the serial drivers: a vehicle profile in tmp_path and a probe on the bus.

The driver runs as a real ``u2sa service`` process; the mock device runs in the test
process on a pty symlink in tmp_path; the probe listens to the driver's STATE_INFO and
Health messages over real LCM multicast.
"""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path
from typing import Any, Callable

import tomli_w
from conftest import REPO, ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.ports.tap import raw_channel

ORIGIN = {"lat": 29.1895, "lon": -81.0483, "alt": 10.0}
SIM_ORIGIN = {"origin_lat": ORIGIN["lat"], "origin_lon": ORIGIN["lon"], "origin_alt": ORIGIN["alt"]}


def write_profile(tmp_path: Path, *, name: str, kind: str, settings: dict[str, Any],
                  devices: dict[str, str] | None = None) -> Path:
    """A vehicle profile with one service *name* of *kind* configured by *settings*, and *devices*
    (device name -> address) as ``[devices.NAME] address = ...`` tables."""
    profile: dict[str, Any] = {
        "vehicle": {"name": "testrover", "system_id": 7, "origin": dict(ORIGIN), "config_dir": "config",
                    "log_dir": "logs", "data_dir": "data"},
        "services": {name: {"kind": kind, "settings": {"health_interval_s": 0.2, **settings}}},
    }
    if devices:
        profile["devices"] = {device: {"address": address} for device, address in devices.items()}
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps(profile))
    return path


def start_driver(services: ServiceProcesses, profile: Path, name: str) -> subprocess.Popen:
    """``u2sa service NAME --vehicle PROFILE`` with the repository importable (drivers/)."""
    return services.start(name, "--vehicle", str(profile), PYTHONPATH=str(REPO))


class DriverProbe:
    """STATE_INFO and Health of one service, as they arrive on the bus."""

    def __init__(self, bus: BusClient, name: str, *, on_state: Callable[[], Any] | None = None) -> None:
        self.name = name
        self._lock = threading.Lock()
        self._on_state = on_state
        self.states: list[tuple[t.StateInformation, Any]] = []  # (message, on_state() when it arrived)
        self.health: list[t.Health] = []
        self.raw: list[t.RawSerial] = []
        bus.transport.subscribe(ch.STATE_INFO, t.StateInformation, self._state)
        bus.transport.subscribe(ch.HEALTH, t.Health, self._health)
        bus.transport.subscribe(raw_channel(name), t.RawSerial, self._raw)

    def _state(self, _channel: str, msg: t.StateInformation) -> None:
        if msg.header.source == self.name:
            extra = self._on_state() if self._on_state else None
            with self._lock:
                self.states.append((msg, extra))

    def _health(self, _channel: str, msg: t.Health) -> None:
        if msg.name == self.name:
            with self._lock:
                self.health.append(msg)

    def _raw(self, _channel: str, msg: t.RawSerial) -> None:
        with self._lock:
            self.raw.append(msg)

    def state_count(self) -> int:
        """How many STATE_INFO messages have arrived so far."""
        with self._lock:
            return len(self.states)

    def states_since(self, index: int) -> list[tuple[t.StateInformation, Any]]:
        """The messages that arrived after the first *index*."""
        with self._lock:
            return list(self.states[index:])

    def wait_states(self, count: int, *, since: int = 0, timeout: float = 15.0,
                    message: str = "") -> list[tuple[t.StateInformation, Any]]:
        """Wait for *count* messages after the first *since*; returns them."""
        wait_until(lambda: self.state_count() - since >= count, timeout=timeout,
                   message=message or f"{count} STATE_INFO messages from {self.name}")
        return self.states_since(since)

    def wait_health(self, predicate: Callable[[dict[str, str], str], bool], *, timeout: float = 15.0,
                    message: str = "") -> dict[str, str]:
        """Wait for a Health message arriving from now on whose (details, status) satisfy *predicate*."""
        with self._lock:
            start = len(self.health)
        found: list[dict[str, str]] = []

        def check() -> bool:
            with self._lock:
                fresh = self.health[start:]
            for msg in fresh:
                details = {kv.key: kv.value for kv in msg.details}
                details["status"] = msg.status
                details["last_error"] = msg.last_error
                if predicate(details, msg.status):
                    found.append(details)
                    return True
            return False

        wait_until(check, timeout=timeout, message=message or f"health of {self.name} matching the condition")
        return found[0]

    def health_after(self, n: int, *, timeout: float = 15.0) -> dict[str, str]:
        """The details of the *n*-th Health message from now on (lets epochs pass)."""
        seen = [0]

        def count(_details: dict[str, str], _status: str) -> bool:
            seen[0] += 1
            return seen[0] >= n

        return self.wait_health(count, timeout=timeout, message=f"{n} health messages from {self.name}")

