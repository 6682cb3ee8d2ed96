"""The pre-arm check ``geofence``: the estimator's newest position inside the profile's fence (docs/geofence.md).

A part of :class:`u2sa_hw.safety.prearm.PrearmChecks`, kept apart so the fence's rules read in one
place. The RC mux asks the checks before every grant of autonomy and, while autonomous, on every
edge it settles, so the same judgement refuses autonomy outside the fence and, once autonomous,
takes it away within the RC mux's reaction to a lost check (``[safety] on_check_lost``: neutral
stops the vehicle, hold holds it).

Fail safe: no position yet, a position older than ``max_position_age_s``, or one without a finite
x and y fails the check, as being outside the fence does. The reason names the area and stays
the same while the breach lasts (no distance in it), so the pilot reads one steady line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from u2sa_hw.safety.prearm_table import GeofenceCheck


@dataclass(frozen=True)
class Position:
    """The estimator's newest horizontal position, as received (host monotonic seconds)."""

    at: float
    x: float
    y: float


def position_of(msg: Any, now: float) -> Position | None:
    """The (x, y) of a STATE_ESTIMATE, or None when it has no finite position."""
    if not (msg.has("x") and msg.has("y")):
        return None
    x, y = msg.get("x"), msg.get("y")
    if x is None or y is None or not (math.isfinite(x) and math.isfinite(y)):
        return None
    return Position(at=now, x=float(x), y=float(y))


def geofence_problem(check: GeofenceCheck, position: Position | None, now: float) -> str:
    """Why the geofence check fails at *now* ("" when it holds)."""
    if position is None:
        return f"no position from {check.service} yet: cannot tell the vehicle is inside the fence (fail safe)"
    if now - position.at > check.max_position_age_s:
        return (f"no position from {check.service} for over {check.max_position_age_s:g} s: cannot tell the "
                "vehicle is inside the fence (fail safe)")
    breach = check.fence.breach(position.x, position.y)
    if breach is None:
        return ""
    return f"{breach.what}; drive back inside in manual"


def age_limit(check: GeofenceCheck, position: Position | None) -> float | None:
    """When the position stops being fresh enough (for the verdict's span), or None without one."""
    return None if position is None else position.at + check.max_position_age_s
