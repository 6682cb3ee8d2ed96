"""The RC mux's decisions as pure logic (drivers/rc_mux/state.py): frames of edges with made-up stamps,
the time passed in, the enable line a recorder. No process, no port, no bus: each test says at which
stamp the mux decided what, so the safety chain's deadlines (RC loss -> neutral, the switch to manual
-> autonomy off) are checked to the nanosecond of the device clock."""

from __future__ import annotations

from typing import Any

import pytest

from u2sa_hw import lcmtypes as t
from u2sa_hw.drivers.rc_mux.outputs import ManualReport, ModeReport, Note, Output
from u2sa_hw.drivers.rc_mux.pulse import MODE_AUTONOMOUS, MODE_MANUAL, MODE_NO_SIGNAL, PulseMeter, RcModeFilter
from u2sa_hw.drivers.rc_mux.state import MuxState
from u2sa_hw.safety.prearm import PrearmChecks
from u2sa_hw.safety.prearm_table import GpsCheck, PrearmTable
from u2sa_hw.service.health import set_details

LINES = {"throttle": 5, "steering": 6, "mode": 13}
FRAME_NS = 20_000_000          # 50 Hz
SLOT_NS = 3_000_000            # each channel's pulse starts this far after the one before
START_NS = 10_000_000_000      # the device clock at the first frame
MANUAL_US, AUTO_US = 1000, 2000
GOOD_GPS = {"fix": True, "fix_type": "3D", "satellites": 9, "h_sigma_m": "0.71", "data": "ok"}


class Rig:
    """One MuxState on a recorded enable line; what it returned, in order."""

    def __init__(self, *, gps: bool = False, on_check_lost: str = "neutral", manual: bool = False) -> None:
        self.line: list[bool] = []   # each level driven (when: the RcMode that goes out with it says)
        table = PrearmTable(gps=GpsCheck("gps") if gps else None, estimator=None, imu=None, required_services=None)
        self.state = MuxState(channels=LINES, mode_channel="mode", meter=PulseMeter(lines=LINES.values()),
                              filter=RcModeFilter(debounce_frames=3, signal_timeout_ns=100_000_000),
                              prearm=PrearmChecks(table), drive_enable=self._drive, on_check_lost=on_check_lost,
                              manual=manual)
        self.state.port_open = True
        self.writes_ok = True
        self.out: list[Output] = []

    def _drive(self, level: bool) -> bool:
        self.line.append(level)
        return self.writes_ok

    def frame(self, start_ns: int, mode_us: int, *, host_ns: int | None = None, step: bool = True) -> int:
        """One frame of pulses from *start_ns* (the loop looks at the clock after it, unless *host_ns* holds it
        up: then its edges are taken at that host time); the mode pulse's falling edge."""
        for slot, (name, line) in enumerate(LINES.items()):
            rise = start_ns + slot * SLOT_NS
            fall = rise + 1000 * (mode_us if name == "mode" else 1600)
            self.out += self.state.take_edge(line, True, rise, host_ns=rise if host_ns is None else host_ns)
            self.out += self.state.take_edge(line, False, fall, host_ns=fall if host_ns is None else host_ns)
        end = start_ns + 2 * SLOT_NS + 1000 * mode_us
        if step:
            self.step(end)
        return end

    def frames(self, start_ns: int, mode_us: int, n: int, **kwargs: Any) -> tuple[list[int], int]:
        """*n* frames from *start_ns*: the mode pulses' falling edges and the next frame's start."""
        ends = [self.frame(start_ns + k * FRAME_NS, mode_us, **kwargs) for k in range(n)]
        return ends, start_ns + n * FRAME_NS

    def step(self, now_ns: int, host_ns: int | None = None) -> None:
        """The loop's look at the device clock (live: the host clock is the device clock)."""
        self.out += self.state.step(now_ns, host_ns=now_ns if host_ns is None else host_ns)

    def reports(self) -> list[ModeReport]:
        return [o for o in self.out if isinstance(o, ModeReport)]

    def changes(self) -> list[tuple[int | None, int, bool, bool, bool]]:
        """(stamp, mode, enabled, armed, hold) of each RcMode that said something new."""
        seen, out = None, []
        for r in self.reports():
            key = (r.mode, r.autonomy_enabled, r.armed, r.hold)
            if key != seen:
                out.append((r.at_ns, *key))
                seen = key
        return out

    def autonomous(self, start_ns: int) -> tuple[int, int]:
        """Arm through manual and switch to autonomous: when the line went high, and the next frame's start."""
        _, start_ns = self.frames(start_ns, MANUAL_US, 3)
        ends, start_ns = self.frames(start_ns, AUTO_US, 3)
        assert self.state.enabled, self.state.autonomy_allowed()
        return ends[-1], start_ns


