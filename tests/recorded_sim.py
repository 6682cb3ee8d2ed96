"""One short recorded simulation per test session, shared by the tests that read a real run's log.

``u2sa sim --record`` of the example ground vehicle for a few seconds of driving; the first
test that asks runs it, later ones (in any module) reuse its directory under the session's
base temp directory.
"""

from __future__ import annotations

import os
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import REPO, U2SA

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.recording.log_reader import LogFile

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


# What in a service's last recorded Health says the recording machine held it up: then what it published
# depended on that machine's load, which the log does not hold, so its rows are reported, not gated.
HELD_UP = {
    # the simulation scripts no RC signal loss: a live signal loss, a stall of the mux's loop or a timed
    # message left out for being a period behind means the machine held up the mock receiver or the mux
    # (the live mux judged that on its wall clock: docs/replay.md, Determinism)
    "rc": ("stalls", "signal_losses", "timed_skipped"),
    # a sentence that came after its epoch was published (a live pty has no kernel time stamp: the
    # live driver groups by when it read, a replay by the recorded stamps)
    "gps": ("supplements",),
}


EPOCH_GAP_S = 0.05   # the GPS driver's epoch_gap_s in the example profiles
_UTC = re.compile(rb"\$[A-Z]{2}(?:GGA|RMC|GST|ZDA|GLL|GNS),(\d{6}(?:\.\d*)?),")


def split_reads(log: Path, device: str = "gps") -> int:
    """How often the live *device* driver read one epoch in two parts more than EPOCH_GAP_S apart: a chunk that
    continues the previous chunk's epoch (no time of its own before a sentence of that time, or the same time)
    stamped that long after it. The live driver was held up between the two reads (the bytes waited in the
    pty: no silence), which the log shows only as the gap, so a replay judges a silence there and publishes the
    epoch in two parts (issue 24: the first fix of a recording whose GPS driver was held up as it started).
    0 for a log that records the live port's silences (RX records without data): its replay sees those only."""
    count, last_stamp, last_utc = 0, None, None
    for m in LogFile(log).messages(f"RAW.{device}"):
        raw = t.RawSerial.decode(m.data)
        if raw.direction != 0:
            continue
        data = bytes(raw.data)
        if not data:
            return 0
        first = _UTC.search(data)
        continues = not data.startswith(b"$") or first is None or first.start() > 0 or first.group(1) == last_utc
        if last_stamp is not None and continues and (raw.header.timestamp_us - last_stamp) / 1e6 >= EPOCH_GAP_S:
            count += 1
        times = _UTC.findall(data)
        last_utc = times[-1] if times else last_utc
        last_stamp = raw.header.timestamp_us
    return count


def held_up(log: Path) -> dict[str, str]:
    """``{service: why}`` for the services whose live output depended on the recording machine's load."""
    last: dict[str, dict[str, str]] = {}
    for m in LogFile(log).messages(ch.HEALTH):
        msg = t.Health.decode(m.data)
        if msg.name in HELD_UP:
            last[msg.name] = {kv.key: kv.value for kv in msg.details}
    reasons = {name: ", ".join(f"{key} {last[name][key]}" for key in keys
                               if last.get(name, {}).get(key, "0") not in ("0", ""))
               for name, keys in HELD_UP.items()}
    split = split_reads(log)
    if split:
        reasons["gps"] = ", ".join(filter(None, (reasons.get("gps"), f"an epoch read in two parts {split}x")))
    return {name: why for name, why in reasons.items() if why}
