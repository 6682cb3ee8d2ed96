"""``u2sa replay-check DIR``: replay every log in a directory against the current code and compare (a CI gate)."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HELP = """\
Replay every MCAP log in DIR (and its subdirectories with --recursive) against the drivers
of this checkout, as `u2sa replay LOG --fast --compare` does, one log after the other: a
progress line per log, then one summary table. Use it as a regression gate on a team's own
field logs (docs/replay.md has a sample CI job): record with record_raw = true, keep the
logs that matter in a directory, run this on every change.

What a replay cannot reproduce is a note under the log's line (and in --json), not a
difference: an I2C driver left out of a log that began after it set its chip up, and what
differs where the recording machine held the RC mux up (docs/replay.md, the corpus).

Each log's recorded pilot messages (RC_MODE, MANUAL_CMD) are checked with the pilot's public
key the log names, as u2sa replay does: a message that fails the check makes the log DIFFERENT.

Logs recorded without a vehicle profile (u2sa record without --vehicle) carry no
vehicle.toml: give the profile with --vehicle FILE, used for every log of the run (as
u2sa replay --vehicle does for one).

Exit status: 0 when every log replayed and matched; 1 when a comparison found a difference;
2 when a log could not be replayed (damaged, no raw device channels, no profile, a driver
that never opened its device, or any other error, reported as that log's result) or DIR
holds no logs. Every log is tried whatever the others did.
"""

EPILOG = """\
examples:
  u2sa replay-check field-logs/                      all logs, --fast, default tolerances
  u2sa replay-check field-logs/ --tolerances tol.toml --json > report.json
  u2sa replay-check field-logs/ --services estimator --keep-outputs out/
  u2sa replay-check bench-logs/ --vehicle rover/vehicle.toml   logs recorded without a profile
"""


@dataclass
class LogResult:
    """One log's outcome."""

    log: Path
    status: str            # "same", "DIFFERENT", "FAILED"
    seconds: float
    duration_s: float = 0.0
    summary: str = ""
    report: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)   # what the replay left out, and why (the plan's notes)


