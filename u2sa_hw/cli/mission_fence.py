"""What ``u2sa mission import`` and ``upload`` do with geofences (docs/geofence.md).

The vehicle enforces one fence: its profile's ``[geofence]`` (which may take its areas from a plan:
``plan = "field.plan"``). So a plan's ``geoFence`` is taken when the profile's fence already holds
every one of its areas, and otherwise refused, naming the fix (add the plan to the profile's
``[geofence]``), unless ``--ignore-geofence`` drops it (warned). A fence that is in a file but
not enforced would be worse than none. Whatever the file, every goal must lie inside the
profile's fence (:mod:`u2sa_hw.services.mission.fence_check`), checked here before anything is
sent, as the mission manager checks it again.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from u2sa_hw.geofence import CIRCLE, FenceArea


def _shape(area: FenceArea) -> tuple[Any, ...]:
    """What an area is, whatever its name, to 1 cm."""
    if area.kind == CIRCLE:
        return (area.inclusion, CIRCLE, round(area.center[0], 2), round(area.center[1], 2), round(area.radius_m, 2))
    return (area.inclusion, area.kind, tuple((round(x, 2), round(y, 2)) for x, y in area.points))


def plan_fence_warnings(plan: dict[str, Any], *, path: Path, profile: Any, origin: Any, ignore: bool,
                        verb: str) -> list[str]:
    """Check the plan's geofence against the profile's; the warnings to print; CliError to refuse."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.geofence_parse import FenceError, plan_areas, profile_fence

    sent = "; nothing was sent" if verb == "upload" else ""
    try:
        areas = plan_areas(plan.get("geoFence"), source=str(path), origin=origin)
    except FenceError as exc:
        if ignore:
            return [f"{path}: the plan's geofence is unreadable and dropped (--ignore-geofence): {exc}"]
        raise CliError(f"mission {verb}: {exc}{sent}") from None
    if not areas:
        return []
    kinds = ", ".join(a.name for a in areas)
    if ignore:
        return [f"{path}: the plan's geofence ({kinds}) dropped (--ignore-geofence): the vehicle enforces only its "
                "profile's [geofence]"]
    fence = profile_fence(profile)
    have = {_shape(a) for a in fence.areas} if fence is not None else set()
    missing = [a for a in areas if _shape(a) not in have]
    if missing:
        where = profile.path or "the vehicle profile"
        raise CliError(f"mission {verb}: {path}: the plan has a geofence ({kinds}) that the vehicle does not "
                       f"enforce: {where} [geofence] does not hold {missing[0].name}. To enforce it, add "
                       f"plan = \"{path.resolve()}\" to [geofence] in {where} and restart the services; to drive "
                       f"without it, pass --ignore-geofence{sent}")
    return []


def check_goals_in_fence(text: str, *, source: str, profile: Any, verb: str) -> None:
    """CliError when a goal of the mission XML *text* lies outside the profile's geofence."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.geofence_parse import profile_fence
    from u2sa_hw.services.mission.fence_check import fence_refusal, mission_fence_problems
    from u2sa_hw.services.mission.xml import parse_mission

    fence = profile_fence(profile)
    if fence is None:
        return
    spec = parse_mission(text, source=source, default_threshold=1.0)
    # a plan's goals: the line numbers would be those of the converted XML, not of the plan
    problems = mission_fence_problems(spec.goals, fence, profile.origin, with_lines=not source.endswith(".plan"))
    if problems:
        sent = "; nothing was sent" if verb == "upload" else ""
        raise CliError(f"mission {verb}: {fence_refusal(source, problems)}{sent}")
