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
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config import field
from u2sa_hw.messages import as_type
from u2sa_hw.service import U2SAService
from u2sa_hw.services.mission.manager import MissionError, MissionManager, from_message, to_waypoint
from u2sa_hw.services.mission.xml import load_mission, parse_mission
from u2sa_hw.services.mission.xmltree import XmlFileError

LOOP_CHOICES = {"file": None, "true": True, "false": False}


class MissionManagerService(U2SAService):
    """Keeps the mission's goals and publishes the current ones."""

    SERVICE_TYPE: ClassVar[str] = "mission_manager"
    CONFIG = (
        field("mission_file", "", "mission XML; a relative path is relative to the vehicle profile's directory"),
        field("default_threshold_m", 2.0, "horizontal completion radius of goals without <threshold>, m"),
        field("loop", "file", "file: as the mission's loop attribute says; true or false: override it"),
        field("publish_interval_s", 1.0, "republish the current goals and the status this often, s"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._lock = threading.Lock()
        self.manager = MissionManager(loop=self._loop_setting(), logger=self.logger,
                                      default_threshold=float(self.config.get("default_threshold_m")))
        self.reports_ignored = 0
        self.commands_refused = 0
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
        except XmlFileError as exc:
            self.error(f"mission not loaded: {exc}")
            self.status = "degraded"
            return False
        with self._lock:
            self.manager.load(spec)
        self.status = "ok"
        self.logger.info("mission %s loaded from %s: %d goals, loop %s", spec.name, path, len(spec.goals),
                         self.manager.looping)
        return True

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
                    self.manager.load(spec)
                else:
                    raise MissionError(f"unknown command {cmd.command!r}; known: goto, skip, restart, upload")
            except (MissionError, XmlFileError) as exc:
                self.commands_refused += 1
                self.error(f"mission command from {who} refused: {exc}")
                return
        self.logger.info("mission command %s%s from %s", verb, f" {cmd.uid}" if cmd.uid else "", who)
        if verb == "upload":
            self.status = "ok"
        self._changed(before)

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
                "reports_ignored": self.reports_ignored, "commands_refused": self.commands_refused}


def _source_of(msg: Any) -> str:
    return as_type(msg, t.GoalInformation).header.source
