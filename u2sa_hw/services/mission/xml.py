"""The mission file (thesis 3.2.3.2, 4.5.2.3): XML waypoints in, :class:`MissionSpec` out.

```xml
<mission name="harbour loop" loop="true">      <!-- loop: after the last goal, start again -->
  <waypoint>
    <name>start</name>                          <!-- the goal's UID (default: its position, "1", "2", ...) -->
    <reference>Local</reference>                <!-- Local (default): x north, y east, z down, m about the origin -->
    <x>0</x> <y>0</y>
    <threshold>2.0</threshold>                  <!-- horizontal completion radius, m (default: config) -->
  </waypoint>
  <waypoint>
    <name>buoy</name>
    <next>dock</next> <next>start</next>        <!-- one or more: the planner may choose (branching) -->
    <reference>Global</reference>               <!-- Global: lat, lon in degrees, alt m above sea level -->
    <lat>29.18975</lat> <lon>-81.04815</lon> <alt>10</alt>
    <psi unit="deg">90</psi>                    <!-- attitude phi/theta/psi: rad, or unit="deg" -->
    <time>120</time>                            <!-- s from mission start -->
    <vertical_threshold>1.0</vertical_threshold>
  </waypoint>
</mission>
```

Rules: a goal without ``<next>`` is followed by the next goal in the file; the last one
by the first when the mission loops, else the mission ends there. ``<x>/<y>/<z>`` belong
to Local goals and ``<lat>/<lon>/<alt>`` to Global ones (the thesis's examples put
geodetic values in x/y with the axes swapped between sections, so global positions get
tags that cannot be misread). A goal needs at least one position value; lat and lon come
together. Every error names the file, the line and the element.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from u2sa_hw.services.mission.xmltree import XmlFileError, XmlNode, parse_bool, parse_xml, read_xml_file

LOCAL, GLOBAL = "LOCAL", "GLOBAL"
# child tag -> may repeat
WAYPOINT_TAGS = {"name": False, "next": True, "reference": False, "x": False, "y": False, "z": False,
                 "lat": False, "lon": False, "alt": False, "phi": False, "theta": False, "psi": False,
                 "time": False, "threshold": False, "vertical_threshold": False}
GOAL_TYPES = ("waypoint",)


@dataclass
class MissionGoal:
    """One goal of a mission (a Waypoint).

    ``values`` holds the present optional fields of the Waypoint message: for LOCAL goals
    x, y, z are NED metres; for GLOBAL ones x = latitude, y = longitude (deg), z = altitude
    (m up), the Waypoint message's GLOBAL convention. ``next_uids`` is as written (empty:
    follow the file order when ``in_sequence``).
    """

    uid: str
    frame: str
    values: dict[str, float]
    horizontal_threshold: float
    next_uids: list[str] = field(default_factory=list)
    in_sequence: bool = True
    completed: bool = False
    line: int = 0
    source: str = ""


@dataclass
class MissionSpec:
    """A parsed mission: its name, whether it loops, and its goals in file order."""

    name: str
    loop: bool
    goals: list[MissionGoal]
    source: str = ""


def _waypoint(node: XmlNode, index: int, default_threshold: float | None) -> MissionGoal:
    tags = node.only_children(WAYPOINT_TAGS)
    one = {k: v[0] for k, v in tags.items() if not WAYPOINT_TAGS[k]}
    reference = one["reference"].word().lower() if "reference" in one else "local"
    if reference not in ("local", "global"):
        raise one["reference"].error(f"must be Local or Global, got {one['reference'].text!r}")
    frame = GLOBAL if reference == "global" else LOCAL
    own, other = (("lat", "lon", "alt"), ("x", "y", "z")) if frame == GLOBAL else (("x", "y", "z"), ("lat", "lon", "alt"))
    for tag in other:
        if tag in one:
            hint = ("Global goals use <lat>, <lon>, <alt>" if frame == GLOBAL
                    else "<lat>/<lon>/<alt> need <reference>Global</reference>")
            raise one[tag].error(f"not allowed in a {reference.capitalize()} waypoint: {hint}")
    values: dict[str, float] = {}
    for tag, slot in zip(own, ("x", "y", "z")):
        if tag in one:
            values[slot] = one[tag].number()
    if not values:
        raise node.error(f"has no position: give at least one of {', '.join(f'<{t}>' for t in own)}")
    if frame == GLOBAL and ("lat" in one) != ("lon" in one):
        raise node.error("a Global waypoint needs <lat> and <lon> together")
    if "lat" in one and not -90.0 <= values["x"] <= 90.0:
        raise one["lat"].error(f"latitude must be within -90..90 degrees, got {one['lat'].text}")
    for tag in ("phi", "theta", "psi"):
        if tag in one:
            values[tag] = one[tag].angle()
    if "time" in one:
        values["time"] = one["time"].number()
    if "vertical_threshold" in one:
        values["vertical_threshold"] = one["vertical_threshold"].positive()
    if "threshold" in one:
        threshold = one["threshold"].positive()
    elif default_threshold is not None:
        threshold = default_threshold
    else:
        raise node.error("has no <threshold> (the horizontal completion radius in m) and no default is configured")
    uid = one["name"].word() if "name" in one else str(index)
    nexts = [n.word() for n in tags.get("next", [])]
    return MissionGoal(uid=uid, frame=frame, values=values, horizontal_threshold=threshold, next_uids=nexts,
                       line=node.line, source=node.source)


def mission_from_tree(root: XmlNode, *, default_threshold: float | None = None) -> MissionSpec:
    """Build a :class:`MissionSpec` from a parsed tree (checks uids and ``next`` links)."""
    if root.key != "mission":
        raise root.error("the root element must be <mission name=\"...\" loop=\"true|false\">")
    if root.text:
        raise root.error(f"stray text {root.text[:30]!r} between the goals")
    loop = parse_bool(root, "loop", False)
    goals: list[MissionGoal] = []
    seen: dict[str, MissionGoal] = {}
    for index, child in enumerate(root.children, start=1):
        if child.key not in GOAL_TYPES:
            raise child.error(f"unknown goal type; known: {', '.join(f'<{g}>' for g in GOAL_TYPES)}")
        goal = _waypoint(child, index, default_threshold)
        if goal.uid in seen:
            raise child.error(f"duplicate name {goal.uid!r} (also on line {seen[goal.uid].line})")
        seen[goal.uid] = goal
        goals.append(goal)
    if not goals:
        raise root.error("has no goals: add at least one <waypoint>")
    for goal in goals:
        for uid in goal.next_uids:
            if uid not in seen:
                raise XmlFileError(root.source, goal.line, "waypoint",
                                   f"<next>{uid}</next> names no goal of this mission (goals: {', '.join(seen)})")
    name = root.attrs.get("name", "").strip() or Path(root.source).stem
    return MissionSpec(name=name, loop=loop, goals=goals, source=root.source)


def parse_mission(text: str | bytes, *, source: str, default_threshold: float | None = None) -> MissionSpec:
    """Parse mission XML *text*; *source* names it in errors (a path, or who uploaded it)."""
    return mission_from_tree(parse_xml(text, source=source), default_threshold=default_threshold)


def load_mission(path: Path | str, *, default_threshold: float | None = None) -> MissionSpec:
    """Read and parse the mission file at *path*."""
    return mission_from_tree(read_xml_file(path), default_threshold=default_threshold)
