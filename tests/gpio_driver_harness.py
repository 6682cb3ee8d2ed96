"""Test harness for the GPIO and RC mux drivers: a collector of bus messages per channel.

The drivers run as real ``u2sa service`` processes (``serial_driver_harness.start_driver``
with a profile from ``write_profile``); the mock GPIO chip, RC receiver and mux run in
the test process; this collector listens over real LCM multicast.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, Callable

from conftest import wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient


class BusCollector:
    """Every message of the subscribed channels, in arrival order."""

    def __init__(self, bus: BusClient) -> None:
        self.bus = bus
        self._lock = threading.Lock()
        self.messages: dict[str, list[Any]] = {}

    def listen(self, channel: str, base: type | None) -> BusCollector:
        """Collect *channel* (decoded as *base*, or by fingerprint when None)."""
        with self._lock:
            self.messages.setdefault(channel, [])
        self.bus.transport.subscribe(channel, base, self._on_message)
        return self

    def _on_message(self, channel: str, msg: Any) -> None:
        with self._lock:
            self.messages[channel].append(msg)

    def count(self, channel: str) -> int:
        """How many messages arrived on *channel* so far."""
        with self._lock:
            return len(self.messages[channel])

    def since(self, channel: str, index: int = 0) -> list[Any]:
        """The messages on *channel* after the first *index*."""
        with self._lock:
            return list(self.messages[channel][index:])

    def wait_for(self, channel: str, predicate: Callable[[Any], object], *, since: int = 0, timeout: float = 15.0,
                 message: str = "") -> Any:
        """The first message on *channel* after *since* that satisfies *predicate* (fails after *timeout*)."""
        found: list[Any] = []

        def check() -> bool:
            for msg in self.since(channel, since):
                if predicate(msg):
                    found.append(msg)
                    return True
            return False

        wait_until(check, timeout=timeout, message=message or f"a matching message on {channel}")
        return found[0]

    def health_of(self, service: str, predicate: Callable[[dict[str, str]], object], *, since: int = 0,
                  timeout: float = 15.0, message: str = "") -> dict[str, str]:
        """The details (plus ``status`` and ``last_error``) of the first matching Health of *service*."""
        def details(msg: t.Health) -> dict[str, str]:
            return {**{kv.key: kv.value for kv in msg.details}, "status": msg.status, "last_error": msg.last_error}

        msg = self.wait_for(ch.HEALTH, lambda m: m.name == service and predicate(details(m)), since=since,
                            timeout=timeout, message=message or f"health of {service} matching the condition")
        return details(msg)


def pwm_duty_us(chip: Path, channel: int = 0) -> float:
    """The duty cycle a driver wrote to *channel* of a sysfs-shaped PWM tree, in µs; -1 while unreadable."""
    try:
        return int((chip / f"pwm{channel}" / "duty_cycle").read_text()) / 1000.0
    except (OSError, ValueError):
        return -1.0
