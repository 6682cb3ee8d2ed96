"""Mission Manager: the XML mission (good and malformed), the goal logic, and the service over real LCM."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from conftest import ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import geo
from u2sa_hw import lcmtypes as t
from u2sa_hw import messages as m
from u2sa_hw.bus.client import BusClient
from u2sa_hw.services.mission.manager import MissionError, MissionManager, from_message, to_waypoint
from u2sa_hw.services.mission.xml import GLOBAL, LOCAL, load_mission, parse_mission
from u2sa_hw.services.mission.xmltree import XmlFileError
from u2sa_hw.profile.vehicle import Origin

ORIGIN = Origin(lat=29.1895, lon=-81.0483, alt=10.0)

MISSION = """\
<?xml version="1.0"?>
<mission name="harbour" loop="true">
  <waypoint>
    <name>A</name>
    <x>10</x>
    <y>-5</y>
    <threshold>1.5</threshold>
  </waypoint>
  <waypoint>
    <name>B</name>
    <next>C</next>
    <next>D</next>
    <reference>Global</reference>
    <lat>29.19</lat><lon>-81.048</lon><alt>12</alt>
    <psi unit="deg">90</psi>
    <time>30</time>
    <vertical_threshold>0.5</vertical_threshold>
  </waypoint>
  <waypoint><name>C</name><x>0</x><y>20</y></waypoint>
  <waypoint><name>D</name><next>A</next><x>-3</x><y>4</y><z>1</z><phi>0.1</phi></waypoint>
</mission>
"""


def spec(text: str = MISSION, **kw: object):  # noqa: ANN201
    return parse_mission(text, source="m.xml", default_threshold=kw.get("default", 2.0))


# -- XML -------------------------------------------------------------------------------------------
def test_parse_local_global_branching_and_units() -> None:
    s = spec()
    assert s.name == "harbour" and s.loop and [g.uid for g in s.goals] == ["A", "B", "C", "D"]
    a, b, c, d = s.goals
    assert a.frame == LOCAL and a.values == {"x": 10.0, "y": -5.0} and a.horizontal_threshold == 1.5 and a.line == 3
    assert b.frame == GLOBAL and b.values["x"] == 29.19 and b.values["y"] == -81.048 and b.values["z"] == 12.0
    assert b.values["psi"] == pytest.approx(math.pi / 2) and b.values["time"] == 30.0
    assert b.values["vertical_threshold"] == 0.5 and b.next_uids == ["C", "D"]
    assert c.horizontal_threshold == 2.0 and c.next_uids == []           # the configured default
    assert d.values == {"x": -3.0, "y": 4.0, "z": 1.0, "phi": 0.1}


def test_thesis_style_waypoints_without_names_get_their_position_as_uid(tmp_path: Path) -> None:
    path = tmp_path / "fg.xml"
    path.write_text("<mission><waypoint><x>1</x><y>2</y></waypoint><waypoint><z>-30</z></waypoint></mission>")
    s = load_mission(path, default_threshold=5.0)
    assert [g.uid for g in s.goals] == ["1", "2"] and s.name == "fg" and not s.loop


def test_uid_is_an_alias_of_name() -> None:
    s = spec("<mission><waypoint><uid>A</uid><x>1</x></waypoint>"
             "<waypoint><name>B</name><uid>B</uid><next>A</next><x>2</x></waypoint></mission>")
    assert [g.uid for g in s.goals] == ["A", "B"] and s.goals[1].next_uids == ["A"]


# The thesis's own examples, copied from its text (3.2.3.2 and 4.5.2.3); a mission file wraps its waypoints.
THESIS_3_2_3_2 = """\
<waypoint>
  <name>1</name>
  <next>2</next>
  <reference>Global</reference>
  <x>10</x>
  <y>15</y>
</waypoint>
"""
THESIS_4_5_2_3 = """\
<waypoint>
  <y>37.466189</y>
  <x>-121.134548</x>
  <z>3000</z>
