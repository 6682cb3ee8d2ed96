"""RC mux driver: pulse measurement and the mode state machine on their own, then the driver
as a real service process against the mock chip, RC receiver and mux in this process."""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import ServiceProcesses, wait_until
from gpio_driver_harness import BusCollector
from serial_driver_harness import start_driver, write_profile

from u2sa_hw.drivers.rc_mux.pulse import (FALL_WITHOUT_RISE, MODE_AUTONOMOUS, MODE_MANUAL, MODE_NO_SIGNAL, RISE_WITHOUT_FALL,
                              TOO_LONG, TOO_SHORT, PulseMeter, RcModeFilter)
from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.rc_receiver import MuxMock, RcReceiverMock
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.ports.tap import raw_channel

MS = 1_000_000
RC_LINES = {"throttle": 5, "steering": 6, "mode": 13}
ENABLE, SELECT = 21, 20


# ---------------------------------------------------------------- pulse measurement ---------------
def test_pulse_width_is_fall_minus_rise_per_line() -> None:
    meter = PulseMeter(lines=[5, 6])
    assert meter.feed(5, True, 1_000_000) is None
    assert meter.feed(6, True, 1_100_000) is None
    p5 = meter.feed(5, False, 2_500_000)
    p6 = meter.feed(6, False, 2_100_123)
    assert p5 is not None and (p5.line, p5.width_us, p5.end_ns) == (5, 1500.0, 2_500_000)
    assert p6 is not None and p6.width_us == pytest.approx(1000.123)
    assert meter.feed(7, True, 0) is None and meter.feed(7, False, 1_500_000) is None  # not an RC line
    assert meter.pulses == 2 and meter.rejected_total == 0


def test_pulses_out_of_range_and_missed_edges_are_rejected_and_counted() -> None:
    meter = PulseMeter(lines=[5], min_us=800, max_us=2200)
    meter.feed(5, True, 0)
    assert meter.feed(5, False, 500_000) is None               # 500 us glitch
    meter.feed(5, True, 10 * MS)
    assert meter.feed(5, False, 10 * MS + 2_300_000) is None   # 2300 us
    meter.feed(5, True, 20 * MS)
    assert meter.feed(5, False, 40 * MS) is None               # a missed fall: a whole frame gap
    assert meter.feed(5, False, 41 * MS) is None               # fall without rise
    meter.feed(5, True, 50 * MS)
    meter.feed(5, True, 70 * MS)                               # rise without fall: the first is dropped
    assert meter.feed(5, False, 71 * MS) is not None
    meter.feed(5, True, 80 * MS)
    meter.reset()                                              # port lost: the half pulse is forgotten
    assert meter.feed(5, False, 81 * MS) is None
    assert dict(meter.rejected) == {TOO_SHORT: 1, TOO_LONG: 2, FALL_WITHOUT_RISE: 2, RISE_WITHOUT_FALL: 1}
    assert meter.pulses == 1
    assert meter.feed(5, True, 90 * MS) is None and meter.feed(5, False, 90 * MS + 800_000).width_us == 800.0
    assert meter.feed(5, True, 95 * MS) is None and meter.feed(5, False, 95 * MS + 2_200_000).width_us == 2200.0
    with pytest.raises(ValueError):
        PulseMeter(lines=[5], min_us=2000, max_us=1000)


# ---------------------------------------------------------------- mode state machine ------------
def frames(f: RcModeFilter, widths: list[float], *, start_ns: int = 0) -> list[int]:
    """Feed one pulse per 20 ms frame; the mode after each."""
    modes = []
    for k, w in enumerate(widths):
        f.on_frame(w, start_ns + k * 20 * MS)
        modes.append(f.mode)
    return modes


