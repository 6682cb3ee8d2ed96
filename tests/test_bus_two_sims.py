"""Two ``u2sa sim`` runs at once on one machine both complete (issue 11: stacks kept apart).

Real processes: each run picks a free private LCM port and CAN port and a fresh key of its
own, and prints them; neither is told a port. A short mission (one waypoint 4 m ahead)
keeps the pair quick; the timeouts are generous, nothing asserts a duration.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
from conftest import REPO, U2SA

MISSION = """<?xml version="1.0" encoding="UTF-8"?>
<mission name="a few metres" loop="false">
  <waypoint><name>ahead</name><reference>Local</reference><x>4</x> <y>0</y><threshold>2.0</threshold></waypoint>
</mission>
"""
VEHICLE = "examples/boat/vehicle.toml"   # any example would do
BUS_LINE = re.compile(r"u2sa sim: bus (\S+), CAN port (\d+), key (\S+) ")


@pytest.mark.timeout(400)
def test_two_sims_at_once_each_on_its_own_bus_both_complete(tmp_path: Path) -> None:
    mission = tmp_path / "short.xml"
    mission.write_text(MISSION)
    runs = [subprocess.Popen([*U2SA, "sim", "--vehicle", VEHICLE, "--mission", str(mission),
                              "--out", str(tmp_path / f"out{i}"), "--timeout", "200"],   # no port given: each picks
                             cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in (1, 2)]
    outputs = []
    try:
        for proc in runs:
            outputs.append(proc.communicate(timeout=330))
    finally:
        for proc in runs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    for proc, (stdout, stderr) in zip(runs, outputs):
        assert proc.returncode == 0, f"u2sa sim failed:\n{stdout[-3000:]}\n{stderr[-3000:]}"
    buses = [BUS_LINE.search(stdout) for stdout, _ in outputs]
    assert all(buses), [o[0][:500] for o in outputs]
    (url1, can1, key1), (url2, can2, key2) = (b.groups() for b in buses)  # type: ignore[union-attr]
    assert url1 != url2 and can1 != can2 and key1 != key2
    for i in (1, 2):
        summary = json.loads((tmp_path / f"out{i}" / "summary.json").read_text())
        assert summary["result"] == "completed" and [g["uid"] for g in summary["goals"]] == ["ahead"], summary