def health(name: str, **details: Any) -> t.Health:
    msg = t.Health()
    msg.name, msg.status = name, "ok"
    msg.header.source = name
    set_details(msg, details)
    return msg


def failsafe(source: str, *, active: bool) -> t.Failsafe:
    msg = t.Failsafe()
    msg.header.source, msg.active, msg.reason = source, active, "test"
    return msg


def test_the_mode_follows_the_pulse_width_after_the_debounce() -> None:
    rig = Rig()
    manual_ends, start = rig.frames(START_NS, MANUAL_US, 3)
    auto_ends, start = rig.frames(start, AUTO_US, 3)
    # the start says no signal; manual on the third manual frame, autonomous on the third autonomous one, and the
    # line high with it: armed by the switch held at manual, no check to fail
    assert rig.changes() == [(None, MODE_NO_SIGNAL, False, False, False),
                             (manual_ends[2], MODE_MANUAL, False, True, False),
                             (auto_ends[2], MODE_AUTONOMOUS, True, True, False)]
    assert rig.line == [True]
    # a pulse in the hysteresis band keeps the side it is on; the widths are measured from the stamps
    rig.frames(start, 1500, 5)
    assert rig.state.filter.mode == MODE_AUTONOMOUS and rig.state.enabled
    assert rig.reports()[-1].pulse_us == [1600, 1600, 1500]


def test_rc_loss_is_no_signal_and_the_line_low_at_the_timeout_judged_at_its_own_time() -> None:
    rig = Rig()
    last, _ = rig.autonomous(START_NS)
    rig.step(last + 100_000_000)   # the timeout itself: still a signal
    assert rig.state.filter.mode == MODE_AUTONOMOUS and rig.state.enabled
    # the loop looks again only 300 ms later: the loss is judged at its own time, not the loop's
    rig.step(last + 400_000_000)
    lost = last + 100_000_000 + 1
    assert rig.line == [True, False]
    assert rig.changes()[-1] == (lost, MODE_NO_SIGNAL, False, False, False)
    assert lost - last <= 200_000_000   # the safety chain's deadline: RC loss -> neutral within 200 ms
    no_signal = [r for r in rig.reports() if r.mode == MODE_NO_SIGNAL and r.at_ns == lost]
    assert no_signal[0].pulse_us == [0, 0, 0] and no_signal[0].blocked_by.startswith("failsafe") is False
    assert rig.state.signal_losses == 1
    # the signal back at autonomous: no autonomy until the pilot re-arms through manual
    rig.frames(last + 500_000_000, AUTO_US, 5)
    assert rig.state.filter.mode == MODE_AUTONOMOUS and not rig.state.enabled
    assert rig.state.autonomy_allowed() == (False, "not armed (switch to manual to re-arm)")


def test_the_manual_switch_drops_autonomy_on_its_first_frame() -> None:
    rig = Rig(manual=True)
    _, start = rig.autonomous(START_NS)
    switched = rig.frame(start, MANUAL_US)   # ONE frame at manual: the safe direction never waits for a debounce
    assert rig.line == [True, False]
    assert switched - start <= 50_000_000   # the deadline: the manual switch stops autonomous outputs within 50 ms
    assert rig.changes()[-1] == (switched, MODE_MANUAL, False, True, False)
    # the pilot has the software-muxed outputs from that frame on: the sticks go out at once
    sticks = [o for o in rig.out if isinstance(o, ManualReport)]
    assert sticks[-1] == ManualReport(switched, {"throttle": 1600, "steering": 1600, "mode": MANUAL_US})


def test_autonomy_is_refused_while_a_prearm_check_fails_and_not_granted_by_itself_after() -> None:
    rig = Rig(gps=True)
    _, start = rig.frames(START_NS, MANUAL_US, 3)
    auto_ends, start = rig.frames(start, AUTO_US, 3)
    assert not rig.state.enabled and rig.line == []
    assert rig.reports()[-1].blocked_by.startswith("pre-arm check failed: gps")
    assert not rig.state.gate.armed   # refused: the attempt is over
    assert any(isinstance(o, Note) and o.text.startswith("autonomy refused: gps") for o in rig.out)
    # the GPS comes good with the switch still at autonomous: nothing hands autonomy over behind the pilot
    rig.state.on_health(health("gps", **GOOD_GPS), now_s=start / 1e9)
    _, start = rig.frames(start, AUTO_US, 3)
    assert not rig.state.enabled
    assert rig.state.autonomy_allowed() == (False, "not armed (switch to manual to re-arm)")
    _, start = rig.frames(start, MANUAL_US, 3)
    ends, start = rig.frames(start, AUTO_US, 3)
    assert rig.state.enabled and rig.line == [True]
    assert rig.changes()[-1] == (ends[2], MODE_AUTONOMOUS, True, True, False)


