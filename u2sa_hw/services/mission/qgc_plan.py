"""QGroundControl ``.plan`` files to and from u2sa missions (docs/core-services.md, "QGroundControl plans").

A plan is JSON: ``{"fileType": "Plan", "version": 1, "mission": {"version": 2,
"plannedHomePosition": [lat, lon, alt], "items": [...]}, "geoFence": {...}, "rallyPoints":
{...}}``; each mission item a ``SimpleItem`` with a MAVLink ``command``, a ``frame``, a
``doJumpId`` and seven ``params`` (latitude, longitude, altitude at 4, 5, 6). Import:

- NAV_WAYPOINT (16) -> a Local ``<waypoint>`` ``wpN`` (N: the item number), lat/lon -> x north,
  y east about the profile's ``[vehicle] origin``; acceptance radius -> ``<threshold>``, yaw -> psi.
- NAV_RETURN_TO_LAUNCH (20) -> a goal ``home`` at ``plannedHomePosition``, where the mission ends.
- DO_JUMP (177) repeating forever -> a ``<next>`` link (``loop="true"`` when it closes the whole
  mission); repeating N times -> the jumped-over goals written N more times (``wp2.2``): the
  mission is traced as the autopilot would drive it, and a ``<next>`` cannot count.
- The geoFence is not read here: :mod:`u2sa_hw.geofence_parse` reads it (``plan_areas``) and the
  commands decide what becomes of it (docs/geofence.md); rally points, altitudes and never-reached
  items are left out with a warning.
- Anything else is refused with its index, command name and the fix.

A plan written by :func:`mission_to_plan` carries the goals' names and the mission's name in a
top-level ``"u2sa"`` object, which QGroundControl ignores (it reads only the keys it knows) and
drops when it saves the plan again; import then names goals ``wpN``.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

from u2sa_hw.geo import GeoOrigin, geodetic_to_ned, ned_to_geodetic
from u2sa_hw.services.mission.xml import GLOBAL, LOCAL, MissionGoal, MissionSpec

WAYPOINT, RTL, JUMP = 16, 20, 177
GLOBAL_FRAMES = (0, 3, 5, 6, 10, 11)          # MAV_FRAME_GLOBAL[_RELATIVE_ALT|_TERRAIN_ALT][_INT]
FRAME_RELATIVE_ALT, FRAME_MISSION = 3, 2
MAV_TYPE_GROUND_ROVER, MAV_TYPE_SURFACE_BOAT = 10, 11
MAV_AUTOPILOT_GENERIC = 0
MAX_GOALS = 1000                              # DO_JUMP repeats unrolled beyond this are refused
FAR_M = 10_000.0                              # geo.py's flat-earth projection holds within ~10 km

_SURFACE = "u2sa vehicles drive on the ground or water"
_NO_CAMERA = "remove it: a u2sa mission has no camera or gimbal commands"
_NO_WAIT = "remove it: a u2sa goal is done when it is reached, nothing waits"
_ACTUATORS = "remove it: a mission does not drive actuators (the control service owns them)"
NAMES = {16: "MAV_CMD_NAV_WAYPOINT", 20: "MAV_CMD_NAV_RETURN_TO_LAUNCH", 177: "MAV_CMD_DO_JUMP"}
REFUSED: dict[int, tuple[str, str]] = {   # command -> (name, why and the fix)
    22: ("MAV_CMD_NAV_TAKEOFF", f"{_SURFACE}; delete it (the mission starts at the first waypoint)"),
    84: ("MAV_CMD_NAV_VTOL_TAKEOFF", f"{_SURFACE}; delete it (the mission starts at the first waypoint)"),
    21: ("MAV_CMD_NAV_LAND", f"{_SURFACE}; replace it with a waypoint, or Return To Launch to end at home"),
    85: ("MAV_CMD_NAV_VTOL_LAND", f"{_SURFACE}; replace it with a waypoint, or Return To Launch to end at home"),
    17: ("MAV_CMD_NAV_LOITER_UNLIM", "nothing loiters: replace it with a waypoint"),
    18: ("MAV_CMD_NAV_LOITER_TURNS", "nothing loiters: replace it with a waypoint"),
    19: ("MAV_CMD_NAV_LOITER_TIME", "nothing loiters: replace it with a waypoint"),
    31: ("MAV_CMD_NAV_LOITER_TO_ALT", "nothing loiters: replace it with a waypoint"),
    82: ("MAV_CMD_NAV_SPLINE_WAYPOINT", "make it a plain waypoint (16)"),
    93: ("MAV_CMD_NAV_DELAY", _NO_WAIT),
    112: ("MAV_CMD_CONDITION_DELAY", _NO_WAIT),
    114: ("MAV_CMD_CONDITION_DISTANCE", _NO_WAIT),
    115: ("MAV_CMD_CONDITION_YAW", "remove it: give the waypoint a yaw instead"),
    178: ("MAV_CMD_DO_CHANGE_SPEED", "remove it: the speed is the path planner's cruise_speed_m_s parameter"),
    179: ("MAV_CMD_DO_SET_HOME", "remove it: home is the plan's planned home position"),
    181: ("MAV_CMD_DO_SET_RELAY", _ACTUATORS),
    182: ("MAV_CMD_DO_REPEAT_RELAY", _ACTUATORS),
    183: ("MAV_CMD_DO_SET_SERVO", _ACTUATORS),
    184: ("MAV_CMD_DO_REPEAT_SERVO", _ACTUATORS),
    189: ("MAV_CMD_DO_LAND_START", f"{_SURFACE}; remove it"),
    195: ("MAV_CMD_DO_SET_ROI_LOCATION", _NO_CAMERA),
    197: ("MAV_CMD_DO_SET_ROI_NONE", _NO_CAMERA),
    201: ("MAV_CMD_DO_SET_ROI", _NO_CAMERA),
    205: ("MAV_CMD_DO_MOUNT_CONTROL", _NO_CAMERA),
    206: ("MAV_CMD_DO_SET_CAM_TRIGG_DIST", _NO_CAMERA),
    530: ("MAV_CMD_SET_CAMERA_MODE", _NO_CAMERA),
    1000: ("MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW", _NO_CAMERA),
    2000: ("MAV_CMD_IMAGE_START_CAPTURE", _NO_CAMERA),
    2001: ("MAV_CMD_IMAGE_STOP_CAPTURE", _NO_CAMERA),
    2500: ("MAV_CMD_VIDEO_START_CAPTURE", _NO_CAMERA),
    2501: ("MAV_CMD_VIDEO_STOP_CAPTURE", _NO_CAMERA),
}


class PlanError(ValueError):
    """The plan cannot become a mission (or the mission a plan); one line naming the file and the item."""


def looks_like_plan(path: Path, data: bytes) -> bool:
    """A ``.plan`` file, or JSON whatever its name (XML never starts with ``{``)."""
    return path.suffix.lower() == ".plan" or data.lstrip()[:1] == b"{"


def load_plan_text(data: bytes, *, source: str) -> dict[str, Any]:
    """The plan's JSON object; PlanError for text that is not UTF-8 JSON holding an object."""
    try:
        # NaN/Infinity (not JSON, but Python and Qt write them) become nan, refused where a number must be finite
        plan = json.loads(data.decode("utf-8"), parse_constant=lambda _c: math.nan)
    except UnicodeDecodeError as exc:
        raise PlanError(f"{source}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise PlanError(f"{source}: not JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
    if not isinstance(plan, dict):
        raise PlanError(f"{source}: a plan is a JSON object {{\"fileType\": \"Plan\", ...}}, not {_kind(plan)}")
    return plan


def _kind(value: Any) -> str:
    names = {bool: "a boolean", int: "a number", float: "a number", str: "a string", list: "an array",
             dict: "an object", type(None): "null"}
    return names.get(type(value), type(value).__name__)


def _get(obj: dict[str, Any], key: str, types: tuple[type, ...], where: str, *, required: bool = True) -> Any:
    """``obj[key]`` checked to be one of *types* (a JSON number is never a boolean)."""
    if key not in obj:
        if required:
            raise PlanError(f"{where}: missing \"{key}\"")
        return None
    value = obj[key]
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
        want = " or ".join(dict.fromkeys(_kind(t()) if t is not type(None) else "null" for t in types))
        raise PlanError(f"{where}: \"{key}\" must be {want}, got {_kind(value)} {json.dumps(value)[:40]}")
    return value


def _finite(value: Any, what: str, where: str, *, low: float = -math.inf, high: float = math.inf) -> float:
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        shown = "null" if value is None else json.dumps(value)[:40]
        raise PlanError(f"{where}: {what} must be a finite number, got {shown}")
    if not low <= value <= high:
        raise PlanError(f"{where}: {what} must be within {low:g}..{high:g}, got {value}")
    return float(value)


def _item(raw: Any, index: int, source: str) -> dict[str, Any]:
    """One mission item checked: {"command", "where", and what the command needs}."""
    where = f"{source}: mission.items[{index}] (item {index + 1})"
    if not isinstance(raw, dict):
        raise PlanError(f"{where}: must be an object, got {_kind(raw)}")
    kind = _get(raw, "type", (str,), where)
    if kind == "ComplexItem":
        what = raw.get("complexItemType", "?")
        raise PlanError(f"{where}: ComplexItem {what!r} cannot be flown: u2sa takes waypoints only; replace the "
                        f"{what} with waypoints in QGroundControl")
    if kind != "SimpleItem":
        raise PlanError(f"{where}: unknown item type {kind!r}; expected SimpleItem")
    command = _get(raw, "command", (int,), where)
    name = NAMES.get(command) or REFUSED.get(command, (f"MAV_CMD {command}",))[0]
    label = f"mission.items[{index}] (item {index + 1}), {name} ({command})"
    where = f"{source}: {label}"
    if command not in NAMES:
        fix = REFUSED.get(command, ("", "remove it, or replace it with a waypoint (16)"))[1]
        raise PlanError(f"{where}: cannot be flown by u2sa: {fix}")
    params = _get(raw, "params", (list,), where)
    if len(params) != 7:
        raise PlanError(f"{where}: \"params\" must hold 7 values, got {len(params)}")
    if _get(raw, "autoContinue", (bool,), where) is not True:
        raise PlanError(f"{where}: autoContinue is false (wait for the operator): u2sa goals never wait; set it true")
    frame = _get(raw, "frame", (int,), where)
    jump_id = _get(raw, "doJumpId", (int,), where, required=False)
    item: dict[str, Any] = {"command": command, "where": where, "label": label, "jump_id": jump_id}
    if command == WAYPOINT:
        if frame not in GLOBAL_FRAMES:
            raise PlanError(f"{where}: frame {frame} is not a global (latitude/longitude) frame; use frame 3")
        item["lat"] = _finite(params[4], "the latitude (params[4])", where, low=-90, high=90)
        item["lon"] = _finite(params[5], "the longitude (params[5])", where, low=-180, high=180)
        hold = 0.0 if params[0] is None else _finite(params[0], "the hold time (params[0])", where)
        if hold != 0:
            raise PlanError(f"{where}: hold {hold:g} s: u2sa goals do not wait at a waypoint; set Hold to 0")
        radius = 0.0 if params[1] is None else _finite(params[1], "the acceptance radius (params[1])", where, low=0)
        item["threshold"] = radius
        yaw = params[3]
        if yaw is not None and not (isinstance(yaw, float) and math.isnan(yaw)):
            item["yaw"] = _finite(yaw, "the yaw (params[3])", where)
        item["alt"] = 0.0 if params[6] is None else _finite(params[6], "the altitude (params[6])", where)
        item["pass"] = 0.0 if params[2] is None else _finite(params[2], "the pass radius (params[2])", where)
    elif command == JUMP:
        target = _finite(params[0], "the target doJumpId (params[0])", where)
        repeat = _finite(params[1], "the repeat count (params[1])", where, low=-1)
        if target != int(target) or repeat != int(repeat):
            raise PlanError(f"{where}: the target and the repeat count must be whole numbers")
        item["target"], item["repeat"] = int(target), int(repeat)
    return item


def plan_to_mission(plan: dict[str, Any], *, source: str, origin: GeoOrigin) -> tuple[MissionSpec, list[str]]:
    """The mission a plan's items fly, with Local goals about *origin*, and warnings (one line each)."""
    if plan.get("fileType") != "Plan":
        got = f"fileType {json.dumps(plan['fileType'])[:40]}" if "fileType" in plan else "no fileType"
        raise PlanError(f"{source}: {got}, not \"Plan\": not a QGroundControl plan (save it from Plan view, File, "
                        "Save As)")
    if _get(plan, "version", (int,), source, required=False) not in (None, 1):
        raise PlanError(f"{source}: plan version {plan['version']}: only version 1 is read")
    warnings: list[str] = []
    rally = _get(plan, "rallyPoints", (dict,), source, required=False) or {}
    if _get(rally, "points", (list,), f"{source}: rallyPoints", required=False):
        warnings.append(f"{source}: rally points left out: return-to-launch goes to the planned home position")
    mission = _get(plan, "mission", (dict,), source)
    where = f"{source}: mission"
    if _get(mission, "version", (int,), where) != 2:
        raise PlanError(f"{where}: version {mission['version']}: only mission version 2 is read")
    home = _get(mission, "plannedHomePosition", (list,), where)
    if len(home) != 3:
        raise PlanError(f"{where}: plannedHomePosition must be [latitude, longitude, altitude]")
    home_lat = _finite(home[0], "the planned home's latitude", where, low=-90, high=90)
    home_lon = _finite(home[1], "the planned home's longitude", where, low=-180, high=180)
    _finite(home[2], "the planned home's altitude", where)
    raws = _get(mission, "items", (list,), where)
    if not raws:
        raise PlanError(f"{where}: \"items\" is empty: the plan has no mission")
    items = [_item(raw, i, source) for i, raw in enumerate(raws)]
    by_id: dict[int, int] = {}
    for i, item in enumerate(items):
        if item["jump_id"] is not None:
            if item["jump_id"] in by_id:
                raise PlanError(f"{item['where']}: doJumpId {item['jump_id']} is also that of item "
                                f"{by_id[item['jump_id']] + 1}: each item needs its own")
            by_id[item["jump_id"]] = i
    for item in items:
        if item["command"] == JUMP and item["target"] not in by_id:
            raise PlanError(f"{item['where']}: jumps to doJumpId {item['target']}, which no item has")
    if high := [it for it in items if it.get("alt")]:
        warnings.append(f"{source}: altitudes left out ({high[0]['label']}: {high[0]['alt']:g} m, "
                        f"{len(high)} item(s) in all): {_SURFACE}")
    if passing := [it for it in items if it.get("pass")]:
        warnings.append(f"{source}: pass radius left out ({len(passing)} item(s)): u2sa goals are reached, not passed")
    names = _names(plan, items, source, warnings)
    goals: list[MissionGoal] = []
    used: set[str] = set()
    seen: dict[tuple[int, tuple[int, ...]], int] = {}
    counters = {i: item["repeat"] for i, item in enumerate(items) if item["command"] == JUMP}
    pc, loop, reached = 0, False, set()
    while pc < len(items):
        state = (pc, tuple(counters.values()))
        if state in seen:   # back where the mission was: close the cycle with a next link
            first = seen[state]
            if first == len(goals):
                raise PlanError(f"{items[pc]['where']}: the jumps loop without reaching a waypoint")
            if first == 0:
                loop = True
            else:
                goals[-1].next_uids = [goals[first].uid]
            break
        seen[state] = len(goals)
        item = items[pc]
        reached.add(pc)
        if item["command"] == JUMP:
            left = counters[pc]
            if left == 0:
                pc += 1
                continue
            counters[pc] = left - 1 if left > 0 else left   # -1: forever
            pc = by_id[item["target"]]
            continue
        lat, lon = (item["lat"], item["lon"]) if item["command"] == WAYPOINT else (home_lat, home_lon)
        north, east, _ = geodetic_to_ned(lat, lon, origin=origin)
        if math.hypot(north, east) > FAR_M:
            what = "the planned home position" if item["command"] == RTL else f"({lat:.6f}, {lon:.6f})"
            raise PlanError(f"{item['where']}: {what} is {math.hypot(north, east) / 1000:.0f} km from the vehicle's "
                            f"origin ({origin.lat:.6f}, {origin.lon:.6f}): a plan for another place, or the profile's "
                            "[vehicle] origin is wrong")
        values = {"x": north, "y": east}
        if "yaw" in item:
            values["psi"] = math.radians(item["yaw"])
        goals.append(MissionGoal(uid=_unique(names.get(pc) or ("home" if item["command"] == RTL else f"wp{pc + 1}"),
                                             used),
                                 frame=LOCAL, values=values, horizontal_threshold=item.get("threshold", 0.0),
                                 source=source))
        if len(goals) > MAX_GOALS:
            raise PlanError(f"{item['where']}: the DO_JUMP repeats make more than {MAX_GOALS} goals")
        if item["command"] == RTL:
            break
        pc += 1
    if not goals:
        raise PlanError(f"{where}: no waypoint is ever reached")
    if never := [str(i + 1) for i, item in enumerate(items) if i not in reached and item["command"] != JUMP]:
        warnings.append(f"{source}: item(s) {', '.join(never)} never reached (after a jump that repeats forever or "
                        "a return-to-launch): left out")
    meta = plan.get("u2sa") if isinstance(plan.get("u2sa"), dict) else {}
    name = meta.get("mission")
    name = name.strip() if isinstance(name, str) and name.strip() else Path(source).stem
    return MissionSpec(name=name, loop=loop, goals=goals, source=source), warnings


def _unique(base: str, used: set[str]) -> str:
    uid, n = base, 1
    while uid in used:
        n += 1
        uid = f"{base}.{n}"
    used.add(uid)
    return uid


def _names(plan: dict[str, Any], items: list[dict[str, Any]], source: str, warnings: list[str]) -> dict[int, str]:
    """Item index -> goal name from the ``"u2sa"`` object an export wrote ({"names": {"3": "dock"}})."""
    meta = plan.get("u2sa")
    raw = meta.get("names") if isinstance(meta, dict) else None
    if not isinstance(raw, dict):
        return {}
    names: dict[int, str] = {}
    for key, name in raw.items():
        index = int(key) - 1 if key.isdigit() else -1
        if not (0 <= index < len(items)) or items[index]["command"] == JUMP or not isinstance(name, str) \
                or not name.strip() or name != name.strip():
            warnings.append(f"{source}: u2sa.names[{key!r}] does not name a waypoint; default names used")
            return {}
        names[index] = name
    return names


def _successor(spec: MissionSpec, i: int) -> str | None:
    """The goal after goal *i* as the mission manager runs it; PlanError for a branching goal."""
    goal = spec.goals[i]
    if len(goal.next_uids) > 1:
        raise PlanError(f"{spec.source}:{goal.line}: goal {goal.uid!r} branches ({', '.join(goal.next_uids)}): a "
                        "QGroundControl plan has no branching; keep one <next>")
    if goal.next_uids:
        return goal.next_uids[0]
    if i + 1 < len(spec.goals):
        return spec.goals[i + 1].uid
    return spec.goals[0].uid if spec.loop else None


def _geodetic(goal: MissionGoal, origin: GeoOrigin, source: str) -> tuple[float, float, float | None]:
    """(lat, lon, altitude m up or None) of a goal."""
    v = goal.values
    if "x" not in v or "y" not in v:
        raise PlanError(f"{source}:{goal.line}: goal {goal.uid!r} has no horizontal position: a plan item needs "
                        f"{'<lat> and <lon>' if goal.frame == GLOBAL else '<x> and <y>'}")
    if goal.frame == GLOBAL:
        return v["x"], v["y"], v.get("z")
    lat, lon, alt = ned_to_geodetic(v["x"], v["y"], v.get("z", 0.0), origin=origin)
    return lat, lon, alt if "z" in v else None


def mission_to_plan(spec: MissionSpec, *, origin: GeoOrigin, vehicle_type: int = MAV_TYPE_GROUND_ROVER,
                    cruise_speed: float = 1.0) -> tuple[dict[str, Any], list[str]]:
    """*spec* as a QGroundControl plan (positions through *origin*), and warnings for what a plan cannot hold."""
    warnings: list[str] = []
    home = (origin.lat, origin.lon, origin.alt)
    successors = [_successor(spec, i) for i in range(len(spec.goals))]
    last = spec.goals[-1]
    rtl = re.fullmatch(r"home(\.\d+)?", last.uid) is not None and successors[-1] is None \
        and set(last.values) <= {"x", "y"}
    if rtl:
        lat, lon, _ = _geodetic(last, origin, spec.source)
        home = (lat, lon, origin.alt)
    # first pass: item numbers (= doJumpId) of the goals and the jumps after them
    ids: dict[str, int] = {}
    n = 0
    for i, goal in enumerate(spec.goals):
        n += 1
        ids[goal.uid] = n
        following = spec.goals[i + 1].uid if i + 1 < len(spec.goals) else None
        n += successors[i] is not None and successors[i] != following
    items: list[dict[str, Any]] = []
    names: dict[str, str] = {}
    for i, goal in enumerate(spec.goals):
        number = ids[goal.uid]
        names[str(number)] = goal.uid
        if rtl and goal is last:
            items.append(_simple(number, RTL, FRAME_MISSION, [0, 0, 0, 0, 0, 0, 0]))
            break
        lat, lon, alt = _geodetic(goal, origin, spec.source)
        dropped = [k for k in ("phi", "theta", "time", "vertical_threshold") if k in goal.values]
        if dropped:
            warnings.append(f"{spec.source}:{goal.line}: goal {goal.uid!r}: {', '.join(dropped)} left out: a plan "
                            "waypoint has no such field")
        yaw = math.degrees(goal.values["psi"]) if "psi" in goal.values else None
        params = [0, max(goal.horizontal_threshold, 0.0), 0, yaw, lat, lon, 0 if alt is None else alt - home[2]]
        items.append(_simple(number, WAYPOINT, FRAME_RELATIVE_ALT, params))
        following = spec.goals[i + 1].uid if i + 1 < len(spec.goals) else None
        if successors[i] is not None and successors[i] != following:
            items.append(_simple(number + 1, JUMP, FRAME_MISSION, [ids[successors[i]], -1, 0, 0, 0, 0, 0]))
    plan = {
        "fileType": "Plan", "version": 1, "groundStation": "u2sa-hw",
        "mission": {"version": 2, "firmwareType": MAV_AUTOPILOT_GENERIC, "vehicleType": vehicle_type,
                    "cruiseSpeed": cruise_speed, "hoverSpeed": cruise_speed, "plannedHomePosition": list(home),
                    "items": items},
        "geoFence": {"version": 2, "circles": [], "polygons": []},
        "rallyPoints": {"version": 2, "points": []},
        "u2sa": {"mission": spec.name, "names": names},
    }
    return plan, warnings


def _simple(number: int, command: int, frame: int, params: list[Any]) -> dict[str, Any]:
    return {"type": "SimpleItem", "autoContinue": True, "command": command, "doJumpId": number, "frame": frame,
            "params": params}


def plan_json(plan: dict[str, Any]) -> str:
    """The plan as QGroundControl writes it: indented JSON, sorted keys, null for an unset value."""
    return json.dumps(plan, indent=4, sort_keys=True, allow_nan=False) + "\n"
