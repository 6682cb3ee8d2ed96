"""The Mission Manager's logic (thesis 3.2.3.2), free of the bus: goals, the current ones, and how they change.

The *current goals* are the goals the vehicle may work on now: one in a sequential
mission, several after a branching goal (``next`` naming more than one), none once the
mission has finished. A completion report for a current goal makes the goals it leads to
current. A goal's successors are its ``next_uids`` if it has any, else the following goal
in the file (in-sequence goals only), else the first goal when the mission loops.

Goal updates (from other services, over the bus) are merged by UID: a known goal takes
the fields the update carries, an unknown one is added but, as the thesis says, is only
reached when another goal's ``next`` names it. The completed flag of an update is not a
completion report (send those on ``GOAL_REPORT``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from u2sa_hw import lcmtypes as t
from u2sa_hw import messages as m
from u2sa_hw.geo import GeoOrigin, geodetic_to_ned
from u2sa_hw.services.mission.xml import GLOBAL, LOCAL, MissionGoal, MissionSpec

EMPTY_MISSION = MissionSpec(name="", loop=False, goals=[], source="")


class MissionError(ValueError):
    """A command the mission cannot carry out (an unknown UID, an empty mission)."""


@dataclass(frozen=True)
class MissionState:
    """A summary for ``MissionStatus``."""

    name: str
    current_uid: str
    current_index: int
    uids: list[str]
    finished: bool
    looping: bool


class MissionManager:
    """Holds one mission and its progress; every change bumps ``version``."""

    def __init__(self, spec: MissionSpec = EMPTY_MISSION, *, loop: bool | None = None,
                 default_threshold: float = 2.0, logger: logging.Logger | None = None) -> None:
        self.logger = logger or logging.getLogger("u2sa.mission")
        self.loop_override = loop
        self.default_threshold = default_threshold
        self.version = 0
        self.load(spec)

    # -- the mission -------------------------------------------------------------------------
    def load(self, spec: MissionSpec) -> None:
        """Replace the mission with *spec* and start it from its first goal."""
        self.spec = spec
        self.goals: dict[str, MissionGoal] = {g.uid: g for g in spec.goals}
        self.restart()

    @property
    def looping(self) -> bool:
        """Whether the last in-sequence goal leads back to the first (the override wins over the file)."""
        return self.spec.loop if self.loop_override is None else self.loop_override

    def set_loop(self, loop: bool | None) -> None:
        """Override the file's loop attribute (None: use the file's)."""
        self.loop_override = loop
        self.version += 1

    @property
    def order(self) -> list[str]:
        """UIDs of the in-sequence goals, in file order."""
        return [uid for uid, g in self.goals.items() if g.in_sequence]

    def successors(self, uid: str) -> list[str]:
        """The goals that become current when *uid* is done (unknown ``next`` names are dropped)."""
        goal = self.goals[uid]
        if goal.next_uids:
            known = [n for n in goal.next_uids if n in self.goals]
            if len(known) != len(goal.next_uids):
                missing = [n for n in goal.next_uids if n not in self.goals]
                self.logger.warning("goal %s names unknown next goal(s) %s; skipping them", uid, ", ".join(missing))
            return list(dict.fromkeys(known))
        order = self.order
        if not goal.in_sequence or uid not in order:
            return []
        i = order.index(uid)
        if i + 1 < len(order):
            return [order[i + 1]]
        return [order[0]] if self.looping else []

    # -- progress -----------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        """True once no goal is current (the mission ended, or it is empty)."""
        return not self.active

    def _activate(self, uids: list[str]) -> None:
        for uid in uids:
            self.goals[uid].completed = False
        self.active = list(uids)
        self.version += 1
        if not uids and self.goals:
            self.logger.info("mission %s finished", self.spec.name or "(unnamed)")

    def restart(self) -> None:
        """Mark every goal not completed and make the first goal current."""
        for goal in self.goals.values():
            goal.completed = False
        first = self.order[:1] or list(self.goals)[:1]
        self.active: list[str] = []
        self._activate(first)

    def complete(self, uid: str) -> bool:
        """A completion report for *uid*: if current, mark it completed and advance; False if ignored."""
        if uid not in self.active:
            self.logger.info("completion of %s ignored: it is not a current goal (current: %s)", uid,
                             ", ".join(self.active) or "none")
            return False
        self.goals[uid].completed = True
        nxt = self.successors(uid)
        self.logger.info("goal %s completed; next: %s", uid, ", ".join(nxt) or "none (end of mission)")
        self._activate(nxt)
        return True

    def skip(self) -> bool:
        """Leave the first current goal without completing it; False when the mission has finished."""
        if not self.active:
            return False
        uid = self.active[0]
        self._activate(self.successors(uid))
        return True

    def goto(self, uid: str) -> None:
        """Make *uid* the current goal now (even if the planner has not finished the current one)."""
        if uid not in self.goals:
            raise MissionError(f"goto {uid!r}: no such goal (goals: {', '.join(self.goals) or 'none'})")
        self._activate([uid])

    # -- updates -------------------------------------------------------------------------------
    def merge(self, update: MissionGoal, *, fields: set[str] | None = None) -> str:
        """Merge *update* by UID: ``"updated"`` or ``"added"`` (:class:`MissionError` for a new goal without position).

        For a known goal only *fields* (default: all) are taken: ``"position"`` (frame and
        x, y, z), each name in ``update.values``, ``"threshold"`` and ``"next"``.
        """
        fields = fields if fields is not None else {"position", "threshold", "next", *update.values}
        old = self.goals.get(update.uid)
        if old is None:
            if not {"x", "y", "z"} & set(update.values):
                raise MissionError(f"new goal {update.uid!r} has no position: a new goal must be a Waypoint "
                                   "with at least one of x, y, z")
            if update.horizontal_threshold <= 0:
                update.horizontal_threshold = self.default_threshold
            update.in_sequence = False
            self.goals[update.uid] = update
            self.version += 1
            return "added"
        if "position" in fields:
            if update.frame != old.frame:
                for k in ("x", "y", "z"):
                    old.values.pop(k, None)
            old.frame = update.frame
        for name, value in update.values.items():
            if name in fields or (name in ("x", "y", "z") and "position" in fields):
                old.values[name] = value
        if "threshold" in fields and update.horizontal_threshold > 0:
            old.horizontal_threshold = update.horizontal_threshold
        if "next" in fields and update.next_uids:
            old.next_uids = list(update.next_uids)
        self.version += 1
        return "updated"

    # -- readout --------------------------------------------------------------------------------
    def current_goals(self) -> list[MissionGoal]:
        """The goals that are current now."""
        return [self.goals[uid] for uid in self.active]

    def state(self) -> MissionState:
        """A summary: name, first current goal and its index, every UID, finished, looping."""
        uids = list(self.goals)
        current = self.active[0] if self.active else ""
        return MissionState(name=self.spec.name, current_uid=current,
                            current_index=uids.index(current) if current else -1,
                            uids=uids, finished=self.finished, looping=self.looping)


# -- conversion to and from Waypoint messages ----------------------------------------------------
def to_waypoint(goal: MissionGoal, *, origin: GeoOrigin, next_uids: list[str]) -> t.Waypoint:
    """*goal* as a LOCAL Waypoint (a GLOBAL goal is converted to NED about *origin*)."""
    wp = t.Waypoint()
    wp.base.uid = goal.uid
    wp.base.completed = goal.completed
    wp.base.next_uids = list(next_uids)
    wp.base.num_next = len(next_uids)
    wp.reference_frame = LOCAL
    values = dict(goal.values)
    if goal.frame == GLOBAL:
        lat, lon, alt = values.pop("x", None), values.pop("y", None), values.pop("z", None)
        if lat is not None and lon is not None:
            values["x"], values["y"], _ = geodetic_to_ned(lat, lon, origin=origin)
        if alt is not None:
            values["z"] = origin.alt - alt
    wp.set(**values)
    wp.horizontal_threshold = goal.horizontal_threshold
    return wp


def from_message(msg: object) -> tuple[MissionGoal, set[str]] | None:
    """A goal update from a GOALS message and the fields it carries; None if it carries no goal."""
    if isinstance(msg, t.Waypoint):
        frame = GLOBAL if msg.reference_frame.strip().upper() in ("GLOBAL", "GEODETIC") else LOCAL
        values = {name: msg.get(name) for name in msg.present_fields()}
        goal = MissionGoal(uid=msg.base.uid, frame=frame, values=values,
                           horizontal_threshold=msg.horizontal_threshold, next_uids=list(msg.base.next_uids))
        fields = {"next", *values} | ({"position"} if {"x", "y", "z"} & set(values) else set())
        if msg.horizontal_threshold > 0:
            fields.add("threshold")
        return goal, fields
    base = m.as_type(msg, t.GoalInformation)
    if not base.next_uids:
        return None
    goal = MissionGoal(uid=base.uid, frame=LOCAL, values={}, horizontal_threshold=0.0, next_uids=list(base.next_uids))
    return goal, {"next"}
