"""Path Planner: avoidance, the goal-type state machine, bookkeeping, and closed-loop missions.

The closed-loop tests run the planner's and the control system's own logic against the
project's SimVehicle in simulated time: the estimate is the simulated truth, a tiny mission
manager advances on the planner's completion reports, and the controller's percentages
drive the simulated wheels, thrusters or steering.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from u2sa_hw.mocks.vehicle_sim import ACKERMANN_MAX_STEER_RAD, SimVehicle
from u2sa_hw import lcmtypes as t
from u2sa_hw.messages import REGISTRY
from u2sa_hw.services.control.controller import ControlSettings, VehicleController
from u2sa_hw.services.control.mixers import build_mixer
from u2sa_hw.services.planner.avoidance import AvoidanceSettings, Obstacle, choose_heading
from u2sa_hw.services.planner.planner import PathPlanner, PlannerTimings
from u2sa_hw.services.planner.states import (GOAL_STATES, GoalState, GuidanceSettings, IdleState, Plan, PlanContext,
                                             Pose, WaypointState, register_goal_state, state_for)
from u2sa_hw.services.world.shapes import distance_to_point

AVOID = AvoidanceSettings(margin_m=1.0, range_m=10.0)


def waypoint(uid: str, x: float | None, y: float | None, *, threshold: float = 1.0, frame: str = "LOCAL") -> t.Waypoint:
    wp = t.Waypoint()
    wp.base.uid, wp.reference_frame, wp.horizontal_threshold = uid, frame, threshold
    if x is not None:
        wp.set(x=x)
    if y is not None:
        wp.set(y=y)
    return wp


def circle(uid: str, x: float, y: float, radius: float, *, level: int = 3, frame: str = "NED") -> t.Circle:
    c = t.Circle()
    b = c.base.base
    b.uid, b.level, b.reference_frame, b.x, b.y = uid, level, frame, x, y
    c.radius = radius
    return c


def rectangle(uid: str, x: float, y: float, *, length: float, width: float, level: int = 3) -> t.Rectangle:
    r = t.Rectangle()
    b = r.base.base
    b.uid, b.level, b.reference_frame, b.x, b.y = uid, level, "NED", x, y
    r.length, r.width = length, width
    return r


def estimate(x: float, y: float, psi: float) -> t.StateInformation:
    return t.StateInformation().set(x=x, y=y, psi=psi)


# -- avoidance --------------------------------------------------------------------------------
def test_clear_way_heads_straight_for_the_goal() -> None:
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=10, obstacles=[Obstacle(circle("far", 0, 30, 2))], settings=AVOID)
    assert s.heading == pytest.approx(math.pi / 4) and s.deflection == 0.0 and not s.blocked


def test_object_on_the_path_is_passed_with_the_margin_and_the_side_is_kept() -> None:
    buoy = Obstacle(circle("buoy", 6, 0, 2))
    s = choose_heading(x=0, y=0, goal_x=12, goal_y=0, obstacles=[buoy], settings=AVOID)
    assert s.deflection != 0.0 and not s.blocked and s.obstacles_near == 1
    # the chosen ray keeps the margin: sample it densely
    for i in range(101):
        d = 6.0 * i / 100
        assert buoy.distance(d * math.cos(s.heading), d * math.sin(s.heading)) >= AVOID.margin_m - 1e-6
    # symmetric obstacle: whichever side was taken before is kept (hysteresis)
    left = choose_heading(x=0, y=0, goal_x=12, goal_y=0, obstacles=[buoy], settings=AVOID, previous_deflection=-0.3)
    right = choose_heading(x=0, y=0, goal_x=12, goal_y=0, obstacles=[buoy], settings=AVOID, previous_deflection=0.3)
    assert left.deflection < 0 < right.deflection


def box(level: int) -> list[Obstacle]:
    """Four walls 3 m around the origin: no ray from inside gets out."""
    return [Obstacle(rectangle(f"wall{i}", x, y, length=length, width=width, level=level))
            for i, (x, y, length, width) in enumerate([(3, 0, 1, 8), (-3, 0, 1, 8), (0, 3, 8, 1), (0, -3, 8, 1)])]


def test_levels_hindrance_crossed_soft_given_up_hard_never_entered() -> None:
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=box(1), settings=AVOID)
    assert s.deflection == 0.0 and s.obstacles_near == 0
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=box(2), settings=AVOID)
    assert s.soft_ignored and not s.blocked and s.deflection == 0.0
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=box(0), settings=AVOID)
    assert s.soft_ignored
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=box(3), settings=AVOID)
    assert s.blocked
    # the wall ahead hard, the others soft: out through a soft wall, never through the hard one
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=box(3)[:1] + box(2)[1:], settings=AVOID)
    assert s.soft_ignored and not s.blocked and abs(s.deflection) > math.radians(45)
    # a goal inside a level-3 object is unreachable, though its margin shrinks to the goal
    rock = Obstacle(circle("rock", 10, 0, 1.0))
    assert choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=[rock], settings=AVOID).blocked


def test_goal_next_to_an_object_and_vehicle_inside_a_margin_stay_workable() -> None:
    buoy = Obstacle(circle("buoy", 10, 1.0, 0.5))      # the goal is 0.5 m from its edge, inside the 1 m margin
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=[buoy], settings=AVOID)
    assert not s.blocked and s.deflection == 0.0
    # pushed to 0.3 m from a rock: any heading that does not close in is allowed; toward the goal is preferred
    rock = Obstacle(circle("rock", 0, 1.3, 1.0))
    s = choose_heading(x=0, y=0, goal_x=10, goal_y=0, obstacles=[rock], settings=AVOID)
    assert not s.blocked and abs(s.deflection) < math.radians(30)
    s = choose_heading(x=0, y=0, goal_x=0, goal_y=10, obstacles=[rock], settings=AVOID)   # the goal behind the rock
    assert not s.blocked and abs(s.deflection) >= math.radians(45)


def test_obstacle_distance_matches_distance_to_point_for_every_shape() -> None:
    poly = t.Polygon()
    poly.base.base.reference_frame = "NED"
    poly.vx, poly.vy, poly.num_vertices = [0.0, 4.0, 4.0], [0.0, 0.0, 3.0], 3
    cloud = t.PointCloud()
    p = t.CloudPoint()
    p.azimuth, p.elevation, p.distance = 0.5, 0.0, 5.0
    cloud.points, cloud.num_points = [p], 1
    point = t.ObjectDescription()
    point.x = 3.0
    sphere = t.Sphere()
    sphere.sphere_radius = 2.0
    for obj in (circle("c", 1, 2, 1.5), rectangle("r", 2, 2, length=3, width=1), poly, cloud, point, sphere):
        for x, y in ((0.0, 0.0), (7.0, -3.0), (2.0, 1.0)):
            assert Obstacle(obj).distance(x, y) == pytest.approx(distance_to_point(obj, x, y))


def test_ray_checks_skip_only_objects_that_cannot_decide_them() -> None:
    """ray_clearance measures an object again only when its Lipschitz bound could matter: the
    result is exactly that of measuring every object at every sample (written out here)."""
    import random

    from u2sa_hw.services.planner.avoidance import TOLERANCE_M, _Near, ray_clearance

    def every_object(near: list, *, x: float, y: float, heading: float, length: float) -> float | None:
        c, s = math.cos(heading), math.sin(heading)
        smallest, along = math.inf, 0.0
        for _ in range(int(length / 0.1) + 2):
            px, py = x + along * c, y + along * s
            step = math.inf
            for item in near:
                d = item.obstacle.distance(px, py)
                if d - item.margin < -TOLERANCE_M or (along > 0.0 and d <= 0.0 and item.obstacle.hard):
                    return None
                step = min(step, d - item.margin)
            smallest = min(smallest, step)
            if along >= length:
                return smallest
            along = min(length, along + max(step, 0.1))
        return smallest

    rng = random.Random(11)
    settings = AvoidanceSettings(margin_m=1.0, range_m=10.0, min_step_m=0.1)
    outcomes = set()
    for _ in range(1000):   # objects strewn along both sides of the ray: the nearest one keeps changing
        objects = [circle(f"c{k}", rng.uniform(1, 10), rng.choice((-1, 1)) * rng.uniform(1.0, 3.5),
                          rng.uniform(0.1, 1.0), level=rng.choice((0, 2, 3))) for k in range(rng.randint(2, 7))]
        objects.append(rectangle("r", rng.uniform(0, 10), rng.uniform(-5, 5), length=rng.uniform(0.5, 4),
                                 width=rng.uniform(0.5, 3), level=rng.choice((2, 3))))
        near = [_Near(Obstacle(o), rng.choice((0.0, 0.5, 1.0))) for o in objects]
        heading, length = rng.gauss(0.0, 0.2), rng.uniform(1.0, 10.0)
        got = ray_clearance(near, x=0.0, y=0.0, heading=heading, length=length, settings=settings)
        assert got == every_object(near, x=0.0, y=0.0, heading=heading, length=length)
        outcomes.add(got is None)
    assert outcomes == {True, False}                                   # both clear and violated rays were tried


# -- the state machine --------------------------------------------------------------------------
def unknown_goal_bytes() -> bytes:
    """A goal type this build does not know: a GoalInformation child with its own fingerprint and a field."""
    parent = t.GoalInformation()
    parent.uid = "orbit-1"
    body = parent.encode()[8:]
    return b"\x13\x37" * 4 + body + b"\x00\x00\x00\x00\x00\x00\x24\x40"   # + a double radius


def test_state_per_goal_type_and_unknown_types_idle() -> None:
    assert isinstance(state_for(waypoint("w", 1, 2)), WaypointState)
    assert isinstance(state_for(None), IdleState)
    goal, known = REGISTRY.decode(unknown_goal_bytes(), t.GoalInformation)
    assert not known and type(goal) is t.GoalInformation and goal.uid == "orbit-1"
    state = state_for(goal)
    assert isinstance(state, IdleState) and state.uid == "orbit-1" and "unsupported goal type" in state.reason
    unusable = state_for(waypoint("w", 1, None))
    assert isinstance(unusable, IdleState) and "no x/y" in unusable.reason
    assert "frame" in state_for(waypoint("g", 1, 2, frame="GEODETIC")).reason


class Loiter:
    """Stands in for a generated extension type of Waypoint (first field ``base``)."""

    __slots__ = ["base", "radius"]

    def __init__(self) -> None:
        self.base = t.Waypoint()
        self.radius = 0.0

    @staticmethod
    def _get_packed_fingerprint() -> bytes:
        return b"loiter!!"


class LoiterState(GoalState):
    name = "loiter"

    def step(self, ctx: PlanContext) -> Plan:
        return Plan.hold("circling")


def test_waypoint_with_a_vertical_threshold_needs_the_height_too_and_time_attitude_change_nothing() -> None:
    settings = GuidanceSettings()

    def plan(wp: t.Waypoint, *, z: float | None) -> Plan:
        return state_for(wp).step(PlanContext(pose=Pose(x=0.0, y=0.0, psi=0.0, z=z), obstacles=[], settings=settings))

    wp = waypoint("dive", 0.5, 0.0, threshold=1.0).set(z=5.0, vertical_threshold=0.5)
    over = plan(wp, z=0.0)
    assert not over.reached and over.speed == 0.0 and (over.x, over.y, over.z) == (0.0, 0.0, 5.0)
    assert over.note == "over the waypoint, 5.0 m down to go"
    assert plan(wp, z=7.0).note == "over the waypoint, 2.0 m up to go"
    assert plan(wp, z=4.6).reached                                 # within 0.5 m vertically
    assert plan(wp, z=None).reached                                # no height estimate: horizontal only
    assert plan(waypoint("flat", 0.5, 0.0).set(z=5.0), z=0.0).reached   # no vertical_threshold: horizontal only
    # time and attitude are carried to the state but do not change the waypoint state's plan
    far = waypoint("far", 10.0, 5.0)
    timed = waypoint("far", 10.0, 5.0).set(time=1.0, psi=3.0, phi=0.2)
    assert plan(far, z=None) == plan(timed, z=None)


def test_an_extension_flies_as_its_parent_until_its_own_state_is_registered() -> None:
    goal = Loiter()
    goal.base.base.uid = "L"
    goal.base.set(x=5.0, y=0.0)
    assert isinstance(state_for(goal), WaypointState)
    register_goal_state(Loiter, LoiterState)
    try:
        state = state_for(goal)
        assert isinstance(state, LoiterState) and state.uid == "L"
    finally:
        del GOAL_STATES[Loiter]
    with pytest.raises(TypeError):
        register_goal_state(Loiter, Plan)  # type: ignore[arg-type]


# -- bookkeeping ------------------------------------------------------------------------------------
def new_planner(*, fence: Any = None, **timings: float) -> PathPlanner:
    return PathPlanner(guidance=GuidanceSettings(avoidance=AVOID), timings=PlannerTimings(**timings), fence=fence)


def status(current: str, uids: list[str], *, finished: bool = False) -> t.MissionStatus:
    s = t.MissionStatus()
    s.current_uid, s.goal_uids, s.num_goals, s.finished = current, uids, len(uids), finished
    return s


def test_nothing_without_estimate_hold_without_goal_and_a_point_ahead_with_one() -> None:
    p = new_planner(estimate_timeout_s=1.0)
    assert p.step(0.0).nav is None and p.summary()["doing"] == "waiting for STATE_ESTIMATE"
    p.on_estimate(t.StateInformation().set(x=0.0, y=0.0), 0.0)        # no heading: not a pose
    assert p.step(0.0).nav is None
    p.on_estimate(estimate(0, 0, math.pi / 2), 0.0)                   # facing east
    nav = p.step(0.1).nav
    assert nav is not None and (nav.x, nav.y, nav.speed, nav.distance_to_goal, nav.goal_uid) == (0, 0, 0, -1, "")
    assert p.summary()["state"] == "idle"
    p.on_goal(waypoint("a", 10, 0), 0.2)                              # due north: to the vehicle's left
    nav = p.step(0.2).nav
    assert nav.goal_uid == "a" and nav.x == pytest.approx(0, abs=1e-9) and nav.y == pytest.approx(-3.0)
    assert nav.speed == pytest.approx(1.0) and nav.distance_to_goal == pytest.approx(10.0)
    assert p.step(1.5).nav is None and p.summary()["doing"] == "waiting for a fresh STATE_ESTIMATE"


def test_report_once_resent_while_still_current_and_again_on_the_next_lap() -> None:
    p = new_planner(report_resend_s=2.0)
    p.on_goal(waypoint("a", 0.5, 0), 0.0)
    p.on_goal(waypoint("b", 20, 0), 0.0)
    p.on_status(status("a", ["a", "b"]), 0.0)
    reports = []
    for i in range(60):                       # 3 s at the goal, the manager not answering
        now = i * 0.05
        p.on_estimate(estimate(0, 0, 0), now)
        cycle = p.step(now)
        assert cycle.nav.speed == 0 and cycle.plan.reached
        if cycle.report:
            reports.append((now, cycle.report.uid, cycle.report.completed))
    assert [(uid, done) for _, uid, done in reports] == [("a", True), ("a", True)]
    assert reports[1][0] - reports[0][0] == pytest.approx(2.0)
    p.on_status(status("b", ["a", "b"]), 3.0)
    assert p.step(3.0).report is None and p.state.uid == "b"
    p.on_status(status("a", ["a", "b"]), 3.1)   # looped back: reported again at once
    report = p.step(3.1).report
    assert report is not None and report.uid == "a"
    p.on_status(status("", ["a", "b"], finished=True), 4.0)
    p.on_estimate(estimate(0, 0, 0), 4.0)
    assert p.step(4.0).nav.goal_uid == "" and p.summary()["doing"] == "mission finished"


def test_objects_expire_and_only_local_ones_are_steered_around() -> None:
    p = new_planner(object_expiry_s=3.0)
    p.on_object(circle("buoy", 6, 0, 2), 0.0)
    p.on_object(circle("rel", 6, 0, 2, frame="FRD"), 0.0)
    assert list(p.objects) == ["buoy"] and p.objects_skipped == 1
    p.on_goal(waypoint("a", 12, 0), 0.0)
    p.on_estimate(estimate(0, 0, 0), 0.0)
    nav = p.step(1.0).nav
    assert abs(math.atan2(nav.y, nav.x)) > math.radians(10) and p.summary()["doing"].startswith("avoiding")
    p.on_estimate(estimate(0, 0, 0), 3.5)
    nav = p.step(3.5).nav
    assert p.objects == {} and math.atan2(nav.y, nav.x) == pytest.approx(0.0)


def test_non_finite_inputs_are_refused_not_followed() -> None:
    nan = float("nan")
    p = new_planner()
    p.on_estimate(estimate(nan, 0, 0), 0.0)
    assert p.pose is None and p.step(0.0).nav is None
    p.on_estimate(estimate(0, 0, 0), 0.0)
    p.on_object(circle("ghost", nan, 0, 1), 0.0)
    assert p.objects == {} and p.objects_skipped == 1
    p.on_goal(waypoint("bad", nan, 5), 0.0)
    cycle = p.step(0.0)
    assert cycle.nav.speed == 0 and "non-finite" in p.summary()["doing"]
    heading = choose_heading(x=0, y=0, goal_x=nan, goal_y=0, obstacles=[Obstacle(circle("c", 3, 0, 1))],
                             settings=AVOID)
    assert heading.blocked      # and above all: it returns


# -- closed loop against the simulated vehicle --------------------------------------------------------
SIM_RATE_HZ = 20.0


@dataclass
class MiniMission:
    """The mission manager's part: current goal, advanced by completion reports."""

    goals: list[t.Waypoint]
    index: int = 0
    arrivals: list[tuple[str, float]] = field(default_factory=list)

    @property
    def finished(self) -> bool:
        return self.index >= len(self.goals)

    def status(self) -> t.MissionStatus:
        uids = [g.base.uid for g in self.goals]
        return status("" if self.finished else uids[self.index], uids, finished=self.finished)

    def report(self, msg: t.GoalReport, now: float) -> None:
        if not self.finished and msg.completed and msg.uid == self.goals[self.index].base.uid:
            self.arrivals.append((msg.uid, now))
            self.index += 1


