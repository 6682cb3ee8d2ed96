"""``u2sa sim``'s progress line and its judgement of when a looping mission has gone round once."""

from __future__ import annotations

import math

from u2sa_hw import lcmtypes as t
from u2sa_hw.services.mission.manager import MissionManager
from u2sa_hw.services.mission.xml import parse_mission
from u2sa_hw.simulation.progress import BusSnapshot, StatusChange, loop_completed, status_text


def _status(uid: str, index: int, *, total: int = 4, finished: bool = False) -> t.MissionStatus:
    st = t.MissionStatus()
    st.mission_name, st.current_uid, st.current_index, st.finished = "block loop", uid, index, finished
    st.goal_uids = ["north_gate", "far_corner", "east_gate", "home"][:total]
    st.num_goals = len(st.goal_uids)
    return st


def _rc(mode: int, enabled: bool = True) -> t.RcMode:
    rc = t.RcMode()
    rc.mode, rc.autonomy_enabled = mode, enabled
    return rc


def test_status_text_says_goal_k_of_n_distance_speed_heading_and_mode() -> None:
    snap = BusSnapshot(estimate=(0.0, 20.0, 3.0, math.radians(87.0), 1.984), status=_status("far_corner", 1),
                       rc=_rc(1))
    assert status_text(snap, elapsed=12.34, goal_total=4, distance=8.14) == (
        "[ 12.3 s] goal 2/4 far_corner   8.1 m | 1.98 m/s | hdg 087 | AUTONOMOUS")
    # heading wraps to 0..359; no distance yet; the mux not enabling autonomy is said so
    snap = BusSnapshot(estimate=(0.0, 0.0, 0.0, math.radians(-90.0), 0.0), status=_status("north_gate", 0),
                       rc=_rc(1, enabled=False))
    assert status_text(snap, elapsed=1.0, goal_total=4, distance=None) == (
        "[  1.0 s] goal 1/4 north_gate | 0.00 m/s | hdg 270 | AUTONOMOUS (not enabled)")


def test_status_text_without_estimate_status_or_with_a_failsafe() -> None:
    assert status_text(BusSnapshot(), elapsed=0.0, goal_total=4, distance=None) == (
        "[  0.0 s] waiting for MISSION_STATUS | no estimate | no RC_MODE")
    failsafe = t.Failsafe()
    failsafe.active = True
    snap = BusSnapshot(estimate=(0.0, 0.0, 0.0, math.nan, math.nan), status=_status("", -1, finished=True),
                       rc=_rc(0), failsafe=failsafe)
    assert status_text(snap, elapsed=50.0, goal_total=4, distance=None) == (
        "[ 50.0 s] mission 'block loop' finished | -- m/s | hdg --- | FAILSAFE")
    assert status_text(BusSnapshot(rc=_rc(2)), elapsed=0.0, goal_total=4, distance=None).endswith("NO RC SIGNAL")


BRANCHING_LOOP = """\
<mission name="branching loop" loop="true">
  <waypoint><name>start</name><next>left</next><next>right</next><x>0</x><y>0</y></waypoint>
  <waypoint><name>left</name><next>join</next><x>10</x><y>-5</y></waypoint>
  <waypoint><name>right</name><next>join</next><x>10</x><y>5</y></waypoint>
  <waypoint><name>join</name><x>20</x><y>0</y></waypoint>
</mission>
"""


def _changes_while_driving(manager: MissionManager, reports: list[str], *, t0: float) -> list[StatusChange]:
    """The MISSION_STATUS timeline a monitor hears while the planner reports *reports* in turn."""
    changes = []
    for step, uid in enumerate([None, *reports]):
        if uid is not None:
            assert manager.complete(uid), uid
        st = manager.state()
        changes.append(StatusChange(t0 + step, st.current_uid, st.current_index, st.finished))
    return changes


def test_a_branching_looping_mission_completes_one_loop_without_the_branch_not_taken() -> None:
    manager = MissionManager(parse_mission(BRANCHING_LOOP, source="m.xml", default_threshold=2.0))
    # before engaging (t 99) the first goal is current; the planner takes the first branch every lap
    changes = _changes_while_driving(manager, ["start", "left"], t0=99.0)
    assert [c.uid for c in changes] == ["start", "left", "join"]
    assert not loop_completed(changes, since=99.5)                    # "right" never current, loop not closed
    changes += _changes_while_driving(manager, ["join"], t0=102.0)[1:]
    assert changes[-1].uid == "start" and "right" not in {c.uid for c in changes}
    assert loop_completed(changes, since=99.5)


def test_loop_counting_starts_at_the_goal_current_when_going_autonomous() -> None:
    a1, b2, a3 = StatusChange(1.0, "a", 0, False), StatusChange(2.0, "b", 1, False), StatusChange(3.0, "a", 0, False)
    assert loop_completed([a1, b2, a3], since=1.5)          # engaged on a: a -> b -> a
    assert not loop_completed([a1, b2, a3], since=2.5)      # engaged on b: b -> a, not back at b yet
    assert loop_completed([a1, b2, a3, StatusChange(4.0, "b", 1, False)], since=2.5)
    assert not loop_completed([a1, b2, a3, StatusChange(4.0, "c", 2, False), StatusChange(5.0, "a", 0, False)],
                              since=2.5)
    assert not loop_completed([a1], since=0.5)              # still on the first goal
    assert not loop_completed([], since=0.0)
    assert not loop_completed([a1, StatusChange(2.0, "", -1, True)], since=0.5)   # finished, not looped
