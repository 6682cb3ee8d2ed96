"""``u2sa replay``: run the real drivers against mock devices fed from a log (hil/, imported lazily)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

REPLAY_HELP = """\
Replay a log against mock devices: every RAW.<device> channel in the log gets a mock
device at a private address, the service that names the device (by its name, its
device_name or a channels entry) runs as a real process on a private LCM bus with the
log's own config, the recorded bytes/frames/register reads/edges are played into the
mocks with the original timing, and what the services publish is recorded to --out.
--compare then checks the replayed outputs against the recorded ones.

Every recorded pilot message (RC_MODE, MANUAL_CMD) of the replayed window is checked with
the pilot's public key the log names: "pilot messages: 412 checked with the recorded pilot
key 3ec94b6c, all signed", or how many fail (with --compare a failure is a difference), or
a note when the log has no pilot signatures (recorded before they existed, or on an open bus).

Exit status: 0 when the replay ran (and, with --compare, nothing differs); 1 when
--compare found a difference; 2 when the replay could not run or failed (a damaged or
unreplayable log, a bad option or --set, a service that died or never opened its device).
"""

EPILOG = """\
examples:
  u2sa replay run1.mcap --fast --compare            regression check of the drivers
  u2sa replay run1.mcap --set gps.uere_m=5 --compare    what does this setting change?
  u2sa replay run1.mcap --rate 2 --start 60 --end 120 --services estimator
  u2sa replay rc.mcap --compare --set rc.autonomous_above_us=1900    (GPIO: RC pulses, e-stops)

