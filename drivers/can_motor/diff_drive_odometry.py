"""Differential-drive odometry: two wheels' travel or speed -> body speed and yaw rate.

Pure (no bus, no clock; the caller passes times in seconds). A wheel reports its surface
travel (m, signed, forward positive) and/or its surface speed (m/s) at its own rate; the
odometry pairs one fresh sample of each side and yields the body motion in the FRD frame
(thesis 4.1.1.5, DESIGN.md section 6):

    speed    = (v_left + v_right) / 2               forward, m/s
    yaw_rate = (v_left - v_right) / track_width     rad/s, positive turning right (clockwise
                                                    seen from above, as psi grows)

With ``source="position"`` each wheel's speed is its travel delta over a sliding window
of ``window_s`` (encoder deltas; a longer window trades latency for less timing jitter);
with ``source="velocity"`` the controller's own speed estimate is used as it is. A travel
jump no wheel could make (faster than ``max_wheel_speed_mps``, e.g. a controller that
rebooted and zeroed its position) restarts that wheel's window and is counted in
``resets`` rather than turned into a speed spike; a speed (either source) beyond it or not finite is
dropped and counted in ``rejected``: the body motion is only made of speeds a wheel can have.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

SIDES = ("left", "right")
SOURCES = ("velocity", "position")


def body_motion(v_left: float, v_right: float, track_width_m: float) -> tuple[float, float]:
    """(forward speed m/s, yaw rate rad/s, positive to the right) of a differential pair."""
    return (v_left + v_right) / 2.0, (v_left - v_right) / track_width_m


@dataclass(frozen=True)
class BodyMotion:
    """One odometry output: the time of the later wheel sample (s), speed (m/s), yaw rate (rad/s)."""

    t: float
    speed_mps: float
    yaw_rate_rad_s: float
    v_left_mps: float
    v_right_mps: float


class WheelTravel:
    """One wheel's speed from its travel samples: the delta over the last ``window_s``."""

    def __init__(self, *, window_s: float, max_wheel_speed_mps: float) -> None:
        if not window_s > 0:
            raise ValueError(f"odometry window_s must be > 0, got {window_s!r}")
        if not max_wheel_speed_mps > 0:
            raise ValueError(f"max_wheel_speed_mps must be > 0, got {max_wheel_speed_mps!r}")
        self.window_s = window_s
        self.max_wheel_speed_mps = max_wheel_speed_mps
        self.resets = 0
        self._samples: deque[tuple[float, float]] = deque()

    def add(self, t: float, position_m: float) -> float | None:
        """Add a sample; the speed over the window, or None until there are two samples."""
        if not (math.isfinite(t) and math.isfinite(position_m)):
            return None
        if self._samples:
            t_last, p_last = self._samples[-1]
            dt = t - t_last
            if dt <= 0:
                return None  # a duplicate or out-of-order sample carries no new information
            if abs(position_m - p_last) > self.max_wheel_speed_mps * dt + 1e-6:
                self.resets += 1
                self._samples.clear()
        self._samples.append((t, position_m))
        # keep the newest sample at least window_s older than this one as the window's start
        while len(self._samples) > 2 and t - self._samples[1][0] >= self.window_s:
            self._samples.popleft()
        if len(self._samples) < 2:
            return None
        t0, p0 = self._samples[0]
        return (position_m - p0) / (t - t0)

    def clear(self) -> None:
        """Forget the window (the wheel's position source went away)."""
        self._samples.clear()


class DiffDriveOdometry:
    """Pairs left and right wheel samples into :class:`BodyMotion` values."""

    def __init__(self, *, track_width_m: float, source: str = "velocity", window_s: float = 0.1,
                 max_wheel_speed_mps: float = 20.0, max_skew_s: float = 0.25) -> None:
        if not track_width_m > 0:
            raise ValueError(f"track_width_m must be > 0, got {track_width_m!r}")
        if source not in SOURCES:
            raise ValueError(f"odometry source must be one of {', '.join(SOURCES)}, got {source!r}")
        self.track_width_m = track_width_m
        self.source = source
        self.max_skew_s = max_skew_s
        self.max_wheel_speed_mps = max_wheel_speed_mps
        self.emitted = 0
        self.rejected = 0  # speeds no wheel can turn at (non-finite or beyond max_wheel_speed_mps)
        self.unpaired = 0  # samples dropped because the other side's was too old
        self._travel = {side: WheelTravel(window_s=window_s, max_wheel_speed_mps=max_wheel_speed_mps)
                        for side in SIDES}
        self._latest: dict[str, tuple[float, float] | None] = {side: None for side in SIDES}

    @property
    def resets(self) -> int:
        """Travel jumps that restarted a wheel's window (both sides)."""
        return sum(w.resets for w in self._travel.values())

    def update(self, side: str, t: float, *, position_m: float | None = None,
               speed_mps: float | None = None) -> BodyMotion | None:
        """One wheel sample; the body motion once both sides have a fresh one, else None."""
        if side not in SIDES:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        if self.source == "position":
            speed = None if position_m is None else self._travel[side].add(t, position_m)
        else:
            speed = speed_mps
        if speed is None:
            return None
        if not (math.isfinite(speed) and abs(speed) <= self.max_wheel_speed_mps):
            self.rejected += 1
            return None
        self._latest[side] = (t, speed)
        left, right = self._latest["left"], self._latest["right"]
        if left is None or right is None:
            return None
        if abs(left[0] - right[0]) > self.max_skew_s:
            self.unpaired += 1
            other = "right" if side == "left" else "left"
            self._latest[other] = None  # stale: wait for the other side's next sample
            return None
        self._latest = {s: None for s in SIDES}
        self.emitted += 1
        speed_body, yaw_rate = body_motion(left[1], right[1], self.track_width_m)
        return BodyMotion(max(left[0], right[0]), speed_body, yaw_rate, left[1], right[1])

    def reset(self, side: str | None = None) -> None:
        """Forget one side (or both), e.g. when its controller fell silent."""
        for s in SIDES if side is None else (side,):
            self._travel[s].clear()
            self._latest[s] = None
