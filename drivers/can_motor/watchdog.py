"""The motor controllers' own command watchdogs (ODrive axis watchdog, VESC ``timeout_msec``), as the
CAN motor drivers set them up: the setting checked against the re-send period, one health line for
all controllers, and where setting one up stands (:class:`WatchdogStep`)."""

from __future__ import annotations

from typing import Any, Callable


def check_hw_watchdog(get: Callable[[str], Any], fail: Callable[[str], Exception]) -> None:
    """Raise *fail*(why) unless hw_watchdog_timeout_s suits command_period_s (shared with the VESC driver)."""
    timeout, period = get("hw_watchdog_timeout_s"), get("command_period_s")
    if get("hw_watchdog") and not timeout > 2 * period:
        raise fail(f"hw_watchdog_timeout_s = {timeout:g} s must be more than twice command_period_s ({period:g} s): "
                   "setpoints are re-sent every command_period_s and one late re-send must not trip the "
                   "controller's watchdog; raise hw_watchdog_timeout_s or lower command_period_s")


def watchdog_summary(texts: dict[str, str]) -> str:
    """One line for health: the common text, or ``name: text`` per controller when they differ."""
    if len(set(texts.values())) == 1:
        return next(iter(texts.values()))
    return "; ".join(f"{name}: {text}" for name, text in texts.items())


class WatchdogStep:
    """Where setting up one controller's watchdog stands: ``pending`` until it is ``on`` (read
    back), ``unverified`` (cannot be done over CAN), ``off`` (not asked for) or ``error``; ``text``
    is what health shows."""

    def __init__(self) -> None:
        self.state = "pending"
        self.text = "pending: not heard yet"
        self.started: float | None = None
        self.tries = 0
        self.next_try = 0.0
        self.version: str | None = None
        self.read: dict[int, bytes] = {}  # endpoint id -> value bytes read back

    @property
    def settled(self) -> bool:
        """No more frames to send for it."""
        return self.state != "pending"

    def settle(self, state: str, text: str) -> None:
        """Record the outcome."""
        self.state, self.text = state, text
