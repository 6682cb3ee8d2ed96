"""Failsafe benchmark: time from each scripted event to every actuator output neutral.

``python bench/failsafe.py [--runs 3] [--case rc_loss ...]`` plays each case's scenario
(``u2sa sim --scenario``, a real run: every service a process, the mock devices in the sim
process) ``--runs`` times and prints, per event kind, the time from the event to every
actuator output that was moving at the event being neutral, measured on the outputs as the
mock devices saw them (the CAN setpoint the ODrive/VESC node applied, the PWM pulse of the
PCA9685 or sysfs chip, the GPIO level): min / median / max over every such event of every
run, against the target where the project has one (issue 10: RC loss <= 200 ms, manual
switch <= 50 ms, GPS fix loss <= 2 s, a lost check <= 1 s; issue 26: a geofence breach <= 1 s,
timed from the true track leaving the fence, sampled at 10 Hz, so the estimator's lag is in it). An event whose outputs never went
neutral before the next event counts as a miss and is listed.

Each run's summary.json stays under ``--out`` (default ``bench-out/failsafe``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port  # noqa: E402


@dataclass(frozen=True)
class Measure:
    """Which events of a case are timed, and the target for their median (ms, None: no target)."""

    label: str
    action: str
    match: str = ""             # a substring of the event's description ("" = every event of the action)
    target_ms: float | None = None
    from_breach: bool = False   # time from the true track leaving the geofence (summary "geofence"), not the event


@dataclass(frozen=True)
class Case:
    """A scenario file on a vehicle, and what to time in it."""

    name: str
    vehicle: str
    scenario: str
    measures: tuple[Measure, ...]


GROUND = "examples/ground_vehicle/vehicle.toml"
CAR = "examples/ackermann_rover/vehicle.toml"
CASES = (
    Case("rc_loss", GROUND, "examples/ground_vehicle/scenarios/rc_loss.toml",
         (Measure("RC loss -> all neutral (CAN wheels)", "rc_loss", target_ms=200.0),)),
    Case("manual_switch", GROUND, "examples/ground_vehicle/scenarios/manual_switch.toml",
         (Measure("manual switch -> autonomous outputs stopped (CAN wheels)", "mode", "manual", target_ms=50.0),)),
    Case("failsafe", GROUND, "examples/ground_vehicle/scenarios/failsafe.toml",
         (Measure("operator failsafe -> all neutral", "failsafe", "active=True"),)),
    Case("gps_fix_loss", GROUND, "examples/ground_vehicle/scenarios/gps_fix_loss.toml",
         (Measure("GPS fix lost -> all neutral", "gps_fix", "fix=False", target_ms=2000.0),)),
    Case("service_kill", GROUND, "examples/ground_vehicle/scenarios/service_kill.toml",
         (Measure("control SIGSTOP -> all neutral (dead-man)", "signal", "service=control signal=STOP"),
          Measure("rc SIGSTOP -> all neutral (stale RC_MODE)", "signal", "service=rc signal=STOP", target_ms=1000.0),
          Measure("wheels driver SIGKILL -> all neutral (ODrive watchdog)", "signal", "service=wheels signal=KILL"))),
    Case("geofence", GROUND, "examples/ground_vehicle/scenarios/geofence.toml",
         (Measure("true track across the geofence -> all neutral (10 Hz samples)", "push", "east_mps=-3.5",
                  target_ms=1000.0, from_breach=True),)),
    Case("ackermann", CAR, "examples/ackermann_rover/scenarios/manual_takeover.toml",
         (Measure("car: manual switch -> pilot's pulses (hardware mux)", "mode", "manual", target_ms=50.0),
          Measure("car: RC loss -> no pulse (hardware mux)", "rc_loss", target_ms=200.0))),
)


def play(case: Case, out: Path) -> dict[str, Any]:
    """One ``u2sa sim --scenario`` run on a bus and CAN port of its own; its summary."""
    lcm_url = private_lcm_url()
    cmd = [sys.executable, "-m", "u2sa_hw.cli", "sim", "--vehicle", case.vehicle, "--scenario", case.scenario,
           "--out", str(out), "--lcm-url", lcm_url, "--can-port", str(private_udp_port()), "--timeout", "150"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    summary_path = out / "summary.json"
    if not summary_path.exists():
        raise SystemExit(f"bench/failsafe.py: {case.name}: u2sa sim wrote no summary (exit {proc.returncode}):\n"
                         f"{proc.stderr[-2000:]}")
    summary = json.loads(summary_path.read_text())
    if summary["result"] not in ("completed", "played"):   # played: the scenario ran to its end
        print(f"  ! {case.name}: run {summary['result']}: {summary['reason']}", flush=True)
    return summary


def timings(summary: dict[str, Any], measure: Measure) -> tuple[list[float], int]:
    """The all-neutral times (ms) of the events *measure* selects, and how many never went neutral."""
    times, misses = [], 0
    for event in summary.get("scenario", {}).get("events", []):
        if event["action"] != measure.action or measure.match not in event["event"]:
            continue
        if event["all_neutral_after_ms"] is None:
            misses += 1
        elif measure.from_breach:
            # both on the scenario's clock (t0: autonomy engaged); the true track is sampled at the sim's 10 Hz,
            # and the time includes the estimator's lag behind the truth (what the vehicle can know)
            out = next(iter((summary.get("geofence") or {}).get("breaches", [])), None)
            if out is None:
                misses += 1
            else:
                times.append(round(event["fired_s"] * 1000.0 + event["all_neutral_after_ms"] - out["at_s"] * 1000.0, 1))
        elif event["all_neutral_after_ms"] > 0 or any(not o["at_event"]["neutral"] for o in event["outputs"].values()):
            times.append(event["all_neutral_after_ms"])
        else:
            misses += 1   # nothing was moving at the event: not a measurement
    return times, misses


def report(measure: Measure, times: list[float], misses: int) -> str:
    """One line: label, n, min / median / max, the target and whether the median meets it."""
    if not times:
        return f"{measure.label:58} no measurement ({misses} events without a moving output or never neutral)"
    median = statistics.median(times)
    verdict = "" if measure.target_ms is None else (
        f"  target <= {measure.target_ms:g}: {'ok' if median <= measure.target_ms else 'MISSED'}")
    miss = f", {misses} never neutral" if misses else ""
    return (f"{measure.label:58} n={len(times):2d}  min {min(times):7.1f}  median {median:7.1f}  "
            f"max {max(times):7.1f} ms{miss}{verdict}")


def main(argv: list[str] | None = None) -> int:
    """Run the cases and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="runs per case (default 3)")
    parser.add_argument("--case", action="append", choices=[c.name for c in CASES],
                        help="only this case (repeatable; default: all)")
    parser.add_argument("--out", type=Path, default=REPO / "bench-out" / "failsafe")
    args = parser.parse_args(argv)
    cases = [c for c in CASES if not args.case or c.name in args.case]
    results: dict[str, tuple[list[float], int]] = {}
    for case in cases:
        for run in range(args.runs):
            started = time.monotonic()
            summary = play(case, args.out / f"{case.name}-{run + 1}")
            print(f"{case.name} run {run + 1}/{args.runs}: {summary['result']} in {time.monotonic() - started:.0f} s",
                  flush=True)
            for measure in case.measures:
                times, misses = timings(summary, measure)
                previous = results.get(measure.label, ([], 0))
                results[measure.label] = (previous[0] + times, previous[1] + misses)
    print(f"\ntime from the event to every moving actuator output neutral, on the outputs ({args.runs} runs each):")
    for case in cases:
        for measure in case.measures:
            print("  " + report(measure, *results[measure.label]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
