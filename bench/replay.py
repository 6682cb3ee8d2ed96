#!/usr/bin/env python3
"""Replay and recorder benchmark.

1. Replay speed, every device class (the default): records ``--minutes`` (default 10;
   ``--quick``: 1) of ``u2sa sim --record`` driving the example ground vehicle
   (examples/ground_vehicle/vehicle.toml, every driver's record_raw on, as tests/recorded_sim.py
   records one) round its block again and again (a mission of more laps than the time allows, cut by the sim's
   ``--timeout``), so the log holds every device class the replay supports: serial (GPS NMEA,
   compass HDG/XDR), I2C (the MPU-9250's register reads), CAN (the
   ODrive's encoder/heartbeat frames and the setpoints sent), GPIO (the RC receiver's pulse
   edges into the RC mux) and PWM (the pan servo's pulse writes). Then replays it as
   ``u2sa replay LOG --fast --compare`` does (u2sa_hw.hil.replay.Replay, u2sa_hw.hil.compare.compare_logs)
   and prints the log's length, the wall time, the speed-up over real time (aim: 20x, GPIO
   included), the records fed per device and compare's summary line. ``--log FILE`` replays
   an existing recording instead (docs/replay.md, Figures: a 3-minute and a 10-minute log).
   Then the figure a CI job pays: the end-to-end time, start-up included (aim: within 2x of
   the playback), and where it goes, step by step (``phases``, wall s, in order): ``plan``
   (reading the whole log to decide what to replay), ``devices`` (the replay devices and the
   log reads their start needs: the GPIO chip's levels, the I2C reads), ``bus``, ``log read
   while starting`` (what is left of the log reading -- the serial devices' recorded silences
   -- done while the services start), ``services`` (then still waiting for every service's
   health and device), ``discover`` (which channels to republish: one round trip), ``play``,
   ``settle`` (the last outputs: 1 s of quiet after them), ``pilot check (after the settle)``
   (read in the settle), ``capture stop``, ``services stop`` (the launcher waits on each
   child's exit), ``clean-up`` and ``compare`` (``--skip-compare``: the replay alone).
   (The earlier synthetic GPS+compass-only log is gone: the compass driver now groups its
   bursts itself -- drivers/compass/bursts.py -- so its outputs can no longer be built here.)
2. Recorder throughput: a publisher process sends the example ground vehicle's channel mix
   at ``--factor`` (default 10) times its nominal rates for ``--seconds``; the recorder's
   BusCapture in this process writes it to MCAP. Prints the rate achieved, what never reached
   the recorder and what it dropped (its queue overflowing).

Usage: ``python bench/replay.py [--minutes 10 | --quick] [--log FILE] [--keep DIR] [--skip-compare]
[--factor 10] [--seconds 10] [--skip-replay|--skip-recorder]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402
from example_mix import EXAMPLE_RATES  # noqa: E402  (bench/ is the script's directory)



LAP = (("north_gate", 20, 0), ("far_corner", 20, 25), ("east_gate", 0, 25), ("home", 0, 0))
SIM_STARTUP_S = 15.0   # the sim's --timeout counts from its start: the stack's start-up on top of the log wanted
ALL_KINDS = ("serial", "i2c", "can", "gpio", "pwm")


def lap_mission(path: Path, laps: int = 30) -> None:
    """The example mission's block loop *laps* times over (each lap ~45 s at the rover's 2 m/s)."""
    points = "\n".join(f"  <waypoint><name>{name}_{i}</name><reference>Local</reference><x>{x}</x> <y>{y}</y>"
                       f"<threshold>2.0</threshold></waypoint>" for i in range(laps) for name, x, y in LAP)
    path.write_text(f'<?xml version="1.0" encoding="UTF-8"?>\n<mission name="bench laps" loop="false">\n'
                    f"{points}\n</mission>\n")


def record_sim(work: Path, minutes: float) -> Path:
    """``u2sa sim --record`` of the example ground vehicle for *minutes* of driving; the recording's path."""
    mission = work / "mission.xml"
    lap_mission(mission, laps=max(4, int(minutes * 60 / 40) + 2))
    out = work / "sim"
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    env.pop("U2SA_LCM_URL", None)   # u2sa sim picks private ports
    timeout = minutes * 60.0 + SIM_STARTUP_S
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "u2sa_hw.cli", "sim", "--out", str(out), "--record",
                           "--mission", str(mission), "--timeout", f"{timeout:g}"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout + 180)
    files = sorted((out / "recording").glob("*.mcap"))
    # exit 3 (the timeout) is the expected end: the mission has more laps than the time allows
    if not files:
        raise SystemExit(f"u2sa sim --record wrote no log (status {done.returncode}): "
                         f"{done.stdout[-2000:]}{done.stderr[-2000:]}")
    print(f"recorded: u2sa sim --record --timeout {timeout:g} of the example ground vehicle lapping its block "
          f"(status {done.returncode}; 3 = the timeout, expected) in {time.monotonic() - started:.0f} s", flush=True)
    return files[0]


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} cores"


