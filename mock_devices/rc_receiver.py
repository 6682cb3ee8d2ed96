"""A mock RC receiver that outputs real PWM pulse trains on a MockGpioChip, and a model of
the hardware RC multiplexer that chooses between the pilot and the autonomy computer.

``RcReceiverMock`` emits one frame every 1/frame_hz s: each channel rises in its own slot
of the frame and falls after its pulse width (1000-2000 us, 1500 neutral). Edge
timestamps are computed from a monotonic frame clock (frame k starts at t0 + k*period),
not read after a sleep, so a driver measuring fall - rise gets the set width exactly; the
edges of a frame are handed to the chip once the frame is over, so no edge is delivered
before its time. The pilot's sticks: ``set_stick(channel, -1..1)``, ``set_sticks(
throttle=..., steering=...)``, ``centre_sticks()``; the mode switch: ``set_mode_switch``.
Faults: ``signal_loss`` (no edges), ``glitch`` (isolated out-of-range frames).

``MuxMock`` models the multiplexer: it selects the autonomous source only while the
autonomy-enable output line is high AND the pilot's mode switch (the mode channel) says
autonomous; otherwise, and on loss of the RC signal, the pilot (RC) side. Software and
pilot must both agree. It switches only the PWM outputs wired through it (the profile's
``[safety] hardware_mux``: :class:`u2sa_hw.mocks.actuation.PwmFeed` asks ``rc_pulse_us`` for
the pilot's pulse); CAN, I2C and GPIO outputs never pass through it. It drives an optional
select read-back input line (1 = autonomous).
Fault: ``stick(side)`` jams the mux on one side whatever its inputs say (a welded relay, a
mux that lost its own RC input); ``stick(None)`` frees it.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

from u2sa_hw.mocks.gpio_chip import MockGpioChip

log = logging.getLogger("u2sa_hw.mocks.rc_receiver")

EDGE_GUARD_NS = 100_000  # a pulse ends at least this long before the next channel's slot
STALL_NOTED_NS = 50_000_000   # this long more than a frame period between two frames: a stall (the thread was not run)


@dataclass(frozen=True)
class RcFrame:
    """One frame: its start on the monotonic clock, and each channel's pulse (None = no signal)."""

    start_ns: int
    pulses_us: dict[str, float] | None


FrameListener = Callable[[RcFrame], None]


