"""What ``u2sa sim`` hears on the bus, and the one progress line it draws from it.

:class:`BusMonitor` listens like any operator tool would: ``STATE_ESTIMATE`` (pose and
speed), ``MISSION_STATUS`` (which goal is current, finished), ``NAV_POINT`` (the
planner's distance to the goal), ``RC_MODE`` (who is in control), ``U2SA_HEALTH``
(which services are up) and ``FAILSAFE``. It keeps the latest of each and the timeline
of mission status changes, with the monotonic time each arrived.

:class:`ProgressLine` redraws one status line in place on a terminal (``\\r`` and
erase-to-end-of-line) and prints events above it; on a pipe (CI logs) it prints the
status line every few seconds instead, so a log stays readable.
"""

from __future__ import annotations

import math
import shutil
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Sequence, TextIO

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.failsafe import FailsafeSources
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence helpers on StateInformation
from u2sa_hw.bus.transport import Transport

MODE_NAMES = {0: "MANUAL", 1: "AUTONOMOUS", 2: "NO RC SIGNAL"}


@dataclass(frozen=True)
class StatusChange:
    """A MISSION_STATUS that differed from the one before: when, which goal, finished."""

    t: float
    uid: str
    index: int
    finished: bool


@dataclass
class BusSnapshot:
    """A consistent copy of what the monitor knows (times are time.monotonic())."""

    estimate: tuple[float, float, float, float, float] | None = None   # t, north, east, psi, speed
    status: t.MissionStatus | None = None
    nav: t.NavigationPoint | None = None
    rc: t.RcMode | None = None
    health: dict[str, tuple[str, str, float]] = field(default_factory=dict)   # name -> status, last error, t
    failsafe: t.Failsafe | None = None
    changes: list[StatusChange] = field(default_factory=list)
    autonomous_since: float | None = None
    rc_changes: list[tuple[int, str]] = field(default_factory=list)   # monotonic ns, rc_state_name()


class BusMonitor:
    """Subscribes to the channels ``u2sa sim`` follows and keeps their latest state."""

    def __init__(self, url: str | None) -> None:
        self.transport = Transport(url, name="u2sa-sim")
        self._lock = threading.Lock()
        self._state = BusSnapshot()
        self._failsafes = FailsafeSources()              # the one model: held per source
        self._failsafe_msgs: dict[str, t.Failsafe] = {}  # source -> its latest active message
        for channel, base, callback in (
                (ch.STATE_ESTIMATE, t.StateInformation, self._on_estimate),
                (ch.MISSION_STATUS, t.MissionStatus, self._on_status),
                (ch.NAV_POINT, t.NavigationPoint, self._on_nav),
                (ch.RC_MODE, t.RcMode, self._on_rc),
                (ch.HEALTH, t.Health, self._on_health),
                (ch.FAILSAFE, t.Failsafe, self._on_failsafe)):
            self.transport.subscribe(channel, base, callback)
        self.transport.start()

    def close(self) -> None:
        """Stop listening."""
        self.transport.stop()

    def snapshot(self) -> BusSnapshot:
        """A copy of the current state."""
        with self._lock:
            s = self._state
            return BusSnapshot(s.estimate, s.status, s.nav, s.rc, dict(s.health), s.failsafe, list(s.changes),
                               s.autonomous_since, list(s.rc_changes))

    def _on_estimate(self, _channel: str, msg: t.StateInformation) -> None:
        if not (msg.has("x") and msg.has("y")):
            return
        psi = msg.get("psi")
        vn, ve = msg.get("x_dot"), msg.get("y_dot")
        speed = math.hypot(vn, ve) if vn is not None and ve is not None else math.nan
        with self._lock:
            self._state.estimate = (time.monotonic(), msg.x, msg.y, math.nan if psi is None else psi, speed)

    def _on_status(self, _channel: str, msg: t.MissionStatus) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._state.changes[-1] if self._state.changes else None
            if last is None or (last.uid, last.index, last.finished) != (msg.current_uid, msg.current_index,
                                                                         msg.finished):
                self._state.changes.append(StatusChange(now, msg.current_uid, msg.current_index, msg.finished))
            self._state.status = msg

    def _on_nav(self, _channel: str, msg: t.NavigationPoint) -> None:
        with self._lock:
            self._state.nav = msg

    def _on_rc(self, _channel: str, msg: t.RcMode) -> None:
        name = rc_state_name(msg)
        with self._lock:
            self._state.rc = msg
            if not self._state.rc_changes or self._state.rc_changes[-1][1] != name:
                self._state.rc_changes.append((time.monotonic_ns(), name))
            autonomous = msg.mode == 1 and msg.autonomy_enabled
            if autonomous and self._state.autonomous_since is None:
                self._state.autonomous_since = time.monotonic()
            elif not autonomous:
                self._state.autonomous_since = None

    def _on_health(self, _channel: str, msg: t.Health) -> None:
        with self._lock:
            self._state.health[msg.name] = (msg.status, msg.last_error, time.monotonic())

    def _on_failsafe(self, _channel: str, msg: t.Failsafe) -> None:
        with self._lock:
            self._failsafes.apply_message(msg)
            if msg.active:
                self._failsafe_msgs[msg.header.source or "?"] = msg
            held = self._failsafes.held()
            self._failsafe_msgs = {src: m for src, m in self._failsafe_msgs.items() if src in held}
            self._state.failsafe = next((self._failsafe_msgs[src] for src in sorted(self._failsafe_msgs)), None)


