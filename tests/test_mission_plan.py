"""QGroundControl .plan files: import (u2sa mission import/upload) and export, against the plan format's documentation.

The plans here are composed from the QGroundControl developer guide's "Plan File Format" page
(fileType "Plan", version 1; mission version 2 with plannedHomePosition and SimpleItems of
command/frame/doJumpId/autoContinue/params[7]; geoFence version 2 with circles and polygons;
rallyPoints version 2) and MAVLink's command numbers, not copied from any project.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import pytest
from conftest import ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import geo
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.cli import CliError
from u2sa_hw.services.mission.xml import LOCAL, MissionSpec, load_mission, parse_mission
from u2sa_hw.profile.vehicle import Origin

ORIGIN = Origin(lat=29.1895, lon=-81.0483, alt=10.0)
HOME = geo.ned_to_geodetic(-4.0, 3.0, origin=ORIGIN)[:2]   # the planned home: 4 m south, 3 m east of the origin


def at(north: float, east: float) -> tuple[float, float]:
    """Latitude and longitude of a point *north*, *east* metres from the origin."""
    lat, lon, _ = geo.ned_to_geodetic(north, east, origin=ORIGIN)
    return lat, lon


def waypoint(jump_id: int, north: float, east: float, *, radius: float = 0.0, yaw: float | None = None,
             alt: float = 0.0) -> dict[str, Any]:
    lat, lon = at(north, east)
    return {"type": "SimpleItem", "autoContinue": True, "command": 16, "doJumpId": jump_id, "frame": 3,
            "params": [0, radius, 0, yaw, lat, lon, alt]}


def simple(jump_id: int, command: int, *params: float | None, frame: int = 2) -> dict[str, Any]:
    return {"type": "SimpleItem", "autoContinue": True, "command": command, "doJumpId": jump_id, "frame": frame,
            "params": [*params, *[0] * (7 - len(params))]}


def plan(items: list[dict[str, Any]], **extra: Any) -> dict[str, Any]:
    """A plan as the format's documentation lays it out (here for a ground rover, ArduPilot firmware)."""
    return {"fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
            "mission": {"version": 2, "firmwareType": 3, "vehicleType": 10, "cruiseSpeed": 2, "hoverSpeed": 1,
                        "plannedHomePosition": [HOME[0], HOME[1], 12.0], "items": items},
            "geoFence": {"version": 2, "circles": [], "polygons": []},
            "rallyPoints": {"version": 2, "points": []}, **extra}


# waypoints 1-3, then "jump back to 2 once", a fifth waypoint, return to launch
COMPOSED = plan([waypoint(1, 10, 0, radius=3.0), waypoint(2, 10, 20), waypoint(3, 0, 20, yaw=45.0),
                 simple(4, 177, 2, 1), waypoint(5, -5, 5), simple(6, 20)])


@pytest.fixture
def vehicle(tmp_path: Path) -> Path:
    path = tmp_path / "vehicle.toml"
    path.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n")
    return path


def write(tmp_path: Path, data: Any, name: str = "field.plan") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(data, indent=2) if not isinstance(data, str) else data)
    return path


def mission_cli(*argv: str) -> int:
    """``u2sa mission ARGV`` in this process (its parser built from the command's own module)."""
    import argparse

    from u2sa_hw.cli import mission_cmd

    parser = argparse.ArgumentParser(prog="u2sa")
    mission_cmd.register(parser.add_subparsers())
    args = parser.parse_args(["mission", *argv])
    return args.func(args)


def imported(path: Path, vehicle: Path, capsys: pytest.CaptureFixture[str], *flags: str) -> MissionSpec:
    """``u2sa mission import PATH``'s printed mission, parsed by the mission manager's parser."""
    assert mission_cli("import", str(path), "--vehicle", str(vehicle), *flags) == 0
    return parse_mission(capsys.readouterr().out, source="printed", default_threshold=0.0)


