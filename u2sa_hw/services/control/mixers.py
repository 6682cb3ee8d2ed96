"""Mixers: a turn command and a throttle command (both -100..100 %) to actuator percentages.

The control system computes what the vehicle should do -- *turn* (positive: turn right,
i.e. clockwise seen from above, the heading psi increasing) and *throttle* (positive:
forward) -- and a mixer says which actuator does it. Each mixer returns a dict actuator
name -> percentage in -100..100, for every actuator it drives (so neutral is the same dict
with zeros). Actuator drivers map the percentage to their hardware (thesis 3.2.3.5).

``differential``   skid-steer wheels: left = throttle + turn, right = throttle - turn. When
                   the sum exceeds 100 % the throttle gives way, never the turn, so the
                   vehicle still turns at full speed (and turns in place at zero throttle).
``twin_thruster``  a boat with a thruster each side: the same mix as differential (a
                   thruster's reverse thrust is the driver's business).
``ackermann``      a steering servo and a throttle: steering = turn (100 % = full lock to
                   the right), throttle = throttle. A car cannot turn in place, so the
                   control system keeps some speed while the heading error is large
                   (its ``turn_speed_fraction``).

Add a mixer by writing a class with ``actuators`` and ``mix(turn, throttle)`` and listing
it in :data:`MIXERS`.
"""

from __future__ import annotations

from typing import Callable, Protocol


def clamp_percent(value: float) -> float:
    """*value* clamped into -100..100."""
    return max(-100.0, min(100.0, value))


class Mixer(Protocol):
    """What the control system needs from a mixer."""

    kind: str

    @property
    def actuators(self) -> tuple[str, ...]:
        """Every actuator name the mixer drives."""

    def mix(self, turn: float, throttle: float) -> dict[str, float]:
        """Actuator percentages for *turn* and *throttle* (each -100..100)."""


def _check_names(kind: str, **names: str) -> None:
    empty = [key for key, value in names.items() if not str(value).strip()]
    if empty:
        raise ValueError(f"{kind} mixer: actuator name {', '.join(empty)} is empty; set it in the control "
                         "system's config to the name the actuator driver answers to")
    values = list(names.values())
    if len(set(values)) != len(values):
        raise ValueError(f"{kind} mixer: the actuator names must differ, got {', '.join(values)}")


class DifferentialMixer:
    """Left and right sides of a skid-steer vehicle; the turn has priority over the throttle."""

    kind = "differential"

    def __init__(self, *, left: str, right: str) -> None:
        _check_names(self.kind, left=left, right=right)
        self.left, self.right = left, right

    @property
    def actuators(self) -> tuple[str, ...]:
        """(left, right)."""
        return (self.left, self.right)

    def mix(self, turn: float, throttle: float) -> dict[str, float]:
        """left = throttle + turn, right = throttle - turn, the throttle reduced to keep both within 100 %."""
        turn, throttle = clamp_percent(turn), clamp_percent(throttle)
        room = 100.0 - abs(turn)
        throttle = max(-room, min(room, throttle))
        return {self.left: clamp_percent(throttle + turn), self.right: clamp_percent(throttle - turn)}


class TwinThrusterMixer(DifferentialMixer):
    """Left and right thrusters of a boat: the differential mix."""

    kind = "twin_thruster"


class AckermannMixer:
    """A steering servo (positive right) and a throttle."""

    kind = "ackermann"

    def __init__(self, *, steering: str, throttle: str) -> None:
        _check_names(self.kind, steering=steering, throttle=throttle)
        self.steering, self.throttle = steering, throttle

    @property
    def actuators(self) -> tuple[str, ...]:
        """(steering, throttle)."""
        return (self.steering, self.throttle)

    def mix(self, turn: float, throttle: float) -> dict[str, float]:
        """steering = turn, throttle = throttle."""
        return {self.steering: clamp_percent(turn), self.throttle: clamp_percent(throttle)}


MIXERS: dict[str, Callable[..., Mixer]] = {
    "differential": lambda *, left, right, **_: DifferentialMixer(left=left, right=right),
    "twin_thruster": lambda *, left, right, **_: TwinThrusterMixer(left=left, right=right),
    "ackermann": lambda *, steering, throttle, **_: AckermannMixer(steering=steering, throttle=throttle),
}
"""Mixer kind -> factory taking the actuator names (left, right, steering, throttle) as keywords."""


def build_mixer(kind: str, *, left: str = "left", right: str = "right", steering: str = "steering",
                throttle: str = "throttle") -> Mixer:
    """The mixer of *kind*; ValueError names the known kinds or the bad actuator name."""
    factory = MIXERS.get(kind.strip().lower())
    if factory is None:
        raise ValueError(f"unknown mixer {kind!r}; use one of {', '.join(MIXERS)}")
    return factory(left=left, right=right, steering=steering, throttle=throttle)