def drive(model: str, goals: list[t.Waypoint], objects: list[object], *, limit_s: float = 120.0,
          fence: Any = None) -> tuple[MiniMission, list[tuple[float, float]]]:
    """Fly *goals* around *objects* with the planner + control logic; returns the mission and the track."""
    sim = SimVehicle(origin_lat=45.0, origin_lon=7.0, model=model, max_speed=2.0)
    mixer = build_mixer("ackermann" if model == "ackermann" else model, left="L", right="R", steering="S",
                        throttle="T")
    control = VehicleController(settings=ControlSettings(), mixer=mixer)
    planner = new_planner(fence=fence)
    mission = MiniMission(goals)
    rc = t.RcMode()
    rc.mode, rc.autonomy_enabled = 1, True
    track = []
    now = 0.0
    while not mission.finished and now < limit_s:
        truth = sim.snapshot()
        track.append((truth.north, truth.east))
        est = t.StateInformation().set(x=truth.north, y=truth.east, psi=truth.yaw, x_dot=truth.v_north,
                                       y_dot=truth.v_east, psi_dot=truth.yaw_rate)
        for goal in goals:
            planner.on_goal(goal, now)
        planner.on_status(mission.status(), now)
        for obj in objects:
            planner.on_object(obj, now)
        planner.on_estimate(est, now)
        cycle = planner.step(now)
        if cycle.report is not None:
            mission.report(cycle.report, now)
        control.on_rc_mode(rc, now)
        control.on_estimate(est, now)
        if cycle.nav is not None:
            control.on_nav(cycle.nav, now)
        out = control.step(now)
        if model == "differential":
            sim.set_wheel_speed("left", out["L"] / 100 * sim.max_speed)
            sim.set_wheel_speed("right", out["R"] / 100 * sim.max_speed)
        elif model == "twin_thruster":
            sim.set_thrust("left", out["L"] / 100)
            sim.set_thrust("right", out["R"] / 100)
        else:
            sim.set_steering(out["S"] / 100 * ACKERMANN_MAX_STEER_RAD)
            sim.set_throttle(out["T"] / 100)
        for _ in range(5):
            sim.step(1.0 / SIM_RATE_HZ / 5)
        now += 1.0 / SIM_RATE_HZ
    return mission, track


