"""RC pulse measurement and the mux mode state machine, as pure logic (no I/O, no clock).

:class:`PulseMeter` turns GPIO edges (line, rising, timestamp in ns) into pulse widths:
a width is ``falling - rising`` on one line, both stamped by the kernel (or the mock
chip) when the edge happened, so reader latency never changes it. Widths outside
``min_us..max_us`` are rejected and counted (a glitch, a missed edge that turned two
pulses or a whole frame gap into one "pulse"), as is a falling edge without a rising one
and a second rising edge without a fall in between.

:class:`RcModeFilter` decides the mode from the mode channel's valid pulses:

- hysteresis: a pulse above ``autonomous_above_us`` asks for autonomous, one below
  ``manual_below_us`` for manual; one in between asks to keep the present side
  (manual when coming out of "no signal"), so a switch resting near a threshold cannot
  make the mode chatter;
- debounce: the mode changes only after ``debounce_frames`` consecutive valid frames ask
  for the same new side, so isolated glitch frames never flip it;
- signal: no valid frame for ``signal_timeout_ns`` -> "no signal" (the caller asks with
  :meth:`RcModeFilter.check_signal` and its own monotonic ``now``; :meth:`RcModeFilter.signal_expiry_ns`
  says when that will be, so a caller can judge it at that very time).

:class:`DueGrid` places a timed message's due times on a fixed grid of a clock (``ceil(k * 1e9 /
hz)`` ns from the clock's zero), so they are the same whenever the clock is, whatever the phase
of the loop that sends them: live on CLOCK_MONOTONIC, replayed on the recorded edge stamps.

The mode numbers are those of the ``RcMode`` message.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Iterable, NamedTuple

MODE_MANUAL = 0
MODE_AUTONOMOUS = 1
MODE_NO_SIGNAL = 2
MODE_NAMES = {MODE_MANUAL: "manual", MODE_AUTONOMOUS: "autonomous", MODE_NO_SIGNAL: "no signal"}

# PulseMeter rejection reasons (the keys of PulseMeter.rejected)
TOO_SHORT = "too_short"
TOO_LONG = "too_long"
FALL_WITHOUT_RISE = "fall_without_rise"
RISE_WITHOUT_FALL = "rise_without_fall"


class Pulse(NamedTuple):
    """One valid pulse: its line, width in microseconds and the falling edge's timestamp (ns)."""

    line: int
    width_us: float
    end_ns: int


@dataclass
class PulseMeter:
    """Pulse widths from edges on *lines*; widths outside ``min_us..max_us`` are rejected."""

    lines: Iterable[int]
    min_us: float = 800.0
    max_us: float = 2200.0
    pulses: int = 0
    rejected: Counter = field(default_factory=Counter)

    def __post_init__(self) -> None:
        self.lines = frozenset(self.lines)
        if not 0 < self.min_us < self.max_us:
            raise ValueError(f"pulse limits need 0 < min_us < max_us, got {self.min_us}..{self.max_us}")
        self._rise_ns: dict[int, int] = {}

    def feed(self, line: int, rising: bool, timestamp_ns: int) -> Pulse | None:
        """One edge; returns the pulse it completes when that pulse is valid, else None."""
        if line not in self.lines:
            return None
        if rising:
            if line in self._rise_ns:
                self.rejected[RISE_WITHOUT_FALL] += 1
            self._rise_ns[line] = timestamp_ns
            return None
        rise = self._rise_ns.pop(line, None)
        if rise is None:
            self.rejected[FALL_WITHOUT_RISE] += 1
            return None
        width_us = (timestamp_ns - rise) / 1000.0
        if width_us < self.min_us:
            self.rejected[TOO_SHORT] += 1
            return None
        if width_us > self.max_us:
            self.rejected[TOO_LONG] += 1
            return None
        self.pulses += 1
        return Pulse(line, width_us, timestamp_ns)

    def reset(self) -> None:
        """Forget half-seen pulses (after the port was lost: edges in between are gone)."""
        self._rise_ns.clear()

    @property
    def rejected_total(self) -> int:
        """Every rejected pulse or edge, whatever the reason."""
        return sum(self.rejected.values())


class LastWidths:
    """Each channel's last valid pulse width (us) and when it ended; as of a time, 0 for a channel without
    one within *timeout_ns* (``RcMode.pulse_us``, the sticks)."""

    def __init__(self, channels: Iterable[str], *, timeout_ns: int) -> None:
        self.channels = tuple(channels)
        self.timeout_ns = timeout_ns
        self._last: dict[str, Pulse] = {}

    def record(self, channel: str, pulse: Pulse) -> None:
        """*pulse* is the newest valid one of *channel*."""
        self._last[channel] = pulse

    def as_of(self, at_ns: int) -> list[int]:
        """Each channel's width in whole us as of *at_ns*, in channel order."""
        widths = []
        for name in self.channels:
            last = self._last.get(name)
            widths.append(round(last.width_us) if last and at_ns - last.end_ns <= self.timeout_ns else 0)
        return widths


