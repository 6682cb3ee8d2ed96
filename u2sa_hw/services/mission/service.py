"""Mission Manager service (requirement S2; thesis 3.2.3.2, 4.5.2.3).

Reads the mission file (:mod:`.xml`), keeps the goals and the current ones
(:mod:`.manager`), and publishes the current goals as LOCAL ``Waypoint`` messages on
``GOALS`` plus a ``MissionStatus`` on ``MISSION_STATUS``, at once on every change and
every ``publish_interval_s``. Its inputs:

- ``GOAL_REPORT``: a ``GoalReport`` with completed = true for a current goal advances the
  mission along that goal's successors;
- ``GOALS``: goal updates from other services, merged by UID (its own messages are skipped);
- ``MISSION_CMD``: ``goto`` uid, ``skip``, ``restart``, or ``upload`` with ``mission_xml``
  (a whole new mission; bad XML is refused, logged with the element and line, and the
  running mission is kept).

A mission file, an upload or a goal update on ``GOALS`` with a goal outside the profile's geofence
(or closer to a line than ``[geofence] margin_m``) is refused the same way, naming the goal and the
area (:mod:`.fence_check`).

Every command is acknowledged on ``U2SA_HEALTH`` at once: the health detail
``last_command`` reads ``"<command> from <sender>: ok"`` or ``"...: refused: <reason>"``
(the sender is the command's ``header.source``), after the changed mission went out.
``u2sa mission`` waits for it (:mod:`u2sa_hw.cli.mission_cmd`).
"""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import MAX_TIMEOUT_S, field
from u2sa_hw.geo import geodetic_to_ned
from u2sa_hw.messages import as_type
from u2sa_hw.geofence_parse import profile_fence
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.services.mission.fence_check import check_mission, goal_problem
from u2sa_hw.services.mission.manager import MissionError, MissionManager, from_message, to_waypoint
from u2sa_hw.services.mission.xml import GLOBAL, MissionSpec, load_mission, parse_mission
from u2sa_hw.services.mission.xmltree import XmlFileError

LOOP_CHOICES = {"file": None, "true": True, "false": False}
FAR_GOAL_M = 100_000.0   # a Global goal this far from the origin is most likely a lat/lon mix-up


