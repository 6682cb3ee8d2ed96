"""The control law, free of the bus: navigation point + estimate + RC mode -> actuator percentages.

Each cycle (:meth:`VehicleController.step`):

1. **Neutral** when any of these holds, with the reason kept in ``neutral_reason``: a
   failsafe is active; no ``RC_MODE`` has arrived within ``rc_timeout_s``, or it is not
   autonomous (0 manual, 2 no signal), or (with ``require_autonomy_enabled``) its
   ``autonomy_enabled`` -- the RC mux's enable line -- is off, or it says ``hold`` (a pre-arm
   check lost with the hold action); no navigation point for this subsystem within
   ``nav_timeout_s``; the navigation point asks for speed 0 (the planner's hold). Neutral
   is every actuator at 0 % at once (not slewed), both integrators and derivative memories
   reset and every rate limiter set to 0, so that handing back to autonomy starts from
   rest and ramps at the rate limit: bumpless both ways.
2. **Heading**: the error is ``atan2(y, x)`` of the body-frame (FRD) navigation point, in
   radians, positive to the right. ``turn = PID(error)`` in %; the derivative uses the
   estimate's yaw rate ``psi_dot`` when it is fresh (derivative on measurement).
3. **Speed**: the desired speed is the point's speed scaled by ``max(turn_speed_fraction,
   cos(error))`` -- slow while pointing away, so a skid-steer turns nearly in place and a
   car keeps enough speed to turn. The measured speed is the estimate's surge, ``x_dot cos
   psi + y_dot sin psi`` (signed, NED velocity onto the heading). ``throttle =
   speed_feedforward * desired + PID(desired - measured)``; without a fresh velocity the
   feedforward acts alone and the speed integrator is held at 0.
4. **Mix and slew**: the mixer turns (turn, throttle) into actuator percentages, and each
   actuator's output moves toward its target by at most ``rate_limit_pct_s`` per second.

:meth:`VehicleController.step` runs all of that (the service calls it for each navigation
point); :meth:`VehicleController.refresh` is a cycle without new navigation (the service's
minimum output rate): it re-checks neutral and slews the outputs on toward the targets of
the latest step, leaving the PID loops alone, so their time steps always span the time
between two navigation points however the cycles interleave.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.failsafe import FailsafeChange, FailsafeSources
from u2sa_hw.services.control.mixers import Mixer
from u2sa_hw.services.control.pid import PidController, PidGains, RateLimiter

RC_MANUAL, RC_AUTONOMOUS, RC_NO_SIGNAL = 0, 1, 2
RC_NAMES = {RC_MANUAL: "manual", RC_AUTONOMOUS: "autonomous", RC_NO_SIGNAL: "no signal"}


@dataclass(frozen=True)
class ControlSettings:
    """Gains, limits and timeouts of the control law."""

    heading: PidGains = field(default_factory=lambda: PidGains(kp=80.0, ki=5.0, kd=10.0, integral_limit=20.0))
    speed: PidGains = field(default_factory=lambda: PidGains(kp=40.0, ki=20.0, kd=0.0, integral_limit=40.0))
    speed_feedforward: float = 50.0    # % throttle per m/s of desired speed
    turn_speed_fraction: float = 0.25  # the desired speed kept when the point is abeam or behind
    rate_limit_pct_s: float = 200.0    # slew limit of every output, %/s (<= 0: none)
    subsystem: str = "vehicle"         # the navigation points this controller follows
    require_autonomy_enabled: bool = True   # RcMode.autonomy_enabled (the mux's enable line) must be set too
    nav_timeout_s: float = 0.5
    rc_timeout_s: float = 0.25   # as the actuators' [safety] rc_mode_timeout_ms: PID does not wind up while they are neutral
    estimate_timeout_s: float = 0.5
    max_dt_s: float = 0.25             # a longer gap between cycles counts as this long


@dataclass
class _Stamped:
    msg: Any
    time: float


class VehicleController:
    """Heading and speed PID, mixed and slewed; neutral while not cleared to drive (module docstring)."""

    def __init__(self, *, settings: ControlSettings, mixer: Mixer) -> None:
        self.settings = settings
        self.mixer = mixer
        self.heading_pid = PidController(settings.heading)
        self.speed_pid = PidController(settings.speed)
        self.limiters = {name: RateLimiter(settings.rate_limit_pct_s) for name in mixer.actuators}
        self.nav: _Stamped | None = None
        self.estimate: _Stamped | None = None
        self.rc: _Stamped | None = None
        self.failsafes = FailsafeSources()
        self.neutral_reason = "starting"
        self.last_step: float | None = None      # the latest cycle (step or refresh): the slew's time base
        self.last_law: float | None = None       # the latest step: the PID loops' time base
        self.targets: dict[str, float] | None = None   # the mixer's output at the latest step, None when neutral
        self.outputs = {name: 0.0 for name in mixer.actuators}
        self.heading_error = 0.0
        self.desired_speed = 0.0
        self.measured_speed: float | None = None
        self.nav_rejected = 0

    def configure(self, *, settings: ControlSettings, mixer: Mixer) -> None:
        """Apply new settings or a new mixer; the controller restarts from neutral."""
        self.settings, self.mixer = settings, mixer
        self.heading_pid = PidController(settings.heading)
        self.speed_pid = PidController(settings.speed)
        self.limiters = {name: RateLimiter(settings.rate_limit_pct_s) for name in mixer.actuators}
        self.outputs = {name: 0.0 for name in mixer.actuators}
        self.targets = None

    # -- inputs ------------------------------------------------------------------------------
    def on_nav(self, msg: t.NavigationPoint, now: float) -> bool:
        """A navigation point; False (counted) when it is for another subsystem or not finite."""
        if msg.subsystem and msg.subsystem != self.settings.subsystem:
            return False
        if not all(math.isfinite(v) for v in (msg.x, msg.y, msg.z, msg.speed)):
            self.nav_rejected += 1
            return False
        self.nav = _Stamped(msg, now)
        return True

    def on_estimate(self, msg: t.StateInformation, now: float) -> None:
        """The state estimate (yaw rate and velocity are used when present)."""
        self.estimate = _Stamped(msg, now)

    def on_rc_mode(self, msg: t.RcMode, now: float) -> None:
        """The RC multiplexer's mode."""
        self.rc = _Stamped(msg, now)

    def on_failsafe(self, msg: t.Failsafe, now: float) -> FailsafeChange:
        """A failsafe message, held per source (u2sa_hw/failsafe.py: a source clears only its own)."""
        return self.failsafes.apply_message(msg)

    # -- the law -----------------------------------------------------------------------------
    def why_neutral(self, now: float) -> str:
        """The reason the outputs must be neutral now, or '' when cleared to drive."""
        s = self.settings
        if self.failsafes.active:
            return f"failsafe: {self.failsafes.reason()}"
        if self.rc is None:
            return "no RC_MODE received"
        if now - self.rc.time > s.rc_timeout_s:
            return f"RC_MODE silent for {now - self.rc.time:.1f} s"
        mode = int(self.rc.msg.mode)
        if mode != RC_AUTONOMOUS:
            return f"RC {RC_NAMES.get(mode, f'mode {mode}')}"
        if s.require_autonomy_enabled and not self.rc.msg.autonomy_enabled:
            return "RC autonomous but the mux's autonomy enable is off"
        if self.rc.msg.hold:
            return f"RC hold: {self.rc.msg.blocked_by or 'a pre-arm check was lost'}"
        if self.nav is None:
            return "no NAV_POINT received"
        if now - self.nav.time > s.nav_timeout_s:
            return f"NAV_POINT silent for {now - self.nav.time:.1f} s"
        if self.nav.msg.speed <= 0.0:
            return "hold (speed 0)"
        return ""

    def _fresh_estimate(self, now: float) -> t.StateInformation | None:
        if self.estimate is None or now - self.estimate.time > self.settings.estimate_timeout_s:
            return None
        return self.estimate.msg

    def go_neutral(self) -> dict[str, float]:
        """Every output 0 % at once, integrators and limiters reset."""
        self.heading_pid.reset()
        self.speed_pid.reset()
        for limiter in self.limiters.values():
            limiter.reset(0.0)
        self.outputs = {name: 0.0 for name in self.mixer.actuators}
        self.targets = None
        self.desired_speed = 0.0
        return dict(self.outputs)

    def _since(self, then: float | None, now: float) -> float:
        return 0.0 if then is None else min(self.settings.max_dt_s, max(0.0, now - then))

    def refresh(self, now: float) -> dict[str, float]:
        """A cycle without a new navigation point: neutral if it must be, else slew on toward the latest targets."""
        self.neutral_reason = self.why_neutral(now)
        if self.neutral_reason or self.targets is None:
            return self.step(now)
        dt = self._since(self.last_step, now)
        self.last_step = now
        self.outputs = {name: self.limiters[name].step(value, dt) for name, value in self.targets.items()}
        return dict(self.outputs)

    def step(self, now: float) -> dict[str, float]:
        """One control cycle at monotonic time *now*: actuator name -> percentage."""
        s = self.settings
        dt = self._since(self.last_law, now)        # the PID loops' step
        slew_dt = self._since(self.last_step, now)  # the outputs' step (shorter after a refresh)
        self.last_step = self.last_law = now
        self.neutral_reason = self.why_neutral(now)
        if self.neutral_reason:
            return self.go_neutral()
        nav = self.nav.msg  # type: ignore[union-attr] - why_neutral checked it
        error = math.atan2(nav.y, nav.x) if (nav.x or nav.y) else 0.0
        estimate = self._fresh_estimate(now)
        yaw_rate = estimate.get("psi_dot") if estimate is not None else None
        turn = self.heading_pid.update(error, dt, rate=yaw_rate)
        desired = nav.speed * max(s.turn_speed_fraction, math.cos(error))
        measured = _surge(estimate) if estimate is not None else None
        if measured is None:
            self.speed_pid.reset()
            correction = 0.0
        else:
            correction = self.speed_pid.update(desired - measured, dt)
        throttle = s.speed_feedforward * desired + correction
        targets = self.targets = self.mixer.mix(turn, throttle)
        self.outputs = {name: self.limiters[name].step(value, slew_dt) for name, value in targets.items()}
        self.heading_error, self.desired_speed, self.measured_speed = error, desired, measured
        return dict(self.outputs)

    def summary(self) -> dict[str, Any]:
        """For health: mode, why neutral, the errors and outputs."""
        return {"driving": not self.neutral_reason, "neutral_reason": self.neutral_reason,
                "heading_error_deg": f"{math.degrees(self.heading_error):.1f}",
                "desired_speed": f"{self.desired_speed:.2f}",
                "measured_speed": "" if self.measured_speed is None else f"{self.measured_speed:.2f}",
                "outputs": ",".join(f"{n}:{v:.1f}" for n, v in self.outputs.items()),
                "nav_rejected": self.nav_rejected}


def _surge(msg: t.StateInformation) -> float | None:
    """Forward speed: the NED velocity projected on the heading; None without finite x_dot, y_dot and psi."""
    if not (msg.has("x_dot") and msg.has("y_dot") and msg.has("psi")):
        return None
    surge = msg.x_dot * math.cos(msg.psi) + msg.y_dot * math.sin(msg.psi)
    return surge if math.isfinite(surge) else None
