"""Whether the RC mux may hand the vehicle to autonomy: the enable verdict, as pure logic.

The enable line into the hardware mux is high only while every condition holds, in this order
(the first that fails is the reason given): not stopping, no failsafe held by any source, the
GPIO port up, no select read-back mismatch, every pre-arm check passing (or a hold already in
force), the pilot's switch at autonomous and the pilot having armed through manual. A failsafe
raised or cleared, a refused attempt or a check lost while autonomous disarms (``require_rearm``),
so autonomy never comes back by itself; a check lost while autonomous takes ``on_check_lost``:
``neutral`` disarms (the line drops), ``hold`` keeps the line and holds every output neutral
until the pilot re-arms. :class:`u2sa_hw.drivers.rc_mux.state.MuxState` owns one
:class:`AutonomyGate` and tells it the rest of the state it judges.
"""

from __future__ import annotations

from typing import Any, Sequence

from u2sa_hw.drivers.rc_mux.outputs import Note
from u2sa_hw.drivers.rc_mux.pulse import MODE_AUTONOMOUS, MODE_NAMES
from u2sa_hw.failsafe import FailsafeSources
from u2sa_hw.safety.config import ON_CHECK_LOST
from u2sa_hw.safety.prearm import CheckFailure, PrearmChecks


class AutonomyGate:
    """The arming, the hold, the failsafes held and the pre-arm verdict, and what they allow."""

    def __init__(self, *, prearm: PrearmChecks, on_check_lost: str, require_rearm: bool) -> None:
        if on_check_lost not in ON_CHECK_LOST:
            raise ValueError(f"on_check_lost must be one of {', '.join(ON_CHECK_LOST)}, got {on_check_lost!r}")
        self.prearm = prearm
        self.failsafes = FailsafeSources()
        self.on_check_lost = on_check_lost
        self.require_rearm = require_rearm
        self.enabled = False     # what the enable line was last driven to
        self.armed = not require_rearm
        self.hold = False
        self.prearm_failures: list[CheckFailure] = []
        self.checks_lost = 0
        self.enable_changes = 0

    def reset_evidence(self, prearm: PrearmChecks) -> None:
        """Start from no evidence and no failsafe (a replay chip hands over the recorded ones)."""
        self.prearm = prearm
        self.failsafes = FailsafeSources()

    def blocked(self, *, stopping: bool, port_open: bool, mismatch: bool, mode: int) -> tuple[bool, str, Any]:
        """(allowed, why not, what the reason is: the pre-arm check and service rather than its text, whose
        sigma changes with every estimate)."""
        if stopping:
            return False, "stopping", "stopping"
        if self.failsafes.active:
            why = f"failsafe ({self.failsafes.reason()})"
            return False, why, why
        if not port_open:
            return False, "GPIO port down", "port"
        if mismatch:
            return False, "mux select read-back mismatch", "mismatch"
        if self.prearm_failures and not (self.hold and self.enabled):
            first = self.prearm_failures[0]
            return False, f"pre-arm check failed: {first.reason}", ("prearm", first.check, first.service)
        if mode != MODE_AUTONOMOUS:
            why = f"mode {MODE_NAMES[mode]}"
            return False, why, why
        if not self.armed:
            return False, "not armed (switch to manual to re-arm)", "armed"
        return True, "", ""

    def apply_failsafe(self, msg: Any, notes: list[Note]) -> None:
        """A FAILSAFE message: held per source (u2sa_hw/failsafe.py); raised or cleared, it disarms, so a clear
        never hands autonomy back by itself."""
        change = self.failsafes.apply_message(msg)
        if change.raised:
            notes.append(Note("warning", f"FAILSAFE from {msg.header.source or '?'}: {msg.reason}"))
        if change.cleared:
            notes.append(Note("info", f"failsafe of {', '.join(change.cleared)} cleared by {msg.header.source or '?'}"
                                      f"{'' if change.active_after else ' (none held now)'}"))
        if (change.active_after or change.cleared) and self.require_rearm:
            self.armed = False

    def take_verdict(self, verdict: Sequence[CheckFailure], *, mode: int, notes: list[Note]) -> None:
        """Take the pre-arm *verdict* (PrearmChecks.verdict, asked now); a check failing at the switch to
        autonomous refuses the attempt, a check lost while autonomous disarms or holds."""
        failures = list(verdict)
        first = failures[0].reason if failures else ""
        key = (failures[0].check, failures[0].service) if failures else None
        old = (self.prearm_failures[0].check, self.prearm_failures[0].service) if self.prearm_failures else None
        if key != old:  # by check and service: a sigma in the reason changes with every estimate
            notes.append(Note("info", f"pre-arm: {first}" if first else "pre-arm: every check holds"))
        self.prearm_failures = failures
        if failures and not self.enabled and self.armed and mode == MODE_AUTONOMOUS and self.require_rearm:
            # refused: the attempt is over, so autonomy cannot start by itself once the check passes
            self.armed = False
            notes.append(Note("warning", f"autonomy refused: {first}; switch through manual to try again"))
        elif failures and self.enabled and not self.hold:
            self.checks_lost += 1
            if self.on_check_lost == "hold":
                self.hold = True
                notes.append(Note("warning", f"pre-arm check lost while autonomous: {first} -> hold (outputs "
                                             "neutral until the pilot re-arms through manual)"))
            else:
                self.armed = False
                notes.append(Note("warning", f"pre-arm check lost while autonomous: {first} -> neutral (autonomy "
                                             "dropped; switch through manual to re-arm)"))
