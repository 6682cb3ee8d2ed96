"""A mission's goals against the profile's geofence: every goal with a horizontal position must lie inside
the fence and at least ``[geofence] margin_m`` from every line (docs/geofence.md).

The mission manager refuses a mission file or an upload that breaks this, and ``u2sa mission upload``
and ``import`` check it before anything is sent, each naming the goal (its number and name), the
area and the fix. A leg between two allowed goals that crosses an exclusion area, or a bend of the
inclusion area, is not refused: the path planner routes around it (it holds, "blocked", where it
cannot).
"""

from __future__ import annotations

from typing import Any, Sequence

from u2sa_hw.geo import GeoOrigin, geodetic_to_ned
from u2sa_hw.geofence import Fence
from u2sa_hw.services.mission.xml import GLOBAL, MissionGoal


def goal_position(goal: MissionGoal, origin: GeoOrigin) -> tuple[float, float] | None:
    """(north, east) m of *goal* about *origin*, or None when it has no horizontal position."""
    v = goal.values
    if "x" not in v or "y" not in v:
        return None
    if goal.frame == GLOBAL:
        north, east, _ = geodetic_to_ned(v["x"], v["y"], origin=origin)
        return north, east
    return v["x"], v["y"]


def goal_problem(goal: MissionGoal, number: int | None, fence: Fence, origin: GeoOrigin, *,
                 with_line: bool = True) -> str | None:
    """Why goal number *number* (1-based; None: a goal on its own) breaks *fence*, or None; *with_line*: name its
    line in the file."""
    at = goal_position(goal, origin)
    if at is None:
        return None
    where = ("goal " if number is None else f"goal {number} ") + f"'{goal.uid}'" \
        + (f" (line {goal.line})" if goal.line and with_line else "")
    breach = fence.breach(*at)
    if breach is not None:
        return (f"{where} at x {at[0]:.1f}, y {at[1]:.1f} is {breach.what} of the geofence: move it inside the "
                "allowed area, or change the fence ([geofence] in the vehicle profile)")
    if fence.margin_m > 0:
        gap = fence.clearance(*at)
        if gap < fence.margin_m:
            return (f"{where} at x {at[0]:.1f}, y {at[1]:.1f} is {gap:.1f} m from a geofence line, closer than "
                    f"[geofence] margin_m = {fence.margin_m:g} m: move it further inside")
    return None


def mission_fence_problems(goals: Sequence[MissionGoal], fence: Fence | None, origin: GeoOrigin, *,
                           with_lines: bool = True) -> list[str]:
    """One line per goal of *goals* that breaks *fence* (empty: the mission keeps inside, or there is no fence)."""
    if fence is None:
        return []
    return [p for i, goal in enumerate(goals)
            if (p := goal_problem(goal, i + 1, fence, origin, with_line=with_lines)) is not None]


def fence_refusal(source: str, problems: list[str]) -> str:
    """One message for every problem: the first in full, and how many more."""
    more = f" (and {len(problems) - 1} more goal(s) outside)" if len(problems) > 1 else ""
    return f"{source}: {problems[0]}{more}"


def check_mission(spec: Any, fence: Fence | None, origin: GeoOrigin) -> None:
    """Raise :class:`~u2sa_hw.services.mission.manager.MissionError` when *spec* breaks *fence*."""
    from u2sa_hw.services.mission.manager import MissionError

    problems = mission_fence_problems(spec.goals, fence, origin)
    if problems:
        raise MissionError(fence_refusal(spec.source, problems))
