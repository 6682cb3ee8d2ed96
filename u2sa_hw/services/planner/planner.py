"""The Path Planner's bookkeeping, free of the bus: goals, the current one, objects, reports.

:class:`PathPlanner` is fed the messages the service receives (``on_goal``, ``on_status``,
``on_object``, ``on_estimate``, each with the monotonic time it arrived) and asked once per
control cycle for a :class:`Cycle`: the navigation point to publish (or None) and a goal
report to send (or None). The service shell (:mod:`.service`) adds the bus; the tests drive
this class directly in a closed loop.

- Goals are kept by UID (the latest message wins). The current goal is the one
  ``MissionStatus.current_uid`` names; before any status arrives, the latest goal received.
  A finished mission, or an empty current UID, leaves the planner idle.
- The state is chosen by the goal's type (:func:`.states.state_for`) and rebuilt when the
  current goal or its message changes, keeping the state's memory for the same UID.
- Objects are kept by UID and dropped ``object_expiry_s`` after their last message; only
  objects in the local frame (NED) can be steered around, others are counted and skipped.
- The profile's geofence (:mod:`u2sa_hw.geofence`), when there is one, is one more level-3 object whose
  distance from a point is the point's distance to the nearest fence line (0 outside): the avoidance keeps
  ``clearance_margin_m`` from the lines, routes around exclusion areas and holds, "blocked", rather than
  leave the fence or head for a goal outside it.
- Without a pose younger than ``estimate_timeout_s`` nothing is published (the control
  system then goes neutral on its own timeout). With a pose but no goal a *hold* point is
  published: x = y = z = 0, speed 0, distance_to_goal -1 and goal_uid ''.
- A goal is reported complete once when it is reached; if the mission manager still names
  it current ``report_resend_s`` later (the report was lost), the report is sent again. A
  UID that stops being current is forgotten, so a looping mission reports it again next lap.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.geofence import Fence, FenceObstacle
from u2sa_hw.messages import as_type
from u2sa_hw.services.planner.avoidance import Obstacle
from u2sa_hw.services.planner.states import GoalState, GuidanceSettings, IdleState, Plan, PlanContext, Pose, state_for

LOCAL_OBJECT_FRAMES = ("", "NED", "LOCAL")


@dataclass(frozen=True)
class PlannerTimings:
    """Timeouts of the planner's inputs and outputs (seconds)."""

    estimate_timeout_s: float = 1.0
    object_expiry_s: float = 3.0
    report_resend_s: float = 2.0


@dataclass(frozen=True)
class Cycle:
    """What one control cycle produced."""

    nav: t.NavigationPoint | None
    report: t.GoalReport | None
    plan: Plan | None


@dataclass
class _Tracked:
    obstacle: Obstacle
    seen: float