class RcModeFilter:
    """Mode from the mode channel's pulses, with hysteresis, debounce and a signal timeout."""

    def __init__(self, *, autonomous_above_us: float = 1700.0, manual_below_us: float = 1300.0,
                 debounce_frames: int = 3, signal_timeout_ns: int = 100_000_000) -> None:
        if not manual_below_us < autonomous_above_us:
            raise ValueError(f"hysteresis needs manual_below_us ({manual_below_us}) < autonomous_above_us "
                             f"({autonomous_above_us})")
        if debounce_frames < 1:
            raise ValueError(f"debounce_frames must be at least 1, got {debounce_frames}")
        if signal_timeout_ns <= 0:
            raise ValueError(f"signal_timeout_ns must be positive, got {signal_timeout_ns}")
        self.autonomous_above_us = autonomous_above_us
        self.manual_below_us = manual_below_us
        self.debounce_frames = debounce_frames
        self.signal_timeout_ns = signal_timeout_ns
        self.mode = MODE_NO_SIGNAL
        self.frames = 0
        self.changes = 0
        self.last_frame_ns: int | None = None
        self._candidate = MODE_NO_SIGNAL
        self._streak = 0
        self.manual_streak = 0   # consecutive valid frames asking for manual

    @property
    def mode_name(self) -> str:
        """``manual``, ``autonomous`` or ``no signal``."""
        return MODE_NAMES[self.mode]

    def wanted(self, width_us: float) -> int:
        """The side one valid pulse asks for (hysteresis: the band between keeps the present side)."""
        if width_us > self.autonomous_above_us:
            return MODE_AUTONOMOUS
        if width_us < self.manual_below_us:
            return MODE_MANUAL
        return MODE_MANUAL if self.mode == MODE_NO_SIGNAL else self.mode

    def on_frame(self, width_us: float, timestamp_ns: int) -> bool:
        """One valid mode-channel pulse ending at *timestamp_ns*; True when the mode changed.

        Debounce is one-sided: leaving autonomy for manual takes one frame (the safe direction
        never waits), any other change ``debounce_frames`` alike in a row.
        """
        self.frames += 1
        if self.last_frame_ns is None or timestamp_ns > self.last_frame_ns:
            self.last_frame_ns = timestamp_ns
        side = self.wanted(width_us)
        self.manual_streak = self.manual_streak + 1 if side == MODE_MANUAL else 0
        if side == self.mode:
            self._candidate, self._streak = side, 0
            return False
        if side == self._candidate:
            self._streak += 1
        else:
            self._candidate, self._streak = side, 1
        needed = 1 if side == MODE_MANUAL and self.mode == MODE_AUTONOMOUS else self.debounce_frames
        if self._streak < needed:
            return False
        self._set(side)
        return True

    @property
    def manual_confirmed(self) -> bool:
        """True when the switch has been at manual for ``debounce_frames`` frames in a row (what arms)."""
        return self.mode == MODE_MANUAL and self.manual_streak >= self.debounce_frames

    def signal_expiry_ns(self) -> int | None:
        """The first time at which :meth:`check_signal` says "no signal" (None: it is already, or no frame yet)."""
        if self.mode == MODE_NO_SIGNAL or self.last_frame_ns is None:
            return None
        return self.last_frame_ns + self.signal_timeout_ns + 1

    def check_signal(self, now_ns: int) -> bool:
        """Go to "no signal" when the last valid frame is older than the timeout; True on change."""
        if self.mode == MODE_NO_SIGNAL:
            return False
        if self.last_frame_ns is not None and now_ns - self.last_frame_ns <= self.signal_timeout_ns:
            return False
        self._set(MODE_NO_SIGNAL)
        return True

    def _set(self, mode: int) -> None:
        self.mode = mode
        self.changes += 1
        if mode == MODE_NO_SIGNAL:
            self.manual_streak = 0
        self._candidate, self._streak = mode, 0


class DueGrid:
    """Due times of a message sent *hz* times a second, on a fixed grid of a clock in ns: the k-th is
    ``origin + ceil(k * 1e9 / hz)``. The grid depends only on the clock (and its origin), never on when
    a loop looked, so a replay on the recorded clock has the recorded due times."""

    def __init__(self, hz: float) -> None:
        if not hz > 0:
            raise ValueError(f"a rate must be positive, got {hz}")
        rate = Fraction(hz).limit_denominator(1_000_000)
        self._num, self._den = rate.numerator, rate.denominator * 1_000_000_000
        self.period_ns = round(1e9 / hz)

    def after(self, t_ns: int, origin_ns: int = 0) -> int:
        """The first due time strictly after *t_ns*."""
        k = ((t_ns - origin_ns) * self._num) // self._den + 1
        return origin_ns - ((-k * self._den) // self._num)
