"""``u2sa run``: the local launcher for a bench or a laptop (no systemd)."""

from __future__ import annotations

import argparse
from typing import Any

from u2sa_hw.cli.common import add_vehicle_option, profile_from

HELP = """\
Start every enabled service of the vehicle profile as its own process
(u2sa service NAME --vehicle FILE), prefix their output with the service name,
restart a crashed service with a backoff that doubles on quick deaths and decays
after healthy uptime, and stop everything on Ctrl-C or SIGTERM (SIGTERM to each
service, SIGKILL after the grace period; a second Ctrl-C kills at once).

A service that exits with status 0 stopped on purpose and is not restarted. A
service is given up when it dies quickly --give-up-after times in a row, or when
it fails --max-failures times within --failure-window seconds however long each
run lasted (a service that crashes every 6 s looks healthy to the quick-death
rule but is not). Then the launcher stops everything and exits 1 (with
--keep-going the others keep running and the exit status is 1 at the end).

The HSM (a service of kind "hsm") asks the launcher to restart services through
the control socket <data_dir>/launcher.sock. See docs/supervision.md.
"""


def register(sub: Any) -> None:
    """Add the ``run`` subcommand."""
    p = sub.add_parser("run", help="run every service of the vehicle profile, supervised (no systemd)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="example:\n  u2sa run --vehicle examples/ground_vehicle/vehicle.toml --only gps,hsm")
    add_vehicle_option(p)
    p.add_argument("--only", action="append", metavar="NAMES",
                   help="comma-separated services to run (repeatable; may name disabled ones)")
    p.add_argument("--grace", type=float, default=5.0, metavar="S",
                   help="seconds between SIGTERM and SIGKILL when stopping a service (default 5)")
    p.add_argument("--give-up-after", type=int, default=5, metavar="N",
                   help="quick deaths in a row before a service is given up (default 5; 0 = never)")
    p.add_argument("--backoff", type=float, default=0.5, metavar="S",
                   help="respawn delay after the first quick death; doubles with each one (default 0.5)")
    p.add_argument("--max-backoff", type=float, default=30.0, metavar="S", help="respawn delay cap (default 30)")
    p.add_argument("--quick-death", type=float, default=5.0, metavar="S",
                   help="a death within S seconds of starting is quick; each S of healthy uptime "
                   "forgives one quick death (default 5)")
    p.add_argument("--max-failures", type=int, default=10, metavar="N",
                   help="failed exits (non-zero status or a signal) within --failure-window before a service is "
                   "given up, whatever its uptime (default 10; 0 = never)")
    p.add_argument("--failure-window", type=float, default=300.0, metavar="S",
                   help="the window of --max-failures, seconds (default 300)")
    p.add_argument("--keep-going", action="store_true",
                   help="keep the other services running when one is given up")
    p.add_argument("--no-color", action="store_true", help="never colour the service names")
    p.set_defaults(func=cmd_run)


def cmd_run(args: Any) -> int:
    """Run the launcher in the foreground until Ctrl-C/SIGTERM or a failure; return its exit status."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.launcher import Launcher, LauncherError, PrefixedOutput, RestartPolicy, select_services

    profile = profile_from(args)
    if profile.path is None:
        raise CliError("run: give the vehicle profile with --vehicle PATH (or set $U2SA_VEHICLE)", 2)
    only = [n.strip() for item in args.only or [] for n in item.split(",") if n.strip()] or None
    if args.grace < 0:
        raise CliError("run: --grace must be >= 0", 2)
    try:
        policy = RestartPolicy(initial_backoff_s=args.backoff, max_backoff_s=args.max_backoff,
                               quick_death_s=args.quick_death, give_up_after=args.give_up_after,
                               max_failures=args.max_failures, failure_window_s=args.failure_window)
        names = [s.name for s in select_services(profile, only)]
    except ValueError as exc:
        raise CliError(f"run: {exc}", 2) from None
    output = PrefixedOutput(names=names, colour=False if args.no_color else None)
    launcher = Launcher(profile, only=only, grace_s=args.grace, policy=policy, keep_going=args.keep_going,
                        output=output)
    try:
        code = launcher.run()
    except LauncherError as exc:
        raise CliError(str(exc)) from None
    if launcher.failed:
        output("launcher", f"exit 1: given up on {', '.join(launcher.failed)}")
    else:
        output("launcher", "all services stopped")
    return code