def rc_state_name(msg: t.RcMode) -> str:
    """``MANUAL``, ``AUTONOMOUS``, ``AUTONOMOUS (not enabled)``, ``NO RC SIGNAL``, with ``, hold`` and
    ``, blocked: <why>`` when RC_MODE says so: the states a scenario's timeline lists."""
    name = MODE_NAMES.get(msg.mode, f"mode {msg.mode}")
    if msg.mode == 1 and not msg.autonomy_enabled:
        name += " (not enabled)"
    if getattr(msg, "hold", False):
        name += ", hold"
    blocked = getattr(msg, "blocked_by", "")
    return name + (f", blocked: {blocked}" if blocked and msg.mode == 1 else "")


def mission_done(status: Any, changes: Sequence[StatusChange], *, since: float | None) -> bool:
    """True when the mission's goals were reached: it finished, or a looping one went round once after *since*.

    *status* is the latest MissionStatus (None: never heard); without *since* (the vehicle
    never went autonomous) a looping mission cannot have gone round.
    """
    if status is None:
        return False
    if status.finished:
        return True
    return bool(status.looping and since is not None and loop_completed(changes, since=since))


def loop_completed(changes: Sequence[StatusChange], *, since: float) -> bool:
    """True once a looping mission went round once after *since* (when the vehicle went autonomous).

    The loop starts at the goal current at *since*; it is complete when that goal is
    current again after another goal was. Which goals lie between does not matter, so a
    mission whose ``<next>`` branches skip some goals on every lap completes too (counting
    the goals seen would wait forever for the branch not taken). A ``restart`` or a
    ``goto`` back to the start goal also closes the loop.
    """
    before = [i for i, c in enumerate(changes) if c.t < since]
    timeline = changes[before[-1] if before else 0:]
    if not timeline or timeline[0].finished:
        return False
    start, left = timeline[0].uid, False
    for change in timeline[1:]:
        if change.finished:
            return False
        if change.uid != start:
            left = True
        elif left:
            return True
    return False


def control_mode(s: BusSnapshot) -> str:
    """Who is in control, as the progress line says it."""
    if s.failsafe is not None:
        return "FAILSAFE"
    if s.rc is None:
        return "no RC_MODE"
    name = MODE_NAMES.get(s.rc.mode, f"mode {s.rc.mode}")
    if s.rc.mode == 1 and not s.rc.autonomy_enabled:
        return "AUTONOMOUS (not enabled)"
    return name


def status_text(s: BusSnapshot, *, elapsed: float, goal_total: int, distance: float | None) -> str:
    """``[ 12.3 s] goal 2/4 far_corner  8.1 m | 1.98 m/s | hdg 087 | AUTONOMOUS``."""
    parts = [f"[{elapsed:5.1f} s]"]
    st = s.status
    if st is None:
        parts.append("waiting for MISSION_STATUS")
    elif st.finished:
        parts.append(f"mission '{st.mission_name}' finished")
    else:
        goal = f"goal {st.current_index + 1}/{goal_total or st.num_goals} {st.current_uid}"
        parts.append(goal + (f" {distance:5.1f} m" if distance is not None and math.isfinite(distance) else ""))
    if s.estimate is not None:
        _t, _n, _e, psi, speed = s.estimate
        speed_text = f"{speed:4.2f} m/s" if math.isfinite(speed) else "-- m/s"
        heading = f"hdg {math.degrees(psi) % 360:03.0f}" if math.isfinite(psi) else "hdg ---"
        parts[-1] += f" | {speed_text} | {heading}"
    else:
        parts[-1] += " | no estimate"
    parts.append(control_mode(s))
    return " | ".join([parts[0] + " " + parts[1]] + parts[2:])


class ProgressLine:
    """One status line redrawn in place on a terminal, events printed above it."""

    def __init__(self, stream: TextIO | None = None, *, interactive: bool | None = None,
                 plain_every_s: float = 5.0) -> None:
        self.stream = stream or sys.stdout
        self.interactive = self.stream.isatty() if interactive is None else interactive
        self.plain_every_s = plain_every_s
        self._shown = ""
        self._last_plain = -math.inf
        self._lock = threading.Lock()

    def _width(self) -> int:
        return max(20, shutil.get_terminal_size((100, 24)).columns - 1)

    def update(self, text: str) -> None:
        """Show *text* as the status line (on a pipe: at most every plain_every_s)."""
        with self._lock:
            if self.interactive:
                text = text[:self._width()]
                if text != self._shown:
                    self.stream.write("\r\x1b[K" + text)
                    self.stream.flush()
                    self._shown = text
            elif time.monotonic() - self._last_plain >= self.plain_every_s:
                self._last_plain = time.monotonic()
                self._write_line(text)

    def event(self, text: str) -> None:
        """Print *text* as a line of its own, above the status line."""
        with self._lock:
            if self.interactive and self._shown:
                self.stream.write("\r\x1b[K")
            self._write_line(text)
            if self.interactive and self._shown:
                self.stream.write(self._shown)
                self.stream.flush()

    def finish(self) -> None:
        """Leave the status line as the last line of output."""
        with self._lock:
            if self.interactive and self._shown:
                self.stream.write("\n")
                self.stream.flush()
            self._shown = ""

    def _write_line(self, text: str) -> None:
        try:
            self.stream.write(text + "\n")
            self.stream.flush()
        except (BrokenPipeError, ValueError):
            pass

    def __call__(self, text: str) -> Any:
        self.event(text)
