"""Every decision of the RC mux, as pure logic: time is passed in, what to do comes back.

:class:`MuxState` takes the GPIO edges, the device clock's ticks and looks, the FAILSAFE, Health and
STATE_ESTIMATE messages, the loop's looks at the host clock and the port opening, each with its time,
and returns what to do in order (``outputs.py``). It holds no bus and no port and reads no clock; the
service (``driver.py``) feeds it one call at a time and carries out what it returns. Everything is
judged on the device clock in the order of the stamps: before an edge is taken, what fell due up to
its stamp happens first, at its own time (the signal timeout, the read-back mismatch, the timed
messages of ``clock.py``), so the batching of the reads changes nothing. The verdict is ``enable.py``'s,
the read-back ``readback.py``'s, the mode ``pulse.py``'s. The enable line is driven through the one
callable it is given, not returned: a write can fail (the port lost), and the next ``RcMode`` must say
what the line is, never what was asked.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

from u2sa_hw import channels as ch
from u2sa_hw.drivers.rc_mux.clock import MANUAL_DUE, MODE_DUE, TIMED_HOLD_NS, LoopWatch, MuxClock
from u2sa_hw.drivers.rc_mux.enable import AutonomyGate
from u2sa_hw.drivers.rc_mux.outputs import ManualReport, ModeReport, Note, Output
from u2sa_hw.drivers.rc_mux.pulse import MODE_MANUAL, MODE_NAMES, MODE_NO_SIGNAL, LastWidths, PulseMeter, RcModeFilter
from u2sa_hw.drivers.rc_mux.readback import SelectReadback
from u2sa_hw.safety.prearm import PrearmChecks


class MuxState:
    """The RC mux's mode, arming, enable line, read-back and timed messages (see the module docstring)."""

    def __init__(self, *, channels: Mapping[str, int], mode_channel: str, meter: PulseMeter, filter: RcModeFilter,
                 prearm: PrearmChecks, drive_enable: Callable[[bool], bool], select_line: int | None = None,
                 on_check_lost: str = "neutral", require_rearm: bool = True, select_mismatch_ms: float = 500.0,
                 publish_hz: float = 20.0, manual_hz: float = 25.0, manual: bool = False,
                 rc_mode_timeout_s: float = 0.25, device: str = "rc") -> None:
        self.channels = dict(channels)
        self.mode_line = self.channels[mode_channel]
        self.names_by_line = {line: name for name, line in self.channels.items()}
        self.meter, self.filter, self.manual = meter, filter, manual
        self.gate = AutonomyGate(prearm=prearm, on_check_lost=on_check_lost, require_rearm=require_rearm)
        self.readback = SelectReadback(line=select_line, mismatch_ms=select_mismatch_ms, device=device)
        self.clock = MuxClock(publish_hz=publish_hz, manual_hz=manual_hz)
        self.widths = LastWidths(self.channels, timeout_ns=filter.signal_timeout_ns)
        self.port_open = False     # the service keeps it current; a failed write of the line clears it
        self.device_clock = False  # a replay chip: its clock, no host-clock judgments
        self.stopping = False
        self.status = "ok"
        self.signal_losses = 0
        self.loop = LoopWatch(signal_timeout_ns=filter.signal_timeout_ns, rc_mode_timeout_s=rc_mode_timeout_s,
                              publish_hz=publish_hz)
        self._drive = drive_enable
        self._out: list[Output] = []
        self._host_ns = 0                          # the host's CLOCK_MONOTONIC at the call being judged
        self._published: tuple | None = None       # what the last RcMode said (its state_key)
        self._settled: tuple | None = None         # what the last settle left (_settle_inputs)

    # -- what it is ------------------------------------------------------------------------
    @property
    def clock_ns(self) -> int | None:
        """The device clock: the latest time judged (None: not started)."""
        return self.clock.now_ns

    @property
    def enabled(self) -> bool:
        """What the enable line was last driven to."""
        return self.gate.enabled

    def autonomy_allowed(self) -> tuple[bool, str]:
        """Whether the enable line may be high, and if not the first reason why not."""
        allowed, why, _ = self._blocked()
        return allowed, why

    def state_key(self) -> tuple:
        """What an RcMode says but the pulse widths (and the sigma in a pre-arm reason): a change goes out at once."""
        g = self.gate
        return (self.filter.mode, g.enabled, self.readback.mismatch, g.armed, g.hold, self._blocked()[2])

    # -- inputs: each returns what to do, in order ------------------------------------------------
    def clock_origin(self, origin_ns: int) -> None:
        """Where the recorded clock's zero lies on the device clock (0 live); taken when the clock starts."""
        self.clock.next_origin_ns = origin_ns

    def take_edge(self, line: int, rising: bool, at_ns: int, *, host_ns: int) -> list[Output]:
        """An edge stamped *at_ns*: what fell due up to it, then the edge, then its effects. (Live, the clock may
        be past the stamp already: an edge delivered late still comes before the timed messages held for it.)"""
        self._begin(host_ns)
        self.clock.advance(at_ns)
        self._advance(at_ns, at_ns)
        self._on_edge(line, rising, at_ns)
        self._settle(at_ns)
        return self._done()

    def take_tick(self, at_ns: int, *, step: bool = False, host_ns: int) -> list[Output]:
        """The chip's clock reached *at_ns*; *step*: the recorded loop looked at its clock then, with edges still
        on their way (what it judged then, as a live :meth:`step`: timed messages held for late edges)."""
        self._begin(host_ns)
        self.clock.advance(at_ns)
        self._advance(at_ns, at_ns - TIMED_HOLD_NS if step else at_ns)
        self._settle(at_ns)
        return self._done()

    def take_bus(self, channel: str, msg: Any, at_ns: int, *, host_ns: int) -> list[Output]:
        """A recorded FAILSAFE, Health or STATE_ESTIMATE (a replay chip's) arrived at *at_ns*, applied as live: a
        FAILSAFE drops the line at once, evidence waits for the next judgement. It does not move the clock."""
        self._begin(host_ns)
        if channel == ch.FAILSAFE:
            self._apply_failsafe(msg)
        elif channel == ch.HEALTH:
            self.gate.prearm.on_health(msg, at_ns / 1e9)
        elif channel == ch.STATE_ESTIMATE:
            self.gate.prearm.on_estimate(msg, at_ns / 1e9)
        return self._done()

    def step(self, now_ns: int | None, *, host_ns: int) -> list[Output]:
        """The loop's look at the device clock (*now_ns*): expiries up to it, timed messages up to it (live: up to
        TIMED_HOLD_NS before it, later ones wait for a later edge), the pre-arm checks and the line. On a replay
        chip everything was judged at its events' stamps: only the first state, and a clock run on by the chip."""
        self._host_ns = host_ns
        if self.device_clock and (self.clock.now_ns is None or now_ns is None or now_ns <= self.clock.now_ns):
            if self._published is None:
                self._settle(None)
            return self._done()
        at = self.clock.advance(now_ns)
        if at is not None:
            self._advance(at, at if self.device_clock else at - TIMED_HOLD_NS)
        self._settle(at)
        return self._done()

    def settle_now(self, *, host_ns: int) -> list[Output]:
        """Judge again at the clock's time (a replay chip gone: said at once, its clock went with it)."""
        self._host_ns = host_ns
        self._settle(self.clock.now_ns)
        return self._done()

    def on_failsafe(self, msg: Any, *, host_ns: int) -> list[Output]:
        """A FAILSAFE from the bus: the line drops now, not at the next judgement."""
        self._host_ns = host_ns
        self._apply_failsafe(msg)
        return self._done()

    def on_health(self, msg: Any, *, now_s: float) -> None:
        """A Health from the bus, arrived at *now_s* (the host's CLOCK_MONOTONIC, what the device clock is live)."""
        self.gate.prearm.on_health(msg, now_s)

    def on_estimate(self, msg: Any, *, now_s: float) -> None:
        """A STATE_ESTIMATE from the bus, arrived at *now_s* (as :meth:`on_health`)."""
        self.gate.prearm.on_estimate(msg, now_s)

    def loop_looked(self, host_ns: int) -> list[Output]:
        """The loop came round at *host_ns* (live only: a replay's load is not the vehicle's); a stall
        (:class:`LoopWatch`) is a signal loss: it disarms."""
        self._host_ns = host_ns
        gap_ns = self.loop.looked(host_ns)
        if gap_ns is not None:
            if self.gate.require_rearm and self.gate.armed:
                self.gate.armed = False
                self._out.append(Note("warning", f"RC service stalled for {gap_ns / 1e6:.0f} ms: disarmed "
                                                 "(switch through manual to re-arm)"))
            self._update_enable()
        return self._done()

    def port_opened(self, *, device_clock: bool, select_level: int | None, prearm: PrearmChecks | None = None) -> None:
        """The port (re)opened with the line low: disarm, forget half-seen pulses; a replay chip's clock starts
        again, and with *prearm* its recorded evidence replaces the bus's. Called from the opening thread, under
        the port's lock, so not under the service's (which is taken before the port's)."""
        self.gate.enabled = False
        if self.gate.require_rearm:
            self.gate.armed = False   # the lines were lost (or never held): the pilot re-arms
        self.meter.reset()
        self.device_clock = device_clock
        if device_clock:
            self.clock.restart()
            if prearm is not None:
                self.gate.reset_evidence(prearm)
        self.readback.level = select_level

    def stop(self, *, host_ns: int) -> list[Output]:
        """Stopping: the line drops, and a last RcMode says so."""
        self._host_ns = host_ns
        self.stopping = True
        self._update_enable()
        self._report_mode(None)
        return self._done()

    def set_live(self, *, require_rearm: bool, select_mismatch_ms: float) -> None:
        """The settings that apply at once when changed."""
        self.gate.require_rearm = require_rearm
        self.readback.mismatch_ms = select_mismatch_ms

    # -- the clock ----------------------------------------------------------------------------
    def _begin(self, host_ns: int) -> None:
        self._host_ns = host_ns
        if self._published is None:
            self._settle(None)   # the state before any input (a replay chip sends nothing before it)

    def _done(self) -> list[Output]:
        out, self._out = self._out, []
        return out

    def _advance(self, limit_ns: int, dues_ns: int) -> None:
        """In time order: every expiry (signal timeout, read-back mismatch) up to *limit_ns*, each timed message
        due up to *dues_ns* or before an expiry, each at its own time."""
        while True:
            expiry = self._next_expiry()
            due = self.clock.next_due()
            expires = expiry is not None and expiry[0] <= limit_ns
            if expires and (due is None or expiry[0] <= due[0]):
                self._expire(expiry[1], expiry[0])
            elif due is not None and (due[0] <= dues_ns or expires):
                self._timed(due[1], due[0], dues_ns)
            else:
                return

    def _next_expiry(self) -> tuple[int, str] | None:
        signal = self.filter.signal_expiry_ns()
        signal_at = None if signal is None else (signal, "signal")
        select = self.readback.expiry_ns()
        if select is None:
            return signal_at
        return (select, "select") if signal_at is None else min(signal_at, (select, "select"))

    def _expire(self, what: str, at_ns: int) -> None:
        if what == "signal":
            if self.filter.check_signal(at_ns):
                self._mode_changed(at_ns)
        else:
            self._check_select(at_ns)
            if not self.readback.mismatch:   # no read-back (any more): nothing left to expire
                self.readback.since = None
        self._settle(at_ns)

    def _timed(self, what: str, due_ns: int, dues_ns: int) -> None:
        """The RC_MODE or MANUAL_CMD due at *due_ns*, with the state as of then. Behind is judged live on the host
        clock, on a replay chip on its clock (ahead of the edges only after a recorded step)."""
        now_ns = (self.clock.now_ns or due_ns) if self.device_clock else self._host_ns
        manual_on = self.filter.mode == MODE_MANUAL and self.manual
        if self.clock.take_due(what, due_ns, dues_ns=dues_ns, now_ns=now_ns, manual_on=manual_on):
            if what == MODE_DUE:
                self._report_mode(due_ns)
            elif what == MANUAL_DUE:
                self._report_manual(due_ns)

    # -- edges and the mode ----------------------------------------------------------------------
    def _on_edge(self, line: int, rising: bool, at_ns: int) -> None:
        if line == self.readback.line:
            self.readback.level = int(rising)
            return
        pulse = self.meter.feed(line, rising, at_ns)
        if pulse is None:
            return
        self.widths.record(self.names_by_line[line], pulse)
        if line != self.mode_line:
            return
        if self.filter.on_frame(pulse.width_us, pulse.end_ns):
            self._mode_changed(pulse.end_ns)
        g = self.gate
        if self.filter.manual_confirmed and (not g.armed or g.hold) and not g.failsafes.active:
            g.armed, g.hold = True, False
            self._out.append(Note("info", "armed: the switch is at manual"))

    def _mode_changed(self, at_ns: int) -> None:
        mode = self.filter.mode
        if mode == MODE_NO_SIGNAL:
            self.signal_losses += 1
            self._out.append(Note("warning", f"RC mode {MODE_NAMES[mode]}: no valid mode pulse for "
                                             f"{self.filter.signal_timeout_ns / 1e6:.0f} ms (signal loss "
                                             f"{self.signal_losses})"))
            if self.gate.require_rearm:
                self.gate.armed = False
        else:
            self._out.append(Note("info", f"RC mode {MODE_NAMES[mode]}"))
        if mode == MODE_MANUAL and self.manual:
            self._report_manual(at_ns)  # the pilot has the software-muxed outputs from the first manual frame
            self.clock.manual_from(at_ns)
        else:
            self.clock.manual_from(None)

    def _check_select(self, at_ns: int) -> None:
        if self.readback.check(at_ns, enabled=self.gate.enabled, notes=self._out) and self.gate.require_rearm:
            self.gate.armed = False

    # -- the judgement after every input -----------------------------------------------------------
    def _settle(self, at_ns: int | None) -> None:
        """After an input at *at_ns*: the pre-arm checks, the line, the read-back, the status, and an RcMode at
        once if what it says changed. What it leaves is a fixed point, so when every input is as the last
        settle left it (:meth:`_settle_inputs`, the verdict by identity) it is skipped: most edges change nothing."""
        failsafe = self.gate.failsafes.reason()
        verdict = self._verdict(at_ns, failsafe)
        settled = self._settled
        if at_ns is not None and settled is not None and self._settle_inputs(verdict, failsafe) == settled:
            return
        self._check_prearm(verdict)
        if at_ns is not None:
            self._check_select(at_ns)   # with the line as it was: a mismatch just found goes out before it clears
        self._update_enable()
        if at_ns is not None:
            self.readback.start_if_disagrees(at_ns, enabled=self.gate.enabled)
        self._refresh_status()
        status = self.status
        if self.state_key() != self._published:
            self._report_mode(at_ns)
        self._settled = self._left(at_ns, verdict, failsafe, status)

    def _left(self, at_ns: int | None, verdict: tuple, failsafe: str, status: str) -> tuple | None:
        """What a settle left (:meth:`_settle_inputs`), or None (the next runs in full) when something changed
        meanwhile that it may not have seen whole (the port opened, from the opening thread)."""
        if at_ns is None:
            return None
        again = self.gate.failsafes.reason()
        if (again != failsafe or self._verdict(at_ns, again) is not verdict or self.status != status
                or self.state_key() != self._published):
            return None
        return self._settle_inputs(verdict, failsafe)

    def _verdict(self, at_ns: int | None, failsafe: str) -> tuple:
        """The pre-arm verdict at *at_ns* (live: the host clock, the time Health is stamped with on arrival;
        before a replay chip's clock starts, its zero); the same object while it stands."""
        judge_s = at_ns / 1e9 if at_ns is not None else 0.0 if self.device_clock else self._host_ns / 1e9
        return self.gate.prearm.verdict(judge_s, rc_link_ok=self.filter.mode != MODE_NO_SIGNAL,
                                        failsafe_reason=failsafe)

    def _settle_inputs(self, verdict: tuple, failsafe: str) -> tuple | None:
        """Everything :meth:`_settle` reads but the time; None while a read-back disagreement is pending (judged on
        the time: then every settle runs in full)."""
        if self.readback.since is not None:
            return None
        g = self.gate
        return (verdict, self.filter.mode, g.enabled, g.armed, g.hold, self.readback.mismatch, self.readback.level,
                self.port_open, self.stopping, failsafe, self._published, self.status, g.require_rearm, g.prearm)

    def _check_prearm(self, verdict: tuple) -> None:
        self.gate.take_verdict(verdict, mode=self.filter.mode, notes=self._out)

    def _apply_failsafe(self, msg: Any) -> None:
        self.gate.apply_failsafe(msg, self._out)
        self._update_enable()

    def _blocked(self) -> tuple[bool, str, Any]:
        return self.gate.blocked(stopping=self.stopping, port_open=self.port_open, mismatch=self.readback.mismatch,
                                 mode=self.filter.mode)

    def _update_enable(self) -> None:
        """Drive the line to what :meth:`autonomy_allowed` says."""
        want, why = self.autonomy_allowed()
        g = self.gate
        if want == g.enabled:
            return
        ok = self._drive(want)
        if not ok:
            self.port_open = False   # a failed write lost the port: the request is released, the line falls
        new = want if ok else False
        if new != g.enabled:
            g.enabled = new
            g.enable_changes += 1
            # handing over to autonomy is normal operation; losing it is worth a warning
            self._out.append(Note("info", "autonomy enable HIGH (all conditions hold)") if new
                             else Note("warning", f"autonomy enable low ({why})"))

    def _refresh_status(self) -> None:
        if not self.stopping:
            bad = not self.port_open or self.readback.mismatch or self.filter.mode == MODE_NO_SIGNAL
            self.status = "degraded" if bad else "ok"

    def _report_mode(self, at_ns: int | None) -> None:
        self._published = self.state_key()
        g = self.gate
        allowed, why = self.autonomy_allowed()
        widths = self.widths.as_of(at_ns if at_ns is not None else self._now_ns())
        self._out.append(ModeReport(at_ns, self.filter.mode, self.filter.mode_name, g.enabled, self.readback.mismatch,
                                    g.armed, g.hold, "" if allowed else why, widths))

    def _report_manual(self, at_ns: int) -> None:
        self._out.append(ManualReport(at_ns, dict(zip(self.channels, self.widths.as_of(at_ns)))))

    def _now_ns(self) -> int:
        return self.clock.now_ns if self.clock.now_ns is not None else self._host_ns
