"""Replay devices for GPIO and PWM: a mock GPIO chip that plays recorded edges into the
driver's input lines (here), and mock PWM outputs (a sysfs-shaped directory or a mock PCA9685)
for a servo driver whose recorded commands come over the bus (hil/replay_pwm.py).

GPIO. :class:`ReplayGpioDevice` serves the mock chip protocol (it *is* a
``u2sa_hw.mocks.gpio_chip.MockGpioChip`` at a socket in the run directory), so the driver
requests its lines exactly as from a real chip. Each recorded ``RawGpioEdge`` drives its
input line when the player reaches it, stamped with the recorded kernel timestamp moved
onto this machine's CLOCK_MONOTONIC by one offset: every interval between edges (a pulse
width, a bounce) is the recorded one to the nanosecond. The offset is fixed at the first
edge so that the edge stamps keep their recorded lag behind the driver's clock (the time
between an edge and its tap, taken from each record's header). Lines start at the level the
recording implies (the level before the window, or the opposite of a line's first edge).
The chip keeps a clock of its own (``device_clock``): the drivers judge their signal
timeouts, debounce, pulse ageing and timed messages by the stamps of the edges they take
(``GpioPort.now_ns``), never by when the edges arrive, so the recorded edges can be played at
any rate or with ``--fast`` and the drivers see the recorded timing. Through a recorded
silence (no edges: an RC signal loss, the end of the window) the device sends clock ticks
every ``TICK_NS`` of recorded time, derived from the edges' own kernel stamps (never ahead
of the next recorded edge), so a timeout expires at the recorded moment; where the recorded
driver published while no edge had reached it for ``STEP_SILENCE_NS`` (edges arriving late on
a held-up machine), a *step* at that time, when the live driver judged its timeouts on its own
clock (:meth:`ReplayGpioDevice.clock_ticks`). The chip tells the
driver the offset (its clock's *origin*), so the driver's timed messages fall on the recorded
clock's grid (drivers/rc_mux/driver.py). In --fast the player waits while ``GPIO_BACKLOG`` frames are
queued for the driver, so nothing is dropped.

Recorded bus inputs. What a GPIO driver decides may also depend on bus messages (the RC mux's
pre-arm checks read every service's Health and the estimate, its enable line drops on FAILSAFE).
The device takes the recorded ``BUS_INPUTS`` in log order with its edges (the player hands
them over as :class:`u2sa_hw.hil.player.RecordedBusMessage`) and the chip passes those a driver asked
for (op ``bus``) on to it between the edges the recorded driver read before and after it (the
log's order: an edge's record was logged when the driver read it), stamped with the edge sent
before it; before the first edge, at its log time less the smallest (log time - kernel stamp)
of the window's edges (the recording machine's CLOCK_REALTIME - CLOCK_MONOTONIC, plus the
quickest tap). Only while the recorded driver ran: from its service's first message (or the
device's first record) to its last output; what came before or after, the recorded driver
never heard (or its reaction is not in the log).
What the driver writes to its output lines is compared by
``--compare`` as the ``RawGpioWrite`` records it taps (the replay keeps ``record_raw`` on).

PWM outputs: hil/replay_pwm.py. :func:`make_device` makes either kind.
"""

from __future__ import annotations

import heapq
import threading
import time
from pathlib import Path
from typing import Any, Iterator

from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.ports.gpio.port import CLOCK_READ_AFTER_NS
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.recording.mcap_log import header_source, header_timestamp_ns

from u2sa_hw.hil.replay_plan import ReplayError
from u2sa_hw.hil.replay_pwm import PwmReplayRig, ReplayPwmDevice

GPIO_MIN_LINES = 64   # lines of the replay chip (more when the log names higher offsets)
TICK_NS = 10_000_000  # the device clock's step through recorded silences (recorded time)
GPIO_BACKLOG = 512    # --fast: frames queued for the driver before the player waits
BUS_INPUTS = ("U2SA_HEALTH", "FAILSAFE", "STATE_ESTIMATE")   # recorded bus channels a GPIO driver may take
# an output of the recorded driver this long after the last edge it read: a step (a log without its looks)
STEP_SILENCE_NS = CLOCK_READ_AFTER_NS


