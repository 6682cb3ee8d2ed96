"""The geofence's geometry (u2sa_hw/geofence.py) and its parsing from the profile and from a QGroundControl
plan (u2sa_hw/geofence_parse.py): pure functions, profiles and plans written to tmp_path."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path
from typing import Any

import pytest
import tomli_w

from conftest import U2SA
from u2sa_hw.geo import ned_to_geodetic
from u2sa_hw.geofence import CIRCLE, POLYGON, Fence, FenceArea, FenceObstacle
from u2sa_hw.geofence_parse import FenceError, checked_polygon, plan_areas, profile_fence
from u2sa_hw.profile.vehicle import Origin, ProfileError
from u2sa_hw.profile.loader import load_profile

ORIGIN = Origin(29.1895, -81.0483, 10.0)
SQUARE = FenceArea("field", True, POLYGON, points=((-10, -10), (30, -10), (30, 35), (-10, 35)))
POND = FenceArea("pond", False, CIRCLE, center=(10.0, 12.0), radius_m=3.0)
FENCE = Fence((SQUARE, POND), source="test", margin_m=1.0)


def geo(north: float, east: float) -> list[float]:
    lat, lon, _ = ned_to_geodetic(north, east, 0.0, origin=ORIGIN)
    return [lat, lon]


# -- geometry ------------------------------------------------------------------------------------
def test_inside_the_inclusion_and_outside_the_exclusion_is_allowed() -> None:
    assert FENCE.breach(0.0, 0.0) is None
    assert FENCE.breach(29.9, 34.9) is None
    assert FENCE.breach(30.0, 0.0) is None   # on the line counts as inside


def test_a_breach_names_the_area_it_breaks() -> None:
    out = FENCE.breach(31.0, 0.0)
    assert out is not None and out.area is SQUARE
    assert out.what == "outside inclusion polygon 'field'" and "1.0 m out" in out.reason
    inside = FENCE.breach(10.0, 13.0)
    assert inside is not None and inside.area is POND and inside.what == "inside exclusion circle 'pond'"
    assert FENCE.breach(math.nan, 0.0) is not None   # cannot tell: fail safe


def test_several_inclusion_areas_are_a_union_and_the_nearest_is_named() -> None:
    east = FenceArea("east field", True, CIRCLE, center=(0.0, 60.0), radius_m=5.0)
    fence = Fence((SQUARE, east))
    assert fence.breach(0.0, 62.0) is None
    far = fence.breach(0.0, 50.0)
    assert far is not None and far.area is east


def test_clearance_and_the_planner_obstacle_measure_to_the_nearest_line() -> None:
    assert FENCE.clearance(0.0, 0.0) == pytest.approx(10.0)
    assert FENCE.clearance(10.0, 16.0) == pytest.approx(1.0)   # 4 m from the pond's centre, radius 3
    assert FENCE.clearance(40.0, 0.0) == 0.0
    obstacle = FenceObstacle(FENCE)
    assert obstacle.hard and obstacle.avoided and obstacle.distance(28.0, 0.0) == pytest.approx(2.0)


def test_a_leg_through_the_exclusion_zone_is_found_where_it_enters() -> None:
    hit = FENCE.segment_breach((10.0, 0.0), (10.0, 25.0))
    assert hit is not None and hit[1].area is POND and hit[0] == pytest.approx(9.0, abs=0.6)
    assert FENCE.segment_breach((0.0, 0.0), (20.0, 0.0)) is None


def test_the_fence_survives_its_json_round_trip() -> None:
    again = Fence.from_json(FENCE.to_json())
    assert again.areas == FENCE.areas and again.margin_m == 1.0


# -- polygons and circles checked ----------------------------------------------------------------
@pytest.mark.parametrize("points, words", [
    ([(0, 0), (1, 1)], "at least 3 distinct corners"),
    ([(0, 0), (1, 1), (2, 2)], "no area"),
    ([(0, 0), (10, 10), (10, 0), (0, 10)], "edges 1 and 3 cross"),
])
def test_a_degenerate_polygon_is_refused_with_the_fix(points: list[tuple[float, float]], words: str) -> None:
    with pytest.raises(FenceError, match=words):
        checked_polygon(points, "f")


def test_a_polygon_written_closed_loses_its_closing_corner() -> None:
    assert checked_polygon([(0, 0), (0, 5), (5, 5), (0, 0)], "f") == ((0, 0), (0, 5), (5, 5))


# -- from a plan ---------------------------------------------------------------------------------
def plan_fence(polygons: list[Any] = (), circles: list[Any] = ()) -> dict[str, Any]:
    return {"version": 2, "polygons": list(polygons), "circles": list(circles)}


def test_a_plans_fence_becomes_named_local_areas() -> None:
    fence = plan_fence([{"inclusion": True, "version": 1, "polygon": [geo(-10, -10), geo(30, -10), geo(30, 35)]}],
                       [{"circle": {"center": geo(10, 12), "radius": 3}, "inclusion": False, "version": 1}])
    areas = plan_areas(fence, source="/x/field.plan", origin=ORIGIN)
    assert [a.name for a in areas] == ["field.plan polygon 1", "field.plan circle 1"]
    assert areas[0].points[1] == pytest.approx((30.0, -10.0), abs=1e-3)
    assert not areas[1].inclusion and areas[1].center == pytest.approx((10.0, 12.0), abs=1e-3)


@pytest.mark.parametrize("fence, words", [
    (plan_fence(circles=[{"circle": {"center": [29.19, -81.05], "radius": -5}, "inclusion": True}]),
     r"circles\[0\] \(circle 1\): the radius must be a number of metres > 0"),
    (plan_fence([{"inclusion": "yes", "polygon": []}]), r"\"inclusion\" must be true or false"),
    (plan_fence([{"inclusion": True, "polygon": [[29.19, -81.05], [29.19, -81.05]]}]), "at least 3 distinct"),
    (plan_fence([{"inclusion": True, "polygon": [[129.19, -81.05]]}]), "not a latitude"),
    (plan_fence([{"inclusion": True, "polygon": [[0.0, 0.0], [0.0, 0.01], [0.01, 0.0]]}]), "km from the vehicle's"),
    ({"version": 1, "polygon": [[1, 2]]}, "version-1 fence"),
    ([1, 2], "must be an object"),
])
def test_a_malformed_plan_fence_is_one_line_naming_the_file(fence: Any, words: str) -> None:
    with pytest.raises(FenceError, match=words) as err:
        plan_areas(fence, source="field.plan", origin=ORIGIN)
    assert str(err.value).startswith("field.plan: geoFence")


# -- from the profile ----------------------------------------------------------------------------
def write_profile(tmp_path: Path, geofence: Any) -> Path:
    data = {"vehicle": {"name": "t", "origin": {"lat": ORIGIN.lat, "lon": ORIGIN.lon, "alt": 10.0}},
            "services": {"estimator": {"kind": "state_estimator"}}, "geofence": geofence}
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps(data))
    return path


def test_the_profile_fence_in_degrees_local_metres_and_from_a_plan(tmp_path: Path) -> None:
    plan = {"fileType": "Plan", "geoFence": plan_fence(
        circles=[{"circle": {"center": geo(20, 20), "radius": 2}, "inclusion": False, "version": 1}])}
    (tmp_path / "field.plan").write_text(json.dumps(plan))
    profile = load_profile(write_profile(tmp_path, {
        "plan": "field.plan", "margin_m": 2.0,
        "polygons": [{"name": "yard", "points": [geo(-10, -10), geo(30, -10), geo(30, 35), geo(-10, 35)]}],
        "circles": [{"name": "pond", "inclusion": False, "local_center": [10, 12], "radius_m": 3}]}))
    fence = profile_fence(profile)
    assert fence is not None and fence.margin_m == 2.0
    assert [a.name for a in fence.areas] == ["field.plan circle 1", "yard", "pond"]
    assert fence.breach(20.0, 20.5).area.name == "field.plan circle 1"
    assert fence.breach(31.0, 0.0).area.name == "yard"


@pytest.mark.parametrize("table, words", [
    ({}, "no areas"),
    ({"polygons": [{"name": "a", "local": [[0, 0], [1, 1]]}]}, r"polygons\[0\] 'a': a polygon needs at least 3"),
    ({"circles": [{"name": "c", "local_center": [0, 0], "radius_m": -1}]}, "radius must be a number"),
    ({"circles": [{"name": "c", "local_center": [0, 0], "center": [1, 1], "radius_m": 1}]}, "either 'center'"),
    ({"circles": [{"name": "c", "local_center": "here", "radius_m": 1}]}, r"\[north, east\] in metres"),
    ({"polygons": [{"name": "a", "local": [[0, 0], [0, 5], [5, 5]], "colour": "red"}]}, "unknown key 'colour'"),
    ({"margin_m": 1e9, "circles": [{"local_center": [0, 0], "radius_m": 1}]}, "'margin_m' must be"),
    ({"plan": "missing.plan"}, "missing.plan: cannot read"),
    ({"circles": [{"name": "c", "local_center": [0, 0], "radius_m": 1},
                  {"name": "c", "local_center": [5, 5], "radius_m": 1}]}, "two areas are named 'c'"),
])
def test_a_bad_geofence_table_is_refused_at_load_naming_the_file(tmp_path: Path, table: dict[str, Any],
                                                                  words: str) -> None:
    path = write_profile(tmp_path, table)
    with pytest.raises(ProfileError, match=words) as err:
        load_profile(path)
    assert f"{path} [geofence]" in str(err.value)


def test_u2sa_check_reports_a_bad_fence_without_a_traceback(tmp_path: Path) -> None:
    path = write_profile(tmp_path, {"circles": [{"name": "c", "local_center": [0, 0], "radius_m": -2}]})
    out = subprocess.run([*U2SA, "check", "--vehicle", str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    assert "Traceback" not in out.stderr + out.stdout
    assert "radius must be a number" in out.stderr + out.stdout
