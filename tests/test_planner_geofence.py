"""The path planner plans inside the geofence (u2sa_hw/services/planner/planner.py with u2sa_hw/geofence.py):
closed loops against the simulated vehicle, as tests/test_planner.py drives them."""

from __future__ import annotations

import math

from test_planner import drive, new_planner, status, waypoint
from u2sa_hw import lcmtypes as t
from u2sa_hw.geofence import CIRCLE, POLYGON, Fence, FenceArea

FIELD = FenceArea("field", True, POLYGON, points=((-5, -5), (25, -5), (25, 8), (-5, 8)))
POND = FenceArea("pond", False, CIRCLE, center=(10.0, 0.0), radius_m=2.5)


def test_a_leg_through_an_exclusion_zone_is_routed_around_it_inside_the_inclusion_area() -> None:
    fence = Fence((FIELD, POND))
    mission, track = drive("differential", [waypoint("far", 20, 0)], [], fence=fence)
    assert [uid for uid, _ in mission.arrivals] == ["far"]
    assert all(fence.breach(n, e) is None for n, e in track), "the track left the fence"
    assert min(POND.edge_distance(n, e) for n, e in track) > 0.5
    assert min(math.hypot(n - 10.0, e) for n, e in track) > POND.radius_m


def test_without_the_fence_the_same_leg_drives_through_the_zone() -> None:
    """The test above can fail: the straight leg crosses the pond."""
    mission, track = drive("differential", [waypoint("far", 20, 0)], [])
    assert [uid for uid, _ in mission.arrivals] == ["far"]
    assert any(POND.contains(n, e) for n, e in track)


def test_a_goal_outside_the_fence_is_held_blocked_naming_the_fence() -> None:
    planner = new_planner(fence=Fence((FIELD,)))
    planner.on_goal(waypoint("out", 40, 0), 0.0)
    planner.on_status(status("out", ["out"]), 0.0)
    planner.on_estimate(t.StateInformation().set(x=0.0, y=0.0, psi=0.0), 0.0)
    cycle = planner.step(0.0)
    assert cycle.nav is not None and cycle.nav.speed == 0.0
    assert cycle.plan.note.startswith("blocked: the goal is inside level-3 object the geofence ('field')")