class ClockTickRecord:
    """A tick of the replay chip's clock at recorded kernel time ``kernel_timestamp_ns`` (made by the
    replay, not recorded); ``step``: the recorded driver's loop looked at its clock then."""

    __slots__ = ("kernel_timestamp_ns", "step")

    def __init__(self, kernel_timestamp_ns: int, step: bool = False) -> None:
        self.kernel_timestamp_ns = kernel_timestamp_ns
        self.step = step


class ReplayGpioDevice:
    """A mock GPIO chip whose input lines replay a log's recorded edges (see the module docstring)."""

    kind = "gpio"
    streamed = True
    bus_inputs = BUS_INPUTS

    def __init__(self, *, name: str, socket_path: Path | str, service: str = "") -> None:
        self.name = name
        self.service = service                    # the recorded driver's service (its messages bound its life)
        self.socket_path = Path(socket_path)
        self.chip: Any = None
        self.timed = False                        # the window holds edges
        self.backlog_limit = GPIO_BACKLOG
        self._edge_times: list[tuple[int, int]] = []   # (log time, kernel stamp) of the window's edges
        self._end_ns = 0
        self._levels: dict[int, int] = {}         # line -> level at the window's start
        self._num_lines = GPIO_MIN_LINES
        self._min_lag_ns: int | None = None       # smallest (tap time - kernel stamp) in the window
        self._min_log_lag_ns: int | None = None   # smallest (log time - kernel stamp) in the window
        self._driver_from_ns: int | None = None   # log time of the recorded driver's first message or record
        self._driver_until_ns: int | None = None  # ... and of its last output (not its contract messages)
        # (log time, publish time or None) of the recorded driver's outputs while no edge came
        self._step_logs: list[tuple[int, int | None]] = []
        self._clock_reads = 0                     # the recorded driver's looks at its clock in the window (tapped)
        self._offset_ns: int | None = None
        self._last_sent_ns: int | None = None     # the latest stamp sent to the driver
        self._lock = threading.Lock()
        self.counts = {"edges": 0, "edges_on_outputs": 0, "repeated_levels": 0, "recorded_writes": 0,
                       "output_changes": 0, "ticks": 0, "steps": 0, "bus_inputs": 0}

    @property
    def address(self) -> str:
        """The chip address the driver's config names."""
        return f"mock:{self.socket_path}"

    def mock_address(self, real: DeviceAddress | None) -> str:
        """``mock+gpio://<this replay chip>/<the recorded address's lines>``."""
        lines = real.lines if real is not None and real.kind == "gpio" else ()
        return make_address("gpio", str(self.socket_path), lines, mock=True, device=self.name).url

    def config_changes(self) -> dict[str, Any]:
        """Nothing besides the address."""
        return {}

    def preload(self, log_path: Path, *, start_ns: int, end_ns: int) -> None:
        """Read the log once: the device's start levels, the lines used, the taps' lag, whether edges are timed,
        and when the recorded driver ran (its first message of any kind, its last output or record)."""
        first_in_window: dict[int, int] = {}
        raw = f"RAW.{self.name}"
        last_edge_log: int | None = None    # log time of the window's latest edge so far
        last_edge_tap: int | None = None    # ... and when the recorded driver tapped it (its header, wall clock)
        for m in LogFile(log_path).messages():
            if m.log_time_ns > end_ns:
                break
            if m.channel != raw:
                if self.service and header_source(m.data) == self.service:
                    if self._driver_from_ns is None:
                        self._driver_from_ns = m.log_time_ns
                    if not m.channel.startswith("U2SA_"):
                        self._driver_until_ns = m.log_time_ns
                        self._note_output(m.log_time_ns, header_timestamp_ns(m.data), last_edge_log, last_edge_tap)
                continue
            try:
                rec, _ = REGISTRY.decode(m.data)
            except MalformedMessage:
                continue
            kind = type(rec).__name__
            if kind not in ("RawGpioEdge", "RawGpioWrite", "RawGpioClockRead"):
                continue
            if self._driver_from_ns is None:
                self._driver_from_ns = m.log_time_ns
            self._driver_until_ns = m.log_time_ns
            if kind == "RawGpioClockRead":
                self._clock_reads += m.log_time_ns >= start_ns
                continue
            if kind == "RawGpioWrite":
                self._note_output(m.log_time_ns, int(rec.header.timestamp_us) * 1000 or None, last_edge_log,
                                  last_edge_tap)
            elif m.log_time_ns >= start_ns:
                last_edge_log, last_edge_tap = m.log_time_ns, int(rec.header.timestamp_us) * 1000 or None
            line = int(rec.line)
            self._num_lines = max(self._num_lines, line + 1)
            if kind != "RawGpioEdge":
                continue
            level = 1 if rec.edge else 0
            if m.log_time_ns < start_ns:
                self._levels[line] = level
                continue
            self.timed = True
            self._edge_times.append((m.log_time_ns, int(rec.kernel_timestamp_ns)))
            first_in_window.setdefault(line, level)
            lag = _tap_lag_ns(rec)
            if lag is not None and (self._min_lag_ns is None or lag < self._min_lag_ns):
                self._min_lag_ns = lag
            log_lag = m.log_time_ns - int(rec.kernel_timestamp_ns)
            if self._min_log_lag_ns is None or log_lag < self._min_log_lag_ns:
                self._min_log_lag_ns = log_lag
        for line, first in first_in_window.items():
            self._levels.setdefault(line, 1 - first)   # an edge to *first* means the line was at the other level
        self._end_ns = end_ns

    def _note_output(self, log_ns: int, published_ns: int | None, last_edge_log: int | None,
                     last_edge_tap: int | None) -> None:
        """An output of the recorded driver logged at *log_ns* and published at *published_ns* (its header, the
        driver's wall clock): a step when no edge was read for STEP_SILENCE_NS, judged on the driver's own clock
        (the edge's tap and the output's header) when both say, else on the log's."""
        if published_ns is not None and last_edge_tap is not None:
            gap = published_ns - last_edge_tap
        elif last_edge_log is not None:
            gap = log_ns - last_edge_log
        else:
            return
        if gap > STEP_SILENCE_NS:
            self._step_logs.append((log_ns, published_ns))

    def clock_ticks(self) -> Iterator[tuple[int, ClockTickRecord]]:
        """``(log time, tick)`` in log order: through every recorded silence longer than TICK_NS, and a step
        wherever the recorded driver published while no edge reached it.

        A silence tick's stamp is a previous edge's kernel stamp plus whole steps, and it stays before the
        next edge's stamp, so the clock never runs ahead of an edge still to come; its log time is the
        previous edge's plus the same steps (before the next edge's), which places it in the play order.
        After the last edge the ticks run to the recorded driver's last output (when the log says, else the
        window's end): a driver that had stopped is not timed out in its place. In a log that holds the
        driver's looks (``RawGpioClockRead``: every look more than CLOCK_READ_AFTER_NS after the latest edge)
        the ticks stop at that limit: later, the replayed driver looks where the live one did and nowhere
        else (a live loop that stopped looking as the service stopped is not timed out in its place; issue
        24: an Ackermann log's replayed mux lost the signal 150 ms after the live one's last look).

        A step is the recorded driver's loop at work (it published: a timed message, a change) more than
        STEP_SILENCE_NS after the last edge it had read: on a live chip edges can arrive late (a stalled
        receiver delivered 280 ms of stamped edges at once), and the live loop judged its timeouts on its
        clock meanwhile. The step carries that clock, taken from the driver's own stamps: the output's header
        time (when it published) less the smallest tap - kernel lag of the window's edges (when it read them),
        both the recording machine's wall clock: earlier than the live look by the quickest tap's delay, later
        only by the publish's own (well under a millisecond). The recorder's log time is later by its receive latency, up to 90 ms on a loaded machine:
        a step placed by it lay past a signal timeout the live mux never reached (issue 24). A log without
        header times falls back on the log time. Whether an output is a step is judged on the same stamps (the
        last edge's tap to the output's header). The step may run ahead of the late edges' stamps.
        """
        return heapq.merge(self._silence_ticks(), self._steps(), key=lambda item: item[0])

    def _steps(self) -> Iterator[tuple[int, ClockTickRecord]]:
        if self._min_log_lag_ns is None or self._clock_reads:
            return   # a log with the driver's looks (RawGpioClockRead) has the steps themselves: feed() plays them
        for log_ns, published_ns in self._step_logs:
            if published_ns is not None and self._min_lag_ns is not None:
                kernel_ns = published_ns - self._min_lag_ns   # the driver's own clock: what its loop had looked at
            else:
                kernel_ns = log_ns - self._min_log_lag_ns     # the recorder's: later by its receive latency
            yield log_ns, ClockTickRecord(kernel_ns, step=True)

    def _silence_ticks(self) -> Iterator[tuple[int, ClockTickRecord]]:
        times = self._edge_times
        end = self._end_ns
        if self._driver_until_ns is not None and times:
            end = max(times[-1][0], min(end, self._driver_until_ns))
        for i, (log_ns, kernel_ns) in enumerate(times):
            if i + 1 < len(times):
                next_log, next_kernel = times[i + 1]
            else:
                next_log = end + 1
                mapped = end + 1 - self._min_log_lag_ns if self._min_log_lag_ns is not None else kernel_ns
                next_kernel = max(kernel_ns + (end + 1 - log_ns), mapped)
            if self._clock_reads:   # the live looks past CLOCK_READ_AFTER_NS are in the log: ticks only up to it
                next_kernel = min(next_kernel, kernel_ns + CLOCK_READ_AFTER_NS + 1)
            step = TICK_NS
            while kernel_ns + step < next_kernel:
                yield min(log_ns + step, next_log - 1), ClockTickRecord(kernel_ns + step)
                step += TICK_NS

    def start(self) -> None:
        """Serve the replay chip with every recorded input line at its starting level."""
        from u2sa_hw.mocks.gpio_chip import MockGpioChip

        self.socket_path.parent.mkdir(parents=True, exist_ok=True)
        self.chip = MockGpioChip(socket_path=str(self.socket_path), num_lines=self._num_lines,
                                 label=f"replay-{self.name}", release_level=None, device_clock=True)
        for line, level in self._levels.items():
            self.chip.drive_input(line, level)
        self.chip.on_output(self._on_output)
        self.chip.start()

    def stop(self) -> None:
        """Stop serving."""
        if self.chip is not None:
            self.chip.stop()
            self.chip = None

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The driver holds its lines (its health says ``port = open`` and the chip has a consumer)."""
        return health.get("port") == "open" and self.chip is not None and bool(self.chip.consumers())

    def feed(self, record: Any) -> None:
        """Drive a recorded edge onto its line (stamped as described above), send a tick or a recorded bus
        message; count a recorded write."""
        kind = type(record).__name__
        if kind == "RawGpioWrite":
            self.counts["recorded_writes"] += 1
            return
        if kind == "ClockTickRecord":
            if self._offset_ns is not None:   # the clock starts with the first edge
                self.chip.tick(self._stamp(record.kernel_timestamp_ns), step=record.step)
                self.counts["steps" if record.step else "ticks"] += 1
            return
        if kind == "RawGpioClockRead":
            # the recorded driver looked at its clock then, no edge read for a while: a step at that very time
            if self._offset_ns is not None:
                self.chip.tick(self._stamp(int(record.clock_ns)), step=True)
                self.counts["steps"] += 1
            return
        if kind == "RecordedBusMessage":
            self._feed_bus(record)
            return
        if kind != "RawGpioEdge":
            return
        kernel_ns = int(record.kernel_timestamp_ns)
        if self._offset_ns is None:
            lag = _tap_lag_ns(record)
            behind = max(0, lag - self._min_lag_ns) if lag is not None and self._min_lag_ns is not None else 0
            self._start_clock(time.monotonic_ns() - behind - kernel_ns)
        stamp = kernel_ns + self._offset_ns
        try:
            changed = self.chip.drive_input(int(record.line), 1 if record.edge else 0, stamp)
        except ValueError:   # the replayed driver uses this line as an output (a changed config)
            self.counts["edges_on_outputs"] += 1
            return
        self._last_sent_ns = stamp if self._last_sent_ns is None else max(self._last_sent_ns, stamp)
        self.counts["edges"] += 1
        if not changed:      # the recording missed the opposite edge (the kernel dropped it): no edge now
            self.counts["repeated_levels"] += 1

    def _start_clock(self, offset_ns: int) -> None:
        """Fix the offset from recorded kernel time to the device clock, and tell the driver (its origin)."""
        self._offset_ns = offset_ns
        self.chip.set_origin(offset_ns)

    def _stamp(self, kernel_ns: int) -> int:
        """Recorded kernel time *kernel_ns* on the device clock, never before what was sent already."""
        stamp = kernel_ns + (self._offset_ns or 0)
        if self._last_sent_ns is not None and stamp < self._last_sent_ns:
            stamp = self._last_sent_ns
        self._last_sent_ns = stamp
        return stamp

    def _feed_bus(self, record: Any) -> None:
        """A recorded bus message to the driver if it asked for its channel, stamped with the edge (or tick)
        sent before it: the recorded driver took it between the edges it read before and after it (the log's
        order), and judged it at its loop's next turn; before the first edge, where the log puts it."""
        if self._min_log_lag_ns is None or self._driver_from_ns is None or record.log_time_ns < self._driver_from_ns \
                or (self._driver_until_ns is not None and record.log_time_ns > self._driver_until_ns):
            return   # no edges to place it among, or while the recorded driver did not run
        if self._last_sent_ns is not None:
            stamp = self._last_sent_ns
        else:
            kernel_ns = min(record.log_time_ns - self._min_log_lag_ns, self._edge_times[0][1])
            if self._offset_ns is None:
                self._start_clock(time.monotonic_ns() - kernel_ns)
            stamp = kernel_ns + self._offset_ns
        if self.chip.bus(stamp, record.channel, record.data):
            self.counts["bus_inputs"] += 1

    def pending(self) -> int:
        """Edges and ticks queued for the driver and not yet sent to it."""
        return self.chip.backlog() if self.chip is not None else 0

    def _on_output(self, line: int, value: int, timestamp_ns: int) -> None:
        with self._lock:
            self.counts["output_changes"] += 1

    def report(self) -> dict[str, Any]:
        """Edges played, recorded writes, and edges the replayed driver could not receive."""
        c = dict(self.counts)
        out: dict[str, Any] = {"kind": self.kind, **c, "divergences": c["edges_on_outputs"]}
        if c["edges_on_outputs"]:
            out["divergence"] = (f"{c['edges_on_outputs']} recorded edges fell on lines the replayed driver "
                                 "drives as outputs (changed line settings?)")
        return out


def _tap_lag_ns(record: Any) -> int | None:
    """How long after its kernel stamp an edge was tapped: header time (wall) - kernel stamp (monotonic).

    The two clocks differ by a constant, so only differences between records mean something.
    """
    stamp_us = int(record.header.timestamp_us)
    return stamp_us * 1000 - int(record.kernel_timestamp_ns) if stamp_us else None


def make_device(kind: str, name: str, run_dir: Path, *, service: str,
                rigs: dict[str, PwmReplayRig]) -> ReplayGpioDevice | ReplayPwmDevice:
    """The replay device for a GPIO or PWM device of *service*; *rigs* shares PWM outputs. It needs nothing
    of the driver's config: the lines and outputs come from the recorded address and records."""
    if kind == "gpio":
        return ReplayGpioDevice(name=name, socket_path=run_dir / f"gpio-{name}.sock", service=service)
    if kind == "pwm":
        rig = rigs.get(service)
        if rig is None:
            rig = rigs[service] = PwmReplayRig(service=service, run_dir=run_dir)
        return ReplayPwmDevice(name=name, rig=rig)
    raise ReplayError(f"RAW.{name}: replaying {kind} devices is not supported")
