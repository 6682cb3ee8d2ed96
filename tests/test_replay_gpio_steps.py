"""Where the replay chip places a *step* (hil/replay_gpio.py): the recorded RC mux published while no edge had
reached it (a receiver or machine held up), and the replayed mux must judge its timeouts at the moment the live
loop looked at its clock, not at the moment the recorder received the output.

Issue 24: on a loaded recording machine the recorder received the mux's outputs up to 90 ms after the mux
published them (`u2sa sim --record` with two `u2sa record` beside it). A step placed by the log time then lay
past the signal timeout the live mux had not reached: the replayed mux lost the signal, disarmed and stayed
disarmed (the pilot never re-armed: live nothing had happened), so its RC_MODE and MANUAL_CMD went their own
way for the rest of the log (`RC_MODE [rc] 1 inserted`, `MANUAL_CMD [rc] 2 inserted` in the corpus). The
output's header and the edges' taps are stamped by the driver itself, on one clock: the step comes from them.
"""

from __future__ import annotations

from pathlib import Path

from u2sa_hw import lcmtypes as t
from u2sa_hw.drivers.rc_mux.pulse import MODE_AUTONOMOUS, MODE_NO_SIGNAL, PulseMeter, RcModeFilter
from u2sa_hw.drivers.rc_mux.state import MuxState
from u2sa_hw.hil.replay_gpio import STEP_SILENCE_NS, ReplayGpioDevice
from u2sa_hw.recording.mcap_log import McapLogWriter
from u2sa_hw.safety.prearm import PrearmChecks
from u2sa_hw.safety.prearm_table import PrearmTable

LINES = {"throttle": 5, "steering": 6, "mode": 13}
FRAME_NS, SLOT_NS = 20_000_000, 6_000_000
KERNEL0 = 10_000_000_000                  # the recorded chip's CLOCK_MONOTONIC at the first frame
WALL = 1_700_000_000_000_000_000          # the recording machine's CLOCK_REALTIME - CLOCK_MONOTONIC
TAP_AFTER_FRAME_NS = 500_000              # the driver read a frame's edges this long after the frame ended
RECORDER_NS = 1_000_000                   # the recorder received most messages this long after they were sent
LATE_RECORDER_NS = 45_000_000             # ... but the step's output this long after it was published
LOOKED_NS = 60_000_000                    # the live loop published this long after it read the last edges
FRAMES = 10


def edge(line: int, rising: bool, kernel_ns: int, tap_ns: int) -> bytes:
    rec = t.RawGpioEdge()
    rec.header.source, rec.header.timestamp_us = "rc", (tap_ns + WALL) // 1000
    rec.device, rec.line, rec.edge, rec.kernel_timestamp_ns = "rc", line, int(rising), kernel_ns
    return rec.encode()


def rc_mode(published_ns: int) -> bytes:
    msg = t.RcMode()
    msg.header.source, msg.header.timestamp_us = "rc", (published_ns + WALL) // 1000
    msg.mode, msg.mode_name, msg.autonomy_enabled, msg.armed = MODE_AUTONOMOUS, "autonomous", True, True
    msg.pulse_us, msg.num_channels = [1600, 1600, 2000], 3
    return msg.encode()


def frame_edges(k: int) -> list[tuple[int, int, bool]]:
    """(kernel stamp, line, rising) of frame *k*: every channel in its slot, the mode channel at 2000 us."""
    start = KERNEL0 + k * FRAME_NS
    out = []
    for slot, (name, line) in enumerate(LINES.items()):
        rise = start + slot * SLOT_NS
        out += [(rise, line, True), (rise + 1000 * (2000 if name == "mode" else 1600), line, False)]
    return out


def record_held_up_log(path: Path) -> tuple[int, int]:
    """Ten frames, then the receiver held (no edge); the live loop published 60 ms after reading the last frame
    and the recorder received that 45 ms late. Returns (the last mode pulse's fall, the live loop's look), kernel
    time."""
    log = McapLogWriter(path.parent, path=path)
    for k in range(FRAMES):
        tap = KERNEL0 + (k + 1) * FRAME_NS + TAP_AFTER_FRAME_NS   # handed over when the frame ended
        for kernel_ns, line, rising in frame_edges(k):
            log.write("RAW.rc", edge(line, rising, kernel_ns, tap), tap + WALL + RECORDER_NS)
    last_tap = KERNEL0 + FRAMES * FRAME_NS + TAP_AFTER_FRAME_NS
    looked = last_tap + LOOKED_NS
    log.write("RC_MODE", rc_mode(looked), looked + WALL + LATE_RECORDER_NS)
    log.close()
    last_fall = frame_edges(FRAMES - 1)[-1][0]
    return last_fall, looked


