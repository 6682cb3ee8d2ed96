"""The software RC mux at each actuator: who may command it right now (pure logic, time passed in).

An actuator hears two command channels: ``MANUAL_CMD`` (the pilot's sticks through the manual
mixer, published by the rc_mux service) and ``ACTUATOR_CMD`` (autonomy: the control system).
:class:`CommandGate` decides, from the newest ``RcMode`` and the failsafes held, which one it
obeys:

============================================  ==========================================
state                                         authority
============================================  ==========================================
any failsafe held                             none (neutral)
no RC_MODE yet, or the newest is older than   none (neutral): the RC service died or hung
``rc_mode_timeout_s``
mode manual                                   manual (an output wired through the hardware
                                              mux ignores MANUAL_CMD: the pilot has the wire)
mode autonomous, autonomy enabled, armed,     autonomous
not on hold
anything else (no signal, not enabled, not    none (neutral)
armed, hold)
============================================  ==========================================

A command from the channel without authority is dropped and counted by why; it never
refreshes the dead-man. When the authority changes, the actuator goes neutral at once, so a
setpoint of the old authority never outlives the switch. :attr:`CommandGate.rearms` counts
the pilot's re-arms as heard: each RC_MODE that says manual and armed after one that did not
(the switch moved through manual, or the RC mux armed there); a driver clears a watchdog trip
its own stall caused only on a re-arm heard after the trip (drivers/can_motor/stall_trip.py).
:attr:`CommandGate.stale_rc_modes` counts the changes to "RC_MODE stale": the RC service died or hung, or this
service's own bus handling was held up (a loaded machine) - then it takes its backlog late, in order, and a
replay of the log cannot reproduce that (hil/held_up.py reads the count). With ``rc_gating`` off (a bench
without an RC receiver) only the failsafe gates autonomous commands; the actuator logs that
at start, and a vehicle should never run that way.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from u2sa_hw.failsafe import FailsafeSources

MANUAL = "manual"
AUTONOMOUS = "autonomous"
RC_MODE_MANUAL, RC_MODE_AUTONOMOUS = 0, 1
STALE = "RC_MODE stale"   # the reason an authority gives when the newest RC_MODE is too old


@dataclass(frozen=True)
class Authority:
    """Who may command the actuator (``manual``, ``autonomous`` or None) and, when nobody may, why."""

    source: str | None
    why: str = ""


class CommandGate:
    """The authority over one actuator service's outputs; thread-safe."""

    def __init__(self, *, rc_mode_timeout_s: float, rc_gating: bool = True) -> None:
        self.rc_mode_timeout_s = rc_mode_timeout_s
        self.rc_gating = rc_gating
        self.failsafes = FailsafeSources()
        self.dropped: dict[str, int] = {}
        self._rc: Any = None
        self._rc_at: float | None = None
        self._lock = threading.Lock()
        self._current = Authority("start")  # so the first evaluation always counts as a change (-> neutral)
        self.rearms = 0
        self.stale_rc_modes = 0   # changes of the authority to "RC_MODE stale"

    @staticmethod
    def _pilot_armed(msg: Any) -> bool:
        return getattr(msg, "mode", None) == RC_MODE_MANUAL and bool(getattr(msg, "armed", False))

    def on_rc_mode(self, msg: Any, now: float) -> None:
        """The newest RcMode, received at *now* (monotonic seconds); counts a re-arm (see the module docstring).
        The first RcMode heard is no re-arm: what came before it is unknown."""
        with self._lock:
            if self._rc is not None and self._pilot_armed(msg) and not self._pilot_armed(self._rc):
                self.rearms += 1
            self._rc, self._rc_at = msg, now

    def authority(self, now: float) -> Authority:
        """Who may command the outputs at *now*."""
        if self.failsafes.active:
            return Authority(None, f"failsafe ({self.failsafes.reason()})")
        if not self.rc_gating:
            return Authority(AUTONOMOUS)
        with self._lock:
            rc, at = self._rc, self._rc_at
        if rc is None or at is None:
            return Authority(None, "no RC_MODE yet")
        age = now - at
        if age > self.rc_mode_timeout_s:
            return Authority(None, f"{STALE} ({age * 1000:.0f} ms old): the RC service died or hung")
        if rc.mode == RC_MODE_MANUAL:
            return Authority(MANUAL)
        if rc.mode != RC_MODE_AUTONOMOUS:
            return Authority(None, f"RC {rc.mode_name or 'no signal'}")
        if not rc.autonomy_enabled:
            return Authority(None, f"autonomy not enabled ({rc.blocked_by or 'the RC mux holds it low'})")
        if not rc.armed:
            return Authority(None, "not armed (switch to manual to re-arm)")
        if rc.hold:
            return Authority(None, f"hold ({rc.blocked_by or 'a pre-arm check was lost'})")
        return Authority(AUTONOMOUS)

    def changed(self, now: float) -> Authority | None:
        """The authority at *now* if it differs from the one last returned here, else None."""
        new = self.authority(now)
        with self._lock:
            if new.source == self._current.source:
                self._current = new  # keep the newest reason without calling it a change
                return None
            self._current = new
            if new.source is None and new.why.startswith(STALE):
                self.stale_rc_modes += 1
        return new

    @property
    def current(self) -> Authority:
        """The authority as of the last :meth:`changed` call."""
        with self._lock:
            return self._current

    def admit(self, channel_source: str, now: float) -> bool:
        """Whether a command from *channel_source* (``manual``/``autonomous``) is obeyed at *now*."""
        auth = self.authority(now)
        if auth.source == channel_source:
            return True
        if auth.source is None:
            kind = "failsafe" if self.failsafes.active else "no_authority"
        else:
            kind = f"{channel_source}_in_{auth.source}"
        with self._lock:
            self.dropped[kind] = self.dropped.get(kind, 0) + 1
        return False

    def count_drop(self, kind: str) -> None:
        """Count a command dropped for another reason (e.g. NaN)."""
        with self._lock:
            self.dropped[kind] = self.dropped.get(kind, 0) + 1

    def drops_text(self) -> str:
        """``kind:n,...`` for health."""
        with self._lock:
            return ",".join(f"{k}:{n}" for k, n in sorted(self.dropped.items()))

    def dropped_total(self) -> int:
        """Every command dropped so far."""
        with self._lock:
            return sum(self.dropped.values())
