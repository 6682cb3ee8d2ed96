"""What the ODrive driver knows about one axis, and how its states and error bits read.

``OdriveAxis`` is the record drivers/can_motor/odrive/driver.py keeps per axis (last heartbeat, estimates,
bus and temperatures, arming backoff, the state of its watchdog set-up, its latched error); ``error_names`` and
``enum_name`` turn the numbers of a heartbeat into the names health and the log show. No bus
and no clock here: the driver mutates an axis under its lock and passes the time in.
"""

from __future__ import annotations

from typing import Any

from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols.odrive_cansimple import AxisState

from u2sa_hw.drivers.can_motor.settings import MotorSpec
from u2sa_hw.drivers.can_motor.watchdog import WatchdogStep
from u2sa_hw.drivers.can_motor.stall_trip import Trip


def watchdog_only(hb: cs.Heartbeat, *, firmware: str) -> bool:
    """The heartbeat's error is the watchdog bit and nothing else (on 0.5, no motor, encoder or controller
    sub-error either): the only error a stall of the driver can cause."""
    bit = cs.OdriveError.WATCHDOG_TIMER_EXPIRED if firmware == "0.6" else cs.AxisError05.WATCHDOG_TIMER_EXPIRED
    return hb.axis_error == int(bit) and not (hb.motor_error_flag or hb.encoder_error_flag
                                              or hb.controller_error_flag)


def error_names(bits: int, *, firmware: str) -> str:
    """``A|B`` names of the axis error bits set in *bits* ("none" for 0; unknown bits in hex)."""
    table = cs.OdriveError if firmware == "0.6" else cs.AxisError05
    names, known = [], 0
    for member in table:
        if member.value and bits & member.value == member.value:
            names.append(str(member.name))
            known |= member.value
    if bits & ~known:
        names.append(hex(bits & ~known))
    return "|".join(names) or "none"


def enum_name(enum: Any, value: int) -> str:
    """The member name of *value* in *enum* (AxisState, ProcedureResult, ...), else the number."""
    try:
        return enum(value).name
    except ValueError:
        return str(value)


class OdriveAxis:
    """What the driver knows about one axis (mutated under the service's lock)."""

    def __init__(self, spec: MotorSpec, *, arm_retry_s: float) -> None:
        self.spec = spec
        self.target = 0.0  # rev/s, direction applied
        self.heartbeat: cs.Heartbeat | None = None
        self.last_heartbeat: float | None = None
        self.silent = False
        self.silent_events = 0
        self.pos_turns: float | None = None
        self.vel_turns_s: float | None = None
        self.bus: tuple[float, float] | None = None
        self.temps: tuple[float, float] | None = None
        self.errors: dict[str, int] = {}  # Get_Error / 0.5 sub-error replies by name
        self.error_events = 0
        self.trip: Trip | None = None   # the latched error as first heard (drivers/can_motor/stall_trip.py)
        self.stall_clears = 0           # watchdog trips of this driver's stalls cleared on the pilot's re-arm
        self.arm_attempts = self.arm_failures = 0
        self.arming_since: float | None = None
        self.arm_retry_s = arm_retry_s
        self.backoff = arm_retry_s
        self.next_arm = 0.0
        self.next_command = self.next_poll = self.next_encoder_poll = 0.0
        self.wd = WatchdogStep()

    @property
    def armed(self) -> bool:
        """The last heartbeat showed CLOSED_LOOP_CONTROL without an error."""
        hb = self.heartbeat
        return hb is not None and hb.axis_state == AxisState.CLOSED_LOOP_CONTROL and not hb.axis_error

    def retry_now(self) -> None:
        """Forget the arming backoff (a clear was asked for, or the node came back)."""
        self.backoff, self.next_arm = self.arm_retry_s, 0.0
