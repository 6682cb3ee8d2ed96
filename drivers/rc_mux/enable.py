"""The RC mux's autonomy-enable line and what decides it (a part of :class:`u2sa_hw.drivers.rc_mux.driver.RcMuxDriver`).

The enable line into the hardware mux is high only while every condition holds: not stopping,
no failsafe held by any source, the GPIO port up, no select read-back mismatch, every pre-arm
check passing (or a hold already in force), the pilot's switch at autonomous and the pilot
having armed through manual. A failsafe raised or cleared, a refused attempt or a check lost
while autonomous disarms (``require_rearm``), so autonomy never comes back by itself. On a replay
chip the Health, FAILSAFE and STATE_ESTIMATE that decide it are the recorded ones, in order
with the edges (docs/replay.md); live they come from the bus and age on CLOCK_MONOTONIC.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Sequence

from u2sa_hw.drivers.rc_mux.pulse import MODE_AUTONOMOUS
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.ports.gpio.wire import BusInput
from u2sa_hw.safety.prearm import CheckFailure


class RcMuxEnable:
    """The enable line, the failsafe sources and the pre-arm checks of the RC mux driver (a mixin of
    :class:`u2sa_hw.drivers.rc_mux.driver.RcMuxDriver`, whose state it reads and moves)."""

    enabled: bool
    armed: bool
    hold: bool
    _enable_lock: threading.RLock
    _recorded_bus: tuple[str, ...]

    # -- the enable line -----------------------------------------------------------------
    def autonomy_allowed(self) -> tuple[bool, str]:
        """Whether the enable line may be high, and if not the first reason why not."""
        allowed, why, _ = self._blocked()
        return allowed, why

    def _blocked(self) -> tuple[bool, str, Any]:
        """(allowed, why not, what the reason is: the pre-arm check and service rather than its text, whose
        sigma changes with every estimate)."""
        if self._stopping:
            return False, "stopping", "stopping"
        if self.failsafes.active:
            why = f"failsafe ({self.failsafes.reason()})"
            return False, why, why
        if not self.gpio.is_open:
            return False, "GPIO port down", "port"
        if self.mismatch:
            return False, "mux select read-back mismatch", "mismatch"
        if self.prearm_failures and not (self.hold and self.enabled):
            first = self.prearm_failures[0]
            return False, f"pre-arm check failed: {first.reason}", ("prearm", first.check, first.service)
        if self.filter.mode != MODE_AUTONOMOUS:
            why = f"mode {self.filter.mode_name}"
            return False, why, why
        if not self.armed:
            return False, "not armed (switch to manual to re-arm)", "armed"
        return True, "", ""

    def state_key(self) -> tuple:
        """What an RcMode says but the pulse widths (and the sigma in a pre-arm reason): a change is published
        at once."""
        return (self.filter.mode, self.enabled, self.mismatch, self.armed, self.hold, self._blocked()[2])

    def update_enable(self) -> None:
        """Drive the enable line to what :meth:`autonomy_allowed` says (safe from any thread)."""
        with self._enable_lock:
            want, why = self.autonomy_allowed()
            if want == self.enabled:
                return
            ok = self.gpio.set(self.enable_line, int(want))
            new = want if ok else False  # a failed write lost the port: the request is released, the line falls
            if new != self.enabled:
                self.enabled = new
                self.enable_changes += 1
                # Handing over to autonomy is normal operation; losing it is worth a warning.
                if new:
                    self.logger.info("autonomy enable HIGH (all conditions hold)")
                else:
                    self.logger.warning("autonomy enable low (%s)", why)

    @property
    def failsafe_active(self) -> bool:
        """True while any source holds a failsafe."""
        return self.failsafes.active

    def _on_failsafe(self, msg: t.Failsafe) -> None:
        if ch.FAILSAFE not in self._recorded_bus:   # on a replay chip the recorded ones come with the edges
            self._apply_failsafe(msg)

    def _on_health(self, msg: t.Health) -> None:
        if ch.HEALTH not in self._recorded_bus:
            self.prearm.on_health(msg, time.monotonic())

    def _on_estimate(self, msg: t.StateInformation) -> None:
        if ch.STATE_ESTIMATE not in self._recorded_bus:
            self.prearm.on_estimate(msg, time.monotonic())

    def _on_bus_input(self, event: BusInput) -> None:
        """A recorded bus message from a replay chip, at its recorded arrival on the device clock."""
        try:
            msg, _ = REGISTRY.decode(event.data, ch.base_type(event.channel))
        except MalformedMessage:
            return
        if event.channel == ch.FAILSAFE:
            self._apply_failsafe(msg)
        elif event.channel == ch.HEALTH:
            self.prearm.on_health(msg, event.timestamp_ns / 1e9)
        elif event.channel == ch.STATE_ESTIMATE:
            self.prearm.on_estimate(msg, event.timestamp_ns / 1e9)

    def _apply_failsafe(self, msg: t.Failsafe) -> None:
        with self._enable_lock:
            change = self.failsafes.apply_message(msg)
            if change.raised:
                self.logger.warning("FAILSAFE from %s: %s", msg.header.source or "?", msg.reason)
            if change.cleared:
                self.logger.info("failsafe of %s cleared by %s%s", ", ".join(change.cleared),
                                 msg.header.source or "?", "" if change.active_after else " (none held now)")
            # raised or cleared: the pilot re-arms after it, so a clear never hands autonomy back by itself
            if (change.active_after or change.cleared) and self.config["require_rearm"]:
                self.armed = False
            self.update_enable()

    def _check_prearm(self, verdict: Sequence[CheckFailure]) -> None:
        """Take the pre-arm *verdict* (PrearmChecks.verdict, asked now); a check lost while autonomous disarms
        or holds."""
        failures = list(verdict)
        first = failures[0].reason if failures else ""
        key = (failures[0].check, failures[0].service) if failures else None
        old = (self.prearm_failures[0].check, self.prearm_failures[0].service) if self.prearm_failures else None
        if key != old:  # by check and service: a sigma in the reason changes with every estimate
            if first:
                self.logger.info("pre-arm: %s", first)
            else:
                self.logger.info("pre-arm: every check holds")
        with self._enable_lock:
            self.prearm_failures = failures
            if (failures and not self.enabled and self.armed and self.filter.mode == MODE_AUTONOMOUS
                    and self.config["require_rearm"]):
                # refused: the attempt is over, so autonomy cannot start by itself once the check passes
                self.armed = False
                self.logger.warning("autonomy refused: %s; switch through manual to try again", first)
            elif failures and self.enabled and not self.hold:
                self.checks_lost += 1
                if self.safety.on_check_lost == "hold":
                    self.hold = True
                    self.logger.warning("pre-arm check lost while autonomous: %s -> hold (outputs neutral until "
                                        "the pilot re-arms through manual)", first)
                else:
                    self.armed = False
                    self.logger.warning("pre-arm check lost while autonomous: %s -> neutral (autonomy dropped; "
                                        "switch through manual to re-arm)", first)