def test_a_step_is_placed_by_the_drivers_own_stamps_not_by_when_the_recorder_got_the_output(tmp_path: Path) -> None:
    last_fall, looked = record_held_up_log(tmp_path / "held.mcap")
    device = ReplayGpioDevice(name="rc", socket_path=tmp_path / "gpio.sock", service="rc")
    device.preload(tmp_path / "held.mcap", start_ns=0, end_ns=2 ** 63 - 1)
    steps = [tick for _, tick in device.clock_ticks() if tick.step]
    assert len(steps) == 1
    step_ns = steps[0].kernel_timestamp_ns
    # the live look was 66.5 ms after the last mode pulse; the step is never later than it (it is earlier by the
    # quickest tap's delay, the mode pulse's fall to its frame's end: 6.5 ms here), so inside the signal timeout
    quickest = KERNEL0 + FRAMES * FRAME_NS + TAP_AFTER_FRAME_NS - last_fall
    assert step_ns == looked - quickest
    assert step_ns - last_fall < 100_000_000
    # by the log time (less the quickest log lag) it would have been 104 ms after it: past the signal timeout
    by_log = looked + LATE_RECORDER_NS - (quickest + RECORDER_NS)
    assert by_log - last_fall > 100_000_000


def test_an_output_the_recorder_got_late_is_no_step_when_the_driver_had_just_read_an_edge(tmp_path: Path) -> None:
    path = tmp_path / "late.mcap"
    log = McapLogWriter(path.parent, path=path)
    tap = KERNEL0 + FRAME_NS + TAP_AFTER_FRAME_NS
    for kernel_ns, line, rising in frame_edges(0):
        log.write("RAW.rc", edge(line, rising, kernel_ns, tap), tap + WALL + RECORDER_NS)
    published = tap + 2_000_000   # published at once after the frame ...
    log.write("RC_MODE", rc_mode(published), published + WALL + STEP_SILENCE_NS + 20_000_000)   # ... received late
    log.close()
    device = ReplayGpioDevice(name="rc", socket_path=tmp_path / "gpio.sock", service="rc")
    device.preload(path, start_ns=0, end_ns=2 ** 63 - 1)
    assert not [tick for _, tick in device.clock_ticks() if tick.step]


def test_the_replayed_mux_keeps_the_signal_through_the_step(tmp_path: Path) -> None:
    """The mux fed the recorded edges and the step: live it did not time the signal out there, nor may the replay."""
    last_fall, _ = record_held_up_log(tmp_path / "held.mcap")
    device = ReplayGpioDevice(name="rc", socket_path=tmp_path / "gpio.sock", service="rc")
    device.preload(tmp_path / "held.mcap", start_ns=0, end_ns=2 ** 63 - 1)
    state = mux_after_frames()
    for tick in sorted((tick for _, tick in device.clock_ticks() if tick.step), key=lambda x: x.kernel_timestamp_ns):
        state.take_tick(tick.kernel_timestamp_ns, step=True, host_ns=0)
    assert state.filter.mode != MODE_NO_SIGNAL, "the step lay past the signal timeout the live mux never reached"


# A log with the driver's own looks (RawGpioClockRead, tapped since 2026-12): the step is the look itself.
QUICK_TAP_NS = 100_000          # each edge read 0.1 ms after it happened
PUBLISH_NS = 400_000            # the look's RC_MODE published 0.4 ms after the look
LOOK_AFTER_FALL_NS = 99_800_000  # the look: 99.8 ms after the last mode pulse, inside the 100 ms signal timeout


def clock_read(clock_ns: int, tap_ns: int) -> bytes:
    rec = t.RawGpioClockRead()
    rec.header.source, rec.header.timestamp_us = "rc", (tap_ns + WALL) // 1000
    rec.device, rec.clock_ns = "rc", clock_ns
    return rec.encode()


def record_borderline_log(path: Path, *, looks: bool) -> int:
    """Ten frames whose edges were read at once, then a held-up receiver; the live loop looked 99.8 ms after the
    last mode pulse (no timeout) and published 0.4 ms later. *looks*: the look itself is recorded. Returns it."""
    log = McapLogWriter(path.parent, path=path)
    for k in range(FRAMES):
        for kernel_ns, line, rising in frame_edges(k):
            log.write("RAW.rc", edge(line, rising, kernel_ns, kernel_ns + QUICK_TAP_NS),
                      kernel_ns + QUICK_TAP_NS + WALL + RECORDER_NS)
    looked = frame_edges(FRAMES - 1)[-1][0] + LOOK_AFTER_FALL_NS
    if looks:
        log.write("RAW.rc", clock_read(looked, looked), looked + WALL + RECORDER_NS)
    log.write("RC_MODE", rc_mode(looked + PUBLISH_NS), looked + PUBLISH_NS + WALL + RECORDER_NS)
    log.close()
    return looked


class TickingChip:
    """What the replay device hands the chip: its origin, the edges and the ticks (with their stamps)."""

    def __init__(self) -> None:
        self.ticks: list[tuple[int, bool]] = []

    def set_origin(self, offset_ns: int) -> None:
        self.origin = offset_ns

    def drive_input(self, line: int, level: int, stamp_ns: int | None = None) -> bool:
        return True

    def tick(self, stamp_ns: int, *, step: bool = False) -> None:
        self.ticks.append((stamp_ns, step))