def bench_replay(minutes: float, log: Path | None, keep: Path | None, *, compare: bool = True) -> None:
    """Part 1: a recorded simulation with every device class replayed with --fast, then compared."""
    from u2sa_hw.hil.compare import compare_logs
    from u2sa_hw.hil.replay import Replay, ReplayOptions

    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-replay-"))
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        work = keep
    print(f"before: {_load()}", flush=True)
    if log is None:
        log = record_sim(work, minutes)
    print(f"log: {log} ({log.stat().st_size / 1e6:.1f} MB)", flush=True)
    print(f"replay: {_load()}", flush=True)
    started = time.monotonic()
    replay = Replay(log, ReplayOptions(fast=True, out=work / "replayed.mcap", progress=False))
    result = replay.run()
    total = time.monotonic() - started
    plan = result.plan
    played = plan.duration_s
    speed = played / result.play.wall_s if result.play.wall_s > 0 else 0.0
    print(f"after: {_load()}")
    print(result.summary(fast=True, rate=1.0))
    print(f"log length {played:.1f} s ({played / 60:.1f} min); services replayed: {', '.join(plan.services)}")
    kinds = sorted({d.kind for d in plan.devices.values() if d.service})
    missing = [k for k in ALL_KINDS if k not in kinds]
    print(f"device classes replayed: {', '.join(kinds)}"
          + (f"; MISSING {', '.join(missing)}" if missing else " (every class the replay supports)"))
    print(f"{'DEVICE':10} {'KIND':7} {'SERVICE':9} {'RECORDS':>8}  REPLAY DEVICE'S COUNTS")
    for name, dev in sorted(plan.devices.items()):
        report = result.devices.get(name, {})
        counts = ", ".join(f"{k} {v}" for k, v in report.items() if isinstance(v, int) and not isinstance(v, bool))
        print(f"{name:10} {dev.kind:7} {dev.service or '-':9} {dev.records:>8}  {counts or 'not replayed'}")
    print(f"replay --fast: {played:.0f} s of log in {result.play.wall_s:.1f} s of playback = {speed:.1f}x real time "
          f"(aim >= 20x: {'MET' if speed >= 20 else 'NOT MET'}); {total:.1f} s in all with {result.startup_s:.1f} s "
          f"starting the services and the wait for the last outputs = {played / total:.1f}x end to end; "
          f"{result.play.records} device records fed")
    if not compare:
        print("phases (wall s): " + ", ".join(f"{k} {v:.2f}" for k, v in result.phases.items())
              + f"; replay {total:.2f} s end to end = {total / max(result.play.wall_s, 1e-9):.2f}x the playback "
              "(no compare)")
        if keep is None:
            shutil.rmtree(work, ignore_errors=True)
        return
    compare_started = time.monotonic()
    report = compare_logs(plan.log, result.out, services=set(plan.services), start_ns=plan.start_ns,
                          end_ns=plan.end_ns, rate=None, replay_start_ns=result.play.started_ns or None)
    compare_s = time.monotonic() - compare_started
    phases = {**result.phases, "compare": compare_s}
    print("phases (wall s): " + ", ".join(f"{k} {v:.2f}" for k, v in phases.items())
          + f"; replay {total:.2f} + compare {compare_s:.2f} = {total + compare_s:.2f} s end to end "
          f"= {(total + compare_s) / result.play.wall_s:.2f}x the playback" if result.play.wall_s > 0 else "")
    text = report.format()
    print(text if not report.ok else report.summary())
    if keep is None:
        shutil.rmtree(work, ignore_errors=True)


