"""``u2sa check``: the vehicle profile checked before anything runs; ``--probe`` looks at each device."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

HELP = """\
Check the vehicle profile against what the code declares, without starting
anything, and list EVERY problem at once, one line each:

  error: FILE [KEY]: what is wrong; fix: what to do

Checked: the tables and their keys (a typo gets a did-you-mean), each service's
kind, every setting in the profile and in the service's config file (type,
choices, range, finite numbers, the kind's own rules), the files a service
reads (mission and objects XML: present and parsed), config_dir and bus_key,
the supervision tables, the device tables and addresses (a query parameter the
scheme does not take is an error with a did-you-mean; a /dev/u2sa/NAME link that
nothing creates is an error with the udev line to add; a SocketCAN address
without bitrate= is a warning: the interface would not come up at boot),
[simulation], and [safety] key by key and against the services' actuators and
RC channels. One mistake does not hide another: each is its own line.

Exit status: 0 when there is no error (warnings are printed but do not fail),
1 with any error, 2 on a usage error. u2sa run, u2sa sim and u2sa install run
the same check first and refuse to go on with errors.

--probe then opens each device, one line per device (the vehicle's own; for a
simulation, run it against the profile u2sa mock writes):
  serial   read for --seconds: line rate, protocol (NMEA, OS5000, binary), share
           of good checksums; on garbage, the other common bauds are tried and
           the one that works is named
  I2C      the chip's identity register against what the driver expects
           (MPU-6050/6500/9250 WHO_AM_I 0x68/0x70/0x71, AK8963 WIA 0x48,
           BNO055 CHIP_ID 0xA0, PCA9685 MODE1 answers)
  CAN      interface state, bitrate and error counters (socketcan), and the node
           ids heard in the window (ODrive heartbeats, VESC status frames)
  GPIO     the lines exist and are free
  PWM      the channel exists
The probe runs after a clean offline check, on every device at once (about one
--seconds window in all), and only reads: stop the services first, a device a
service holds is reported busy. A device that cannot be opened or does not
answer as expected fails the probe (exit 1). See docs/check.md.
"""


def register(sub: Any) -> None:
    """Add the ``check`` subcommand."""
    p = sub.add_parser("check", help="check a vehicle profile (all problems at once); --probe looks at the devices",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="examples:\n  u2sa check --vehicle examples/boat/vehicle.toml\n"
                              "  u2sa check --vehicle /etc/u2sa/vehicle.toml --probe\n"
                              "  u2sa check --vehicle vehicle.toml --json | jq '.problems[].key'")
    p.add_argument("--vehicle", metavar="PATH",
                   help="vehicle profile (default: $U2SA_VEHICLE, then /etc/u2sa/vehicle.toml)")
    p.add_argument("--probe", action="store_true", help="also open each device and look at it (one line per device)")
    p.add_argument("--seconds", type=float, default=3.0, metavar="S",
                   help="how long --probe listens to a serial port or a CAN bus (default 3)")
    p.add_argument("--sim", action="store_true",
                   help="check for u2sa sim: every device needs a mock; host device nodes are not looked at")
    p.add_argument("--json", action="store_true", help="print one JSON object (problems, probes, ok) instead of lines")
    p.set_defaults(func=cmd_check)


def profile_path(args: Any, *, command: str = "check") -> Path:
    """The profile --vehicle names, else $U2SA_VEHICLE, else /etc/u2sa/vehicle.toml (CliError 2 without one)."""
    import os

    from u2sa_hw.cli import CliError
    from u2sa_hw.profile.loader import SYSTEM_PROFILE, VEHICLE_ENV

    text = getattr(args, "vehicle", None) or os.environ.get(VEHICLE_ENV)
    if text:
        return Path(text)
    if SYSTEM_PROFILE.exists():
        return SYSTEM_PROFILE
    raise CliError(f"{command}: give the vehicle profile with --vehicle PATH (or set $U2SA_VEHICLE)", 2)


def cmd_check(args: Any) -> int:
    """Print every problem (and with --probe one line per device); 1 when there is an error."""
    from u2sa_hw.check import check_profile, errors_of
    from u2sa_hw.cli import CliError

    if args.seconds <= 0:
        raise CliError("check: --seconds must be > 0", 2)
    path = profile_path(args)
    problems = check_profile(path, for_sim=args.sim)
    errors = errors_of(problems)
    probes: list[Any] = []
    if args.probe and not errors:
        from u2sa_hw.check.probe import probe_profile
        from u2sa_hw.profile.loader import load_profile

        probes = probe_profile(load_profile(path), seconds=args.seconds)
    failed = [p for p in probes if not p.ok]
    ok = not errors and not failed
    if args.json:
        print(json.dumps({"profile": str(path), "ok": ok, "problems": [p.to_dict() for p in problems],
                          "probes": [p.to_dict() for p in probes],
                          "probe_skipped": bool(args.probe and errors)}, indent=2))
        return 0 if ok else 1
    for problem in problems:
        print(problem)
    for result in probes:
        print(result)
    warnings = len(problems) - len(errors)
    summary = f"{path}: {len(errors)} error(s), {warnings} warning(s)"
    if args.probe:
        skipped = sum(1 for p in probes if not p.probed)
        summary += (", probe skipped (fix the errors first)" if errors
                    else f", {len(probes) - skipped} device(s) probed, {len(failed)} failed"
                    + (f", {skipped} with no probe for their kind" if skipped else ""))
    print(summary)
    return 0 if ok else 1


def refuse_on_errors(path: Path, *, command: str, for_sim: bool = False, force: bool = False) -> None:
    """Run the offline check for *command* (run, sim): print warnings, CliError listing every error.

    *force*: print the errors and go on, unless one is in ``[safety]`` (a wrong safety wiring never runs).
    """
    from u2sa_hw.check import check_profile, errors_of
    from u2sa_hw.cli import CliError

    problems = check_profile(path, for_sim=for_sim)
    errors = errors_of(problems)
    if force and not any(p.key.split(".")[0] == "safety" for p in errors):
        for problem in problems:
            print(f"u2sa {command}: {problem}", file=sys.stderr)
        if errors:
            print(f"u2sa {command}: --force: starting despite {len(errors)} error(s)", file=sys.stderr)
        return
    if not errors:
        for problem in problems:   # warnings: shown, and the command goes on
            print(f"u2sa {command}: {problem}", file=sys.stderr)
        return
    if len(errors) == 1:
        raise CliError(f"{command}: {errors[0]} (nothing was started)", 1)
    lines = "\n".join(f"  {p}" for p in errors)
    raise CliError(f"{command}: {path} has {len(errors)} error(s); nothing was started:\n{lines}\n"
                   f"(u2sa check --vehicle {path} lists them again)", 1)