def mux_after_frames() -> MuxState:
    state = MuxState(channels=LINES, mode_channel="mode", meter=PulseMeter(lines=LINES.values()),
                     filter=RcModeFilter(debounce_frames=3, signal_timeout_ns=100_000_000),
                     prearm=PrearmChecks(PrearmTable(gps=None, estimator=None, imu=None, required_services=None)),
                     drive_enable=lambda level: True)
    state.port_open = True
    state.port_opened(device_clock=True, select_level=None)
    for k in range(FRAMES):
        for kernel_ns, line, rising in frame_edges(k):
            state.take_edge(line, rising, kernel_ns, host_ns=0)
    assert state.filter.mode == MODE_AUTONOMOUS
    return state


def played_steps(path: Path, tmp_path: Path) -> tuple[ReplayGpioDevice, list[int]]:
    """The replay device fed the log's RAW.rc records: the steps it sent the chip, in recorded kernel time."""
    from u2sa_hw.messages import REGISTRY
    from u2sa_hw.recording.log_reader import LogFile

    device = ReplayGpioDevice(name="rc", socket_path=tmp_path / "gpio.sock", service="rc")
    device.preload(path, start_ns=0, end_ns=2 ** 63 - 1)
    device.chip = TickingChip()
    for m in LogFile(path).messages():
        if m.channel == "RAW.rc":
            device.feed(REGISTRY.decode(m.data)[0])
    return device, [stamp - device.chip.origin for stamp, step in device.chip.ticks if step]


def test_a_recorded_look_is_the_step_to_the_nanosecond(tmp_path: Path) -> None:
    path = tmp_path / "looks.mcap"
    looked = record_borderline_log(path, looks=True)
    device, steps = played_steps(path, tmp_path)
    assert not [tick for _, tick in device.clock_ticks() if tick.step], "no step estimated from the outputs"
    assert steps == [looked] and device.counts["steps"] == 1


def test_the_replayed_mux_judges_a_borderline_look_as_the_live_one_did(tmp_path: Path) -> None:
    """Live, the look 99.8 ms after the last mode pulse kept the signal. Estimated from the output's header (0.4 ms
    after the look) less the quickest tap (0.1 ms) the step lands 100.1 ms after it, past the timeout: the replayed
    mux lost a signal the live one kept (issue 24, the corpus under load). The recorded look keeps it."""
    looked = record_borderline_log(tmp_path / "estimated.mcap", looks=False)
    estimated = ReplayGpioDevice(name="rc", socket_path=tmp_path / "gpio.sock", service="rc")
    estimated.preload(tmp_path / "estimated.mcap", start_ns=0, end_ns=2 ** 63 - 1)
    [step] = [tick.kernel_timestamp_ns for _, tick in estimated.clock_ticks() if tick.step]
    assert step == looked + PUBLISH_NS - QUICK_TAP_NS
    lost = mux_after_frames()
    lost.take_tick(step, step=True, host_ns=0)
    assert lost.filter.mode == MODE_NO_SIGNAL, "the estimate lies past the timeout (why looks are recorded)"
    record_borderline_log(tmp_path / "looks.mcap", looks=True)
    _, steps = played_steps(tmp_path / "looks.mcap", tmp_path)
    kept = mux_after_frames()
    for stamp in steps:
        kept.take_tick(stamp, step=True, host_ns=0)
    assert steps and kept.filter.mode == MODE_AUTONOMOUS


def test_in_a_log_with_looks_the_silence_ticks_stop_where_the_looks_take_over(tmp_path: Path) -> None:
    """After the last edge the live loop's looks past CLOCK_READ_AFTER_NS are in the log; a live loop that stopped
    looking (its service stopping) must not be timed out in its place by ticks running on to its last output."""
    path = tmp_path / "looks.mcap"
    looked = record_borderline_log(path, looks=True)
    device = ReplayGpioDevice(name="rc", socket_path=tmp_path / "gpio.sock", service="rc")
    device.preload(path, start_ns=0, end_ns=2 ** 63 - 1)
    last_edge = frame_edges(FRAMES - 1)[-1][0]
    ticks = [tick.kernel_timestamp_ns for _, tick in device.clock_ticks()]
    assert ticks and max(ticks) - last_edge <= STEP_SILENCE_NS < looked - last_edge
    # a log without looks keeps its ticks to the driver's last output
    record_borderline_log(tmp_path / "old.mcap", looks=False)
    old = ReplayGpioDevice(name="rc", socket_path=tmp_path / "gpio2.sock", service="rc")
    old.preload(tmp_path / "old.mcap", start_ns=0, end_ns=2 ** 63 - 1)
    assert max(tick.kernel_timestamp_ns for _, tick in old.clock_ticks() if not tick.step) - last_edge > STEP_SILENCE_NS