</waypoint>
"""


def test_the_thesis_mission_examples_load() -> None:
    # 3.2.3.2 names a next goal "2" that its snippet does not show: add one
    s = spec(f"<mission>\n{THESIS_3_2_3_2}<waypoint><name>2</name><x>0</x></waypoint></mission>")
    first = s.goals[0]
    assert (first.uid, first.frame, first.next_uids) == ("1", GLOBAL, ["2"])
    assert first.values == {"x": 15.0, "y": 10.0}                 # x = lon, y = lat: as latitude 15, longitude 10
    assert first.line == 2
    # 4.5.2.3: FlightGear's lat/lon/altitude waypoints, in a mission whose goals are Global by default
    s = spec(f'<mission loop="true" reference="Global">\n{THESIS_4_5_2_3}{THESIS_4_5_2_3}</mission>')
    assert s.loop and [g.uid for g in s.goals] == ["1", "2"] and s.goals[1].line == 7
    assert s.goals[0].frame == GLOBAL and s.goals[0].values == {"x": 37.466189, "y": -121.134548, "z": 3000.0}
    # the same lines without the Global default are local metres, as the file says nothing else
    assert spec(f"<mission>{THESIS_4_5_2_3}</mission>").goals[0].frame == LOCAL


@pytest.mark.parametrize(("text", "line", "element", "words"), [
    ("<mission>\n<waypoint><x>1</x>\n</mission>", 3, "waypoint", "mismatched tag"),
    ("<mission>\n  <waypoint>\n    <x>1</x><speed>3</speed>\n  </waypoint>\n</mission>", 3, "speed",
     "unknown element inside <waypoint>"),
    ("<mission>\n<waypoint>\n<x>ten</x></waypoint></mission>", 3, "x", "expected a number, got 'ten'"),
    ("<mission>\n<waypoint><reference>Global</reference>\n<x>29.1</x></waypoint></mission>", 2, "waypoint",
     "needs <y> and <x> together (<x> is the longitude, <y> the latitude)"),
    ("<mission>\n<waypoint><reference>Global</reference><lat>29.1</lat>\n<x>-81</x></waypoint></mission>", 3, "x",
     "either <lat>/<lon>/<alt> or the thesis's <x> = longitude"),
    ("<mission>\n<waypoint><reference>Global</reference><x>-81</x>\n<y>181</y></waypoint></mission>", 3, "y",
     "<y> is the latitude in a Global waypoint: must be within -90..90"),
    ("<mission>\n<waypoint><reference>Global</reference><lat>29</lat>\n<lon>-181</lon></waypoint></mission>", 3,
     "lon", "longitude must be within -180..180"),
    ("<mission reference='ECEF'>\n<waypoint><x>1</x></waypoint></mission>", 1, "mission",
     'reference="ECEF" must be Local or Global'),
    ("<mission>\n<waypoint><name>A</name>\n<uid>B</uid><x>1</x></waypoint></mission>", 3, "uid",
     "'B' differs from <name> 'A' on line 2"),
    ("<mission>\n<waypoint><lat>29.1</lat><lon>-81</lon></waypoint></mission>", 2, "lat",
     "need <reference>Global</reference>"),
    ("<mission>\n\n<waypoint><reference>Global</reference><lat>29.1</lat></waypoint></mission>", 3, "waypoint",
     "<lat> and <lon> together"),
    ("<mission>\n<waypoint><name>A</name><x>1</x></waypoint>\n<waypoint><name>A</name><x>2</x></waypoint>"
     "</mission>", 3, "waypoint", "duplicate name 'A' (also on line 2)"),
    ("<mission>\n<waypoint><next>Z</next><x>1</x></waypoint></mission>", 2, "waypoint",
     "<next>Z</next> names no goal"),
    ("<mission>\n<waypoint><x>1</x>\n<x>2</x></waypoint></mission>", 3, "x", "appears twice"),
    ("<mission>\n<waypoint><name>q</name></waypoint></mission>", 2, "waypoint", "has no position"),
    ("<mission>\n<waypoint><x>1</x><threshold>-1</threshold></waypoint></mission>", 2, "threshold",
     "greater than 0"),
    ("<mission>\n<waypoint><x>1</x><psi unit='grad'>1</psi></waypoint></mission>", 2, "psi", "unit must be"),
    ("<mission loop='maybe'>\n</mission>", 1, "mission", "loop=\"maybe\" must be true or false"),
    ("<mission>\n<goal/></mission>", 2, "goal", "unknown goal type"),
    ("<waypoint><x>1</x></waypoint>", 1, "waypoint", "a single <waypoint> must be wrapped in one"),
    ("<mission>\n</mission>", 1, "mission", "has no goals"),
])
def test_malformed_missions_name_file_line_and_element(text: str, line: int, element: str, words: str) -> None:
    with pytest.raises(XmlFileError) as err:
        spec(text)
    e = err.value
    assert (e.source, e.line, e.element) == ("m.xml", line, element), str(e)
    assert str(e).startswith(f"m.xml:{line}: <{element}>") and words in str(e)


def test_missing_threshold_without_default_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(XmlFileError, match=r"m.xml:1: <waypoint> has no <threshold>"):
        parse_mission("<mission><waypoint><x>1</x></waypoint></mission>", source="m.xml")
    with pytest.raises(XmlFileError, match=r"nope.xml: no such file"):
        load_mission(tmp_path / "nope.xml")


# -- manager logic -----------------------------------------------------------------------------------
def test_sequential_then_branching_then_explicit_loop() -> None:
    mm = MissionManager(spec())
    assert mm.active == ["A"] and mm.successors("A") == ["B"]
    assert not mm.complete("C")                                   # not current: ignored
    assert mm.complete("A") and mm.active == ["B"] and mm.goals["A"].completed
    assert mm.complete("B") and mm.active == ["C", "D"]           # the planner may choose
    assert mm.successors("C") == ["D"]                            # file order
    assert mm.complete("D") and mm.active == ["A"] and not mm.goals["A"].completed   # D -> A, reset
    state = mm.state()
    assert (state.current_uid, state.current_index, state.uids, state.finished) == ("A", 0, ["A", "B", "C", "D"], False)


def test_ending_and_looping_and_the_loop_override() -> None:
    text = "<mission loop='false'><waypoint><x>1</x></waypoint><waypoint><x>2</x></waypoint></mission>"
    mm = MissionManager(spec(text))
    assert mm.complete("1") and mm.complete("2") and mm.finished and mm.state().current_index == -1
    assert not mm.skip()
    mm = MissionManager(spec(text), loop=True)
    assert mm.complete("1") and mm.complete("2") and mm.active == ["1"] and mm.state().looping
    mm.set_loop(False)
    assert mm.complete("1") and mm.complete("2") and mm.finished


def test_goto_skip_restart() -> None:
    mm = MissionManager(spec())
    mm.goto("C")
    assert mm.active == ["C"]
    assert mm.skip() and mm.active == ["D"] and not mm.goals["C"].completed
    with pytest.raises(MissionError, match="no such goal"):
        mm.goto("Q")
    mm.complete("D")
    mm.restart()
    assert mm.active == ["A"] and not any(g.completed for g in mm.goals.values())


def merge(mm: MissionManager, msg: object) -> str:
    goal, fields = from_message(msg)
    return mm.merge(goal, fields=fields)


def test_merge_updates_known_goals_and_new_ones_wait_for_a_link() -> None:
    mm = MissionManager(spec(), default_threshold=3.0)
    wp = m.Waypoint().set(x=11.0, psi=0.5)
    wp.base.uid = "A"
    assert merge(mm, wp) == "updated"
    assert mm.goals["A"].values == {"x": 11.0, "y": -5.0, "psi": 0.5} and mm.goals["A"].horizontal_threshold == 1.5

    new = m.Waypoint().set(x=50.0, y=50.0)
    new.base.uid = "N"
    assert merge(mm, new) == "added"
    assert mm.goals["N"].horizontal_threshold == 3.0 and "N" not in mm.successors("D")
    link = t.GoalInformation()
    link.uid, link.next_uids, link.num_next = "A", ["N"], 1
    assert merge(mm, link) == "updated"
    assert mm.complete("A") and mm.active == ["N"] and mm.successors("N") == []
    orphan = t.GoalInformation()
    orphan.uid, orphan.next_uids, orphan.num_next = "Z", ["A"], 1
    with pytest.raises(MissionError, match="no position"):
        merge(mm, orphan)


def test_waypoint_messages_are_local_ned_with_successors() -> None:
    mm = MissionManager(spec())
    b = mm.goals["B"]
    wp = to_waypoint(b, origin=ORIGIN, next_uids=mm.successors("B"))
    north, east, _ = geo.geodetic_to_ned(29.19, -81.048, origin=ORIGIN)
    assert wp.reference_frame == "LOCAL" and wp.base.uid == "B" and list(wp.base.next_uids) == ["C", "D"]
    assert (wp.x, wp.y, wp.z) == pytest.approx((north, east, -2.0)) and wp.get("psi") == pytest.approx(math.pi / 2)
    assert wp.horizontal_threshold == 2.0 and wp.get("vertical_threshold") == 0.5 and not wp.has("phi")
    assert b.values["x"] == 29.19                                  # the goal itself stays geodetic


# -- the service over real LCM -----------------------------------------------------------------------
def _health(bus_health: list[t.Health]) -> t.Health | None:
    return bus_health[-1] if bus_health else None


def test_service_publishes_advances_merges_and_takes_commands(services: ServiceProcesses, bus: BusClient,
                                                             tmp_path: Path) -> None:
    (tmp_path / "mission.xml").write_text(MISSION)
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
                       "[services.mission]\nkind = \"mission_manager\"\n"
                       "settings = { mission_file = \"mission.xml\", publish_interval_s = 0.3, "
                       "health_interval_s = 0.2 }\n")
    goals: list[object] = []
    status: list[t.MissionStatus] = []
    health: list[t.Health] = []
    bus.transport.subscribe(ch.GOALS, t.GoalInformation, lambda _c, msg: goals.append(msg))
    bus.transport.subscribe(ch.MISSION_STATUS, t.MissionStatus, lambda _c, msg: status.append(msg))
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: health.append(msg) if msg.name == "mission" else None)
    services.start("mission", "--vehicle", str(vehicle))

    wait_until(lambda: len(status) >= 3, timeout=20, message="periodic MissionStatus")
    s = status[-1]
    assert (s.mission_name, s.current_uid, s.current_index, list(s.goal_uids), s.looping) == (
        "harbour", "A", 0, ["A", "B", "C", "D"], True)
    a = next(g for g in goals if g.base.uid == "A")
    assert isinstance(a, t.Waypoint) and (a.x, a.y, a.reference_frame) == (10.0, -5.0, "LOCAL")

    def report(uid: str) -> None:
        r = t.GoalReport()
        r.uid, r.completed = uid, True
        bus.publish(ch.GOAL_REPORT, r)

    report("A")
    wait_until(lambda: status[-1].current_uid == "B", timeout=10, message="B to become current")
    b = next(g for g in reversed(goals) if g.base.uid == "B")
    assert b.x == pytest.approx(geo.geodetic_to_ned(29.19, -81.048, origin=ORIGIN)[0])

    update = m.Waypoint().set(x=99.0, y=1.0)
    update.base.uid = "B"
    bus.publish(ch.GOALS, update)
    wait_until(lambda: any(g.base.uid == "B" and isinstance(g, t.Waypoint) and g.x == 99.0
                           and g.base.header.source == "mission" for g in goals[-6:]),
               timeout=10, message="the merged B on GOALS")

    cmd = t.MissionCommand()
    cmd.command, cmd.mission_xml = "upload", "<mission>\n<waypoint><x>1</x>\n<bogus/></waypoint></mission>"
    bus.publish(ch.MISSION_CMD, cmd)
    wait_until(lambda: (h := _health(health)) and "<bogus> unknown element" in h.last_error, timeout=10,
               message="the refused upload in health")
    assert ":3: <bogus>" in health[-1].last_error and status[-1].mission_name == "harbour"

    cmd.mission_xml = "<mission name='short'><waypoint><name>P</name><x>1</x><y>1</y></waypoint></mission>"
    bus.publish(ch.MISSION_CMD, cmd)
    wait_until(lambda: status[-1].mission_name == "short" and status[-1].current_uid == "P", timeout=10,
               message="the uploaded mission")
    report("P")
    wait_until(lambda: status[-1].finished and status[-1].current_uid == "", timeout=10, message="the end")
    goto = t.MissionCommand()
    goto.command, goto.uid = "goto", "P"
    bus.publish(ch.MISSION_CMD, goto)
    wait_until(lambda: status[-1].current_uid == "P" and not status[-1].finished, timeout=10, message="goto P")


# -- u2sa mission: the operator's command line against a real mission manager ----------------------------
def mission_cli(*argv: str) -> int:
    """``u2sa mission ARGV`` in this process (its parser built from the command's own module)."""
    import argparse

    from u2sa_hw.cli import mission_cmd

    parser = argparse.ArgumentParser(prog="u2sa")
    mission_cmd.register(parser.add_subparsers())
    args = parser.parse_args(["mission", *argv])
    return args.func(args)


def test_mission_command_line_status_goto_skip_restart_upload(services: ServiceProcesses, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    from u2sa_hw.cli import CliError

    (tmp_path / "mission.xml").write_text(MISSION)
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
                       "[services.mission]\nkind = \"mission_manager\"\n"
                       "settings = { mission_file = \"mission.xml\", publish_interval_s = 0.5 }\n")
    v = ("--vehicle", str(vehicle))
    services.start("mission", *v)

    assert mission_cli("status", *v, "--timeout", "20") == 0
    out = capsys.readouterr().out
    assert out.startswith("mission 'harbour' (mission): goal 1 of 4: A, looping\n") and "  >  1 A\n" in out

    assert mission_cli("goto", "C", *v) == 0
    assert capsys.readouterr().out.startswith("mission 'harbour' (mission): goal 3 of 4: C")
    assert mission_cli("skip", *v, "--json") == 0
    assert json.loads(capsys.readouterr().out)["current_uid"] == "D"
    assert mission_cli("restart", *v) == 0
    assert "goal 1 of 4: A" in capsys.readouterr().out

    with pytest.raises(CliError, match=r"mission goto: mission refused: goto 'Q': no such goal \(goals: A, B, C, D\)"):
        mission_cli("goto", "Q", *v)

    bad = tmp_path / "bad.xml"
    bad.write_text("<mission name='bad'>\n<waypoint><x>1</x>\n<speed>3</speed></waypoint>\n</mission>\n")
    with pytest.raises(CliError, match=rf"mission upload: {bad}:3: <speed> unknown element .*nothing was sent"):
        mission_cli("upload", str(bad), *v)
    with pytest.raises(CliError, match=r"cannot read"):
        mission_cli("upload", str(tmp_path / "missing.xml"), *v)

    good = tmp_path / "survey.xml"
    good.write_text('<?xml version="1.0" encoding="UTF-8"?>\n<mission name="survey">'
                    "<waypoint><uid>P</uid><x>5</x><y>5</y></waypoint><waypoint><uid>Q</uid><x>9</x></waypoint>"
                    "</mission>\n")
    assert mission_cli("upload", str(good), *v) == 0
    assert capsys.readouterr().out.startswith("mission 'survey' (mission): goal 1 of 2: P\n")
    assert mission_cli("goto", "Q", *v) == 0
    capsys.readouterr()


def test_mission_command_line_without_a_mission_manager_says_so(tmp_path: Path, lcm_url: str) -> None:
    from u2sa_hw.cli import CliError

    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text("[vehicle]\nname = \"lonely\"\n")
    with pytest.raises(CliError, match=r"mission skip: no mission manager acknowledged within 0.5 s"):
        mission_cli("skip", "--vehicle", str(vehicle), "--timeout", "0.5")
    with pytest.raises(CliError, match=r"mission status: no MISSION_STATUS within 0.5 s"):
        mission_cli("status", "--vehicle", str(vehicle), "--timeout", "0.5")
    with pytest.raises(CliError, match=r"mission goto: give the goal UID") as err:
        mission_cli("goto", "--vehicle", str(vehicle))
    assert err.value.code == 2