def test_mode_changes_only_after_debounce_frames() -> None:
    f = RcModeFilter(debounce_frames=3)
    assert f.mode == MODE_NO_SIGNAL and f.mode_name == "no signal"
    assert frames(f, [1000, 1000, 1000]) == [MODE_NO_SIGNAL, MODE_NO_SIGNAL, MODE_MANUAL]
    assert frames(f, [2000, 2000, 2000, 2000], start_ns=100 * MS) == [MODE_MANUAL, MODE_MANUAL, MODE_AUTONOMOUS,
                                                                       MODE_AUTONOMOUS]
    assert f.mode_name == "autonomous" and f.changes == 2 and f.frames == 7


def test_glitches_never_grant_autonomy_and_one_manual_frame_takes_it_away() -> None:
    f = RcModeFilter(debounce_frames=3)
    frames(f, [1000] * 3)
    assert set(frames(f, [2000, 1000, 2000, 2000, 1000, 2000, 1000] * 5, start_ns=MS)) == {MODE_MANUAL}
    assert f.manual_confirmed is False, "the last frames were not 3 manual in a row"
    frames(f, [1000] * 3, start_ns=5_000 * MS)
    assert f.manual_confirmed, "3 manual frames in a row: what arms"
    frames(f, [2000] * 3, start_ns=10_000 * MS)
    assert f.mode == MODE_AUTONOMOUS and not f.manual_confirmed
    # the safe direction never waits: one manual frame leaves autonomy, but does not arm
    assert frames(f, [1000, 2000], start_ns=20_000 * MS) == [MODE_MANUAL, MODE_MANUAL]
    assert not f.manual_confirmed


def test_hysteresis_band_keeps_the_present_side() -> None:
    f = RcModeFilter(autonomous_above_us=1700, manual_below_us=1300, debounce_frames=2)
    frames(f, [1500, 1500])
    assert f.mode == MODE_MANUAL                     # from no signal, the band means manual
    assert frames(f, [1650] * 5 + [1699] * 5) == [MODE_MANUAL] * 10
    frames(f, [1701, 1701])
    assert f.mode == MODE_AUTONOMOUS
    assert frames(f, [1350] * 5 + [1301] * 5) == [MODE_AUTONOMOUS] * 10
    frames(f, [1299, 1299])
    assert f.mode == MODE_MANUAL


def test_no_valid_frame_for_the_timeout_is_no_signal() -> None:
    f = RcModeFilter(debounce_frames=1, signal_timeout_ns=200 * MS)
    assert not f.check_signal(10_000 * MS)           # already no signal: no change
    f.on_frame(1000, 1000 * MS)
    assert f.mode == MODE_MANUAL
    assert not f.check_signal(1200 * MS)             # exactly the timeout: still there
    assert f.check_signal(1200 * MS + 1)
    assert f.mode == MODE_NO_SIGNAL
    f.on_frame(2000, 1300 * MS)
    assert f.mode == MODE_AUTONOMOUS                 # the signal is back; debounce 1
    f.on_frame(2000, 1250 * MS)                      # an older stamp never moves the last frame back
    assert f.last_frame_ns == 1300 * MS


@pytest.mark.parametrize("kwargs", [dict(autonomous_above_us=1300, manual_below_us=1700), dict(debounce_frames=0),
                                    dict(signal_timeout_ns=0)])
