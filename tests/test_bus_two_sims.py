"""Two ``u2sa sim`` runs at once on one machine both complete (issue 11: stacks kept apart).

Real processes: each run picks a free private LCM port and CAN port and a fresh key of its
own, and prints them; neither is told a port. A short mission (one waypoint 4 m ahead)
keeps the pair quick; the timeouts are generous, nothing asserts a duration.

Both completing would not prove the stacks stayed apart (the audit's mixed stacks printed
each other's goals): each run flies a mission of its own, one waypoint of a name the other
does not have, and only its own appears in its output and its summary. Neither launcher nor
HSM restarted anything (the summary's restarts count the HSM's too: it restarts through the
launcher), and no service logged a dropped message of another vehicle signed with its key
(``foreign``). Forged packets are not asserted absent: a third party on this machine could send them.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
from conftest import REPO, U2SA

MISSION = """<?xml version="1.0" encoding="UTF-8"?>
<mission name="{name} run" loop="false">
  <waypoint><name>{name}_point</name><reference>Local</reference><x>4</x> <y>0</y><threshold>2.0</threshold></waypoint>
</mission>
"""
RUNS = ("alpha", "bravo")   # each run's own waypoint, alpha_point and bravo_point: neither name is in the other
VEHICLE = "examples/boat/vehicle.toml"   # any example would do
BUS_LINE = re.compile(r"u2sa sim: bus (\S+), CAN port (\d+), key (\S+) ")


@pytest.mark.timeout(400)
def test_two_sims_at_once_each_on_its_own_bus_both_complete(tmp_path: Path) -> None:
    runs = []
    for name in RUNS:
        mission = tmp_path / f"{name}.xml"
        mission.write_text(MISSION.format(name=name))
        runs.append(subprocess.Popen([*U2SA, "sim", "--vehicle", VEHICLE, "--mission", str(mission),
                                      "--out", str(tmp_path / name), "--timeout", "200"],   # no port given: each picks
                                     cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
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
    for name, other, (stdout, stderr) in ((RUNS[0], RUNS[1], outputs[0]), (RUNS[1], RUNS[0], outputs[1])):
        out = tmp_path / name
        assert f"goal 1/1 {name}_point reached" in stdout, stdout[-3000:]
        assert f"{other}_point" not in stdout + stderr, f"run {name} printed run {other}'s goal:\n{stdout[-3000:]}"
        summary = json.loads((out / "summary.json").read_text())
        assert summary["result"] == "completed", summary
        assert [g["uid"] for g in summary["goals"]] == [f"{name}_point"], summary["goals"]
        assert [a["uid"] for a in summary["arrivals"]] == [f"{name}_point"], summary["arrivals"]
        restarted = {s: v["restarts"] for s, v in summary["services"].items() if v["restarts"]}
        assert restarted == {}, f"run {name}: the launcher restarted {restarted}"
        hsm = (out / "logs" / "hsm.log").read_text()
        assert "restarting " not in hsm, hsm[-3000:]      # the HSM restarted nothing (it would through the launcher)
        foreign = [line for log in sorted((out / "logs").glob("*.log")) for line in log.read_text().splitlines()
                   if "dropping foreign message" in line]
        assert foreign == [], foreign