class PathPlanner:
    """Goals, objects and pose in; navigation points and completion reports out."""

    def __init__(self, *, guidance: GuidanceSettings, timings: PlannerTimings, subsystem: str = "vehicle",
                 logger: logging.Logger | None = None, fence: Fence | None = None) -> None:
        self.guidance = guidance
        self.timings = timings
        self.subsystem = subsystem
        self.logger = logger or logging.getLogger("u2sa.planner")
        self.goals: dict[str, Any] = {}
        self.fence_obstacles = [FenceObstacle(fence)] if fence is not None else []
        self.status: t.MissionStatus | None = None
        self.latest_goal_uid = ""
        self.objects: dict[str, _Tracked] = {}
        self.pose: Pose | None = None
        self.pose_time = -float("inf")
        self.state: GoalState = IdleState()
        self._state_goal: Any = None
        self.memory: dict[str, Any] = {}
        self.reported: dict[str, float] = {}
        self.reports_sent = 0
        self.objects_skipped = 0
        self.last_plan: Plan | None = None
        self.waiting_for = "STATE_ESTIMATE"
        self._logged: set[str] = set()

    # -- inputs ----------------------------------------------------------------------------
    def on_goal(self, msg: Any, now: float) -> None:
        """A goal from GOALS (a Waypoint, or any GoalInformation)."""
        uid = as_type(msg, t.GoalInformation).uid
        if not uid:
            self._log_once("goal-without-uid", "a goal without a UID on GOALS was ignored")
            return
        self.goals[uid] = msg
        self.latest_goal_uid = uid

    def on_status(self, msg: t.MissionStatus, now: float) -> None:
        """The mission manager's status: which goal is current; goals no longer in the mission are dropped."""
        self.status = msg
        current = "" if msg.finished else msg.current_uid
        self.reported = {uid: sent for uid, sent in self.reported.items() if uid == current}
        if msg.num_goals:
            keep = set(msg.goal_uids)
            self.goals = {uid: g for uid, g in self.goals.items() if uid in keep}

    def on_object(self, msg: Any, now: float) -> None:
        """An object from WORLD (local NED); others cannot be steered around and are counted."""
        base = as_type(msg, t.ObjectDescription)
        frame = base.reference_frame.strip().upper()
        if frame not in LOCAL_OBJECT_FRAMES:
            self.objects_skipped += 1
            self._log_once(f"frame-{frame}", f"object {base.uid or '?'} in frame {base.reference_frame!r} skipped: the "
                                              "planner steers around local NED objects (the world modeler's output)")
            return
        if not all(math.isfinite(v) for v in (base.x, base.y)):
            self.objects_skipped += 1
            self._log_once("object-nan", f"object {base.uid or '?'} with a non-finite position skipped")
            return
        uid = base.uid or f"{base.source}@{base.x:.1f},{base.y:.1f}"
        self.objects[uid] = _Tracked(Obstacle(msg), now)

    def on_estimate(self, msg: t.StateInformation, now: float) -> None:
        """The state estimate; one without a finite x, y and psi is not a pose."""
        pose = Pose.from_estimate(msg)
        if pose is None:
            self._log_once("no-pose", "STATE_ESTIMATE lacks a finite x, y or psi: waiting for a full pose")
            return
        self.pose, self.pose_time = pose, now

    # -- the current goal -------------------------------------------------------------------
    def current_uid(self) -> str:
        """The UID of the goal to work on ('' for none)."""
        if self.status is not None:
            return "" if self.status.finished else self.status.current_uid
        return self.latest_goal_uid

    def _update_state(self) -> None:
        uid = self.current_uid()
        goal = self.goals.get(uid) if uid else None
        if goal is not None and goal is self._state_goal:
            return
        previous_uid = self.state.uid
        self._state_goal = goal
        if goal is None:
            reason = "mission finished" if self.status is not None and self.status.finished else (
                f"waiting for goal {uid}" if uid else "no current goal")
            self.state = IdleState(reason=reason)
        else:
            self.state = state_for(goal)
        if self.state.uid != previous_uid:
            self.memory = {}
            if self.state.uid:
                self.logger.info("working on goal %s (%s state)", self.state.uid, self.state.name)
        if isinstance(self.state, IdleState) and goal is not None:
            self._log_once(f"idle-{uid}-{type(goal).__name__}", f"goal {uid}: {self.state.reason}; holding")

    # -- one cycle ------------------------------------------------------------------------
    def expire_objects(self, now: float) -> None:
        """Forget objects not refreshed within ``object_expiry_s``."""
        limit = self.timings.object_expiry_s
        if limit > 0:
            self.objects = {uid: tr for uid, tr in self.objects.items() if now - tr.seen <= limit}

    def step(self, now: float) -> Cycle:
        """Run the current state once: the nav point to publish and a report to send, if any."""
        self.expire_objects(now)
        if self.pose is None or now - self.pose_time > self.timings.estimate_timeout_s:
            self.waiting_for = "STATE_ESTIMATE" if self.pose is None else "a fresh STATE_ESTIMATE"
            self.last_plan = None
            return Cycle(nav=None, report=None, plan=None)
        self.waiting_for = ""
        self._update_state()
        ctx = PlanContext(pose=self.pose, obstacles=[*(tr.obstacle for tr in self.objects.values()),
                                                     *self.fence_obstacles],
                          settings=self.guidance, memory=self.memory)
        plan = self.state.step(ctx)
        self.last_plan = plan
        report = self._report(plan, now)
        return Cycle(nav=self._nav_point(plan), report=report, plan=plan)

    def _report(self, plan: Plan, now: float) -> t.GoalReport | None:
        uid = self.state.uid
        if not plan.reached or not uid:
            return None
        sent = self.reported.get(uid)
        if sent is not None and now - sent < self.timings.report_resend_s:
            return None
        if sent is not None:
            self.logger.warning("goal %s still current %.1f s after its completion report: sending it again",
                                uid, now - sent)
        else:
            self.logger.info("goal %s reached (%.2f m from it)", uid, plan.distance_to_goal)
        self.reported[uid] = now
        self.reports_sent += 1
        msg = t.GoalReport()
        msg.uid, msg.completed = uid, True
        msg.detail = f"within {plan.distance_to_goal:.2f} m ({self.state.name})"
        return msg

    def _nav_point(self, plan: Plan) -> t.NavigationPoint:
        nav = t.NavigationPoint()
        nav.subsystem, nav.goal_uid = self.subsystem, self.state.uid
        nav.x, nav.y, nav.z = plan.x, plan.y, plan.z
        nav.speed, nav.distance_to_goal = plan.speed, plan.distance_to_goal
        return nav

    # -- health ---------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """State, goal, what the planner does or waits for, counters."""
        plan = self.last_plan
        return {"state": self.state.name, "goal": self.state.uid or "none",
                "doing": self.waiting_for and f"waiting for {self.waiting_for}" or (plan.note if plan else ""),
                "distance_to_goal": f"{plan.distance_to_goal:.2f}" if plan and plan.distance_to_goal >= 0 else "",
                "objects": len(self.objects), "objects_skipped": self.objects_skipped,
                "reports_sent": self.reports_sent}

    def _log_once(self, key: str, text: str) -> None:
        if key not in self._logged:
            self._logged.add(key)
            self.logger.warning(text)
