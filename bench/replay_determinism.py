#!/usr/bin/env python3
"""Replay determinism under load: N ``--fast`` replays of one recorded simulation while busy
processes keep every core loaded, each checked against the recording (as ``u2sa replay --fast
--compare`` does) and against an idle replay, message by message.

The log (``--log FILE``, else ``u2sa sim --record`` of the example ground vehicle for
``--seconds``, 25 by default, as tests/recorded_sim.py records one) holds every device class:
GPS and compass (serial), the IMU (I2C), the wheels (CAN), the pan servo (PWM) and the RC mux
(GPIO, with the pilot's switch to autonomous). One replay on the idle machine is the reference;
then ``--runs`` (default 10) replays run while ``--workers`` busy processes (default: one per
core, as bench/cpu_hog.py) compete with them. For each the script prints what ``--compare``
says against the recording and whether every message of every replayed stream (RC_MODE,
MANUAL_CMD and the RC mux's enable writes included, every field but the header's time and
sequence) is the reference's. The issue 14 aim: every replay the same and clean.

Usage: ``python bench/replay_determinism.py [--runs 10] [--workers N] [--log FILE | --seconds 25] [--keep DIR]``
Exit status 0 when every replay is the same and clean, 1 otherwise.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.hil.stream_align import first_difference  # noqa: E402
from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402


def burn() -> None:
    """Spin until killed (as bench/cpu_hog.py's hogs: same priority as the replay)."""
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0xFFFFFFFF


def record(work: Path, seconds: float) -> Path:
    """``u2sa sim --record`` of the example ground vehicle; the recording's path."""
    out = work / "sim"
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    env.pop("U2SA_LCM_URL", None)   # u2sa sim picks private ports
    done = subprocess.run([sys.executable, "-m", "u2sa_hw.cli", "sim", "--out", str(out), "--record", "--timeout",
                           f"{seconds:g}"], cwd=REPO, env=env, capture_output=True, text=True, timeout=seconds + 180)
    files = sorted((out / "recording").glob("*.mcap"))
    if not files:
        raise SystemExit(f"u2sa sim --record wrote no log (status {done.returncode}): {done.stdout[-2000:]}"
                         f"{done.stderr[-2000:]}")
    return files[0]


def replay(log: Path, out: Path) -> tuple[dict[str, list[tuple[str, dict[str, Any]]]], Any, float]:
    """One --fast replay: its streams (type, fields), compare's report against the recording, the wall time."""
    from u2sa_hw.hil.compare import compare_logs, load_streams
    from u2sa_hw.hil.replay import Replay, ReplayOptions

    started = time.monotonic()
    result = Replay(log, ReplayOptions(fast=True, out=out, progress=False)).run()
    took = time.monotonic() - started
    plan = result.plan
    services = set(plan.services)
    report = compare_logs(plan.log, result.out, services=services, start_ns=plan.start_ns, end_ns=plan.end_ns,
                          rate=None)
    streams = load_streams(out, sources=services)
    return {k: [(s.type_name, s.fields) for s in v] for k, v in streams.items()}, report, took


def main() -> int:
    """Record (or take) a log, replay it idle once and --runs times under the hogs; print and judge."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=10, help="replays under the hogs (default 10)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 2, help="busy processes (default: one per core)")
    p.add_argument("--log", type=Path, help="replay this recording (record_raw on) instead of recording one")
    p.add_argument("--seconds", type=float, default=25.0, help="simulation to record (default 25 s)")
    p.add_argument("--keep", type=Path, help="keep the recording and the replays in this directory")
    args = p.parse_args()
    use_run_key()
    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-determinism-")) if args.keep is None else args.keep
    work.mkdir(parents=True, exist_ok=True)
    try:
        log = args.log or record(work, args.seconds)
        print(f"log: {log} ({log.stat().st_size / 1e6:.1f} MB)", flush=True)
        reference, report, took = replay(log, work / "idle.mcap")
        counts = ", ".join(f"{k} {len(v)}" for k, v in sorted(reference.items()))
        print(f"idle     {took:5.1f} s  {report.summary()}\n         messages: {counts}", flush=True)
        clean = report.ok
        same = 0
        hogs = [multiprocessing.get_context("fork").Process(target=burn, daemon=True) for _ in range(args.workers)]
        for h in hogs:
            h.start()
        try:
            for i in range(args.runs):
                got, report, took = replay(log, work / f"loaded-{i}.mcap")
                diff = first_difference(reference, got)
                same += not diff
                clean &= report.ok
                print(f"hog {i + 1:2d}   {took:5.1f} s  {'same' if not diff else 'DIFFERENT: ' + diff}; "
                      f"{report.summary()}", flush=True)
        finally:
            load = os.getloadavg()
            for h in hogs:
                h.terminate()
            for h in hogs:
                h.join(timeout=5)
        print(f"replay determinism: {same} of {args.runs} replays under {args.workers} busy processes (load "
              f"{load[0]:.1f}) gave the idle replay's messages; --compare against the recording "
              f"{'clean every time' if clean else 'NOT clean every time'}")
        return 0 if same == args.runs and clean else 1
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
