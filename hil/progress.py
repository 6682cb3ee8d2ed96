"""A one-line progress bar for long runs: log time played of the total, speed, elapsed and ETA.

Drawn on stderr with a carriage return, at most a few times a second, and only when stderr
is a terminal (a pipe or a CI log gets no half-lines). The final summary line is printed
by the caller in every case.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

BAR_WIDTH = 24


def format_duration(seconds: float) -> str:
    """``m:ss`` below an hour, ``h:mm:ss`` above; ``--:--`` when unknown."""
    if seconds != seconds or seconds < 0 or seconds == float("inf"):
        return "--:--"
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def progress_line(done_s: float, total_s: float, elapsed_s: float, *, label: str = "replay") -> str:
    """``replay [#####.....]  12.0/60.0 s  20%  4.1x  elapsed 0:03  ETA 0:12`` (no newline)."""
    frac = min(1.0, max(0.0, done_s / total_s)) if total_s > 0 else 1.0
    filled = int(frac * BAR_WIDTH)
    bar = "#" * filled + "." * (BAR_WIDTH - filled)
    speed = done_s / elapsed_s if elapsed_s > 0 else 0.0
    eta = (total_s - done_s) / speed if speed > 0 else float("nan")
    return (f"{label} [{bar}] {done_s:7.1f}/{total_s:.1f} s {frac * 100:4.0f}%  {speed:5.1f}x  "
            f"elapsed {format_duration(elapsed_s)}  ETA {format_duration(eta)}")


class ProgressBar:
    """Redraws :func:`progress_line` in place on a terminal; silent otherwise."""

    def __init__(self, total_s: float, *, stream: TextIO | None = None, label: str = "replay",
                 interval_s: float = 0.2, enabled: bool | None = None) -> None:
        self.total_s = total_s
        self.stream = stream or sys.stderr
        self.label = label
        self.interval_s = interval_s
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self.started = time.monotonic()
        self._last_draw = 0.0
        self._drawn = False
        self.done_s = 0.0

    @property
    def elapsed_s(self) -> float:
        """Wall seconds since the bar was created."""
        return time.monotonic() - self.started

    def update(self, done_s: float, *, force: bool = False) -> None:
        """Note that *done_s* seconds of the total are done; redraw if it is time to."""
        self.done_s = done_s
        if not self.enabled:
            return
        now = time.monotonic()
        if force or now - self._last_draw >= self.interval_s:
            self._last_draw = now
            line = progress_line(done_s, self.total_s, now - self.started, label=self.label)
            self.stream.write("\r" + line)
            self.stream.flush()
            self._drawn = True

    def close(self) -> None:
        """Draw the final state and end the line (only if anything was drawn)."""
        if self.enabled:
            self.update(self.done_s, force=True)
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