def register(sub: Any) -> None:
    """Add ``replay-check``."""
    p = sub.add_parser("replay-check", help="replay every log in a directory against this code and compare (CI gate)",
                       description=HELP, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dir", help="a directory of MCAP logs recorded with record_raw = true")
    p.add_argument("--recursive", action="store_true", help="also logs in subdirectories")
    p.add_argument("--rate", type=float, default=None, metavar="X",
                   help="play at X times real time and check timing too (default: --fast, no clock)")
    p.add_argument("--vehicle", metavar="FILE", help="the vehicle profile for every log, instead of the one each "
                   "log carries (needed for logs recorded without one)")
    p.add_argument("--services", nargs="+", default=[], metavar="NAME",
                   help="also run these services of each log's profile (e.g. estimator)")
    p.add_argument("--tolerance", type=float, default=1e-6, metavar="D", help="float difference allowed (default 1e-6)")
    p.add_argument("--tolerances", metavar="FILE", help="per-field tolerances (TOML, see u2sa replay --help)")
    p.add_argument("--time-tolerance", type=float, default=0.5, metavar="S", help="with --rate (default 0.5 s)")
    p.add_argument("--edge", type=int, default=1, metavar="N",
                   help="unmatched messages allowed at each end of a stream (default 1)")
    p.add_argument("--ignore", action="append", default=[], metavar="GLOB", help="fields not compared (repeatable)")
    p.add_argument("--keep-outputs", metavar="DIR", help="write each replayed log here (default: a temporary directory)")
    p.add_argument("--json", action="store_true", help="print the results as JSON on stdout (progress stays on stderr)")
    p.set_defaults(func=cmd_replay_check)


def find_logs(directory: Path, *, recursive: bool) -> list[Path]:
    """The ``.mcap`` files in *directory*, sorted; replayed outputs (``*.replay.mcap``) left out."""
    pattern = "**/*.mcap" if recursive else "*.mcap"
    return sorted(p for p in directory.glob(pattern) if p.is_file() and not p.name.endswith(".replay.mcap"))


def check_one(log: Path, out: Path, args: Any, tolerances: Any) -> LogResult:
    """Replay and compare one log; never raises: whatever goes wrong is this log's FAILED result."""
    began = time.monotonic()
    try:
        return _replay_and_compare(log, out, args, tolerances, began)
    except Exception as exc:  # noqa: BLE001 - one log's failure, of any kind, must not stop the gate
        from u2sa_hw.hil.replay_plan import ReplayError

        expected = isinstance(exc, (ReplayError, RuntimeError, OSError, ValueError))
        first = (str(exc).splitlines() or [""])[0]
        why = first if expected and first else f"unexpected {type(exc).__name__}: {first}"
        return LogResult(log, "FAILED", time.monotonic() - began, summary=why)


def _replay_and_compare(log: Path, out: Path, args: Any, tolerances: Any, began: float) -> LogResult:
    from u2sa_hw.hil.compare import compare_logs
    from u2sa_hw.hil.replay import Replay, ReplayOptions

    fast = args.rate is None
    replay = Replay(log, ReplayOptions(rate=args.rate or 1.0, fast=fast, services=args.services, out=out,
                                       vehicle=Path(args.vehicle) if args.vehicle else None, progress=False))
    result = replay.run()
    report = compare_logs(result.plan.log, result.out, services=set(result.plan.services),
                          start_ns=result.plan.start_ns, end_ns=result.plan.end_ns,
                          rate=None if fast else args.rate, tolerance=tolerances, edge=args.edge,
                          time_tolerance_s=args.time_tolerance, ignore=tuple(args.ignore),
                          replay_start_ns=result.play.started_ns or None, pilot=result.pilot,
                          held=result.plan.held_windows())
    duration = (result.plan.end_ns - result.plan.start_ns) / 1e9 if result.plan.end_ns else 0.0
    return LogResult(log, "same" if report.ok else "DIFFERENT", time.monotonic() - began, duration,
                     report.summary(), report.to_dict(), list(result.plan.notes))


def summary_table(results: list[LogResult], root: Path) -> str:
    """One row per log and a total line."""
    lines = [f"{'LOG':40} {'LENGTH s':>8} {'TOOK s':>7} {'STREAMS':>7} {'DIFFER':>6} {'INS':>4} {'DEL':>4}  RESULT"]
    for r in results:
        streams = (r.report or {}).get("streams", [])
        name = str(r.log.relative_to(root)) if r.log.is_relative_to(root) else str(r.log)
        lines.append(f"{name[-40:]:40} {r.duration_s:>8.1f} {r.seconds:>7.1f} {len(streams):>7} "
                     f"{sum(s['different'] for s in streams):>6} {sum(s['inserted'] for s in streams):>4} "
                     f"{sum(s['deleted'] for s in streams):>4}  {r.status}")
    counts = {k: sum(r.status == k for r in results) for k in ("same", "DIFFERENT", "FAILED")}
    lines.append(f"replay-check: {len(results)} logs: {counts['same']} same, {counts['DIFFERENT']} different, "
                 f"{counts['FAILED']} could not be replayed")
    return "\n".join(lines)


def cmd_replay_check(args: Any) -> int:
    """Run the gate; exit 0 all same, 1 a difference, 2 a log that could not be replayed (or none found)."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.cli.replay_cmd import load_tolerances

    root = Path(args.dir)
    if not root.is_dir():
        raise CliError(f"{root}: not a directory (give the directory that holds the .mcap logs)", 2)
    if args.rate is not None and args.rate <= 0:
        raise CliError(f"--rate must be > 0, got {args.rate:g}", 2)
    if args.vehicle and not Path(args.vehicle).is_file():
        raise CliError(f"{args.vehicle}: no such file (--vehicle names a vehicle profile, vehicle.toml)", 2)
    tolerances = load_tolerances(args)
    logs = find_logs(root, recursive=args.recursive)
    if not logs:
        raise CliError(f"{root}: no .mcap logs{'' if args.recursive else ' (use --recursive for subdirectories)'}", 2)
    keep = Path(args.keep_outputs) if args.keep_outputs else None
    results: list[LogResult] = []
    with tempfile.TemporaryDirectory(prefix="u2sa-replay-check-") as tmp:
        out_dir = keep or Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        for n, log in enumerate(logs, 1):
            print(f"[{n}/{len(logs)}] {log}: replaying ...", file=sys.stderr, flush=True)
            r = check_one(log, out_dir / f"{n:03d}-{log.stem}.replay.mcap", args, tolerances)
            results.append(r)
            print(f"[{n}/{len(logs)}] {log}: {r.status} in {r.seconds:.1f} s: {r.summary}", file=sys.stderr, flush=True)
            for note in r.notes:
                print(f"    note: {note}", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps([{"log": str(r.log), "status": r.status, "seconds": round(r.seconds, 3),
                           "duration_s": r.duration_s, "summary": r.summary, "notes": r.notes, "report": r.report} for r in results],
                         indent=1))
    else:
        print(summary_table(results, root))
    if any(r.status == "FAILED" for r in results):
        return 2
    return 1 if any(r.status == "DIFFERENT" for r in results) else 0