@pytest.mark.parametrize("action", ["neutral", "hold"])
def test_a_check_lost_while_autonomous_takes_on_check_lost(action: str) -> None:
    rig = Rig(gps=True, on_check_lost=action)
    rig.state.on_health(health("gps", **GOOD_GPS), now_s=START_NS / 1e9)
    _, start = rig.autonomous(START_NS)
    rig.state.on_health(health("gps", **{**GOOD_GPS, "fix_type": "2D"}), now_s=start / 1e9)
    lost = rig.frame(start, AUTO_US)
    assert rig.state.gate.checks_lost == 1
    last = rig.reports()[-1]
    assert last.blocked_by == "" if action == "hold" else last.blocked_by.startswith("pre-arm check failed: gps")
    if action == "neutral":   # autonomy dropped: the line low at the first judgement after the loss
        assert rig.line == [True, False] and not rig.state.gate.armed and not last.hold
        assert last.at_ns is not None and last.at_ns <= lost
    else:                     # the line stays, every output neutral until the pilot re-arms
        assert rig.line == [True] and rig.state.gate.hold and last.hold and last.autonomy_enabled
        rig.frames(start + FRAME_NS, MANUAL_US, 3)
        assert not rig.state.gate.hold and rig.state.gate.armed and not rig.state.enabled


def test_a_failsafe_drops_the_line_at_once_and_its_clear_needs_a_re_arm() -> None:
    rig = Rig()
    _, start = rig.autonomous(START_NS)
    rig.out += rig.state.on_failsafe(failsafe("hsm", active=True), host_ns=start)
    assert rig.line == [True, False] and not rig.state.enabled   # in the callback, not at the next loop turn
    rig.out += rig.state.on_failsafe(failsafe("hsm", active=False), host_ns=start)
    _, start = rig.frames(start, AUTO_US, 3)
    assert not rig.state.enabled and not rig.state.gate.armed
    _, start = rig.frames(start, MANUAL_US, 3)
    rig.frames(start, AUTO_US, 3)
    assert rig.state.enabled


def test_a_held_up_loop_judges_its_frames_in_device_clock_order() -> None:
    """The same frames, taken as they come and all at once 300 ms late (a starved loop), give the same
    decisions at the same stamps: the signal timeout inside the batch is judged before the edges after it."""
    def script(rig: Rig, host_ns: int | None) -> int:
        start = START_NS
        for mode_us, n in ((MANUAL_US, 3), (AUTO_US, 4)):
            _, start = rig.frames(start, mode_us, n, host_ns=host_ns, step=host_ns is None)
        for k in range(1, 16):   # no pulse for 150 ms: a signal loss in the middle of the batch
            if host_ns is None:
                rig.step(start + k * 10_000_000)
        start += 150_000_000
        _, start = rig.frames(start, MANUAL_US, 4, host_ns=host_ns, step=host_ns is None)
        return start

    live = Rig()
    end = script(live, None)
    held = Rig()
    assert script(held, end + 300_000_000) == end
    held.step(end, host_ns=end + 300_000_000)
    assert held.changes() == live.changes()
    assert held.line == live.line == [True, False]
    lost = live.changes()[3]
    assert lost[1] == MODE_NO_SIGNAL and lost[0] == START_NS + 6 * FRAME_NS + 2 * SLOT_NS + 1000 * AUTO_US + 100_000_001
    stamps = [r.at_ns for r in held.reports() if r.at_ns is not None]
    assert stamps == sorted(stamps)
    # the timed RcModes it was too late for are left out, not sent in a burst, and counted
    assert held.state.clock.skipped > 0 == live.state.clock.skipped
    assert len(held.reports()) < len(live.reports())


def test_a_failed_write_of_the_line_is_never_reported_as_autonomy() -> None:
    rig = Rig()
    _, start = rig.frames(START_NS, MANUAL_US, 3)
    rig.writes_ok = False   # the port is lost as the mux raises the line
    ends, _ = rig.frames(start, AUTO_US, 3)
    assert rig.line == [True] and not rig.state.enabled
    said = [r for r in rig.reports() if r.at_ns == ends[2]]
    assert said and not any(r.autonomy_enabled for r in said)
    assert said[-1].blocked_by == "GPIO port down"