class RcReceiverMock:
    """PWM pulses on *lines* (channel name -> chip line) of *chip*, *frame_hz* frames a second."""

    def __init__(self, chip: MockGpioChip, *, lines: dict[str, int], frame_hz: float = 50.0,
                 mode_channel: str = "mode", history_size: int = 10_000) -> None:
        if not lines:
            raise ValueError("RcReceiverMock needs at least one channel line")
        if frame_hz <= 0:
            raise ValueError(f"frame_hz must be positive, not {frame_hz}")
        self.chip = chip
        self.lines = dict(lines)
        self.mode_channel = mode_channel
        self.frame_period_ns = round(1e9 / frame_hz)
        self.slot_ns = self.frame_period_ns // len(self.lines)
        self.history: deque[RcFrame] = deque(maxlen=history_size)
        self.frames_sent = 0
        # (when it ended, how much longer than a frame period no frame was handed over) for each stall of at least
        # STALL_NOTED_NS: a real receiver never stalls, this thread does on an overloaded machine, and an RC mux
        # then rightly sees a signal loss
        self.stalls: deque[tuple[int, int]] = deque(maxlen=1000)
        self._pulses_ns = {name: 1_500_000 for name in self.lines}
        if mode_channel in self._pulses_ns:
            self._pulses_ns[mode_channel] = 1_000_000  # manual until the pilot flips the switch
        self._lock = threading.Lock()
        self._signal_lost = False
        self._glitches_pending = 0
        self._glitch: tuple[str | None, int] = (None, 500_000)
        self._last_was_glitch = False
        self._listeners: list[FrameListener] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def address(self) -> str:
        """The chip's address, which the RC driver config names."""
        return self.chip.address

    def set_pulse(self, channel: str, us: float) -> None:
        """Set *channel*'s pulse width in microseconds (normally 1000-2000)."""
        width_ns = round(us * 1000)
        self._check_width(channel, width_ns)
        with self._lock:
            self._pulses_ns[channel] = width_ns

    def pulse_us(self, channel: str) -> float:
        """The pulse width currently set for *channel*, in microseconds."""
        with self._lock:
            return self._pulses_ns[channel] / 1000

    def set_stick(self, channel: str, position: float) -> None:
        """Move the stick on *channel* to *position*, -1..1 (clamped): 1000..2000 us, 0 = centred (1500 us)."""
        self.set_pulse(channel, 1500.0 + 500.0 * max(-1.0, min(1.0, float(position))))

    def set_sticks(self, **positions: float) -> None:
        """Move several sticks at once: ``set_sticks(throttle=0.5, steering=-0.2)``; unknown channels refused first."""
        for channel in positions:
            if channel not in self.lines:
                raise ValueError(f"unknown RC channel {channel!r}; channels are {sorted(self.lines)}")
        for channel, position in positions.items():
            self.set_stick(channel, position)

    def stick_position(self, channel: str) -> float:
        """The position of the stick on *channel*, -1..1."""
        return (self.pulse_us(channel) - 1500.0) / 500.0

    def centre_sticks(self) -> None:
        """Let go of every stick (each channel but the mode switch back to 1500 us)."""
        for channel in self.lines:
            if channel != self.mode_channel:
                self.set_pulse(channel, 1500.0)

    @property
    def signal_lost(self) -> bool:
        """True while ``signal_loss(True)`` is in force."""
        with self._lock:
            return self._signal_lost

    def set_mode_switch(self, autonomous: bool) -> None:
        """Flip the pilot's mode switch: 2000 us = autonomous, 1000 us = manual."""
        self.set_pulse(self.mode_channel, 2000 if autonomous else 1000)

    def signal_loss(self, on: bool) -> None:
        """Fault: while on, the receiver outputs no pulses at all (lines stay low)."""
        with self._lock:
            self._signal_lost = on

    def glitch(self, n: int = 1, *, channel: str | None = None, pulse_us: float = 500.0) -> None:
        """Fault: *n* isolated single-frame glitches (each followed by a good frame) in which
        *channel* (every channel when None) carries an out-of-range *pulse_us* pulse."""
        width_ns = round(pulse_us * 1000)
        for name in [channel] if channel is not None else self.lines:
            self._check_width(name, width_ns)
        with self._lock:
            self._glitches_pending += n
            self._glitch = (channel, width_ns)

    def add_frame_listener(self, listener: FrameListener) -> None:
        """Call ``listener(frame)`` after every frame period (also during signal loss)."""
        with self._lock:
            self._listeners.append(listener)

    def start(self) -> RcReceiverMock:
        """Start the frame thread."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="rc-receiver-mock", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the frame thread (lines are low between frames, so they are left low)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _check_width(self, channel: str, width_ns: int) -> None:
        if channel not in self.lines:
            raise ValueError(f"unknown RC channel {channel!r}; channels are {sorted(self.lines)}")
        if not 0 < width_ns <= self.slot_ns - EDGE_GUARD_NS:
            raise ValueError(f"pulse of {width_ns / 1000:g} us does not fit the {self.slot_ns / 1000:g} us "
                             f"channel slot (frame period / channels)")

    def _run(self) -> None:
        start_ns = time.monotonic_ns()
        handed_ns: int | None = None   # when the last frame was handed over
        while True:
            delay_ns = start_ns + self.frame_period_ns - time.monotonic_ns()
            if self._stop.wait(max(delay_ns, 0) / 1e9):
                return
            now_ns = time.monotonic_ns()
            if handed_ns is not None and now_ns - handed_ns - self.frame_period_ns >= STALL_NOTED_NS:
                self.stalls.append((now_ns, now_ns - handed_ns - self.frame_period_ns))
            handed_ns = now_ns
            self._emit(start_ns)
            start_ns += self.frame_period_ns
            behind = time.monotonic_ns() - start_ns
            if behind > 5 * self.frame_period_ns:  # stalled (suspend, overload): rejoin the frame grid
                start_ns += (behind // self.frame_period_ns) * self.frame_period_ns

    def _frame_widths(self) -> dict[str, int] | None:
        with self._lock:
            if self._signal_lost:
                return None
            widths = dict(self._pulses_ns)
            if self._glitches_pending and not self._last_was_glitch:
                self._glitches_pending -= 1
                channel, width_ns = self._glitch
                for name in [channel] if channel is not None else widths:
                    widths[name] = width_ns
                self._last_was_glitch = True
            else:
                self._last_was_glitch = False
            return widths

    def _emit(self, start_ns: int) -> None:
        widths = self._frame_widths()
        if widths is not None:
            for slot, (name, line) in enumerate(self.lines.items()):
                rise_ns = start_ns + slot * self.slot_ns
                try:
                    self.chip.drive_input(line, 1, rise_ns)
                    self.chip.drive_input(line, 0, rise_ns + widths[name])
                except ValueError as exc:  # e.g. a driver requested the line as an output
                    log.error("RC channel %s: %s", name, exc)
            self.frames_sent += 1
        frame = RcFrame(start_ns, None if widths is None else {n: w / 1000 for n, w in widths.items()})
        self.history.append(frame)
        with self._lock:
            listeners = list(self._listeners)
        for listener in listeners:
            try:
                listener(frame)
            except Exception:  # noqa: BLE001 - a broken listener must not stop the receiver
                log.exception("RC frame listener failed")


class MuxMock:
    """The hardware RC multiplexer: ``selected`` is "autonomous" only while the chip's
    *enable_line* output is high and the pilot's mode channel reads autonomous
    (>= *threshold_us*); otherwise "rc". Mode pulses outside *valid_us* are ignored (the
    last decision stands); a frame without signal selects "rc" at once. ``stick(side)`` jams it."""

    SIDES = ("rc", "autonomous")

    def __init__(self, chip: MockGpioChip, rc: RcReceiverMock, *, enable_line: int, select_line: int | None = None,
                 threshold_us: float = 1500.0, valid_us: tuple[float, float] = (900.0, 2100.0)) -> None:
        self.chip = chip
        self.rc = rc
        self.enable_line = enable_line
        self.select_line = select_line
        self.threshold_us = threshold_us
        self.valid_us = valid_us
        self.history: deque[tuple[int, str]] = deque(maxlen=10_000)
        self._lock = threading.Lock()
        self._enabled = False
        self._pilot_autonomous = False
        self._selected = "rc"
        self._active = False
        self._stuck: str | None = None

    @property
    def selected(self) -> str:
        """The side the mux passes to the actuators: "rc" or "autonomous"."""
        with self._lock:
            return self._selected

    @property
    def stuck(self) -> str | None:
        """The side ``stick()`` jammed the mux on, or None while it follows its inputs."""
        with self._lock:
            return self._stuck

    def stick(self, side: str | None) -> None:
        """Fault: select *side* ("rc" or "autonomous") and drive the read-back to it whatever the
        enable line and the pilot's switch say, until ``stick(None)`` lets the inputs decide again."""
        if side is not None and side not in self.SIDES:
            raise ValueError(f"MuxMock.stick: side must be 'rc', 'autonomous' or None, not {side!r}")
        with self._lock:
            self._stuck = side
        self._update()

    def rc_pulse_us(self, channel: str) -> float | None:
        """The pulse the pilot's receiver puts out on *channel* now (None during signal loss): what the
        mux passes to an output wired through it while it selects the pilot."""
        if self.rc.signal_lost:
            return None
        return self.rc.pulse_us(channel)

    def start(self) -> MuxMock:
        """Watch the enable line and the RC frames; drive the read-back line to "rc" (0)."""
        with self._lock:
            self._active = True
            self._enabled = self.chip.read_output(self.enable_line) == 1
        self.chip.on_output(self._on_output)
        self.rc.add_frame_listener(self._on_frame)
        self._update(force=True)
        return self

    def stop(self) -> None:
        """Stop following the inputs (the selection stays where it is)."""
        with self._lock:
            self._active = False

    def _on_output(self, line: int, value: int, timestamp_ns: int) -> None:
        if line == self.enable_line:
            with self._lock:
                self._enabled = value == 1
            self._update()

    def _on_frame(self, frame: RcFrame) -> None:
        with self._lock:
            if frame.pulses_us is None:
                self._pilot_autonomous = False
            else:
                mode_us = frame.pulses_us.get(self.rc.mode_channel)
                if mode_us is not None and self.valid_us[0] <= mode_us <= self.valid_us[1]:
                    self._pilot_autonomous = mode_us >= self.threshold_us
        self._update()

    def _update(self, *, force: bool = False) -> None:
        # the read-back line is driven under the mux lock so that updates from the chip's
        # thread (enable line) and the receiver's thread (mode switch) cannot reorder
        with self._lock:
            if not self._active:
                return
            side = self._stuck or ("autonomous" if self._enabled and self._pilot_autonomous else "rc")
            if side == self._selected and not force:
                return
            self._selected = side
            stamp = time.monotonic_ns()
            self.history.append((stamp, side))
            if self.select_line is not None:
                self.chip.drive_input(self.select_line, int(side == "autonomous"), stamp)


def _pairs(text: str) -> dict[str, str]:
    return dict(item.split("=", 1) for item in text.split(",") if item)


def main(argv: list[str] | None = None) -> None:
    """Run a mock chip with an RC receiver on it until SIGTERM/SIGINT (for other processes)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--socket", required=True, help="Unix socket path of the mock chip")
    parser.add_argument("--lines", default="throttle=5,steering=6,mode=13", help="channel=line,...")
    parser.add_argument("--pulse", default="", help="channel=us,... initial pulse widths")
    parser.add_argument("--frame-hz", type=float, default=50.0)
    args = parser.parse_args(argv)
    chip = MockGpioChip(socket_path=args.socket).start()
    rc = RcReceiverMock(chip, lines={k: int(v) for k, v in _pairs(args.lines).items()}, frame_hz=args.frame_hz)
    for channel, us in _pairs(args.pulse).items():
        rc.set_pulse(channel, float(us))
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    rc.start()
    print(f"ready {chip.address}", flush=True)
    done.wait()
    rc.stop()
    chip.stop()


if __name__ == "__main__":
    main()