Devices replayed: serial (bytes into a pty), I2C (register reads answered), CAN (frames
onto a private bus), GPIO (edges on a mock chip, with their recorded spacing) and PWM
(a sysfs-shaped directory or a mock PCA9685; the driver's recorded commands are played
on the bus and its pulse writes compared). --fast plays each device as fast as its
driver reads (no clock; silences are not reproduced); GPIO edges carry their recorded
kernel timestamps and the GPIO drivers judge time by them, so GPIO logs play at any speed.
See docs/replay.md for what each mode means for each driver.
"""


def register(sub: Any) -> None:
    """Add ``replay``."""
    p = sub.add_parser("replay", help="replay a log's raw device I/O into the real drivers and record them",
                       description=REPLAY_HELP, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", help="an MCAP log recorded with record_raw = true in the driver configs")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=float, default=1.0, metavar="X", help="play X times real time (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as the drivers take their input (GPIO included)")
    p.add_argument("--start", type=float, default=0.0, metavar="S", help="begin S seconds into the log")
    p.add_argument("--end", type=float, default=None, metavar="S", help="stop S seconds into the log")
    p.add_argument("--services", nargs="+", default=[], metavar="NAME",
                   help="also run these services of the log's profile (e.g. estimator)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SERVICE.FIELD=VALUE",
                   help="change a config field for the replay (repeatable), e.g. --set gps.uere_m=5")
    p.add_argument("-o", "--out", metavar="FILE", help="output log (default: <file>.replay.mcap)")
    p.add_argument("--vehicle", metavar="PATH", help="use this profile instead of the one in the log")
    p.add_argument("--compare", action="store_true", help="compare the outputs with the recorded ones; "
                   "exit status 1 on a difference (2 means the replay itself failed)")
    p.add_argument("--tolerance", type=float, default=1e-6, metavar="D", help="float difference allowed (default 1e-6)")
    p.add_argument("--time-tolerance", type=float, default=0.5, metavar="S",
                   help="timing offset allowed, not checked with --fast (default 0.5 s)")
    p.add_argument("--edge", type=int, default=1, metavar="N",
                   help="unmatched messages allowed at each end of a stream (default 1)")
    p.add_argument("--ignore", action="append", default=[], metavar="GLOB",
                   help="fields not compared, e.g. --ignore 'psi_sigma' (repeatable)")
    p.add_argument("--tolerances", metavar="FILE",
                   help='per-field float tolerances, TOML: default = 1e-6, [fields] "*sigma*" = 1e-3, '
                        'ignore = ["psi_sigma"] (docs/replay.md)')
    p.add_argument("--json", action="store_true", help="with --compare: print the comparison as JSON on stdout")
    p.add_argument("--keep", action="store_true", help="keep the run directory (configs, service logs)")
    p.add_argument("--verbose", action="store_true", help="show the services' output")
    p.set_defaults(func=cmd_replay)


def cmd_replay(args: Any) -> int:
    """Run the replay, print the summary (and the comparison)."""
    from u2sa_hw.cli import CliError

    failed = 2   # exit status of a replay that could not run (1 is kept for "outputs differ")
    try:
        from u2sa_hw.hil.compare import compare_logs
        from u2sa_hw.hil.replay import Replay, ReplayOptions
        from u2sa_hw.hil.replay_plan import ReplayError
    except ModuleNotFoundError as exc:
        if exc.name != "u2sa_hw.hil":
            raise
        raise CliError("u2sa replay needs the hil package of u2sa-hw, which this installation lacks: "
                       "reinstall u2sa-hw (make venv, or pip install -e . in the source tree)", failed) from None

    if args.rate <= 0:
        raise CliError(f"--rate must be > 0, got {args.rate:g}", 2)
    tolerances = load_tolerances(args)
    options = ReplayOptions(rate=args.rate, fast=args.fast, start_s=args.start, end_s=args.end,
                            services=args.services, overrides=args.overrides,
                            out=Path(args.out) if args.out else None,
                            vehicle=Path(args.vehicle) if args.vehicle else None, keep_run_dir=args.keep)
    echo = (lambda line: print(line, file=sys.stderr)) if args.verbose else None
    try:
        replay = Replay(args.file, options, echo=echo)
    except ReplayError as exc:
        raise CliError(str(exc), failed) from None
    for note in replay.plan.notes:
        print(f"u2sa: note: {note}", file=sys.stderr)
    try:
        result = replay.run()
    except (ReplayError, RuntimeError) as exc:
        raise CliError(f"{exc}\n(replay files kept in {replay.run_dir})", failed) from None
    out = sys.stderr if args.json else sys.stdout   # --json keeps stdout for the JSON alone
    print(result.summary(fast=replay.fast, rate=replay.rate), file=out)
    if result.pilot is not None and (args.json or not args.compare):   # else it is a line of the comparison
        print(result.pilot.line(), file=out)
    for name, report in result.devices.items():
        if report.get("divergences"):
            print(f"u2sa: note: device {name}: {report.get('divergence', 'diverged from the recording')}",
                  file=sys.stderr)
    if result.run_dir is not None:
        print(f"run directory kept: {result.run_dir}", file=out)
    if not args.compare:
        return 0
    report = compare_logs(result.plan.log, result.out, services=set(result.plan.services),
                          start_ns=result.plan.start_ns, end_ns=result.plan.end_ns,
                          rate=None if replay.fast else replay.rate, tolerance=tolerances, edge=args.edge,
                          time_tolerance_s=args.time_tolerance, ignore=tuple(args.ignore),
                          replay_start_ns=result.play.started_ns or None, pilot=result.pilot,
                          held=result.plan.held_windows())
    if args.json:
        print(json.dumps(report.to_dict(), indent=1))
    else:
        print(report.format())
    if result.lost:
        print(f"note: {result.lost} messages of the replayed services were lost on the replay bus; "
              "count differences may come from that rather than from the drivers", file=sys.stderr)
    return 0 if report.ok else 1


def load_tolerances(args: Any) -> Any:
    """The ``Tolerances`` of ``--tolerance`` and ``--tolerances FILE``; CliError (exit 2) naming the file."""
    from u2sa_hw.hil.compare_values import Tolerances
    from u2sa_hw.cli import CliError

    if args.tolerance < 0 or args.tolerance != args.tolerance:
        raise CliError(f"--tolerance must be a number >= 0, got {args.tolerance!r}", 2)
    if not args.tolerances:
        return Tolerances(args.tolerance)
    try:
        return Tolerances.load(args.tolerances, default=args.tolerance)
    except ValueError as exc:
        raise CliError(str(exc), 2) from None