class MissionManagerService(U2SAService):
    """Keeps the mission's goals and publishes the current ones."""

    SERVICE_TYPE: ClassVar[str] = "mission_manager"
    CONFIG = (
        field("mission_file", "", "mission XML; a relative path is relative to the vehicle profile's directory",
              file=True),
        field("default_threshold_m", 2.0, "horizontal completion radius of goals without <threshold>, m", gt=0, le=10000.0),
        field("loop", "file", "file: as the mission's loop attribute says; true or false: override it"),
        field("publish_interval_s", 1.0, "republish the current goals and the status this often, s", gt=0, le=MAX_TIMEOUT_S),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._lock = threading.Lock()
        self.fence = profile_fence(self.profile)
        self.manager = MissionManager(loop=self._loop_setting(), logger=self.logger,
                                      default_threshold=float(self.config.get("default_threshold_m")))
        self.reports_ignored = 0
        self.commands_refused = 0
        self.last_command = ""
        self.register_subscriber(ch.GOAL_REPORT, t.GoalReport, self._on_report)
        self.register_subscriber(ch.GOALS, t.GoalInformation, self._on_goal_update)
        self.register_subscriber(ch.MISSION_CMD, t.MissionCommand, self._on_command)
        self.register_publisher(ch.GOALS, t.Waypoint)
        self.register_publisher(ch.MISSION_STATUS, t.MissionStatus)

    # -- configuration -------------------------------------------------------------------------
    def _loop_setting(self) -> bool | None:
        value = str(self.config.get("loop")).strip().lower()
        if value not in LOOP_CHOICES:
            self.error(f"config loop = {value!r}: use file, true or false; using the mission file's setting")
            return None
        return LOOP_CHOICES[value]

    def mission_path(self) -> Path | None:
        """The configured mission file, resolved against the profile's directory."""
        return self.profile.resolve_path(str(self.config.get("mission_file")))

    def load_configured_mission(self) -> bool:
        """Load ``mission_file``; on error keep the current mission, log it and degrade."""
        path = self.mission_path()
        if path is None:
            self.logger.warning("no mission_file configured: waiting for a mission upload on %s", ch.MISSION_CMD)
            return False
        try:
            spec = load_mission(path, default_threshold=float(self.config.get("default_threshold_m")))
            check_mission(spec, self.fence, self.profile.origin)
        except (XmlFileError, MissionError) as exc:
            self.error(f"mission not loaded: {exc}")
            self.status = "degraded"
            return False
        self._warn_far_goals(spec)
        with self._lock:
            self.manager.load(spec)
        self.status = "ok"
        self.logger.info("mission %s loaded from %s: %d goals, loop %s", spec.name, path, len(spec.goals),
                         self.manager.looping)
        return True

    def _warn_far_goals(self, spec: MissionSpec) -> None:
        """Log Global goals over FAR_GOAL_M from the origin: latitude and longitude swapped, or a wrong origin."""
        origin = self.profile.origin
        for goal in spec.goals:
            if goal.frame != GLOBAL or "x" not in goal.values:
                continue
            north, east, _ = geodetic_to_ned(goal.values["x"], goal.values["y"], origin=origin)
            if math.hypot(north, east) > FAR_GOAL_M:
                self.logger.warning("%s:%d: goal %s (latitude %.6f, longitude %.6f) is %.0f km from the origin "
                                    "(%.6f, %.6f): check the vehicle profile's origin and, for <x>/<y> in a Global "
                                    "waypoint, that <x> is the longitude and <y> the latitude", goal.source,
                                    goal.line, goal.uid, goal.values["x"], goal.values["y"],
                                    math.hypot(north, east) / 1000.0, origin.lat, origin.lon)

    def setup(self) -> None:
        """Load the mission file."""
        self.load_configured_mission()

    def on_config_change(self, name: str, value: Any) -> None:
        """Reload on a new mission file; apply a loop override or default threshold live."""
        if name == "mission_file":
            if self.load_configured_mission():
                self.publish_mission()
        elif name == "loop":
            with self._lock:
                self.manager.set_loop(self._loop_setting())
            self.publish_mission()
        elif name == "default_threshold_m":
            self.manager.default_threshold = float(value)

    # -- inputs ----------------------------------------------------------------------------------
    def _changed(self, before: int) -> None:
        if self.manager.version != before:
            self.publish_mission()

    def _on_report(self, msg: t.GoalReport) -> None:
        if not msg.completed:
            self.logger.info("goal %s reported not completed by %s: %s", msg.uid, msg.header.source or "?",
                             msg.detail or "no detail")
            return
        with self._lock:
            before = self.manager.version
            if not self.manager.complete(msg.uid):
                self.reports_ignored += 1
        self._changed(before)

    def _on_goal_update(self, msg: Any) -> None:
        if _source_of(msg) == self.name:
            return
        parsed = from_message(msg)
        if parsed is None:
            return
        goal, fields = parsed
        with self._lock:
            before = self.manager.version
            try:
                if self.fence is not None and (problem := goal_problem(goal, None, self.fence, self.profile.origin)):
                    raise MissionError(f"goal update: {problem}")
                result = self.manager.merge(goal, fields=fields)
            except MissionError as exc:
                self.commands_refused += 1
                self.error(f"goal update from {_source_of(msg) or '?'} refused: {exc}")
                return
        self.logger.info("goal %s %s by %s", goal.uid, result, _source_of(msg) or "?")
        self._changed(before)

    def _on_command(self, cmd: t.MissionCommand) -> None:
        who = cmd.header.source or "?"
        verb = cmd.command.strip().lower()
        what = f"{verb} {cmd.uid}" if verb == "goto" else verb
        refused: Exception | None = None
        with self._lock:
            before = self.manager.version
            try:
                if verb == "goto":
                    self.manager.goto(cmd.uid)
                elif verb == "skip":
                    if not self.manager.skip():
                        raise MissionError("skip: the mission has finished; nothing to skip")
                elif verb == "restart":
                    self.manager.restart()
                elif verb == "upload":
                    spec = parse_mission(cmd.mission_xml, source=f"mission uploaded by {who}",
                                         default_threshold=float(self.config.get("default_threshold_m")))
                    self._warn_far_goals(spec)
                    check_mission(spec, self.fence, self.profile.origin)
                    self.manager.load(spec)
                else:
                    raise MissionError(f"unknown command {cmd.command!r}; known: goto, skip, restart, upload")
            except (MissionError, XmlFileError) as exc:
                refused = exc
                self.commands_refused += 1
        if refused is not None:
            self.last_command = f"{what} from {who}: refused: {refused}"
            self.error(f"mission command from {who} refused: {refused}")
            self.publish_health()   # the acknowledgement (outside the lock: health_details takes it)
            return
        self.logger.info("mission command %s from %s", what, who)
        if verb == "upload":
            self.status = "ok"
        self._changed(before)
        self.last_command = f"{what} from {who}: ok"
        self.publish_health()   # the acknowledgement, after the mission it changed

    # -- outputs -----------------------------------------------------------------------------------
    def publish_mission(self) -> None:
        """Publish the current goals on GOALS and the status on MISSION_STATUS."""
        with self._lock:
            origin = self.profile.origin
            goals = [to_waypoint(g, origin=origin, next_uids=self.manager.successors(g.uid))
                     for g in self.manager.current_goals()]
            state = self.manager.state()
        for wp in goals:
            self.publish(ch.GOALS, wp)
        status = t.MissionStatus()
        status.mission_name, status.current_uid, status.current_index = state.name, state.current_uid, state.current_index
        status.goal_uids, status.num_goals = state.uids, len(state.uids)
        status.finished, status.looping = state.finished, state.looping
        self.publish(ch.MISSION_STATUS, status)

    def run(self) -> None:
        """Republish the mission every ``publish_interval_s``."""
        self.publish_mission()
        while self.wait(max(0.05, float(self.config.get("publish_interval_s")))):
            self.publish_mission()

    def health_details(self) -> dict[str, Any]:
        """Mission name, progress, and the refused inputs."""
        with self._lock:
            state = self.manager.state()
        return {"mission": state.name, "current": state.current_uid,
                "progress": f"{state.current_index + 1}/{len(state.uids)}" if not state.finished else "finished",
                "reports_ignored": self.reports_ignored, "commands_refused": self.commands_refused,
                "last_command": self.last_command}


def _source_of(msg: Any) -> str:
    return as_type(msg, t.GoalInformation).header.source