def publisher(url: str, factor: float, seconds: float) -> None:
    """Child process: publish the example vehicle's mix at *factor* times its rates; print the count sent."""
    from u2sa_hw.bus.transport import Transport

    tx = Transport(url, name="bench-publisher")   # signed, as every u2sa publisher is
    plan = [(ch, rate * factor, b"\x00" * size) for ch, (rate, size) in EXAMPLE_RATES.items()]
    sent = 0
    start = time.monotonic()
    credit = {ch: 0.0 for ch, _, _ in plan}
    tick = 0.002
    while (now := time.monotonic()) - start < seconds:
        for ch, rate, payload in plan:
            due = rate * (now - start) - credit[ch]
            while due >= 1.0:
                tx.publish_bytes(ch, payload)
                credit[ch] += 1.0
                due -= 1.0
                sent += 1
        time.sleep(max(0.0, tick - (time.monotonic() - now)))
    print(sent, flush=True)


def bench_recorder(factor: float, seconds: float) -> None:
    """Part 2: the recorder's capture under the example vehicle's mix times *factor*."""
    from u2sa_hw.services.recorder.capture import BusCapture
    from u2sa_hw.bus.transport import Transport

    nominal = sum(r for r, _ in EXAMPLE_RATES.values())
    url = private_lcm_url(options="ttl=0&recv_buf_size=4194304")
    work = Path(tempfile.mkdtemp(prefix="u2sa-bench-recorder-"))
    transport = Transport(url, name="bench-recorder")
    writer = McapLogWriter(work, path=work / "throughput.mcap", run=RunInfo(vehicle="bench"))
    capture = BusCapture(transport, writer, min_free_mb=50)
    capture.start()
    transport.start()
    child = subprocess.run([sys.executable, __file__, "--publisher", url, str(factor), str(seconds)],
                           capture_output=True, text=True, timeout=seconds + 60, env=dict(os.environ))
    deadline = time.monotonic() + 5.0
    while capture.queue_depth and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    capture.stop()
    transport.stop()
    sent = int(child.stdout.strip() or 0)
    s = capture.stats
    print(f"recorder: example vehicle mix {nominal:.0f} msg/s x {factor:g} = {nominal * factor:.0f} msg/s target "
          f"on {len(EXAMPLE_RATES)} channels for {seconds:g} s")
    print(f"  sent {sent} ({sent / seconds:.0f} msg/s achieved by the publisher); the recorder received {s.received} "
          f"and wrote {s.written} ({s.written / seconds:.0f} msg/s), dropped {s.dropped} (its queue full); "
          f"{sent - s.received} never reached it; file {writer.files[0].stat().st_size / 1e6:.1f} MB")
    shutil.rmtree(work, ignore_errors=True)


def main() -> int:
    """Run the benchmarks."""
    if len(sys.argv) == 5 and sys.argv[1] == "--publisher":
        publisher(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=10.0, help="log length to record (default 10)")
    p.add_argument("--quick", action="store_true", help="a 1-minute log instead")
    p.add_argument("--log", type=Path, help="replay this recording (record_raw on) instead of recording one")
    p.add_argument("--keep", type=Path, help="keep the recording and the replayed log in this directory")
    p.add_argument("--factor", type=float, default=10.0, help="times the example vehicle's rates (default 10)")
    p.add_argument("--seconds", type=float, default=10.0, help="recorder test length (default 10)")
    p.add_argument("--skip-compare", action="store_true", help="replay only (the compare of the two logs is "
                   "a step of its own, as --compare is to u2sa replay)")
    p.add_argument("--skip-replay", action="store_true")
    p.add_argument("--skip-recorder", action="store_true")
    args = p.parse_args()
    use_run_key()
    minutes = 1.0 if args.quick else args.minutes
    if not args.skip_replay:
        bench_replay(minutes, args.log, args.keep, compare=not args.skip_compare)
    if not args.skip_recorder:
        bench_recorder(args.factor, args.seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
