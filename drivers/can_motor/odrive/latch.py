"""The ODrive driver's latched axis errors: which a stall of the driver explains, and what clears them.

A mixin of :class:`u2sa_hw.drivers.can_motor.odrive.driver.OdriveCanMotor` (its axes, gate, stall watch, logger and
config). Each axis keeps its error as first heard (``OdriveAxis.trip``, a
:class:`u2sa_hw.drivers.can_motor.stall_trip.Trip`); a WATCHDOG_TIMER_EXPIRED alone that this driver's own stall
explains is cleared on the pilot's next re-arm through manual and logged with the stall; every
other error waits for ``clear_errors`` (or ``rearm_on_error``). Health says what clears them
(``to_clear``), which the pre-arm refusal shows. See docs/safety.md, "Stall trips and hardware
faults".
"""

from __future__ import annotations

import logging
import time
from typing import Any

from u2sa_hw.protocols import odrive_cansimple as cs

from u2sa_hw.drivers.can_motor.odrive.axis import OdriveAxis, error_names, watchdog_only
from u2sa_hw.drivers.can_motor.stall_trip import StallWatch, Trip, may_clear

REARM_FIX = "switch through manual to re-arm (clears a watchdog trip of the driver's own stall)"


class OdriveTripLatch:
    """Latched axis errors and the re-arm rule for stall trips (mixed into the ODrive driver, which gives
    ``_label``, and through CanMotorService ``stall_trip_gap_s`` and ``link_up``)."""

    name: str
    firmware: str
    axes: dict[str, OdriveAxis]
    stalls: StallWatch
    gate: Any
    config: Any
    logger: logging.Logger

    @property
    def clear_command(self) -> str:
        """The deliberate clear of a latched axis error, as an operator types it."""
        return f"u2sa param set {self.name} clear_errors true"

    def latch(self, axis: OdriveAxis, hb: cs.Heartbeat) -> None:
        """A heartbeat: keep the axis error as first heard (when, the pilot's re-arm count then), or forget it."""
        if not hb.axis_error:
            axis.trip = None
        elif axis.trip is None or axis.trip.bits != hb.axis_error:
            axis.trip = Trip(hb.axis_error, seen=time.monotonic(), rearms=self.gate.rearms,
                             watchdog_only=watchdog_only(hb, firmware=self.firmware))

    def error_advice(self, axis: OdriveAxis) -> str:
        """What the error log line says about clearing the axis's new error."""
        if self.config.get("rearm_on_error"):
            return "clearing and re-arming"
        stall_note = " (if this driver stalled, the pilot's next re-arm through manual clears it)" \
            if axis.trip is not None and axis.trip.watchdog_only else ""
        return f"to clear it and re-arm: {self.clear_command}{stall_note}"

    def attribute_trip(self, axis: OdriveAxis) -> None:
        """A watchdog-only trip: look for this driver's own stall behind it (said once, when found)."""
        trip = axis.trip
        if trip is None:
            return
        stall = trip.attribute(self.stalls, min_s=self.stall_trip_gap_s())
        if stall is not None:
            self.logger.warning("%s: WATCHDOG_TIMER_EXPIRED from this driver's own stall (%s), not a hardware "
                                "fault: cleared at the pilot's next re-arm through manual", self._label(axis),
                                stall.describe())

    def stall_trip_clears(self, axis: OdriveAxis, hb: cs.Heartbeat) -> bool:
        """The pilot re-armed after a trip of this driver's own stall, and the link is back: clear it (logged)."""
        trip = axis.trip
        if not may_clear(trip, bits_now=hb.axis_error, rearms_now=self.gate.rearms, link_up=self.link_up):
            return False
        assert trip is not None and trip.stall is not None
        axis.stall_clears += 1
        trip.rearms = self.gate.rearms   # one clear per re-arm: should it not take, the next re-arm clears it
        self.logger.warning("%s: clearing WATCHDOG_TIMER_EXPIRED on the pilot's re-arm and re-arming; it came from "
                            "this driver's own stall (%s)", self._label(axis), trip.stall.describe())
        return True

    def error_problem(self, axis: OdriveAxis, hb: cs.Heartbeat) -> str:
        """The health reason for an axis in error: its names and whether a stall of this driver explains it."""
        trip = axis.trip
        why = f"this driver stalled {trip.stall.duration:.2f} s" if trip is not None and trip.stall is not None \
            and trip.stall_trip else "latched"
        return f"{axis.spec.name} (node {axis.spec.can_id}) error {error_names(hb.axis_error, firmware=self.firmware)} " \
               f"({why})"

    def to_clear(self) -> str:
        """What clears the latched axis errors, for health (``to_clear``; pre-arm shows it): the pilot's re-arm when
        every one is a trip of this driver's own stall, else the deliberate clear; "" when nothing is latched."""
        errors = [a for a in self.axes.values() if a.heartbeat is not None and a.heartbeat.axis_error]
        if not errors or self.config.get("rearm_on_error"):
            return ""
        if all(a.trip is not None and a.trip.stall_trip for a in errors):
            return REARM_FIX
        return self.clear_command
