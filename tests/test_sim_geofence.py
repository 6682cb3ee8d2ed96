"""``u2sa sim --scenario examples/ground_vehicle/scenarios/geofence.toml``: the rover, pushed west across its
yard's fence mid-leg, has its wheels stopped by the geofence pre-arm check, and the summary names the breach
(a real ``u2sa sim``: every service a process; order and outcome asserted, never a timing)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_sim_scenarios import WHEELS, play, still, stopped

from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.simulation.events import ScenarioError, load_scenario_file
from u2sa_hw.simulation.fence_report import fence_lines, fence_report
from u2sa_hw.simulation.summary import TrackSample
from u2sa_hw.geofence import POLYGON, Fence, FenceArea


@pytest.mark.timeout(240)
def test_a_push_across_the_fence_stops_the_wheels_and_the_summary_names_it(tmp_path: Path, lcm_url: str) -> None:
    summary, events = play(tmp_path, lcm_url, "examples/ground_vehicle/vehicle.toml",
                           "examples/ground_vehicle/scenarios/geofence.toml")
    fence = summary["geofence"]
    assert fence["areas"] == ["yard", "pond"]
    assert [b["area"] for b in fence["breaches"]] == ["yard"], fence
    assert fence["breaches"][0]["what"] == "outside inclusion polygon 'yard'"
    assert fence["breaches"][0]["estimate_out_s"] is not None   # the estimate left too: what the vehicle acted on
    push, calm = events
    assert push["action"] == "push" and stopped(push, WHEELS), push
    assert any("geofence: outside inclusion polygon 'yard'" in mode for mode in push["rc_modes"]), push["rc_modes"]
    assert still(calm, WHEELS), "the wheels stay stopped: autonomy does not come back by itself"
    text = (tmp_path / "out" / "summary.txt").read_text()
    assert "geofence             BREACHED at" in text and "outside inclusion polygon 'yard'" in text


@pytest.mark.parametrize("text, error", [
    ("[[event]]\nat_s = 1\naction = \"push\"\neast_mps = 50\n", r"push speeds must be within -20..20 m/s"),
    ("[[event]]\nat_s = 1\naction = \"push\"\neast_mps = \"fast\"\n", r"east_mps has the wrong type"),
    ("[[event]]\nat_s = 1\naction = \"push\"\nwest_mps = 1\n", r"unknown key\(s\) west_mps for push"),
])
def test_a_bad_push_names_the_file_the_event_and_the_key(tmp_path: Path, text: str, error: str) -> None:
    path = tmp_path / "scen.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError, match=error):
        load_scenario_file(path)


def test_a_push_moves_the_true_vehicle_its_gps_velocity_but_not_its_odometry() -> None:
    sim = SimVehicle(origin_lat=29.19, origin_lon=-81.05)
    sim.set_push(0.0, -2.0)
    for _ in range(100):
        sim.step(0.01)
    truth = sim.snapshot()
    assert (truth.north, truth.east) == (pytest.approx(0.0), pytest.approx(-2.0))
    assert truth.v_east == pytest.approx(-2.0) and truth.speed == pytest.approx(2.0)
    assert truth.wheel_left_m == truth.wheel_right_m == 0.0
    sim.set_push(0.0, 0.0)
    sim.step(0.5)
    assert sim.snapshot().east == pytest.approx(-2.0)


def test_the_summary_says_kept_inside_or_each_breach() -> None:
    fence = Fence((FenceArea("yard", True, POLYGON, points=((0, 0), (10, 0), (10, 10), (0, 10))),))
    inside = [TrackSample(t=float(i), north=5.0, east=1.0 + i, yaw=0.0, speed=1.0) for i in range(3)]
    kept = fence_report(fence, inside, t_engage=0.0)
    assert kept["breaches"] == [] and kept["closest_to_a_line_m"] == 1.0
    assert fence_lines(kept) == ["  geofence             kept inside (yard), closest 1.00 m from a line"]
    out = inside + [TrackSample(t=3.0 + i, north=5.0, east=10.5 + i, yaw=0.0, speed=1.0, est_north=5.0,
                                est_east=9.0 + i) for i in range(3)]
    report = fence_report(fence, out, t_engage=0.0)
    assert report["breaches"] == [{"at_s": 3.0, "area": "yard", "what": "outside inclusion polygon 'yard'",
                                   "max_out_m": 2.5, "estimate_out_s": 5.0}]
    assert fence_lines(report) == ["  geofence             BREACHED at 3.0 s: outside inclusion polygon 'yard' "
                                   "(up to 2.5 m)"]
    assert fence_report(None, out, t_engage=0.0) is None and fence_lines(None) == []