def positions(spec: MissionSpec) -> list[tuple[str, float, float]]:
    return [(g.uid, round(g.values["x"], 3), round(g.values["y"], 3)) for g in spec.goals]


# -- import --------------------------------------------------------------------------------------------
def test_a_composed_plan_imports_as_the_mission_it_flies(tmp_path: Path, vehicle: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    spec = imported(write(tmp_path, COMPOSED), vehicle, capsys)
    # the jump back to item 2, once, drives 2 and 3 a second time; RTL ends the mission at the planned home
    assert positions(spec) == [("wp1", 10, 0), ("wp2", 10, 20), ("wp3", 0, 20), ("wp2.2", 10, 20),
                               ("wp3.2", 0, 20), ("wp5", -5, 5), ("home", -4, 3)]
    assert not spec.loop and all(g.next_uids == [] and g.frame == LOCAL for g in spec.goals)
    assert spec.name == "field" and [g.horizontal_threshold for g in spec.goals][:2] == [3.0, 0.0]
    assert spec.goals[2].values["psi"] == pytest.approx(math.radians(45.0)) and "z" not in spec.goals[0].values


def test_a_jump_forever_is_a_next_link_or_the_loop(tmp_path: Path, vehicle: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    # back to item 2 forever: 3 -> 2; the RTL after the jump is never reached, and said so
    path = write(tmp_path, plan([waypoint(1, 0, 0), waypoint(2, 10, 0), waypoint(3, 10, 10), simple(4, 177, 2, -1),
                                 simple(5, 20)]))
    assert mission_cli("import", str(path), "--vehicle", str(vehicle)) == 0
    printed = capsys.readouterr()
    spec = parse_mission(printed.out, source="printed", default_threshold=0.0)
    assert [(g.uid, g.next_uids) for g in spec.goals] == [("wp1", []), ("wp2", []), ("wp3", ["wp2"])]
    assert not spec.loop
    assert printed.err == f"u2sa: warning: {path}: item(s) 5 never reached (after a jump that repeats forever or " \
                          "a return-to-launch): left out\n"
    # back to the first forever: the mission loops
    spec = imported(write(tmp_path, plan([waypoint(1, 0, 0), waypoint(2, 10, 0), simple(3, 177, 1, -1)])),
                    vehicle, capsys)
    assert spec.loop and [(g.uid, g.next_uids) for g in spec.goals] == [("wp1", []), ("wp2", [])]


@pytest.mark.parametrize(("item", "name", "fix"), [
    (simple(2, 22, 0, 0, 0, None, *at(0, 0), 10, frame=3), "MAV_CMD_NAV_TAKEOFF (22)", "delete it"),
    (simple(2, 21, 0, 0, 0, None, *at(0, 0), 0, frame=3), "MAV_CMD_NAV_LAND (21)", "replace it with a waypoint"),
    (simple(2, 17, 0, 0, 5, None, *at(0, 0), 0, frame=3), "MAV_CMD_NAV_LOITER_UNLIM (17)", "nothing loiters"),
    (simple(2, 19, 30, 0, 5, None, *at(0, 0), 0, frame=3), "MAV_CMD_NAV_LOITER_TIME (19)", "nothing loiters"),
    (simple(2, 183, 1, 1500), "MAV_CMD_DO_SET_SERVO (183)", "does not drive actuators"),
    (simple(2, 178, 1, 3, -1), "MAV_CMD_DO_CHANGE_SPEED (178)", "cruise_speed_m_s"),
    (simple(2, 206, 5), "MAV_CMD_DO_SET_CAM_TRIGG_DIST (206)", "no camera"),
    (simple(2, 31337), "MAV_CMD 31337", "replace it with a waypoint (16)"),
    ({"type": "ComplexItem", "complexItemType": "survey", "version": 5}, "ComplexItem 'survey'",
     "replace the survey with waypoints"),
    ({**waypoint(2, 5, 5), "params": [10, 0, 0, None, *at(5, 5), 0]}, "MAV_CMD_NAV_WAYPOINT (16): hold 10 s",
     "set Hold to 0"),
    ({**waypoint(2, 5, 5), "frame": 1}, "MAV_CMD_NAV_WAYPOINT (16): frame 1", "use frame 3"),
    ({**waypoint(2, 5, 5), "autoContinue": False}, "autoContinue is false", "set it true"),
])
def test_each_item_u2sa_cannot_fly_is_refused_with_its_index_name_and_fix(tmp_path: Path, vehicle: Path,
                                                                         item: dict[str, Any], name: str,
                                                                         fix: str) -> None:
    path = write(tmp_path, plan([waypoint(1, 0, 0), item, waypoint(3, 10, 10)]))
    with pytest.raises(CliError) as err:
        mission_cli("import", str(path), "--vehicle", str(vehicle))
    text = str(err.value)
    assert text.startswith(f"mission import: {path}: mission.items[1] (item 2)") and name in text and fix in text, text
    assert "\n" not in text


def _edit(change: Any) -> Any:
    data = copy.deepcopy(plan([waypoint(1, 0, 0), waypoint(2, 10, 0), simple(3, 177, 1, -1)]))
    change(data)
    return data


@pytest.mark.parametrize(("data", "words"), [
    ("{\"fileType\": \"Plan\",", "not JSON: Expecting property name enclosed in double quotes (line 1, column 21)"),
    ("[1, 2]", "a plan is a JSON object"),
    (_edit(lambda d: d.update(fileType="Mission")), 'fileType "Mission", not "Plan"'),
    (_edit(lambda d: d.pop("mission")), 'missing "mission"'),
    (_edit(lambda d: d["mission"].pop("plannedHomePosition")), 'mission: missing "plannedHomePosition"'),
    (_edit(lambda d: d["mission"].update(items=[])), '"items" is empty'),
    (_edit(lambda d: d["mission"].update(items={})), '"items" must be an array, got an object'),
    (_edit(lambda d: d["mission"]["items"][1].pop("params")), 'items[1] (item 2), MAV_CMD_NAV_WAYPOINT (16): missing '
                                                               '"params"'),
    (_edit(lambda d: d["mission"]["items"][1].update(command="16")), 'items[1] (item 2): "command" must be a number, '
                                                                    'got a string'),
    (_edit(lambda d: d["mission"]["items"][1]["params"].pop()), '"params" must hold 7 values, got 6'),
    (_edit(lambda d: d["mission"]["items"][1]["params"].__setitem__(4, "29.1")),
     "the latitude (params[4]) must be a finite number, got \"29.1\""),
    (_edit(lambda d: d["mission"]["items"][1]["params"].__setitem__(5, None)),
     "items[1] (item 2), MAV_CMD_NAV_WAYPOINT (16): the longitude (params[5]) must be a finite number, got null"),
    (_edit(lambda d: d["mission"]["items"][0]["params"].__setitem__(4, 91)), "latitude (params[4]) must be within"),
    (_edit(lambda d: d["mission"]["items"][2]["params"].__setitem__(0, 7)), "jumps to doJumpId 7, which no item"),
    (_edit(lambda d: d["mission"]["items"][1].update(doJumpId=1)), "doJumpId 1 is also that of item 1"),
    (_edit(lambda d: d["mission"]["items"][0]["params"].__setitem__(4, 30.0)), "km from the vehicle's origin"),
])
def test_bad_plans_get_one_line_naming_the_file_and_item(tmp_path: Path, vehicle: Path, data: Any,
                                                         words: str) -> None:
    path = write(tmp_path, data)
    with pytest.raises(CliError) as err:
        mission_cli("import", str(path), "--vehicle", str(vehicle))
    text = str(err.value)
    assert text.startswith(f"mission import: {path}: ") and words in text and "\n" not in text, text


def test_nan_coordinates_and_other_input_errors(tmp_path: Path, vehicle: Path) -> None:
    text = json.dumps(plan([waypoint(1, 0, 0), waypoint(2, 10, 0)])).replace(str(at(10, 0)[0]), "NaN")
    with pytest.raises(CliError, match=r"items\[1\] \(item 2\), MAV_CMD_NAV_WAYPOINT \(16\): the latitude "
                                       r"\(params\[4\]\) must be a finite number, got NaN"):
        mission_cli("import", str(write(tmp_path, text)), "--vehicle", str(vehicle))
    binary = tmp_path / "binary.plan"
    binary.write_bytes(b"{\xff\xfe}")
    with pytest.raises(CliError, match=r"binary.plan: not UTF-8 text"):
        mission_cli("import", str(binary), "--vehicle", str(vehicle))
    with pytest.raises(CliError, match=r"missing.plan: cannot read"):
        mission_cli("import", str(tmp_path / "missing.plan"), "--vehicle", str(vehicle))
    bare = tmp_path / "bare.toml"
    bare.write_text("[vehicle]\nname = \"no origin\"\n")
    with pytest.raises(CliError, match=r"bare.toml sets none: add origin = \{ lat"):
        mission_cli("import", str(write(tmp_path, COMPOSED)), "--vehicle", str(bare))
    with pytest.raises(CliError, match=r"--from is not an option of import") as err:
        mission_cli("import", str(write(tmp_path, COMPOSED)), "--from", "x.xml")
    assert err.value.code == 2


# -- export ---------------------------------------------------------------------------------------------------
def assert_a_plan_qgroundcontrol_opens(data: dict[str, Any]) -> None:
    """The keys and types the Plan File Format page gives, and what its loader requires."""
    assert (data["fileType"], data["version"], type(data["groundStation"])) == ("Plan", 1, str)
    mission = data["mission"]
    assert mission["version"] == 2 and all(isinstance(mission[k], (int, float)) for k in
                                           ("firmwareType", "vehicleType", "cruiseSpeed", "hoverSpeed"))
    assert len(mission["plannedHomePosition"]) == 3 and all(math.isfinite(v) for v in mission["plannedHomePosition"])
    ids = [item["doJumpId"] for item in mission["items"]]
    assert ids == list(range(1, len(ids) + 1))
    for item in mission["items"]:
        assert set(item) == {"type", "autoContinue", "command", "doJumpId", "frame", "params"}
        assert item["type"] == "SimpleItem" and item["autoContinue"] is True and len(item["params"]) == 7
        if item["command"] == 16:
            assert item["frame"] == 3 and all(math.isfinite(v) for v in item["params"][4:7])
        if item["command"] == 177:
            assert item["params"][0] in ids
    assert data["geoFence"] == {"version": 2, "circles": [], "polygons": []}
    assert data["rallyPoints"] == {"version": 2, "points": []}


HARBOUR = """\
<mission name="harbour loop">
  <waypoint><name>east_mark</name><x>0</x><y>20</y><threshold>2.5</threshold></waypoint>
  <waypoint><name>north_mark</name><reference>Global</reference><lat>29.1896</lat><lon>-81.0482</lon></waypoint>
  <waypoint><name>west_mark</name><x>15</x><y>0</y><psi unit="deg">-90</psi></waypoint>
  <waypoint><name>dock</name><next>north_mark</next><x>0</x><y>0</y></waypoint>
</mission>
"""


def same_mission(a: MissionSpec, b: MissionSpec) -> None:
    """Equal as the mission manager runs them: name, loop, goals, local positions, thresholds, links, headings."""
    def local(goal: Any) -> tuple[float, float]:
        if goal.frame == LOCAL:
            return goal.values["x"], goal.values["y"]
        return geo.geodetic_to_ned(goal.values["x"], goal.values["y"], origin=ORIGIN)[:2]

    assert (a.name, a.loop, [g.uid for g in a.goals]) == (b.name, b.loop, [g.uid for g in b.goals])
    for ga, gb in zip(a.goals, b.goals):
        assert local(ga) == pytest.approx(local(gb), abs=2e-3), ga.uid
        assert (ga.horizontal_threshold, ga.next_uids) == (gb.horizontal_threshold, gb.next_uids), ga.uid
        assert ga.values.get("psi", 9) == pytest.approx(gb.values.get("psi", 9)), ga.uid


def test_export_then_import_gives_the_same_mission(tmp_path: Path, vehicle: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    source = tmp_path / "harbour.xml"
    source.write_text(HARBOUR)
    out = tmp_path / "harbour.plan"
    assert mission_cli("export", str(out), "--from", str(source), "--vehicle", str(vehicle)) == 0
    assert capsys.readouterr().out == f"{out}: mission 'harbour loop' from {source}, 4 goals in 5 plan items\n"
    data = json.loads(out.read_text())
    assert_a_plan_qgroundcontrol_opens(data)
    commands = [(i["command"], i["params"][:2] if i["command"] == 177 else None) for i in data["mission"]["items"]]
    assert commands == [(16, None), (16, None), (16, None), (16, None), (177, [2, -1])]   # dock -> north_mark
    assert data["mission"]["items"][0]["params"][1] == 2.5 and data["mission"]["items"][2]["params"][3] == -90
    assert data["mission"]["plannedHomePosition"] == [ORIGIN.lat, ORIGIN.lon, ORIGIN.alt]
    same_mission(imported(out, vehicle, capsys), load_mission(source, default_threshold=0.0))
    # a looping mission: one jump back to the first item, read back as loop="true"
    source.write_text(HARBOUR.replace("<next>north_mark</next>", "").replace('">', '" loop="true">', 1))
    assert mission_cli("export", str(out), "--from", str(source), "--vehicle", str(vehicle), "--force") == 0
    assert json.loads(out.read_text())["mission"]["items"][-1]["params"][:2] == [1, -1]
    capsys.readouterr()
    looping = imported(out, vehicle, capsys)
    assert looping.loop and not any(g.next_uids for g in looping.goals)
    same_mission(looping, load_mission(source, default_threshold=0.0))

    # and a plan made in QGroundControl comes back from an export unchanged
    first = imported(write(tmp_path, COMPOSED), vehicle, capsys)
    (tmp_path / "composed.xml").write_text(mission_to_text(first))
    again = tmp_path / "again.plan"
    assert mission_cli("export", str(again), "--from", str(tmp_path / "composed.xml"), "--vehicle", str(vehicle)) == 0
    exported = json.loads(again.read_text())
    assert_a_plan_qgroundcontrol_opens(exported)
    assert exported["mission"]["items"][-1]["command"] == 20   # the goal "home" at the end is return-to-launch
    assert exported["mission"]["plannedHomePosition"][:2] == pytest.approx(list(HOME), abs=1e-8)
    capsys.readouterr()
    same_mission(imported(again, vehicle, capsys), first)


def mission_to_text(spec: MissionSpec) -> str:
    from u2sa_hw.services.mission.xml import mission_to_xml

    return mission_to_xml(spec)


def test_export_takes_the_profiles_mission_and_keeps_existing_files(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "harbour.xml").write_text(HARBOUR)
    vehicle = tmp_path / "boat.toml"
    vehicle.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
                       "[services.mission]\nkind = \"mission_manager\"\nsettings = { mission_file = \"harbour.xml\" }\n"
                       "[services.planner]\nkind = \"path_planner\"\nsettings = { cruise_speed_m_s = 1.5 }\n"
                       "[simulation]\nmodel = \"twin_thruster\"\n")
    out = tmp_path / "out.plan"
    assert mission_cli("export", str(out), "--vehicle", str(vehicle)) == 0
    data = json.loads(out.read_text())
    assert (data["mission"]["vehicleType"], data["mission"]["cruiseSpeed"], data["u2sa"]["mission"]) == (
        11, 1.5, "harbour loop")
    with pytest.raises(CliError, match=r"out.plan exists; pass --force to replace it"):
        mission_cli("export", str(out), "--vehicle", str(vehicle))
    assert mission_cli("export", str(out), "--vehicle", str(vehicle), "--force") == 0
    branching = tmp_path / "branch.xml"
    branching.write_text("<mission><waypoint><name>A</name><next>B</next><next>C</next><x>1</x><y>1</y></waypoint>"
                         "<waypoint><name>B</name><x>2</x><y>2</y></waypoint>"
                         "<waypoint><name>C</name><x>3</x><y>3</y></waypoint></mission>")
    with pytest.raises(CliError, match=r"branch.xml:1: goal 'A' branches \(B, C\): a QGroundControl plan has no "
                                       r"branching; keep one <next>"):
        mission_cli("export", str(tmp_path / "b.plan"), "--from", str(branching), "--vehicle", str(vehicle))
    with pytest.raises(CliError, match=r"name it \*.plan"):
        mission_cli("export", str(tmp_path / "harbour.xml"), "--vehicle", str(vehicle))
    assert (tmp_path / "harbour.xml").read_text() == HARBOUR


# -- upload to a real mission manager ---------------------------------------------------------------------------
def test_upload_a_plan_to_a_running_mission_manager_and_fly_it(services: ServiceProcesses, bus: BusClient,
                                                              tmp_path: Path, vehicle: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    vehicle.write_text(vehicle.read_text() + "[services.mission]\nkind = \"mission_manager\"\n"
                       "settings = { publish_interval_s = 0.3 }\n")
    goals: list[t.Waypoint] = []
    status: list[t.MissionStatus] = []
    bus.transport.subscribe(ch.GOALS, t.Waypoint, lambda _c, msg: goals.append(msg))
    bus.transport.subscribe(ch.MISSION_STATUS, t.MissionStatus, lambda _c, msg: status.append(msg))
    services.start("mission", "--vehicle", str(vehicle))
    wait_until(lambda: status, timeout=20, message="the mission manager's first MissionStatus")

    path = write(tmp_path, plan([waypoint(1, 10, 0, radius=1.5), waypoint(2, 10, 20), waypoint(3, 0, 20),
                                 simple(4, 177, 2, -1)]))
    assert mission_cli("upload", str(path), "--vehicle", str(vehicle), "--timeout", "20") == 0
    assert capsys.readouterr().out.startswith("mission 'field' (mission): goal 1 of 3: wp1\n")
    wait_until(lambda: status[-1].mission_name == "field", timeout=10, message="the uploaded plan's mission")
    assert list(status[-1].goal_uids) == ["wp1", "wp2", "wp3"]
    first = next(g for g in reversed(goals) if g.base.uid == "wp1")
    assert (first.x, first.y, first.horizontal_threshold) == (pytest.approx(10.0, abs=1e-3),
                                                              pytest.approx(0.0, abs=1e-3), 1.5)

    def complete(uid: str) -> None:
        report = t.GoalReport()
        report.uid, report.completed = uid, True
        bus.publish(ch.GOAL_REPORT, report)

    for done, following in (("wp1", "wp2"), ("wp2", "wp3"), ("wp3", "wp2")):   # the jump: 3 -> 2 forever
        complete(done)
        wait_until(lambda f=following: status[-1].current_uid == f, timeout=10, message=f"{following} current")
    wp3 = next(g for g in reversed(goals) if g.base.uid == "wp3")
    assert list(wp3.base.next_uids) == ["wp2"]
    assert (wp3.x, wp3.y) == (pytest.approx(0.0, abs=1e-3), pytest.approx(20.0, abs=1e-3))