SQUARE = [waypoint("p1", 12, 0), waypoint("p2", 12, 12), waypoint("p3", 0, 12), waypoint("p4", 0, 0)]


@pytest.mark.parametrize("model", ["differential", "twin_thruster", "ackermann"])
def test_closed_loop_completes_a_sequence_of_waypoints(model: str) -> None:
    mission, track = drive(model, SQUARE, [])
    assert [uid for uid, _ in mission.arrivals] == ["p1", "p2", "p3", "p4"], f"{model} reached {mission.arrivals}"
    for (uid, when), goal in zip(mission.arrivals, SQUARE):
        index = round(when * SIM_RATE_HZ)
        north, east = track[index]
        assert math.hypot(north - goal.x, east - goal.y) <= goal.horizontal_threshold + 0.2


@pytest.mark.parametrize("model", ["differential", "ackermann"])
def test_closed_loop_avoids_an_obstacle_on_the_path(model: str) -> None:
    rock = circle("rock", 10.0, 0.0, 2.0)                       # dead on the line from (0, 0) to (20, 0)
    mission, track = drive(model, [waypoint("far", 20, 0)], [rock])
    assert [uid for uid, _ in mission.arrivals] == ["far"]
    closest = min(math.hypot(n - 10.0, e) for n, e in track)
    assert closest > rock.radius + 0.5, f"came within {closest:.2f} m of the rock's centre (radius 2)"
    assert min(distance_to_point(rock, n, e) for n, e in track) > 0.5


