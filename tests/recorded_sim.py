"""One short recorded simulation per test session, shared by the tests that read a real run's log.

``u2sa sim --record`` of the example ground vehicle for a few seconds of driving; the first
test that asks runs it, later ones (in any module) reuse its directory under the session's
base temp directory.
"""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import REPO, U2SA

SIM_TIMEOUT_S = "25"   # the rover engages autonomy a few seconds in; the run ends (status 3) at this timeout


@dataclass(frozen=True)
class RecordedSim:
    """The run's directory, its recording and its service logs."""

    out: Path
    log: Path
    logs: Path


def recorded_sim(factory: pytest.TempPathFactory) -> RecordedSim:
    """The session's recorded simulation, run on first use."""
    out = factory.getbasetemp() / "recorded-sim"
    files = sorted((out / "recording").glob("*.mcap"))
    if not files:
        env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
        env.pop("U2SA_LCM_URL", None)   # u2sa sim picks private ports
        done = subprocess.run([*U2SA, "sim", "--out", str(out), "--record", "--timeout", SIM_TIMEOUT_S], cwd=REPO,
                              env=env, capture_output=True, text=True, timeout=180)
        files = sorted((out / "recording").glob("*.mcap"))
        assert files, f"u2sa sim --record wrote no log (status {done.returncode}): {done.stdout[-2000:]}{done.stderr[-2000:]}"
    return RecordedSim(out, files[0], out / "logs")
