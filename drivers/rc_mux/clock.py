"""The RC mux's judgments in device-clock order (a part of :class:`u2sa_hw.drivers.rc_mux.driver.RcMuxDriver`).

Everything the mux decides by time is judged on the port's device clock (CLOCK_MONOTONIC on a
real chip, the recorded edge stamps on a replay chip) in the order of the edges' stamps: before
an edge is taken, whatever falls due up to its stamp happens first, at its own time (the signal
timeout and the read-back mismatch when they expire; ``RC_MODE`` and ``MANUAL_CMD`` on a fixed
grid of the clock, :class:`u2sa_hw.drivers.rc_mux.pulse.DueGrid`, each with the state as of its due time).
So what is published depends on the edges and their stamps, not on how the loop batched its
reads, and a replay gives the live messages (docs/replay.md). The methods here work on the
driver's own state; they live apart only to keep each module to one job.
"""

from __future__ import annotations

import time
from typing import Any

from u2sa_hw.drivers.rc_mux.pulse import MODE_MANUAL, MODE_NO_SIGNAL
from u2sa_hw.ports.gpio.wire import BusInput, ClockTick, EdgeEvent, GpioEvent

# Live, a timed message due at D waits until an edge stamped after D is taken, or until the clock is
# this far past D: an edge stamped before D but delivered late (a kernel chip: microseconds; the
# mock receiver hands a frame's edges over at the frame's end) is still in it. It only waits
# while no edge comes (a lost signal): then every RcMode is at most a period and this old.
TIMED_HOLD_NS = 50_000_000


