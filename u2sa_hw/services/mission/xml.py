"""The mission file (thesis 3.2.3.2, 4.5.2.3): XML waypoints in, :class:`MissionSpec` out.

```xml
<mission name="harbour loop" loop="true">      <!-- loop: after the last goal, start again -->
  <waypoint>
    <name>start</name>                          <!-- the goal's UID; <uid> is the same (default: "1", "2", ...) -->
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
by the first when the mission loops, else the mission ends there. ``<x>/<y>/<z>`` of a
Local goal are NED metres. A Global goal is best written with ``<lat>/<lon>/<alt>``,
which cannot be misread; the thesis's own files write it as ``<x>`` = longitude,
``<y>`` = latitude, ``<z>`` = altitude (4.5.2.3, the FlightGear mission; 3.2.3.2's
Global x/y example fits the same reading), and that form is accepted too. Mixing the two
forms in one goal is an error. ``<mission reference="Global">`` makes Global the default
of every goal without its own ``<reference>`` (the thesis's 4.5.2.3 waypoints have none).
A goal needs at least one position value; a Global goal's latitude and longitude come
together and are range-checked. Every error names the file, the line and the element.
:func:`mission_to_xml` writes a :class:`MissionSpec` back as such a file (``u2sa mission
import`` prints a QGroundControl plan that way, :mod:`.qgc_plan`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from u2sa_hw.services.mission.xmltree import XmlFileError, XmlNode, parse_bool, parse_xml, read_xml_file

LOCAL, GLOBAL = "LOCAL", "GLOBAL"
# child tag -> may repeat
WAYPOINT_TAGS = {"name": False, "uid": False, "next": True, "reference": False, "x": False, "y": False, "z": False,
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


def _frame(node: XmlNode, one: dict[str, XmlNode], default_reference: str) -> str:
    reference = one["reference"].word().lower() if "reference" in one else default_reference
    if reference not in ("local", "global"):
        where = one["reference"] if "reference" in one else node
        raise where.error(f"reference must be Local or Global, got {reference!r}")
    return GLOBAL if reference == "global" else LOCAL


def _local_position(one: dict[str, XmlNode]) -> dict[str, float]:
    for tag in ("lat", "lon", "alt"):
        if tag in one:
            raise one[tag].error("not allowed in a Local waypoint: "
                                 "<lat>/<lon>/<alt> need <reference>Global</reference>")
    return {slot: one[slot].number() for slot in ("x", "y", "z") if slot in one}


def _global_position(node: XmlNode, one: dict[str, XmlNode]) -> dict[str, float]:
    """x = latitude, y = longitude, z = altitude (the Waypoint message's GLOBAL convention)."""
    geodetic = [tag for tag in ("lat", "lon", "alt") if tag in one]
    thesis = [tag for tag in ("x", "y", "z") if tag in one]
    if geodetic and thesis:
        raise one[thesis[0]].error(f"a Global waypoint uses either <lat>/<lon>/<alt> or the thesis's <x> = longitude, "
                                   f"<y> = latitude, <z> = altitude, not both (it also has <{geodetic[0]}>)")
    lat_tag, lon_tag, alt_tag = ("y", "x", "z") if thesis else ("lat", "lon", "alt")
    if (lat_tag in one) != (lon_tag in one):
        raise node.error(f"a Global waypoint needs <{lat_tag}> and <{lon_tag}> together"
                         + (" (<x> is the longitude, <y> the latitude)" if thesis else ""))
    values: dict[str, float] = {}
    if lat_tag in one:
        values["x"], values["y"] = one[lat_tag].number(), one[lon_tag].number()
        if not -90.0 <= values["x"] <= 90.0:
            what = "<y> is the latitude in a Global waypoint" if thesis else "latitude"
            raise one[lat_tag].error(f"{what}: must be within -90..90 degrees, got {one[lat_tag].text}")
        if not -180.0 <= values["y"] <= 180.0:
            raise one[lon_tag].error(f"longitude must be within -180..180 degrees, got {one[lon_tag].text}")
    if alt_tag in one:
        values["z"] = one[alt_tag].number()
    return values


def _uid(node: XmlNode, one: dict[str, XmlNode], index: int) -> str:
    """``<name>`` or its alias ``<uid>`` (both: they must agree), else the goal's position in the file."""
    name = one["name"].word() if "name" in one else None
    uid = one["uid"].word() if "uid" in one else None
    if name is not None and uid is not None and name != uid:
        raise one["uid"].error(f"{uid!r} differs from <name> {name!r} on line {one['name'].line}: "
                               "<uid> and <name> are the same thing, keep one")
    return name or uid or str(index)


def _waypoint(node: XmlNode, index: int, default_threshold: float | None, default_reference: str) -> MissionGoal:
    tags = node.only_children(WAYPOINT_TAGS)
    one = {k: v[0] for k, v in tags.items() if not WAYPOINT_TAGS[k]}
    frame = _frame(node, one, default_reference)
    values = _global_position(node, one) if frame == GLOBAL else _local_position(one)
    if not values:
        own = "<lat>/<lon>/<alt> (or <x>/<y>/<z>)" if frame == GLOBAL else "<x>, <y>, <z>"
        raise node.error(f"has no position: give at least one of {own}")
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
    nexts = [n.word() for n in tags.get("next", [])]
    return MissionGoal(uid=_uid(node, one, index), frame=frame, values=values, horizontal_threshold=threshold,
                       next_uids=nexts, line=node.line, source=node.source)


def mission_from_tree(root: XmlNode, *, default_threshold: float | None = None) -> MissionSpec:
    """Build a :class:`MissionSpec` from a parsed tree (checks uids and ``next`` links)."""
    if root.key != "mission":
        raise root.error("the root element must be <mission name=\"...\" loop=\"true|false\"> "
                         "(a single <waypoint> must be wrapped in one)")
    if root.text:
        raise root.error(f"stray text {root.text[:30]!r} between the goals")
    loop = parse_bool(root, "loop", False)
    default_reference = root.attrs.get("reference", "Local").strip().lower()
    if default_reference not in ("local", "global"):
        raise root.error(f"attribute reference=\"{root.attrs['reference']}\" must be Local or Global")
    goals: list[MissionGoal] = []
    seen: dict[str, MissionGoal] = {}
    for index, child in enumerate(root.children, start=1):
        if child.key not in GOAL_TYPES:
            raise child.error(f"unknown goal type; known: {', '.join(f'<{g}>' for g in GOAL_TYPES)}")
        goal = _waypoint(child, index, default_threshold, default_reference)
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


# -- writing ----------------------------------------------------------------------------------------
def _num(value: float, places: int = 3) -> str:
    """*value* rounded to *places* decimals, without trailing zeros (metres: to the millimetre)."""
    text = f"{value:.{places}f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def mission_to_xml(spec: MissionSpec, *, comment: str = "") -> str:
    """*spec* as mission XML that :func:`parse_mission` reads back to the same goals.

    Local positions are written to the millimetre, Global ones as ``<lat>/<lon>/<alt>`` to
    1e-8 degree, attitudes in degrees (``unit="deg"``). A goal's ``horizontal_threshold``
    of 0 or less means "the configured default": no ``<threshold>`` is written. *comment*
    (one or more lines) goes in an XML comment above ``<mission>``.
    """
    from xml.sax.saxutils import escape, quoteattr

    lines = ['<?xml version="1.0" encoding="UTF-8"?>']
    if comment:
        lines.append("<!-- " + comment.replace("--", "- -").replace("\n", "\n     ") + " -->")
    lines.append(f"<mission name={quoteattr(spec.name)} loop=\"{'true' if spec.loop else 'false'}\">")
    for goal in spec.goals:
        parts = [f"<name>{escape(goal.uid)}</name>"]
        parts += [f"<next>{escape(uid)}</next>" for uid in goal.next_uids]
        values = goal.values
        if goal.frame == GLOBAL:
            parts.append("<reference>Global</reference>")
            parts += [f"<{tag}>{_num(values[slot], 8)}</{tag}>" for tag, slot in (("lat", "x"), ("lon", "y"))
                      if slot in values]
            if "z" in values:
                parts.append(f"<alt>{_num(values['z'])}</alt>")
        else:
            parts += [f"<{slot}>{_num(values[slot])}</{slot}>" for slot in ("x", "y", "z") if slot in values]
        parts += [f'<{tag} unit="deg">{_num(math.degrees(values[tag]), 6)}</{tag}>'
                  for tag in ("phi", "theta", "psi") if tag in values]
        parts += [f"<{tag}>{_num(values[tag])}</{tag}>" for tag in ("time", "vertical_threshold") if tag in values]
        if goal.horizontal_threshold > 0:
            parts.append(f"<threshold>{_num(goal.horizontal_threshold)}</threshold>")
        lines.append("  <waypoint>" + "".join(parts) + "</waypoint>")
    lines.append("</mission>")
    return "\n".join(lines) + "\n"
