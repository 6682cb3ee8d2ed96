"""``u2sa sim --scenario examples/ground_vehicle/scenarios/geofence.toml``: the rover, pushed west across its
yard's fence mid-leg, has its wheels stopped by the geofence pre-arm check, and the summary names the breach
(a real ``u2sa sim``: every service a process; order and outcome asserted, never a timing)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_sim_scenarios import WHEELS, play, still, stopped


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