class RcMuxClock:
    """The device-clock scheduling of the RC mux driver (a mixin of :class:`u2sa_hw.drivers.rc_mux.driver.RcMuxDriver`,
    whose state it reads and moves: the clock, the due grids, the filter, the enable line)."""

    clock_ns: int | None
    timed_skipped: int
    _device_clock: bool
    _published: Any
    _settled: tuple | None   # what the last settle left (_settle_inputs); None: settle in full

    def _take(self, event: GpioEvent, wall_ns: int) -> None:
        """One event from the chip at its stamp: what fell due up to it, then the event, then its effects.
        (Live, the clock may already be past the stamp, read at the loop's last look: an edge delivered late
        still comes before the timed messages due after it that were held for it.)

        A recorded bus input (a replay chip's) is applied as the live callbacks apply a message: a
        FAILSAFE drops the enable line at once, a Health or estimate waits for the next judgement; what
        they change is published with the next edge or tick, as the recorded driver did at its loop's
        next turn. It does not move the clock (it is stamped at the edge before it)."""
        if self._published is None:
            self._settle(None)   # the state before any input (a replay chip sends nothing before it)
        if isinstance(event, BusInput):
            self._on_bus_input(event)
            return
        at = event.timestamp_ns
        self._advance_clock(at)
        if isinstance(event, ClockTick) and event.step:
            # the recorded loop looked at its clock here while edges were still on their way (late): what
            # it judged then, as the live step does (expiries up to now, timed messages held for them)
            self._advance(at, at - TIMED_HOLD_NS, wall_ns)
            self._settle(at)
            return
        self._advance(at, at, wall_ns)
        if isinstance(event, EdgeEvent):
            self._on_edge(event.line, event.rising, at)
        self._settle(at)

    def _step(self, now_ns: int | None, wall_ns: int) -> None:
        """The loop's look at the clock: expiries up to *now_ns*, timed messages up to it (live: up to
        TIMED_HOLD_NS before it, later ones wait for a later edge), the pre-arm checks and the enable line.
        On a replay chip everything was judged at the stamps of its events: only the first state, and a
        clock that runs on after DEVICE_CLOCK_GRACE_S of silence (a stalled replay times out, fail safe)."""
        if self._device_clock and (self.clock_ns is None or now_ns is None or now_ns <= self.clock_ns):
            if self._published is None:
                self._settle(None)
            return
        at = self._advance_clock(now_ns)
        if at is not None:
            self._advance(at, at if self._device_clock else at - TIMED_HOLD_NS, wall_ns)
        self._settle(at)

    def _advance_clock(self, now_ns: int | None) -> int | None:
        """The device clock moved to *now_ns* (it never goes back); its time now (None: not started). The
        timed messages start with it."""
        if now_ns is not None:
            if self.clock_ns is None:
                self._origin_ns = self._origin_of()
            self.clock_ns = now_ns if self.clock_ns is None else max(self.clock_ns, now_ns)
        if self.clock_ns is not None and self._next_publish_ns is None:
            self._next_publish_ns = self.mode_grid.after(self.clock_ns - 1, self._origin_ns)
        return self.clock_ns

    def _advance(self, limit_ns: int, dues_ns: int, wall_ns: int) -> None:
        """In time order: every expiry (signal timeout, read-back mismatch) up to *limit_ns*, each timed
        message due up to *dues_ns* or before an expiry, each at its own time."""
        while True:
            expiry = self._next_expiry()
            due = self._next_timed()
            expires = expiry is not None and expiry[0] <= limit_ns
            if expires and (due is None or expiry[0] <= due[0]):
                self._expire(expiry[1], expiry[0])
            elif due is not None and (due[0] <= dues_ns or expires):
                self._timed(due[1], due[0], dues_ns, wall_ns)
            else:
                return

    def _next_expiry(self) -> tuple[int, str] | None:
        signal = self.filter.signal_expiry_ns()
        signal_at = None if signal is None else (signal, "signal")
        if self._mismatch_since is None or self.mismatch:
            return signal_at
        select = (self._mismatch_since + int(self.config["select_mismatch_ms"] * 1e6) + 1, "select")
        return select if signal_at is None else min(signal_at, select)

    def _next_timed(self) -> tuple[int, str] | None:
        mode, manual = self._next_publish_ns, self._next_manual_ns
        if mode is None or manual is None:
            return (mode, "mode") if mode is not None else None if manual is None else (manual, "manual")
        return min((mode, "mode"), (manual, "manual"))

    def _expire(self, what: str, at_ns: int) -> None:
        if what == "signal":
            if self.filter.check_signal(at_ns):
                self._mode_changed(at_ns)
        else:
            self._check_select(at_ns)
            if not self.mismatch:   # no read-back (any more): nothing left to expire
                self._mismatch_since = None
        self._settle(at_ns)

    def _timed(self, what: str, due_ns: int, dues_ns: int, wall_ns: int) -> None:
        """The RC_MODE or MANUAL_CMD due at *due_ns*, with the state as of then. One more than a period behind
        the clock is left out when the next is due too (no burst after a stall): live the wall clock, on a
        replay chip its clock (ahead of the edges only after a recorded step, where the live loop was)."""
        grid = self.mode_grid if what == "mode" else self.manual_grid
        following = grid.after(due_ns, self._origin_ns)
        now_ns = (self.clock_ns or due_ns) if self._device_clock else wall_ns
        behind = now_ns - due_ns > grid.period_ns and following <= dues_ns
        if behind:
            self.timed_skipped += 1   # health: the loop fell behind (a replay cannot know the wall clock's gaps)
        if what == "mode":
            self._next_publish_ns = following
            if not behind:
                self.publish_mode(due_ns)
        else:
            self._next_manual_ns = following if self.filter.mode == MODE_MANUAL and self.sticks is not None else None
            if not behind and self._next_manual_ns is not None:
                self.publish_manual(due_ns)

    def _settle(self, at_ns: int | None) -> None:
        """After an event at *at_ns*: the pre-arm checks, the enable line, the read-back, the status, and
        RC_MODE at once if what it says changed.

        What it leaves is a fixed point: run again on the same inputs it changes nothing. So when every
        input is as the last settle left it (:meth:`_settle_inputs`, the pre-arm verdict by identity),
        it is skipped: most edges change nothing it reads, and it ran after every one."""
        failsafe = self.failsafes.reason()
        verdict = self._verdict(at_ns, failsafe)
        settled = self._settled
        if at_ns is not None and settled is not None and self._settle_inputs(verdict, failsafe) == settled:
            return   # (None whenever the time matters or another thread moved something: _settle_inputs, _left)
        self._check_prearm(verdict)
        if at_ns is not None:
            self._check_select(at_ns)   # with the line as it was: a mismatch just found goes out before it clears
        self.update_enable()
        if at_ns is not None and self.select_level is not None and self._mismatch_since is None \
                and self.select_level != int(self.enabled):
            self._mismatch_since = at_ns   # the line just changed and the read-back disagrees from now
        self._refresh_status()
        status = self.status
        if self.state_key() != self._published:
            self.publish_mode(at_ns)
        self._settled = self._left(at_ns, verdict, failsafe, status)

    def _left(self, at_ns: int | None, verdict: tuple, failsafe: str, status: str) -> tuple | None:
        """What a settle at *at_ns* on *verdict* and *failsafe* left (:meth:`_settle_inputs`), or None (the next
        runs in full) when something came meanwhile from another thread (a FAILSAFE, evidence, a stop) that it
        may not have seen whole."""
        if at_ns is None:
            return None
        again = self.failsafes.reason()
        if (again != failsafe or self._verdict(at_ns, again) is not verdict or self.status != status
                or self.state_key() != self._published):
            return None
        return self._settle_inputs(verdict, failsafe)

    def _verdict(self, at_ns: int | None, failsafe: str) -> tuple:
        """The pre-arm verdict at *at_ns* with the *failsafe* reason held now (the same object while it
        stands: PrearmChecks.verdict)."""
        return self.prearm.verdict(self._judge_s(at_ns), rc_link_ok=self.filter.mode != MODE_NO_SIGNAL,
                                   failsafe_reason=failsafe)

    def _settle_inputs(self, verdict: tuple, failsafe: str) -> tuple | None:
        """Everything :meth:`_settle` reads but the time; None while a read-back disagreement is pending,
        which is judged on the time (then every settle runs in full)."""
        if self._mismatch_since is not None:
            return None
        return (verdict, self.filter.mode, self.enabled, self.armed, self.hold, self.mismatch, self.select_level,
                self.gpio.is_open, self._stopping, failsafe, self._published, self.status,
                self.config["require_rearm"], self.prearm)

    def _judge_s(self, at_ns: int | None) -> float:
        """The time the pre-arm checks judge ages at: the device clock (live: CLOCK_MONOTONIC, the time
        Health is stamped with on arrival); before a replay chip's clock starts, its zero."""
        if at_ns is not None:
            return at_ns / 1e9
        return 0.0 if self._device_clock else time.monotonic()
