"""Control System: PID, mixers, rate limits, neutral and bumpless handback; planner + control over LCM."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tests.conftest import ServiceProcesses, wait_until
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.geo import ned_to_geodetic
from u2sa_hw.services.control.controller import ControlSettings, VehicleController
from u2sa_hw.services.control.mixers import AckermannMixer, DifferentialMixer, TwinThrusterMixer, build_mixer
from u2sa_hw.services.control.pid import PidController, PidGains, RateLimiter
from u2sa_hw.profile.vehicle import Origin


# -- PID and rate limiter ---------------------------------------------------------------------------
def test_pid_terms_windup_and_reset() -> None:
    p_only = PidController(PidGains(kp=10.0))
    assert p_only.update(0.5, 0.1) == pytest.approx(5.0) and p_only.update(-20.0, 0.1) == -100.0
    pi = PidController(PidGains(kp=0.0, ki=2.0, integral_limit=50.0))
    outs = [pi.update(1.0, 0.5) for _ in range(4)]
    assert outs == pytest.approx([1.0, 2.0, 3.0, 4.0])            # ki * error * t
    for _ in range(100):
        pi.update(1.0, 0.5)
    assert pi.integral == pytest.approx(50.0)                     # clamped
    pi.reset()
    assert pi.integral == 0.0 and pi.update(0.0, 0.1) == 0.0


def test_pid_does_not_wind_up_while_saturated() -> None:
    pid = PidController(PidGains(kp=100.0, ki=10.0, output_limit=100.0, integral_limit=100.0))
    for _ in range(50):
        assert pid.update(2.0, 0.1) == 100.0                      # P alone saturates
    assert pid.integral == 0.0
    assert pid.update(-0.1, 0.1) == pytest.approx(-10.0 - 0.1)    # responds at once on the way back


def test_pid_derivative_from_the_rate_or_the_error() -> None:
    pid = PidController(PidGains(kp=0.0, kd=2.0))
    assert pid.update(1.0, 0.1) == 0.0                            # no history: no kick
    assert pid.update(1.5, 0.1) == pytest.approx(10.0)            # 2 * 0.5 / 0.1
    assert pid.update(0.3, 0.1, rate=0.4) == pytest.approx(-0.8)  # on the measurement: -kd * rate
    assert pid.update(5.0, 0.1, rate=float("nan")) == pytest.approx(2 * 4.7 / 0.1)
    with pytest.raises(ValueError):
        pid.update(float("nan"), 0.1)


def test_rate_limiter() -> None:
    lim = RateLimiter(50.0)
    assert [lim.step(100.0, 0.5) for _ in range(5)] == [25.0, 50.0, 75.0, 100.0, 100.0]
    assert lim.step(-100.0, 0.1) == 95.0
    lim.reset()
    assert lim.value == 0.0 and RateLimiter(0.0).step(80.0, 0.01) == 80.0


# -- mixers --------------------------------------------------------------------------------------------
def test_differential_and_twin_thruster_mix_with_turn_priority() -> None:
    for mixer in (DifferentialMixer(left="L", right="R"), TwinThrusterMixer(left="L", right="R")):
        assert mixer.actuators == ("L", "R")
        assert mixer.mix(0.0, 60.0) == {"L": 60.0, "R": 60.0}
        assert mixer.mix(20.0, 50.0) == {"L": 70.0, "R": 30.0}        # turn right: left side faster
        assert mixer.mix(40.0, 90.0) == {"L": 100.0, "R": 20.0}       # throttle gives way, the turn stays 40
        assert mixer.mix(-150.0, 0.0) == {"L": -100.0, "R": 100.0}    # in place, left
        assert mixer.mix(0.0, -120.0) == {"L": -100.0, "R": -100.0}
    assert build_mixer("twin_thruster", left="port", right="starboard").kind == "twin_thruster"


def test_ackermann_mix_and_bad_mixer_config() -> None:
    mixer = AckermannMixer(steering="servo", throttle="esc")
    assert mixer.mix(-30.0, 45.0) == {"servo": -30.0, "esc": 45.0}
    assert mixer.mix(130.0, -130.0) == {"servo": 100.0, "esc": -100.0}
    with pytest.raises(ValueError, match="unknown mixer 'tank'; use one of differential, twin_thruster, ackermann"):
        build_mixer("tank")
    with pytest.raises(ValueError, match="actuator name left is empty"):
        build_mixer("differential", left=" ", right="R")
    with pytest.raises(ValueError, match="must differ"):
        build_mixer("ackermann", steering="x", throttle="x")


# -- the control law ------------------------------------------------------------------------------------
def nav(x: float, y: float, speed: float, *, subsystem: str = "vehicle") -> t.NavigationPoint:
    n = t.NavigationPoint()
    n.subsystem, n.x, n.y, n.speed = subsystem, x, y, speed
    return n


def rc(mode: int, *, enabled: bool | None = None) -> t.RcMode:
    r = t.RcMode()
    r.mode = mode
    r.autonomy_enabled = mode == 1 if enabled is None else enabled
    return r


def controller(**overrides: object) -> VehicleController:
    overrides.setdefault("rc_timeout_s", 1.0)   # these tests step the clock in jumps of up to 0.7 s
    settings = ControlSettings(**overrides)  # type: ignore[arg-type]
    return VehicleController(settings=settings, mixer=DifferentialMixer(left="L", right="R"))


def feed(c: VehicleController, now: float, *, point: t.NavigationPoint, mode: int = 1,
         speed: float | None = None, psi: float = 0.0) -> dict[str, float]:
    c.on_rc_mode(rc(mode), now)
    c.on_nav(point, now)
    if speed is not None:
        c.on_estimate(t.StateInformation().set(psi=psi, x_dot=speed * math.cos(psi), y_dot=speed * math.sin(psi),
                                               psi_dot=0.0), now)
    return c.step(now)


def test_neutral_reasons() -> None:
    c = controller()
    assert c.step(0.0) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "no RC_MODE received"
    c.on_rc_mode(rc(1), 0.0)
    assert c.step(0.1) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "no NAV_POINT received"
    out = feed(c, 0.2, point=nav(3, 0, 1.0))
    assert c.neutral_reason == "" and out["L"] > 0 and out["R"] > 0
    assert feed(c, 0.3, point=nav(3, 0, 0.0)) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "hold (speed 0)"
    feed(c, 0.4, point=nav(3, 0, 1.0), mode=2)
    assert c.neutral_reason == "RC no signal"
    c.on_rc_mode(rc(1, enabled=False), 0.45)                   # switch autonomous, mux not enabled (not re-armed)
    assert c.step(0.45) == {"L": 0.0, "R": 0.0}
    assert c.neutral_reason == "RC autonomous but the mux's autonomy enable is off"
    lenient = controller(require_autonomy_enabled=False)
    feed(lenient, 0.0, point=nav(3, 0, 1.0))
    lenient.on_rc_mode(rc(1, enabled=False), 0.0)
    assert lenient.step(0.05)["L"] > 0 and lenient.neutral_reason == ""
    c.on_rc_mode(rc(1), 0.5)
    c.on_nav(nav(3, 0, 1.0), 0.5)
    c.step(0.5)
    assert c.neutral_reason == ""
    assert c.step(1.2) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "NAV_POINT silent for 0.7 s"
    c.on_nav(nav(3, 0, 1.0), 1.6)
    assert c.step(1.6) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "RC_MODE silent for 1.1 s"
    fs = t.Failsafe()
    fs.active, fs.reason, fs.header.source = True, "gps silent", "hsm"
    c.on_failsafe(fs, 1.7)
    feed(c, 1.7, point=nav(3, 0, 1.0))
    assert c.neutral_reason == "failsafe: hsm: gps silent"
    other = t.Failsafe()
    other.active, other.header.source = False, "estop"      # another source's clear is not the HSM's
    c.on_failsafe(other, 1.75)
    feed(c, 1.75, point=nav(3, 0, 1.0))
    assert c.neutral_reason == "failsafe: hsm: gps silent"
    fs.active = False
    c.on_failsafe(fs, 1.8)
    feed(c, 1.8, point=nav(3, 0, 1.0))
    assert c.neutral_reason == ""
    held = rc(1)
    held.hold, held.blocked_by = True, "gps: no 3D fix"
    c.on_rc_mode(held, 1.85)
    c.on_nav(nav(3, 0, 1.0), 1.85)
    assert c.step(1.85) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "RC hold: gps: no 3D fix"


def test_heading_and_speed_loops_steer_toward_the_point() -> None:
    c = controller(rate_limit_pct_s=0.0)
    out = feed(c, 0.0, point=nav(3, 1, 1.0), speed=1.0)                  # point to the right, at speed
    assert out["L"] > out["R"] and c.heading_error == pytest.approx(math.atan2(1, 3))
    out = feed(c, 0.05, point=nav(3, -1, 1.0), speed=1.0)                # to the left
    assert out["L"] < out["R"]
    c = controller(rate_limit_pct_s=0.0)
    slow = feed(c, 0.0, point=nav(3, 0, 1.0), speed=0.2)
    c = controller(rate_limit_pct_s=0.0)
    fast = feed(c, 0.0, point=nav(3, 0, 1.0), speed=1.8)
    assert slow["L"] > 50.0 > fast["L"]                                 # feedforward 50 %/(m/s) +- correction
    c = controller(rate_limit_pct_s=0.0)
    behind = feed(c, 0.0, point=nav(-3, 0.01, 1.0), speed=0.0)
    assert c.desired_speed == pytest.approx(0.25) and behind["L"] > 0 > behind["R"]   # turning, little speed


def test_rate_limit_on_every_output() -> None:
    c = controller(rate_limit_pct_s=100.0)
    previous = {"L": 0.0, "R": 0.0}
    for i in range(40):
        out = feed(c, i * 0.05, point=nav(3, 2, 2.0), speed=0.0)
        for name in out:
            assert abs(out[name] - previous[name]) <= 100.0 * 0.05 + 1e-9
        previous = out
    assert previous["L"] > 90.0                                          # got there in the end


def test_manual_resets_integrators_and_handback_is_bumpless() -> None:
    c = controller(rate_limit_pct_s=100.0)
    now = 0.0
    for _ in range(100):                                                # 5 s autonomous, too slow: integrals grow
        out = feed(c, now, point=nav(3, 1, 1.0), speed=0.5)
        now += 0.05
    assert c.speed_pid.integral > 5.0 and c.heading_pid.integral > 1.0 and max(out.values()) > 50
    out = feed(c, now, point=nav(3, 1, 1.0), speed=0.5, mode=0)         # the pilot takes over
    assert out == {"L": 0.0, "R": 0.0} and c.neutral_reason == "RC manual"
    assert c.speed_pid.integral == 0.0 and c.heading_pid.integral == 0.0
    for _ in range(20):
        now += 0.05
        assert feed(c, now, point=nav(3, 1, 1.0), speed=0.5, mode=0) == {"L": 0.0, "R": 0.0}
    steps = []
    for _ in range(10):                                                 # handed back
        now += 0.05
        steps.append(feed(c, now, point=nav(3, 1, 1.0), speed=0.5))
    assert max(abs(v) for v in steps[0].values()) <= 5.0 + 1e-9         # starts from rest, slewed
    for a, b in zip(steps, steps[1:]):
        assert all(abs(b[n] - a[n]) <= 5.0 + 1e-9 for n in a)


def test_a_cycle_without_a_new_point_slews_on_and_leaves_the_loops_alone() -> None:
    c = controller(rate_limit_pct_s=100.0, heading=PidGains(kp=80.0, ki=5.0, kd=10.0, integral_limit=20.0))
    c.on_estimate(t.StateInformation().set(psi=0.0, x_dot=0.5, y_dot=0.0), 0.0)   # no yaw rate: d from the error
    feed(c, 0.0, point=nav(3, 1, 1.0))
    first = feed(c, 0.05, point=nav(3, 1, 1.0))
    integral, terms, targets = c.heading_pid.integral, c.heading_pid.terms, dict(c.targets)
    assert max(abs(v - targets[n]) for n, v in first.items()) > 5.0     # still slewing toward the targets
    refreshed = c.refresh(0.08)                                         # the rate's cycle: no new point
    assert c.heading_pid.integral == integral and c.heading_pid.terms == terms and c.targets == targets
    for name, value in refreshed.items():                               # on toward the same targets, 30 ms worth
        assert abs(value - first[name]) == pytest.approx(min(100.0 * 0.03, abs(targets[name] - first[name])))
    # the next point's PID step spans the 50 ms since the last point; the slew, the 20 ms since the refresh
    error = math.atan2(1.5, 3.0)
    after = feed(c, 0.1, point=nav(3, 1.5, 1.0))
    assert c.heading_pid.integral == pytest.approx(integral + 5.0 * error * 0.05)
    assert c.heading_pid.terms[2] == pytest.approx(10.0 * (error - math.atan2(1, 3)) / 0.05)
    assert all(abs(after[n] - refreshed[n]) <= 100.0 * 0.02 + 1e-9 for n in after)
    assert c.refresh(0.7) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "NAV_POINT silent for 0.6 s"
    assert c.targets is None and c.heading_pid.integral == 0.0


def test_other_subsystems_and_non_finite_points_are_not_followed() -> None:
    c = controller()
    assert not c.on_nav(nav(3, 0, 1.0, subsystem="gimbal"), 0.0)
    bad = nav(float("nan"), 0, 1.0)
    assert not c.on_nav(bad, 0.0) and c.nav_rejected == 1
    c.on_rc_mode(rc(1), 0.0)
    assert c.step(0.0) == {"L": 0.0, "R": 0.0} and c.neutral_reason == "no NAV_POINT received"


def test_a_non_finite_velocity_leaves_the_feedforward_alone() -> None:
    c = controller(rate_limit_pct_s=0.0)
    c.on_estimate(t.StateInformation().set(psi=0.0, x_dot=float("nan"), y_dot=0.0), 0.0)
    c.on_rc_mode(rc(1), 0.0)
    c.on_nav(nav(3, 0, 1.0), 0.0)
    assert c.step(0.0) == {"L": 50.0, "R": 50.0} and c.measured_speed is None


# -- planner and control as real services over LCM -------------------------------------------------------
ORIGIN = Origin(lat=47.0, lon=8.0, alt=400.0)


def test_planner_and_control_processes_drive_and_report(services: ServiceProcesses, bus: BusClient,
                                                         tmp_path: Path) -> None:
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text(
        f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
        "[services.planner]\nkind = \"path_planner\"\nsettings = { lookahead_m = 3.0, cruise_speed_m_s = 1.0 }\n"
        "[services.control]\nkind = \"control\"\n"
        "settings = { mixer = \"differential\", left_actuator = \"wheel_l\", right_actuator = \"wheel_r\" }\n")
    navs: list[t.NavigationPoint] = []
    cmds: list[t.PercentageCommand] = []
    reports: list[t.GoalReport] = []
    bus.transport.subscribe(ch.NAV_POINT, t.NavigationPoint, lambda _c, m: navs.append(m))
    bus.transport.subscribe(ch.ACTUATOR_CMD, t.ActuatorCommand, lambda _c, m: cmds.append(m))
    bus.transport.subscribe(ch.GOAL_REPORT, t.GoalReport, lambda _c, m: reports.append(m))
    health: dict[str, dict[str, str]] = {}
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, m: health.update(
        {m.name: {kv.key: kv.value for kv in m.details}}))
    services.start("planner", "--vehicle", str(vehicle))
    services.start("control", "--vehicle", str(vehicle))

    lat, lon, _ = ned_to_geodetic(10.0, 0.0, origin=ORIGIN)        # a GLOBAL waypoint 10 m north
    goal = t.Waypoint()
    goal.base.uid, goal.reference_frame, goal.horizontal_threshold = "north10", "GLOBAL", 1.5
    goal.set(x=lat, y=lon)

    def publish(mode: int, *, x: float = 0.0) -> None:
        bus.publish(ch.STATE_ESTIMATE, t.StateInformation().set(x=x, y=0.0, psi=0.0, x_dot=0.0, y_dot=0.0))
        bus.publish(ch.GOALS, goal)
        bus.publish(ch.RC_MODE, rc(mode))

    def driving() -> bool:
        publish(1)
        recent = [m for m in cmds[-6:] if isinstance(m, t.PercentageCommand)]
        return any(m.percentage > 5.0 for m in recent)

    wait_until(driving, timeout=20, interval=0.05, message="wheel commands above 5 % in autonomous mode")
    point = next(n for n in reversed(navs) if n.goal_uid == "north10")
    assert point.x == pytest.approx(3.0, abs=0.01) and point.y == pytest.approx(0.0, abs=0.01)
    assert point.distance_to_goal == pytest.approx(10.0, abs=0.01) and point.speed > 0
    assert {m.base.actuator_name for m in cmds[-4:]} == {"wheel_l", "wheel_r"}
    wait_until(lambda: driving() and health.get("planner", {}).get("doing") == "to waypoint"
               and health.get("control", {}).get("driving") == "True", timeout=10, interval=0.05,
               message="health of both services saying they drive to the waypoint")
    assert health["planner"]["state"] == "waypoint" and health["planner"]["goal"] == "north10"
    assert health["control"]["mixer"] == "differential"

    def neutral() -> bool:
        publish(0)
        recent = cmds[-4:]
        return len(recent) == 4 and all(isinstance(m, t.PercentageCommand) and m.percentage == 0.0 for m in recent)

    wait_until(neutral, timeout=10, interval=0.05, message="neutral commands once RC_MODE is manual")

    def reported() -> bool:
        publish(1, x=9.0)                                              # within 1.5 m of the goal
        return any(r.uid == "north10" and r.completed for r in reports)

    wait_until(reported, timeout=10, interval=0.05, message="the completion report on GOAL_REPORT")

    def holding() -> bool:
        publish(1, x=9.0)
        recent = cmds[-4:]
        return bool(navs) and navs[-1].speed == 0.0 and all(m.percentage == 0.0 for m in recent)

    wait_until(holding, timeout=10, interval=0.05, message="the hold at the goal to reach the wheels")


def test_planner_and_control_answer_each_input_at_once_with_their_rates_as_the_floor(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    vehicle = tmp_path / "vehicle.toml"
    # one cycle per 30 s from the rates: what answers the inputs below within seconds is the inputs' doing
    vehicle.write_text(
        f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
        "[services.planner]\nkind = \"path_planner\"\nsettings = { control_rate_hz = 0.033 }\n"
        "[services.control]\nkind = \"control\"\nsettings = { control_rate_hz = 0.033, nav_timeout_s = 60.0, "
        "rc_timeout_s = 60.0, left_actuator = \"wheel_l\", right_actuator = \"wheel_r\" }\n")
    navs: list[t.NavigationPoint] = []
    cmds: list[t.PercentageCommand] = []
    bus.transport.subscribe(ch.NAV_POINT, t.NavigationPoint, lambda _c, m: navs.append(m))
    bus.transport.subscribe(ch.ACTUATOR_CMD, t.PercentageCommand, lambda _c, m: cmds.append(m))
    seen: set[str] = set()
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, m: seen.add(m.name))
    services.start("planner", "--vehicle", str(vehicle))
    services.start("control", "--vehicle", str(vehicle))
    wait_until(lambda: {"planner", "control"} <= seen, timeout=20, message="both services' health")
    goal = t.Waypoint()
    goal.base.uid, goal.reference_frame = "ahead", "LOCAL"
    goal.set(x=20.0, y=0.0)
    bus.publish(ch.RC_MODE, rc(1))
    wait_until(lambda: cmds, timeout=10, message="the neutral commands of the first cycle, at start")
    base_navs, base_cmds = len(navs), len(cmds)
    for k in range(1, 4):
        bus.publish(ch.GOALS, goal)
        bus.publish(ch.STATE_ESTIMATE, t.StateInformation().set(x=0.1 * k, y=0.0, psi=0.0, x_dot=0.0, y_dot=0.0))
        wait_until(lambda: len(navs) >= base_navs + k and len(cmds) >= base_cmds + 2 * k, timeout=10,
                   message=f"the point and the two commands answering estimate {k}")
    assert navs[-1].goal_uid == "ahead" and navs[-1].speed > 0
    assert {c.base.actuator_name for c in cmds[-2:]} == {"wheel_l", "wheel_r"}
    assert all(c.percentage > 0 for c in cmds[-2:])                      # driving, slewed up from rest
    mark = len(cmds)
    bus.publish(ch.RC_MODE, rc(0))                                       # the pilot takes over: neutral at once
    wait_until(lambda: len(cmds) >= mark + 2, timeout=10, message="neutral commands answering RC manual")
    assert all(c.percentage == 0.0 for c in cmds[mark:mark + 2])
