"""The RC mux's device clock and the due times of its timed messages, as pure logic.

Everything the mux decides by time is judged on the port's device clock (CLOCK_MONOTONIC on a
real chip, the recorded edge stamps on a replay chip), which never goes back. The timed messages
(``RC_MODE`` at ``publish_hz``, ``MANUAL_CMD`` at ``manual_hz`` in manual) are due on a fixed grid
of that clock (:class:`u2sa_hw.drivers.rc_mux.pulse.DueGrid`, from the recorded clock's zero), so a
replay has the recorded due times whatever the phase of the loop that sends them. One more than a
period behind is left out when the next is due too (no burst after a stall) and counted. The
loop's own stalls are judged on the host clock (:class:`LoopWatch`).
:class:`u2sa_hw.drivers.rc_mux.state.MuxState` asks this object what is due and when.
"""

from __future__ import annotations

from u2sa_hw.drivers.rc_mux.pulse import DueGrid

# Live, a timed message due at D waits until an edge stamped after D is taken, or until the clock is
# this far past D: an edge stamped before D but delivered late (a kernel chip: microseconds; the
# mock receiver hands a frame's edges over at the frame's end) is still in it. It only waits
# while no edge comes (a lost signal): then every RcMode is at most a period and this old.
TIMED_HOLD_NS = 50_000_000

MODE_DUE = "mode"
MANUAL_DUE = "manual"


class MuxClock:
    """The device clock as far as it has been judged, and the next ``RC_MODE`` and ``MANUAL_CMD`` due."""

    def __init__(self, *, publish_hz: float, manual_hz: float) -> None:
        self.mode_grid, self.manual_grid = DueGrid(publish_hz), DueGrid(manual_hz)
        self.now_ns: int | None = None         # the latest time judged (None: the clock has not started)
        self.origin_ns = 0                     # the recorded clock's zero, taken when the clock starts
        self.next_origin_ns = 0                # where the port says that zero is now
        self.next_mode_ns: int | None = None   # the next RC_MODE due (None: the clock has not started)
        self.next_manual_ns: int | None = None  # the next MANUAL_CMD due (None: not in manual)
        self.skipped = 0                       # timed messages left out: more than a period behind

    def restart(self) -> None:
        """The clock starts again from its next time (a replay chip (re)opened: its own clock)."""
        self.now_ns = self.next_mode_ns = self.next_manual_ns = None

    def advance(self, now_ns: int | None) -> int | None:
        """The clock moved to *now_ns* (never back); its time now (None: not started). The timed
        messages start with it."""
        if now_ns is not None:
            if self.now_ns is None:
                self.origin_ns = self.next_origin_ns
            self.now_ns = now_ns if self.now_ns is None else max(self.now_ns, now_ns)
        if self.now_ns is not None and self.next_mode_ns is None:
            self.next_mode_ns = self.mode_grid.after(self.now_ns - 1, self.origin_ns)
        return self.now_ns

    def next_due(self) -> tuple[int, str] | None:
        """The first timed message due: (due time, ``mode`` or ``manual``), or None."""
        mode, manual = self.next_mode_ns, self.next_manual_ns
        if mode is None or manual is None:
            return (mode, MODE_DUE) if mode is not None else None if manual is None else (manual, MANUAL_DUE)
        return min((mode, MODE_DUE), (manual, MANUAL_DUE))

    def manual_from(self, at_ns: int | None) -> None:
        """The sticks went out at *at_ns* (the switch to manual): the next are due on the grid after it;
        None: no more (not in manual)."""
        self.next_manual_ns = None if at_ns is None else self.manual_grid.after(at_ns, self.origin_ns)

    def take_due(self, what: str, due_ns: int, *, dues_ns: int, now_ns: int, manual_on: bool) -> bool:
        """The message *what* due at *due_ns* is handled: its next is set; True when it goes out. It is left
        out (and counted) when *now_ns* is more than a period past it and the next is due by *dues_ns* too.
        *manual_on*: the sticks keep going out (the mode is manual and there is a mixer)."""
        grid = self.mode_grid if what == MODE_DUE else self.manual_grid
        following = grid.after(due_ns, self.origin_ns)
        behind = now_ns - due_ns > grid.period_ns and following <= dues_ns
        if behind:
            self.skipped += 1
        if what == MODE_DUE:
            self.next_mode_ns = following
            return not behind
        self.next_manual_ns = following if manual_on else None
        return not behind and self.next_manual_ns is not None


class LoopWatch:
    """The loop's looks at the host clock: a gap longer than the signal timeout, or long enough that the
    actuators may have seen RC_MODE go stale (less a publish period and TIMED_HOLD_NS), is a stall (the
    process was stopped or starved)."""

    def __init__(self, *, signal_timeout_ns: int, rc_mode_timeout_s: float, publish_hz: float) -> None:
        stale_ns = int((rc_mode_timeout_s - 1.0 / publish_hz) * 1e9) - TIMED_HOLD_NS
        self.stall_after_ns = max(20_000_000, min(signal_timeout_ns, stale_ns))
        self.stalls = 0
        self._last_ns: int | None = None

    def looked(self, host_ns: int) -> int | None:
        """The loop looked at *host_ns*: the gap since its last look when that is a stall (counted), else None."""
        last, self._last_ns = self._last_ns, host_ns
        if last is None or host_ns - last <= self.stall_after_ns:
            return None
        self.stalls += 1
        return host_ns - last
