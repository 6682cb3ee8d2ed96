"""A simulation says "completed" only when the mission's goals were reached, and its distance is the
simulated track's (issue 26).

``manual_takeover`` once said "completed in 16.1 s" with no goal reached, and the sticks
scenario "distance driven 0.0 m" while its track.csv showed 2.7 m: a scenario that plays to
its end is "played" (exit 0), and the distance is measured along the whole track, engaged or not.
"""

from __future__ import annotations

import csv
import json
import math
import re
import subprocess
from pathlib import Path

import pytest
from conftest import REPO, U2SA

from u2sa_hw.simulation.progress import StatusChange, mission_done
from u2sa_hw.simulation.summary import Goal, RunRecord, TrackSample, summarise, summary_text
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.udp_ports import private_udp_port


def _record(*, engaged: bool, result: str, changes: list[StatusChange]) -> RunRecord:
    path = [(0, 0.0, 0.0), (1, 0.0, 0.0), (2, 3.0, 0.0), (3, 3.0, 4.0)]   # 3 m north, then 4 m east: 7 m
    samples = [TrackSample(t=100.0 + s, north=n, east=e, yaw=0.0, speed=1.0) for s, n, e in path]
    return RunRecord(vehicle="rover", mission="m", looping=False, goals=[Goal("a", 30.0, 0.0, 1.0)], obstacles=[],
                     samples=samples, changes=changes, t_start=95.0, t_engage=101.5 if engaged else None,
                     t_end=103.0, result=result)


@pytest.mark.parametrize("engaged", [False, True], ids=["by-hand", "engaged"])
def test_the_distance_is_the_whole_simulated_track(engaged: bool) -> None:
    summary = summarise(_record(engaged=engaged, result="played", changes=[]))
    assert summary["distance_m"] == 7.0
    text = summary_text(summary)
    assert "distance driven      7.0 m" in text, text
    assert not re.search(r": completed in", text) and "not completed (0 of 1 goals reached)" in text, text


def test_a_finished_mission_is_completed_and_a_running_one_is_not() -> None:
    status = t.MissionStatus()
    status.finished, status.looping = False, False
    assert not mission_done(status, [StatusChange(1.0, "a", 0, False)], since=0.5)
    assert not mission_done(None, [], since=0.5)
    status.finished = True
    assert mission_done(status, [StatusChange(1.0, "a", 0, False), StatusChange(2.0, "", -1, True)], since=0.5)
    text = summary_text(summarise(_record(engaged=True, result="completed", changes=[])))
    assert re.search(r"mission 'm' on rover: completed in 1\.5 s", text), text


def _track_length(track_csv: Path) -> float:
    with track_csv.open() as fh:
        rows = [(float(r["north"]), float(r["east"])) for r in csv.DictReader(fh)]
    return sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(rows, rows[1:]))


@pytest.mark.timeout(200)
def test_the_sticks_scenario_reports_the_distance_of_its_track_and_is_not_completed(tmp_path: Path,
                                                                                    lcm_url: str) -> None:
    out = tmp_path / "out"
    proc = subprocess.run([*U2SA, "sim", "--vehicle", "examples/ground_vehicle/vehicle.toml", "--scenario",
                           "examples/ground_vehicle/scenarios/sticks.toml", "--out", str(out), "--lcm-url", lcm_url,
                           "--can-port", str(private_udp_port()), "--timeout", "150"],
                          cwd=REPO, capture_output=True, text=True, timeout=200)
    assert proc.returncode == 0, f"u2sa sim failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-2000:]}"
    summary = json.loads((out / "summary.json").read_text())
    driven = _track_length(out / "track.csv")
    assert driven > 0.5, "the pilot's sticks moved the rover"
    assert summary["distance_m"] == pytest.approx(driven, abs=0.02)
    assert summary["result"] == "played" and summary["startup_s"] is None   # by hand: never autonomous
    text = (out / "summary.txt").read_text()
    assert not re.search(r": completed in", text) and "not completed" in text, text
    assert f"distance driven      {summary['distance_m']:.1f} m" in text