def test_closed_loop_mission_around_a_wall_and_a_buoy() -> None:
    wall = rectangle("wall", 6.0, 0.0, length=1.0, width=6.0)   # across the first leg (east -3..3)
    buoy = circle("buoy", 12.0, 6.0, 1.0)                      # on the second leg
    mission, track = drive("differential", SQUARE, [wall, buoy])
    assert [uid for uid, _ in mission.arrivals] == ["p1", "p2", "p3", "p4"]
    for obj in (wall, buoy):
        assert min(distance_to_point(obj, n, e) for n, e in track) > 0.5


# -- goal states from outside u2sa-hw: goal_state_modules and the u2sa_hw.goal_states entry points ---------
# The example of docs/core-services-planner-control.md, as a team would write it in its own package.
LOITER_LCM = """\
package team_goals;

struct Loiter
{
    u2sa_hw.lcmtypes.Waypoint base;
    double duration_s;
}
"""
TEAM_STATES = '''\
"""Team goal states for the u2sa path planner: loiter at a point for a while."""

import time

from team_goals import Loiter
from u2sa_hw.services.planner.states import Plan, PlanContext, WaypointState, register_goal_state


class LoiterState(WaypointState):
    """Go to the loiter point as to a waypoint, then hold there duration_s before it counts as done."""

    name = "loiter"

    def step(self, ctx: PlanContext) -> Plan:
        plan = super().step(ctx)                  # drive there, around the objects
        if not plan.reached:
            ctx.memory.pop("arrived", None)       # not there (or drifted out): the clock starts again
            return plan
        arrived = ctx.memory.setdefault("arrived", time.monotonic())
        waited = time.monotonic() - arrived
        if waited < self.goal.duration_s:
            return Plan.hold(f"loitering {waited:.0f}/{self.goal.duration_s:.0f} s",
                             distance_to_goal=plan.distance_to_goal)
        return plan                               # reached: the planner reports the goal complete


register_goal_state(Loiter, LoiterState)
'''


