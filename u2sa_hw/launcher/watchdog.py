"""The launcher's watchdog: systemd's ``WatchdogSec=`` for the children of ``u2sa run``.

The period comes from the same place systemd gets it: ``WatchdogSec=`` (and
``TimeoutAbortSec=``, how long SIGABRT has before SIGKILL) in the project's unit files,
``u2sa-hsm.service`` for the HSM and ``u2sa@.service`` for every other service, so a service
runs under the same watchdog on the bench as on the vehicle. Without the unit files (an
installed package without the source tree) the defaults are systemd's values in those units:
2 s and 1 s.

As under systemd, a child gets ``WATCHDOG_USEC`` in its environment, the watchdog is armed
by its first ``READY=1`` or ``WATCHDOG=1`` (a child that never speaks the protocol is never
judged by it), each ``WATCHDOG=1`` re-arms it, ``WATCHDOG=trigger`` fires it at once, and
``STOPPING=1`` ends it for the run: a service on its way out (closing a recording, say) stops
looping, and systemd does not judge a unit that is stopping by its watchdog either.

Unlike systemd, the launcher is an ordinary process, and under ``u2sa sim`` the same process
also serves the mock devices. When it does not run for a while (starved on a loaded machine,
a long pause, SIGSTOP), a child that waits on one of those mocks (an IMU's I2C read, the RC
mux's GPIO write) cannot ping either, and on the launcher's next turn its silence included
the launcher's own pause: a healthy child was killed for the launcher's stall. So a child's
silence is measured on a :class:`WatchedClock`, as the HSM measures heartbeats: time the
launcher could not watch does not count against a child. Each turn of its loop (every 0.1 s
at most) advances the clock by the real time elapsed, but by at most ``STALL_STEP_S``. A hung
child is still killed: after its timeout of watched time, which is real time while the
launcher runs normally, and at most ``gap / STALL_STEP_S`` times longer while it is itself
starved to one turn per ``gap``.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from u2sa_hw.install.units import HSM_KIND, HSM_UNIT, TEMPLATE

UNIT_DIR = Path(__file__).resolve().parents[2] / "systemd"
DEFAULT_WATCHDOG_S = 2.0
DEFAULT_ABORT_S = 1.0
STALL_STEP_S = 0.25   # the most one turn of the launcher's loop (normally <= 0.1 s apart) counts as watched time

_UNITS = {"us": 1e-6, "usec": 1e-6, "ms": 1e-3, "msec": 1e-3, "s": 1.0, "sec": 1.0, "second": 1.0,
          "seconds": 1.0, "m": 60.0, "min": 60.0, "minute": 60.0, "minutes": 60.0, "h": 3600.0, "hr": 3600.0,
          "hour": 3600.0, "hours": 3600.0}
_PART = re.compile(r"\s*([0-9]+(?:\.[0-9]+)?)\s*([a-z]*)")


@dataclass(frozen=True)
class WatchdogSetting:
    """A child's watchdog: *timeout_s* without a ping (0: off), then SIGABRT, SIGKILL *abort_s* later."""

    timeout_s: float = DEFAULT_WATCHDOG_S
    abort_s: float = DEFAULT_ABORT_S
    source: str = "default"

    @property
    def usec(self) -> int:
        """The value of ``WATCHDOG_USEC`` for the child."""
        return int(round(self.timeout_s * 1e6))


def parse_timespan(text: str) -> float:
    """Seconds in a systemd time span (``2s``, ``500ms``, ``1min 30s``, a bare number is seconds; ``infinity``: 0).

    ValueError names the text when it is not one.
    """
    text = text.strip().lower()
    if text in ("infinity", ""):
        return 0.0
    total, pos = 0.0, 0
    while pos < len(text):
        match = _PART.match(text, pos)
        if match is None or match.group(2) not in ("", *_UNITS):
            raise ValueError(f"'{text}' is not a systemd time span (e.g. 2s, 500ms, 1min 30s)")
        total += float(match.group(1)) * _UNITS.get(match.group(2), 1.0)
        pos = match.end()
        while pos < len(text) and text[pos] == " ":
            pos += 1
    return total


def unit_watchdog(path: Path) -> WatchdogSetting:
    """``WatchdogSec=`` and ``TimeoutAbortSec=`` of the ``[Service]`` section of unit file *path*.

    A setting the unit does not make keeps its default; ValueError names the file and line of a bad one.
    """
    timeout, abort, section = DEFAULT_WATCHDOG_S, DEFAULT_ABORT_S, ""
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        key, sep, value = line.partition("=")
        if section != "Service" or not sep or key.strip() not in ("WatchdogSec", "TimeoutAbortSec"):
            continue
        try:
            seconds = parse_timespan(value)
        except ValueError as exc:
            raise ValueError(f"{path}:{number}: {key.strip()}: {exc}") from None
        if key.strip() == "WatchdogSec":
            timeout = seconds
        else:
            abort = seconds
    return WatchdogSetting(timeout, abort, str(path))


def watchdog_for(kind: str, *, unit_dir: Path = UNIT_DIR) -> WatchdogSetting:
    """The watchdog of a service of *kind*: its unit file's, else the defaults (2 s, 1 s)."""
    path = unit_dir / (HSM_UNIT if kind == HSM_KIND else TEMPLATE)
    if not path.is_file():
        return WatchdogSetting()
    return unit_watchdog(path)


class WatchdogTimer:
    """One child run's watchdog state: armed by READY=1 or WATCHDOG=1, fired after *timeout_s* without a ping."""

    def __init__(self, setting: WatchdogSetting) -> None:
        self.setting = setting
        self.last_ping: float | None = None
        self.fired = False
        self.triggered = False
        self.stopping = False

    def reset(self) -> None:
        """A new run: disarmed until it speaks."""
        self.last_ping, self.fired, self.triggered, self.stopping = None, False, False, False

    def on_fields(self, fields: dict[str, str], now: float) -> None:
        """Apply one sd_notify message's fields received at *now*."""
        if fields.get("STOPPING") == "1":
            self.stopping = True
        watchdog = fields.get("WATCHDOG")
        if watchdog == "1" or (fields.get("READY") == "1" and self.last_ping is None):
            self.last_ping = now
        elif watchdog == "trigger":
            self.triggered = True

    def overdue(self, now: float) -> float | None:
        """Seconds since the last ping when the watchdog should fire now (once per run), else None."""
        if self.fired or self.stopping or self.setting.timeout_s <= 0 or self.last_ping is None:
            return None
        silent = now - self.last_ping
        if self.triggered or silent > self.setting.timeout_s:
            self.fired = True
            return silent
        return None


class WatchedClock:
    """The launcher's time for judging silences: real time, but a gap between two readings counts at most *max_step_s*.

    A gap longer than that is the launcher not running (see the module docstring): the children
    could not be watched, and the ones waiting on devices the launcher's process serves could
    not ping. Monotonic; *clock* is injectable for tests.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, max_step_s: float = STALL_STEP_S) -> None:
        if max_step_s <= 0:
            raise ValueError(f"max_step_s must be > 0, got {max_step_s}")
        self._clock = clock
        self.max_step_s = max_step_s
        self._last_real = clock()
        self._watched = self._last_real
        self.unwatched_s = 0.0   # real time not counted so far (the launcher's own stalls)

    def __call__(self) -> float:
        real = self._clock()
        step = max(0.0, real - self._last_real)
        counted = min(step, self.max_step_s)
        self.unwatched_s += step - counted
        self._watched += counted
        self._last_real = real
        return self._watched
