"""Steering around world objects: pick the clear heading nearest the bearing to the goal.

Pure logic, free of the bus. The planner asks :func:`choose_heading` once per control
cycle with the vehicle's position, the goal and the objects the world modeler published
(local NED). The method is candidate-heading sampling, in the spirit of tangent-bug:

1. Candidate headings are the bearing to the goal and offsets from it of
   ``heading_step_deg``, alternately left and right, out to +-180 degrees.
2. A candidate is *clear* when the straight ray from the vehicle along it, out to
   ``range_m`` (or to the goal when that is nearer), keeps every avoided object at least
   its margin away. Each object's ``distance_to_point`` (from the world modeler's
   :mod:`u2sa_hw.services.world.shapes`) is a true distance, so the ray is checked by
   sphere tracing: from each sample the march advances by the smallest clearance left
   (never less than ``min_step_m``), which cannot jump over an object.
3. Of the clear candidates, the one deviating least from the goal bearing wins (best goal
   progress); the side the vehicle already turned to gets a ``hysteresis_deg`` bonus so a
   symmetric obstacle dead ahead does not make it dither between left and right.

Object levels (thesis 3.2.3.5): 3 "avoid at all costs" is *hard*: it is never entered and
a heading through its margin is never chosen; when no heading clears the hard objects the
result is ``blocked`` and the vehicle stops. 2 "avoid if possible" and 0 "unknown" are
*soft*: avoided with the same margin while a clear heading exists, given up (and flagged)
when only a heading through them remains. 1 "hindrance" is not steered around: it may be
crossed.

The margin of an object shrinks where it must: never above the vehicle's present distance
to it (a vehicle pushed inside a margin may take any heading that does not close in
further) nor above the goal's distance to it (a waypoint placed next to a buoy stays
reachable). A hard object is still never entered, so a goal inside one is unreachable
(``blocked`` at once, with the reason). Limitations: the rays are straight and checked ``range_m`` ahead, so a
U-shaped obstacle bigger than that can trap the vehicle (a local minimum), as it would
trap any reactive method.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import wrap_angle
from u2sa_hw.messages import REGISTRY, as_type
from u2sa_hw.services.world.shapes import DISTANCE_FUNCTIONS, distance_to_point

HARD_LEVELS = frozenset({3})
SOFT_LEVELS = frozenset({0, 2})
TOLERANCE_M = 1e-6


@dataclass(frozen=True)
class AvoidanceSettings:
    """Tuning of the obstacle avoidance (all lengths in metres)."""

    margin_m: float = 1.0           # clearance kept from avoided objects (half the vehicle's width + safety)
    range_m: float = 10.0           # how far ahead a candidate heading is checked
    heading_step_deg: float = 5.0   # spacing of the candidate headings
    hysteresis_deg: float = 15.0    # bonus for staying on the side already taken
    min_step_m: float = 0.1         # smallest march step along a ray (> 0)


class Obstacle:
    """One world object with its distance function resolved once (``distance_to_point`` semantics)."""

    __slots__ = ("uid", "level", "message", "_view", "_fn")

    def __init__(self, message: Any) -> None:
        base = as_type(message, t.ObjectDescription)
        self.uid: str = base.uid
        self.level: int = int(base.level)
        self.message = message
        # distance_to_point resolves the type's ancestry on every call; a ray check calls it
        # hundreds of times per cycle, so resolve it here and keep the bound view.
        self._fn: Callable[..., float] | None = None
        for cls in REGISTRY.ancestry(type(message)):
            fn = DISTANCE_FUNCTIONS.get(cls)
            if fn is not None:
                self._fn, self._view = fn, as_type(message, cls)
                break

    def distance(self, x: float, y: float) -> float:
        """Horizontal distance (m) from (x, y) to the object's closest point; 0 inside."""
        if self._fn is None:
            return distance_to_point(self.message, x, y)
        return self._fn(self._view, x, y, None)

    @property
    def hard(self) -> bool:
        """Level 3: avoid at all costs."""
        return self.level in HARD_LEVELS

    @property
    def avoided(self) -> bool:
        """Steered around at all (every level but 1, hindrance)."""
        return self.level in HARD_LEVELS or self.level in SOFT_LEVELS


@dataclass(frozen=True)
class Steering:
    """The outcome of one heading choice."""

    heading: float            # NED heading to follow, rad clockwise from north
    deflection: float         # heading minus the bearing to the goal, rad in [-pi, pi)
    clearance: float          # smallest clearance beyond the margin along the chosen ray, m (inf: nothing near)
    blocked: bool = False     # no heading clears the hard objects: stop
    soft_ignored: bool = False   # only a heading through a soft object's margin was left
    obstacles_near: int = 0   # avoided objects within reach
    reason: str = ""          # why blocked


@dataclass
class _Near:
    obstacle: Obstacle
    margin: float


def _near_objects(obstacles: Iterable[Obstacle], *, x: float, y: float, gx: float, gy: float, reach: float,
                  settings: AvoidanceSettings) -> list[_Near]:
    near = []
    for ob in obstacles:
        if not ob.avoided:
            continue
        d_vehicle = ob.distance(x, y)
        if d_vehicle > reach + settings.margin_m:
            continue
        margin = min(settings.margin_m, d_vehicle, ob.distance(gx, gy))
        near.append(_Near(ob, max(0.0, margin)))
    return near