def team_package(root: Path) -> Path:
    """The team's package team_goals (Loiter generated by lcm-gen, and its state) under *root*."""
    import subprocess

    from u2sa_hw.message_codegen import find_lcm_gen

    root.mkdir(parents=True, exist_ok=True)
    (root / "loiter.lcm").write_text(LOITER_LCM)
    subprocess.run([find_lcm_gen(), "-p", "--ppath", str(root), str(root / "loiter.lcm")], check=True)
    (root / "team_goals" / "states.py").write_text(TEAM_STATES)
    return root


def planner_profile(tmp_path: Path, settings: str = "") -> Path:
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text("[vehicle]\nname = \"bench\"\n[services.planner]\nkind = \"path_planner\"\n"
                       f"settings = {{ health_interval_s = 0.2{settings} }}\n")
    return vehicle


def test_a_goal_state_module_on_the_path_adds_a_goal_type(services: Any, bus: Any, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from conftest import wait_until

    from u2sa_hw import channels as ch

    team = team_package(tmp_path / "team")
    monkeypatch.syspath_prepend(str(team))
    from team_goals import Loiter   # the generated type only: this process registers no state

    health: list[t.Health] = []
    reports: list[t.GoalReport] = []
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, m: health.append(m) if m.name == "planner" else None)
    bus.transport.subscribe(ch.GOAL_REPORT, t.GoalReport, lambda _c, m: reports.append(m))
    vehicle = planner_profile(tmp_path, ', goal_state_modules = ["team_goals.states"]')
    services.start("planner", "--vehicle", str(vehicle), PYTHONPATH=str(team))

    goal = Loiter()
    goal.base.base.uid, goal.base.reference_frame, goal.base.horizontal_threshold = "hover", "LOCAL", 2.0
    goal.base.set(x=1.0, y=0.0)
    goal.duration_s = 1.0
    here = estimate(0.0, 0.0, 0.0)

    def details() -> dict[str, str]:
        return {kv.key: kv.value for kv in health[-1].details} if health else {}

    def loitering() -> bool:
        bus.publish(ch.STATE_ESTIMATE, here)
        bus.publish(ch.GOALS, goal)
        return details().get("state") == "loiter" and details().get("doing", "").startswith("loitering")

    wait_until(loitering, timeout=20, message="the planner working on the Loiter goal in the team's loiter state")

    def reported() -> bool:
        bus.publish(ch.STATE_ESTIMATE, here)
        return any(r.uid == "hover" and r.completed and "(loiter)" in r.detail for r in reports)

    wait_until(reported, timeout=20, message="the loiter goal reported complete after its duration")
    log = (tmp_path / "planner.stderr").read_text()
    assert log.count("goal state module team_goals.states: states for Loiter") == 1


