"""A motor controller's watchdog trip caused by this driver's own stall, told apart from a fault.

A controller's CAN watchdog (the ODrive's ``enable_watchdog``) disarms its axis when no frame
reaches it for its timeout. When the driver's process was stopped or starved that long (a slow
board at start-up, a SIGSTOP), the trip says nothing about the hardware: the driver stalled.
Such a trip is cleared once the link is back and the pilot re-arms through manual; anything
else stays latched until a deliberate ``clear_errors``. Pure logic, time passed in:

- :class:`StallWatch` is told each turn of the driver's loop (its own monotonic clock) and
  keeps the gaps between turns: a gap is a stretch in which the driver sent nothing.
- :class:`Trip` is one latched error as first heard, with the pilot's re-arm count then
  (:attr:`u2sa_hw.safety.gate.CommandGate.rearms`) and the stall that explains it, if any.
- :func:`may_clear` is the rule. Fail safe: whatever is not proven a stall trip stays latched.

A stall explains a trip only when the error is the watchdog bit alone, the stall was long
enough to starve the watchdog (``timeout - command_period``: a frame goes out at least every
period), and the trip was first heard during it or within ``EXPLAIN_WINDOW_S`` after it (the
error heartbeat waits in the socket while the driver is stopped and is read first on waking).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

STALL_FLOOR_S = 0.1       # loop gaps shorter than this are scheduling noise: not kept
KEEP = 16                 # the newest stalls kept
EXPLAIN_WINDOW_S = 1.0    # a trip first heard later than this after a stall ended is not that stall's


@dataclass(frozen=True)
class Stall:
    """A gap in the driver's loop: nothing was sent from *start* to *end* (its monotonic clock, s);
    *wall_start* is *start* as UNIX time, for the log."""

    start: float
    end: float
    wall_start: float

    @property
    def duration(self) -> float:
        """How long the driver went without sending (s)."""
        return self.end - self.start

    def describe(self) -> str:
        """``sent nothing for 0.52 s from 20:31:02.114 UTC``."""
        stamp = time.strftime("%H:%M:%S", time.gmtime(self.wall_start))
        millis = int((self.wall_start % 1.0) * 1000)
        return f"sent nothing for {self.duration:.2f} s from {stamp}.{millis:03d} UTC"


class StallWatch:
    """The gaps between the turns of one driver's loop (see the module docstring)."""

    def __init__(self, *, floor_s: float = STALL_FLOOR_S, keep: int = KEEP,
                 wall: Callable[[], float] = time.time) -> None:
        self.floor_s = floor_s
        self._wall = wall
        self._last: float | None = None
        self.stalls: deque[Stall] = deque(maxlen=keep)
        self.count = 0
        self.longest_s = 0.0

    def turn(self, now: float) -> Stall | None:
        """The loop turned at *now*; returns the stall that just ended, if the gap since the last turn is one."""
        last, self._last = self._last, now
        if last is None or now - last < self.floor_s:
            return None   # the first turn, a short gap, or a clock that went back: nothing to keep
        stall = Stall(start=last, end=now, wall_start=self._wall() - (now - last))
        self.stalls.append(stall)
        self.count += 1
        self.longest_s = max(self.longest_s, stall.duration)
        return stall

    def explaining(self, seen: float, *, min_s: float, window_s: float = EXPLAIN_WINDOW_S) -> Stall | None:
        """The longest kept stall of at least *min_s* during which, or up to *window_s* after which, a trip
        was first heard at *seen*; None when none fits (then the trip is not this driver's doing)."""
        fits = [s for s in self.stalls if s.duration >= min_s and s.start <= seen <= s.end + window_s]
        return max(fits, key=lambda s: s.duration, default=None)

    def details(self) -> dict[str, str | int]:
        """Health details: how many stalls, the longest, the newest."""
        newest = self.stalls[-1].describe() if self.stalls else ""
        return {"stalls": self.count, "longest_stall_s": f"{self.longest_s:.2f}", "last_stall": newest}


@dataclass
class Trip:
    """A controller's error as first heard: its *bits*, when (*seen*, the driver's monotonic clock),
    whether it is the watchdog bit alone, the pilot's re-arm count then, and the stall that explains it."""

    bits: int
    seen: float
    watchdog_only: bool
    rearms: int
    stall: Stall | None = None

    def attribute(self, watch: StallWatch, *, min_s: float) -> Stall | None:
        """Find the own stall behind a watchdog-only trip (once); returns it when newly found."""
        if not self.watchdog_only or self.stall is not None:
            return None
        self.stall = watch.explaining(self.seen, min_s=min_s)
        return self.stall

    @property
    def stall_trip(self) -> bool:
        """A watchdog trip this driver's own stall explains (cleared by the pilot's re-arm)."""
        return self.watchdog_only and self.stall is not None


def may_clear(trip: Trip | None, *, bits_now: int, rearms_now: int, link_up: bool) -> bool:
    """Whether the pilot's re-arm clears *trip* now: it is a stall trip, the error is still exactly what was
    latched, the pilot armed through manual after it was heard, and the link is back. Anything else (a
    hardware fault, an unexplained watchdog trip, no re-arm yet, the bus down) stays latched."""
    return (trip is not None and trip.stall_trip and bits_now == trip.bits and rearms_now > trip.rearms
            and link_up)


def trip_gap_s(*, watchdog_timeout_s: float, command_period_s: float) -> float:
    """The shortest loop gap that can starve a controller watchdog of *watchdog_timeout_s*: a frame goes
    out at least every *command_period_s*, so a gap of ``timeout - period`` can leave it unfed that long."""
    return max(STALL_FLOOR_S, watchdog_timeout_s - command_period_s)
