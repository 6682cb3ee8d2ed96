"""A PID controller with anti-windup, and a rate limiter (slew limiter) for outputs.

Pure logic; time steps are given by the caller so the same code runs in a service's loop
and in a test's simulated time.

:class:`PidController` -- output = kp * e + ki * integral(e) + kd * de/dt, clamped to
``output_limit``:

- the integral is clamped to ``integral_limit`` (in output units: ``ki * integral``), and it
  does not grow while the output is saturated in the direction the error pushes
  (conditional integration), so a long saturation does not wind it up;
- the derivative is taken on the measurement when the caller knows its rate
  (``update(error, dt, rate=...)``: d e/dt = -rate for a fixed setpoint, e.g. the yaw rate for a
  heading error), which also avoids a kick when the setpoint jumps; otherwise it is the
  finite difference of the error, 0 on the first update after a reset;
- :meth:`reset` clears the integral and the derivative memory (bumpless re-engagement).

:class:`RateLimiter` -- moves its output toward a target by at most ``rate`` units per second;
``rate <= 0`` means no limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class PidGains:
    """Gains and limits of one PID loop (output units per error unit, seconds)."""

    kp: float = 1.0
    ki: float = 0.0
    kd: float = 0.0
    output_limit: float = 100.0      # |output| <= this
    integral_limit: float = 50.0     # |ki * integral| <= this


class PidController:
    """A PID loop with clamped, conditionally integrated integral (module docstring)."""

    def __init__(self, gains: PidGains) -> None:
        self.gains = gains
        self.integral = 0.0          # in output units (ki already applied), so a gain change does not jump it
        self.last_error: float | None = None
        self.last_output = 0.0
        self.terms = (0.0, 0.0, 0.0)  # the last (p, i, d), for health and tests

    def reset(self) -> None:
        """Forget the integral and the derivative memory."""
        self.integral = 0.0
        self.last_error = None
        self.last_output = 0.0
        self.terms = (0.0, 0.0, 0.0)

    def update(self, error: float, dt: float, *, rate: float | None = None) -> float:
        """One step with *error* after *dt* seconds; *rate* is the measurement's rate, if known."""
        g = self.gains
        if not math.isfinite(error):
            raise ValueError(f"PID error must be finite, got {error!r}")
        dt = max(0.0, dt)
        p = g.kp * error
        if rate is not None and math.isfinite(rate):
            d = -g.kd * rate
        elif self.last_error is not None and dt > 0.0:
            d = g.kd * (error - self.last_error) / dt
        else:
            d = 0.0
        self.last_error = error
        limit = abs(g.output_limit)
        candidate = self.integral + g.ki * error * dt
        candidate = max(-abs(g.integral_limit), min(abs(g.integral_limit), candidate))
        unclamped = p + candidate + d
        # conditional integration: keep the old integral if the new one only deepens a saturation
        if abs(unclamped) > limit and abs(candidate) > abs(self.integral) and candidate * unclamped > 0:
            candidate = self.integral
        self.integral = candidate
        out = max(-limit, min(limit, p + self.integral + d))
        self.terms = (p, self.integral, d)
        self.last_output = out
        return out


class RateLimiter:
    """Slews its value toward a target by at most ``rate`` per second (``rate <= 0``: no limit)."""

    def __init__(self, rate: float, *, value: float = 0.0) -> None:
        self.rate = rate
        self.value = value

    def reset(self, value: float = 0.0) -> None:
        """Jump to *value* (used for an immediate neutral)."""
        self.value = value

    def step(self, target: float, dt: float) -> float:
        """Move toward *target* for *dt* seconds; returns the new value."""
        if self.rate <= 0.0:
            self.value = target
        else:
            max_change = self.rate * max(0.0, dt)
            self.value += max(-max_change, min(max_change, target - self.value))
        return self.value