def test_goal_state_entry_points_are_loaded_without_config(services: Any, tmp_path: Path) -> None:
    from conftest import wait_until

    team = team_package(tmp_path / "team")
    info = team / "team_goals-1.0.dist-info"    # what pip install writes for the package's entry points
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: team-goals\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[u2sa_hw.goal_states]\nloiter = team_goals.states\n")
    services.start("planner", "--vehicle", str(planner_profile(tmp_path)), PYTHONPATH=str(team))
    wait_until(lambda: "goal state module team_goals.states: states for Loiter"
               in (tmp_path / "planner.stderr").read_text(), timeout=20, message="the entry point loaded")


@pytest.mark.parametrize(("module_text", "modules", "words"), [
    (None, '["no_such_team_module"]', "no module 'no_such_team_module': install its package"),
    ("import no_such_dependency\n", '["team_bad"]', "module 'team_bad' failed to import: No module named "
                                                    "'no_such_dependency'"),
    ("raise RuntimeError('calibration table missing')\n", '["team_bad"]',
     "module 'team_bad' failed to import: RuntimeError: calibration table missing"),
    ("X = 1\n", '["team_bad"]', "module 'team_bad' registered no goal state; call register_goal_state"),
    (None, '["team bad"]', "'team bad' is not a module name"),
])
def test_a_bad_goal_state_module_stops_the_planner_naming_it(tmp_path: Path, lcm_url: str, module_text: str | None,
                                                             modules: str, words: str) -> None:
    import os
    import subprocess

    from conftest import U2SA

    if module_text is not None:
        (tmp_path / "team_bad.py").write_text(module_text)
    vehicle = planner_profile(tmp_path, f", goal_state_modules = {modules}")
    proc = subprocess.run([*U2SA, "service", "planner", "--vehicle", str(vehicle)], capture_output=True, text=True,
                          timeout=60, env=dict(os.environ, PYTHONPATH=str(tmp_path)))
    assert proc.returncode == 1, proc.stderr
    assert f"u2sa: planner: goal_state_modules: {words}" in proc.stderr
    assert "vehicle profile's settings" in proc.stderr


def test_register_goal_state_refuses_what_cannot_be_a_goal_or_a_state() -> None:
    before = dict(GOAL_STATES)
    with pytest.raises(TypeError, match="Header is not a goal: its first field must be 'base'"):
        register_goal_state(t.Header, WaypointState)
    with pytest.raises(TypeError, match="is not a GoalState subclass"):
        register_goal_state(t.Waypoint, object)   # type: ignore[arg-type]
    with pytest.raises(TypeError, match="is not an LCM type"):
        register_goal_state(dict, WaypointState)
    # An LCM type that is no goal is refused before it reaches the message registry.
    stranger = type("Stranger", (), {"__slots__": ["x"], "_get_packed_fingerprint": staticmethod(lambda: b"\x5a" * 8)})
    with pytest.raises(TypeError, match="Stranger is not a goal"):
        register_goal_state(stranger, WaypointState)
    assert REGISTRY.by_fingerprint(b"\x5a" * 8) is None
    assert GOAL_STATES == before