def ray_clearance(near: list[_Near], *, x: float, y: float, heading: float, length: float,
                  settings: AvoidanceSettings) -> float | None:
    """Smallest clearance beyond the margins along the ray, or None when the ray violates one.

    A hard object must also never be entered (distance 0), even where its margin shrank to 0.

    Every ``distance_to_point`` is a distance to a set, so it changes by at most as much as
    the point moves: an object's distance at the previous sample, less the step since, is a
    lower bound at this one. An object whose bound, less its margin, is no smaller than the
    smallest clearance already found this sample cannot be the nearest and cannot be
    violated, and is not measured again; the steps and the result are exactly those of
    measuring every object at every sample.
    """
    if not near:
        return math.inf
    if not (math.isfinite(length) and math.isfinite(heading)):
        return None
    c, s = math.cos(heading), math.sin(heading)
    min_step = max(settings.min_step_m, 0.01)
    smallest = math.inf
    along = 0.0
    bounds = [-math.inf] * len(near)   # a lower bound of each object's distance from the current sample
    order = list(range(len(near)))     # the nearest of the previous sample first: it usually still is
    for _ in range(int(length / min_step) + 2):   # every step but the last is >= min_step: a bound, not a cut
        px, py = x + along * c, y + along * s
        step = math.inf
        nearest = order[0]
        for i in order:
            item = near[i]
            hard = item.obstacle.hard
            if bounds[i] - item.margin >= step and not (hard and bounds[i] <= 0.0):
                continue
            d = bounds[i] = item.obstacle.distance(px, py)
            spare = d - item.margin
            if spare < -TOLERANCE_M or (along > 0.0 and d <= 0.0 and hard):
                return None
            if spare < step:
                step, nearest = spare, i
        smallest = min(smallest, step)
        if along >= length:
            return smallest
        advanced = min(length, along + max(step, min_step))
        moved = advanced - along
        bounds = [b - moved for b in bounds]
        along = advanced
        if order[0] != nearest:
            order.remove(nearest)
            order.insert(0, nearest)
    return smallest


def _best_clear(near: list[_Near], *, x: float, y: float, bearing: float, length: float, previous: float,
                settings: AvoidanceSettings) -> tuple[float, float] | None:
    """(deflection, clearance) of the preferred clear candidate, or None when none is clear."""
    direct = ray_clearance(near, x=x, y=y, heading=bearing, length=length, settings=settings)
    if direct is not None:
        return 0.0, direct
    step = math.radians(max(0.5, settings.heading_step_deg))
    bonus = math.radians(max(0.0, settings.hysteresis_deg))
    preferred = 1.0 if previous > 0 else -1.0 if previous < 0 else 0.0
    found: dict[float, tuple[float, float]] = {}
    k = 1
    while k * step <= math.pi + 1e-9:
        offset = k * step
        for side in (1.0, -1.0):
            if side in found:
                continue
            clearance = ray_clearance(near, x=x, y=y, heading=bearing + side * offset, length=length,
                                      settings=settings)
            if clearance is not None:
                found[side] = (side * offset, clearance)
        if found:
            best = min(found.values(), key=lambda fc: abs(fc[0]) - (bonus if fc[0] * preferred > 0 else 0.0))
            # the other side can only still win while its offset is within the bonus of the best
            if len(found) == 2 or offset > abs(best[0]) + bonus:
                return best
        k += 1
    if found:
        return min(found.values(), key=lambda fc: abs(fc[0]) - (bonus if fc[0] * preferred > 0 else 0.0))
    return None


def choose_heading(*, x: float, y: float, goal_x: float, goal_y: float, obstacles: Iterable[Obstacle],
                   settings: AvoidanceSettings, previous_deflection: float = 0.0) -> Steering:
    """The heading to follow from (x, y) toward (goal_x, goal_y) around *obstacles* (module docstring)."""
    bearing = math.atan2(goal_y - y, goal_x - x)
    distance = math.hypot(goal_x - x, goal_y - y)
    reach = min(settings.range_m, distance)
    near = _near_objects(obstacles, x=x, y=y, gx=goal_x, gy=goal_y, reach=reach, settings=settings)
    if not near:
        return Steering(heading=bearing, deflection=0.0, clearance=math.inf)
    inside = [n.obstacle.uid for n in near if n.obstacle.hard and n.obstacle.distance(goal_x, goal_y) <= 0.0]
    if inside:
        return Steering(heading=bearing, deflection=0.0, clearance=0.0, blocked=True, obstacles_near=len(near),
                        reason=f"the goal is inside level-3 object {inside[0] or '?'}")
    found = _best_clear(near, x=x, y=y, bearing=bearing, length=reach, previous=previous_deflection,
                        settings=settings)
    if found is not None:
        deflection, clearance = found
        return Steering(heading=wrap_angle(bearing + deflection), deflection=deflection, clearance=clearance,
                        obstacles_near=len(near))
    hard = [n for n in near if n.obstacle.hard]
    found = _best_clear(hard, x=x, y=y, bearing=bearing, length=reach, previous=previous_deflection,
                        settings=settings) if len(hard) < len(near) else None
    if found is not None:
        deflection, clearance = found
        return Steering(heading=wrap_angle(bearing + deflection), deflection=deflection, clearance=clearance,
                        soft_ignored=True, obstacles_near=len(near))
    return Steering(heading=bearing, deflection=0.0, clearance=0.0, blocked=True, obstacles_near=len(near),
                    reason="no heading clears the level-3 objects")
