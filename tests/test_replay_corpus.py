"""Issue 24's gate on unchanged logs: a corpus of recordings of varied runs, built here by the project's own
commands (tests/replay_corpus.py: both example vehicles and the boat, the sticks scenario, an RC loss, a GPS
fix loss, a manual switch, a driver killed and restarted mid-recording, recordings started while the stack
runs (one as it comes up, one cut by SIGKILL and recovered, one under autonomy), and ``u2sa record`` of a ``u2sa mock`` + ``u2sa run`` stack), every
one replayed by ``u2sa replay-check`` with its defaults: each is "same", first and last messages included.

A recording begun after a driver set its I2C chip up cannot reproduce what that driver did (its
identification and calibration are before the cut), nor one begun with the RC mux armed in autonomous mode
(the pilot armed it before the cut): the replay leaves that service out and says so in a note, which is
checked here too (the one started under autonomy is such a log). ``bench/replay_corpus.py`` runs the same check under ``bench/cpu_hog.py``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO
from replay_corpus import build_corpus

from u2sa_hw.drivers.imu.bno055 import Bno055ImuDriver
from u2sa_hw.drivers.imu.mpu9250 import Mpu9250ImuDriver
from u2sa_hw.hil.replay_cut import autonomy_armed_at_start, i2c_setup_recorded
from u2sa_hw.recording.log_reader import LogFile

U2SA = [sys.executable, "-m", "u2sa_hw.cli"]
KINDS = {"ground-sim", "ackermann-sim", "boat-sim", "sticks", "rc-loss", "gps-fix-loss", "manual-switch",
         "restart", "mid-run", "killed-recovered", "mid-drive", "mock-run"}
MID_RUN = {"mid-run", "killed-recovered", "mid-drive"}   # recordings started while the stack ran


@pytest.fixture(scope="module")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return build_corpus(tmp_path_factory.mktemp("corpus") / "logs")


def replay_check(directory: Path, cwd: Path) -> tuple[subprocess.CompletedProcess, dict[str, dict]]:
    done = subprocess.run([*U2SA, "replay-check", str(directory), "--json"], cwd=cwd, capture_output=True, text=True,
                          timeout=900, env={**os.environ, "PYTHONPATH": str(REPO)})
    return done, {Path(r["log"]).stem: r for r in json.loads(done.stdout)}


@pytest.mark.timeout(1200)   # the corpus fixture builds twelve recordings first (about a minute on 2 quiet cores)
def test_every_recording_of_the_corpus_replays_same(corpus: dict[str, Path], tmp_path: Path) -> None:
    assert set(corpus) == KINDS and len(corpus) >= 10
    logs = next(iter(corpus.values())).parent
    done, results = replay_check(logs, tmp_path)
    assert set(results) == KINDS, done.stderr
    unclean = {name: (r["status"], r["summary"]) for name, r in results.items() if r["status"] != "same"}
    assert not unclean, f"{unclean}\n{done.stderr[-4000:]}"
    assert done.returncode == 0, done.stderr[-2000:]
    noted = set()
    for name, r in results.items():
        streams = r["report"]["streams"]
        assert streams and all(s["inserted"] == s["deleted"] == s["different"] == 0 for s in streams), (name, streams)
        # a log begun after the IMU's set-up leaves it out, and says so; every other log replays it
        if any("set its chip up" in n for n in r["notes"]):
            noted.add(name)
        driver = Bno055ImuDriver if name == "boat-sim" else Mpu9250ImuDriver   # the boat's IMU is a BNO055
        whole = i2c_setup_recorded(LogFile(corpus[name]), "imu", identity_register=driver.IDENTITY_REGISTER)
        assert (name in noted) == (not whole), (name, r["notes"])
        # a log begun with the RC mux armed in autonomous mode leaves the mux out, and says so (the actuators get
        # its recorded RC_MODE); the one started under autonomy is such a log
        armed = autonomy_armed_at_start(LogFile(corpus[name]), "rc", start_ns=0)
        assert any("armed in autonomous mode" in n for n in r["notes"]) == armed, (name, r["notes"])
        assert armed == (name == "mid-drive"), name
    # only the recorders started while the stack drove can begin after the IMU's set-up (on a loaded machine
    # they may start before it: then nothing is left out, and the rule above says so)
    assert noted <= MID_RUN, noted
    assert done.stderr.count(": same in ") == len(KINDS), done.stderr   # the progress line of each
