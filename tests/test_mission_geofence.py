"""Missions and the geofence: ``u2sa mission import/upload`` with a plan's geoFence, goals outside the profile's
fence refused by the commands before anything is sent, and by a real mission manager process on the bus."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from conftest import ServiceProcesses, wait_until
from test_mission_plan import at, mission_cli, plan, waypoint, write

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.cli import CliError
from u2sa_hw.services.mission.xml import parse_mission
from test_mission_plan import ORIGIN

FIELD = {"inclusion": True, "version": 1, "polygon": [list(at(-5, -5)), list(at(30, -5)), list(at(30, 30)),
                                                      list(at(-5, 30))]}
POND = {"inclusion": False, "version": 1, "circle": {"center": list(at(20, 20)), "radius": 3}}
FENCE = {"version": 2, "polygons": [FIELD], "circles": [POND]}
INSIDE = [waypoint(1, 0, 0), waypoint(2, 10, 0)]


def profile(tmp_path: Path, geofence: str = "", services: str = "") -> Path:
    path = tmp_path / "vehicle.toml"
    path.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
                    "[services.estimator]\nkind = \"state_estimator\"\n" + services + geofence)
    return path


def test_a_plans_fence_the_profile_does_not_enforce_is_refused_naming_the_fix(tmp_path: Path,
                                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, plan(INSIDE, geoFence=FENCE))
    vehicle = profile(tmp_path)
    with pytest.raises(CliError) as err:
        mission_cli("import", str(path), "--vehicle", str(vehicle))
    text = str(err.value)
    assert "the plan has a geofence (field.plan polygon 1, field.plan circle 1) that the vehicle does not " \
           "enforce" in text and f'plan = "{path.resolve()}"' in text and "--ignore-geofence" in text
    with pytest.raises(CliError, match="does not enforce.*nothing was sent"):
        mission_cli("upload", str(path), "--vehicle", str(vehicle))
    assert capsys.readouterr().out == ""
    assert mission_cli("import", str(path), "--vehicle", str(vehicle), "--ignore-geofence") == 0
    printed = capsys.readouterr()
    assert [g.uid for g in parse_mission(printed.out, source="p", default_threshold=0.0).goals] == ["wp1", "wp2"]
    assert printed.err.startswith("u2sa: warning: ") and "geofence (field.plan polygon 1, field.plan circle 1) " \
                                                         "dropped (--ignore-geofence)" in printed.err


def test_a_plans_fence_the_profile_takes_from_it_imports_without_a_word(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, plan(INSIDE, geoFence=FENCE))
    vehicle = profile(tmp_path, '[geofence]\nplan = "field.plan"\n')
    assert mission_cli("import", str(path), "--vehicle", str(vehicle)) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("items, words", [
    ([waypoint(1, 0, 0), waypoint(2, 40, 0)], "goal 2 'wp2' at x 40.0, y 0.0 is outside inclusion polygon "
                                              "'field.plan polygon 1' of the geofence"),
    ([waypoint(1, 20, 20)], "goal 1 'wp1' at x 20.0, y 20.0 is inside exclusion circle 'field.plan circle 1'"),
    ([waypoint(1, 29.5, 0)], "is 0.5 m from a geofence line, closer than \\[geofence\\] margin_m = 1 m"),
])
def test_a_goal_outside_the_fence_is_refused_naming_it(tmp_path: Path, items: list[Any], words: str) -> None:
    write(tmp_path, plan(INSIDE, geoFence=FENCE), name="fence.plan")
    path = write(tmp_path, plan(items, geoFence=FENCE), name="field.plan")
    vehicle = profile(tmp_path, '[geofence]\nplan = "field.plan"\n')
    with pytest.raises(CliError, match=words):
        mission_cli("import", str(path), "--vehicle", str(vehicle))


def test_an_xml_upload_outside_the_fence_is_refused_before_anything_is_sent(tmp_path: Path) -> None:
    vehicle = profile(tmp_path, "[geofence]\n[[geofence.circles]]\nname = \"yard\"\nlocal_center = [0, 0]\n"
                                "radius_m = 15\n")
    mission = tmp_path / "far.xml"
    mission.write_text("<mission name=\"far\"><waypoint><name>a</name><x>5</x><y>0</y></waypoint>"
                       "<waypoint><name>b</name><x>50</x><y>0</y></waypoint></mission>")
    with pytest.raises(CliError, match="goal 2 'b' .* is outside inclusion circle 'yard'.*nothing was sent"):
        mission_cli("upload", str(mission), "--vehicle", str(vehicle))


def test_a_malformed_plan_fence_is_one_line_naming_the_file(tmp_path: Path) -> None:
    bad = {"version": 2, "circles": [{"inclusion": True, "circle": {"center": list(at(0, 0)), "radius": -1}}]}
    path = write(tmp_path, plan(INSIDE, geoFence=bad))
    with pytest.raises(CliError, match=r"field.plan: geoFence.circles\[0\] \(circle 1\): the radius must be"):
        mission_cli("import", str(path), "--vehicle", str(profile(tmp_path)))


def test_the_mission_manager_refuses_a_mission_outside_its_fence(services: ServiceProcesses, bus: BusClient,
                                                               tmp_path: Path) -> None:
    inside = tmp_path / "inside.xml"
    inside.write_text("<mission name=\"in\"><waypoint><name>a</name><x>5</x><y>0</y></waypoint></mission>")
    vehicle = profile(tmp_path, "[geofence]\n[[geofence.circles]]\nname = \"yard\"\nlocal_center = [0, 0]\n"
                                "radius_m = 15\n",
                      services="[services.mission]\nkind = \"mission_manager\"\n"
                               "settings = { mission_file = \"inside.xml\", publish_interval_s = 0.3 }\n")
    status: list[t.MissionStatus] = []
    goals: list[t.Waypoint] = []
    acks: list[str] = []
    bus.transport.subscribe(ch.GOALS, t.Waypoint, lambda _c, msg: goals.append(msg))
    bus.transport.subscribe(ch.MISSION_STATUS, t.MissionStatus, lambda _c, msg: status.append(msg))
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: acks.extend(
        kv.value for kv in msg.details if kv.key == "last_command" and kv.value))
    services.start("mission", "--vehicle", str(vehicle))
    wait_until(lambda: status and status[-1].mission_name == "in", timeout=20, message="the mission inside the fence")
    cmd = t.MissionCommand()
    cmd.command = "upload"
    cmd.mission_xml = "<mission name=\"out\"><waypoint><name>far</name><x>40</x><y>0</y></waypoint></mission>"
    bus.publish(ch.MISSION_CMD, cmd)
    wait_until(lambda: any("refused" in a for a in acks), timeout=20, message="the upload's refusal")
    refusal = next(a for a in acks if "refused" in a)
    assert "goal 1 'far'" in refusal and "outside inclusion circle 'yard' of the geofence" in refusal
    assert status[-1].mission_name == "in"

    moved = t.Waypoint()                                  # another service moves goal 'a' out of the fence
    moved.base.uid, moved.reference_frame = "a", "LOCAL"
    moved.set(x=30.0, y=0.0)
    errors: list[str] = []
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: errors.append(msg.last_error)
                            if msg.name == "mission" else None)
    bus.publish(ch.GOALS, moved)
    wait_until(lambda: any("goal update: goal 'a' at x 30.0, y 0.0 is outside inclusion circle 'yard'" in e
                           for e in errors), timeout=20, message="the goal update's refusal in the manager's health")
    del goals[:]
    inside_goal = wait_until(lambda: next((g for g in reversed(goals) if g.base.uid == "a"), None), timeout=20,
                             message="goal a republished")
    assert (inside_goal.x, inside_goal.y) == (5.0, 0.0)   # still where the mission put it