def test_nonsense_filter_settings_are_refused(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        RcModeFilter(**kwargs)


# ---------------------------------------------------------------- the driver as a service ------
class RcRig:
    """Mock chip + RC receiver + mux in this process; the driver as a service; a bus collector."""

    def __init__(self, *, chip: MockGpioChip, rc: RcReceiverMock, mux: MuxMock, proc: subprocess.Popen,
                 bus: BusClient, collector: BusCollector) -> None:
        self.chip, self.rc, self.mux, self.proc, self.bus, self.col = chip, rc, mux, proc, bus, collector

    def mode(self, predicate: Any, *, since: int | None = None, message: str = "", timeout: float = 15.0) -> t.RcMode:
        start = self.col.count(ch.RC_MODE) if since is None else since
        return self.col.wait_for(ch.RC_MODE, predicate, since=start, timeout=timeout, message=message)

    def health(self, predicate: Any, *, message: str = "") -> dict[str, str]:
        return self.col.health_of("rc", predicate, since=self.col.count(ch.HEALTH), message=message)

    def failsafe(self, active: bool) -> None:
        msg = t.Failsafe()
        msg.active, msg.reason = active, "test says so" if active else ""
        self.bus.publish(ch.FAILSAFE, msg)

    def to_autonomous(self) -> None:
        """From manual: the pilot flips the switch; the driver enables and the mux selects autonomous."""
        self.rc.set_mode_switch(True)
        self.mode(lambda m: m.mode == MODE_AUTONOMOUS and m.autonomy_enabled, message="autonomous and enabled")
        wait_until(lambda: self.mux.selected == "autonomous", message="the mux to select autonomous")


@pytest.fixture
def socket_dir() -> Iterator[Path]:
    path = Path(tempfile.mkdtemp(prefix="u2sa-rc-", dir="/tmp"))  # short: Unix socket paths are limited
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def rig(request: pytest.FixtureRequest, socket_dir: Path, tmp_path: Path, services: ServiceProcesses,
        bus: BusClient) -> Iterator[RcRig]:
    extra = getattr(request, "param", {})
    # release_level None: a released output keeps its level, so a low enable line after a stop
    # is the driver's own doing, not the mock board's pull-down
    chip = MockGpioChip(socket_path=str(socket_dir / "gpio.sock"), release_level=None).start()
    rc = RcReceiverMock(chip, lines=RC_LINES, frame_hz=50).start()
    mux = MuxMock(chip, rc, enable_line=ENABLE, select_line=SELECT).start()
    collector = BusCollector(bus).listen(ch.RC_MODE, t.RcMode).listen(ch.HEALTH, t.Health)
    collector.listen(raw_channel("rc"), None)
    settings = {"channels": "throttle=5,steering=6,mode=13", "mode_channel": "mode",
                "enable_line": ENABLE, "select_line": SELECT, "debounce_frames": 3, "signal_timeout_ms": 400.0,
                "select_mismatch_ms": 1500.0, "publish_hz": 20.0, **extra}
    proc = start_driver(services, write_profile(tmp_path, name="rc", kind="rc_mux", settings=settings,
                                                devices={"rc": f"mock+gpio://{chip.socket_path}"}), "rc")
    rig = RcRig(chip=chip, rc=rc, mux=mux, proc=proc, bus=bus, collector=collector)
    try:
        rig.mode(lambda m: m.mode == MODE_MANUAL, since=0, message="the pilot's manual mode", timeout=30.0)
        yield rig
    finally:
        services.stop_all()
        mux.stop()
        rc.stop()
        chip.stop()


@pytest.mark.parametrize("rig", [{"record_raw": True}], indirect=True)
def test_pilot_switch_failsafe_rearm_and_sigterm(rig: RcRig) -> None:
    first = rig.mode(lambda m: m.mode == MODE_MANUAL, message="manual")
    assert (first.mode_name, first.autonomy_enabled, first.select_mismatch) == ("manual", False, False)
    rig.mode(lambda m: list(m.pulse_us) == [1500, 1500, 1000], message="exact pulse widths")
    rig.rc.set_pulse("throttle", 1623)
    rig.mode(lambda m: list(m.pulse_us) == [1623, 1500, 1000], message="the new throttle width")
    assert rig.chip.read_output(ENABLE) == 0 and rig.mux.selected == "rc"

    rig.to_autonomous()
    assert rig.chip.read_output(ENABLE) == 1

    rig.failsafe(True)
    wait_until(lambda: rig.chip.read_output(ENABLE) == 0, message="the enable line to drop on FAILSAFE")
    wait_until(lambda: rig.mux.selected == "rc", message="the mux back to RC")
    rig.mode(lambda m: m.mode == MODE_AUTONOMOUS and not m.autonomy_enabled, message="autonomous, not enabled")
    rig.failsafe(False)
    # the pre-arm verdict is taken on the mux's loop: a health between the clear and that turn may still
    # name the failsafe; the next names what still blocks, the disarm
    details = rig.health(lambda d: d["failsafe"] == "False" and "failsafe held" not in d["enable_blocked_by"],
                         message="the failsafe cleared")
    assert "not armed" in details["enable_blocked_by"] and rig.chip.read_output(ENABLE) == 0

    rig.rc.set_mode_switch(False)           # the pilot re-arms through manual (held for debounce_frames)
    rig.mode(lambda m: m.mode == MODE_MANUAL and m.armed, message="manual again, armed")
    rig.to_autonomous()

    raw = rig.col.since(raw_channel("rc"))
    assert any(isinstance(r, t.RawGpioEdge) and r.line == 13 and r.device == "rc" for r in raw)
    assert any(isinstance(r, t.RawGpioWrite) and (r.line, r.value) == (ENABLE, 1) for r in raw)

    rig.proc.terminate()
    assert rig.proc.wait(timeout=10) == 0
    assert rig.chip.read_output(ENABLE) == 0, "the driver drives enable low on SIGTERM"
    assert rig.mux.selected == "rc"


def test_signal_loss_is_no_signal_counted_and_autonomy_needs_rearming(rig: RcRig) -> None:
    rig.to_autonomous()
    assert rig.health(lambda d: d["mode"] == "autonomous")["signal_losses"] == "0"
    rig.rc.signal_loss(True)
    lost = rig.mode(lambda m: m.mode == MODE_NO_SIGNAL, message="no signal")
    assert lost.mode_name == "no signal" and not lost.autonomy_enabled and list(lost.pulse_us) == [0, 0, 0]
    assert rig.chip.read_output(ENABLE) == 0 and rig.mux.selected == "rc"
    details = rig.health(lambda d: d["mode"] == "no signal")
    assert details["status"] == "degraded" and details["signal_losses"] == "1"

    rig.rc.signal_loss(False)               # the switch is still at autonomous
    back = rig.col.count(ch.RC_MODE)
    rig.mode(lambda m: m.mode == MODE_AUTONOMOUS, since=back, message="the signal back")
    rig.mode(lambda m: m.mode == MODE_AUTONOMOUS, message="another message in autonomous")
    assert not any(m.autonomy_enabled for m in rig.col.since(ch.RC_MODE, back))
    assert rig.chip.read_output(ENABLE) == 0
    assert "not armed" in rig.health(lambda d: d["mode"] == "autonomous")["enable_blocked_by"]

    rig.rc.set_mode_switch(False)           # the pilot re-arms through manual ...
    rig.mode(lambda m: m.mode == MODE_MANUAL and m.armed, message="manual again, armed")
    rig.to_autonomous()                     # ... and autonomy can be enabled again
    assert rig.chip.read_output(ENABLE) == 1
    details = rig.health(lambda d: d["autonomy_enabled"] == "True", message="enabled again in health")
    assert details["status"] == "ok" and details["signal_losses"] == "1" and details["armed"] == "True"


def test_glitch_frames_do_not_flip_the_mode(rig: RcRig) -> None:
    start = rig.col.count(ch.RC_MODE)
    rig.rc.glitch(4, channel="mode", pulse_us=2000)       # valid width, the other side, one frame each
    wait_until(lambda: sum(1 for f in rig.rc.history if f.pulses_us and f.pulses_us["mode"] == 2000) >= 4,
               message="four autonomous-looking glitch frames sent")
    rig.rc.glitch(4, channel="mode", pulse_us=500)        # out of range
    details = rig.health(lambda d: "too_short:4" in d["rejected_kinds"], message="four rejected 500 us pulses")
    assert details["mode"] == "manual" and details["mode_changes"] == "1"   # only no signal -> manual
    assert {m.mode for m in rig.col.since(ch.RC_MODE, start)} == {MODE_MANUAL}
    assert not any(r.kind == "output" and r.line == ENABLE and r.value == 1 for r in rig.chip.history)


def test_unusable_config_change_over_the_bus_is_refused(rig: RcRig) -> None:
    resp = rig.bus.set_config("rc", "channels", "throttle=5,steering=6")
    assert resp is not None and not resp.ok
    assert "mode_channel 'mode' is not one of the channels" in resp.error
    resp = rig.bus.set_config("rc", "manual_below_us", "1800.0")
    assert resp is not None and not resp.ok and "hysteresis needs" in resp.error
    resp = rig.bus.set_config("rc", "select_mismatch_ms", "900.0")
    assert resp is not None and resp.ok


def test_select_readback_mismatch_is_reported(rig: RcRig) -> None:
    rig.to_autonomous()
    rig.mux.stick("autonomous")             # the mux stays on autonomous whatever the enable line says
    rig.failsafe(True)
    wait_until(lambda: rig.chip.read_output(ENABLE) == 0, message="enable dropped")
    bad = rig.mode(lambda m: m.select_mismatch, message="a select mismatch")
    assert not bad.autonomy_enabled and rig.mux.selected == "autonomous"
    details = rig.health(lambda d: d["select_mismatch"] == "True", message="the mismatch in health")
    assert details["status"] == "degraded" and details["select_mismatches"] == "1"
    assert "select line 20 reads autonomous but autonomy enable is low" in details["last_error"]
    rig.mux.stick(None)                     # the mux follows its inputs again: back to RC
    rig.mode(lambda m: not m.select_mismatch, message="the mismatch cleared")
    assert rig.mux.selected == "rc"


def test_mux_stuck_on_rc_is_a_mismatch_that_drops_and_disarms_autonomy(rig: RcRig) -> None:
    rig.mux.stick("rc")
    rig.rc.set_mode_switch(True)
    rig.mode(lambda m: m.mode == MODE_AUTONOMOUS and m.autonomy_enabled, message="autonomous and enabled")
    bad = rig.mode(lambda m: m.select_mismatch, message="a select mismatch")
    assert not bad.autonomy_enabled and rig.mux.selected == "rc"
    wait_until(lambda: rig.chip.read_output(ENABLE) == 0, message="enable dropped on the mismatch")
    details = rig.health(lambda d: d["select_mismatches"] == "1" and d["select_mismatch"] == "False",
                         message="the mismatch counted, then agreeing again (both low)")
    assert "select line 20 reads rc but autonomy enable is high" in details["last_error"]
    assert "not armed" in details["enable_blocked_by"] and rig.chip.read_output(ENABLE) == 0
    rig.mux.stick(None)
    rig.rc.set_mode_switch(False)           # re-armed through manual, autonomy works with a healthy mux
    rig.mode(lambda m: m.mode == MODE_MANUAL and m.armed, message="manual again, armed")
    rig.to_autonomous()


def test_lost_gpio_port_drops_enable_and_is_reopened(rig: RcRig) -> None:
    rig.to_autonomous()
    assert rig.chip.disconnect("u2sa:rc") == 1
    details = rig.health(lambda d: d["port_losses"] == "1" and d["port"] == "open", message="lost and reopened")
    assert details["chip"] == rig.chip.address
    wait_until(lambda: rig.chip.read_output(ENABLE) == 0, message="the reopened request drives enable low")
    rig.mode(lambda m: m.mode == MODE_AUTONOMOUS and not m.autonomy_enabled, message="disarmed after the loss")
    assert rig.proc.poll() is None


def test_bad_config_stops_the_service_with_the_reason(tmp_path: Path, services: ServiceProcesses) -> None:
    settings = {"channels": "throttle=5,steering=6", "mode_channel": "mode"}
    proc = start_driver(services, write_profile(tmp_path, name="rc", kind="rc_mux", settings=settings,
                                                devices={"rc": "mock+gpio:///nonexistent.sock"}), "rc")
    assert proc.wait(timeout=20) != 0
    text = (tmp_path / "rc.stderr").read_text()
    assert "mode_channel 'mode' is not one of the channels" in text
