"""``u2sa run``: the local launcher for a bench or a laptop (no systemd)."""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile
from typing import Any, Iterator

from u2sa_hw.cli.common import add_vehicle_option, profile_from

REALTIME_HELP = ("run the safety chain (RC mux, actuator drivers, HSM) at normal priority instead of SCHED_FIFO; "
                 "by default it runs real-time when permitted (root, CAP_SYS_NICE or ulimit -r), so other work on "
                 "the board cannot delay a failsafe; see docs/safety.md")


def add_realtime_option(p: Any) -> None:
    """The ``--no-realtime`` option of ``u2sa run`` and ``u2sa sim``."""
    p.add_argument("--no-realtime", dest="realtime", action="store_false", help=REALTIME_HELP)

HELP = """\
Start every enabled service of the vehicle profile as its own process
(u2sa service NAME --vehicle FILE), prefix their output with the service name,
restart a crashed service with a backoff that doubles on quick deaths and decays
after healthy uptime, and stop everything on Ctrl-C or SIGTERM (SIGTERM to each
service; SIGKILL for one that does not acknowledge within the grace, stops making progress
for a grace after acknowledging, or is still alive 30 s after SIGTERM; a second Ctrl-C kills
at once). A loaded board lengthens the wait, not the verdict (docs/supervision.md).

A service that exits with status 0 stopped on purpose and is not restarted; one
that exits with status 3 refused to start (another of its name already runs on
the bus, or its bus cannot be kept on this board: its line says which) and is
not restarted either, as RestartPreventExitStatus=3 does under systemd. A service
is given up when it dies quickly --give-up-after times in a row, or when it fails
--max-failures times within --failure-window seconds however long each run lasted
(a service that crashes every 6 s looks healthy to the quick-death rule but is
not). After a refusal or a give-up the launcher stops everything and exits 1 (with
--keep-going the others keep running and the exit status is 1 at the end).

Bus key: $U2SA_BUS_KEY_FILE, else the profile's bus_key (which must exist), else
/etc/u2sa/bus.key; without any, the run signs with a fresh key of its own and
prints where. Run as root, the services set lo's MULTICAST flag, so a ttl=0 bus
stays on this board (docs/security.md, "Where the vehicle listens").

Like systemd, the launcher watches each service's watchdog: a service pings
WATCHDOG=1 from its own loop; one silent for WatchdogSec of its unit file
(systemd/u2sa@.service, u2sa-hsm.service for the HSM: 2 s) is hung: it gets
SIGABRT (its stacks are printed), SIGKILL after TimeoutAbortSec, and is restarted
by the rules above, logged as a watchdog timeout. --watchdog S sets the timeout
for every service (0 turns the watchdog off).

The safety chain runs real-time, as the units run it (docs/safety.md): the RC
mux at SCHED_FIFO 30, the actuator drivers (odrive_can, vesc_can, pwm_servo,
gpio_output) at 25, the HSM at 20; every other service at normal priority. So a
board kept busy by other work cannot delay the pilot's hand-over or a motor's
dead-man timer. It needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO (ulimit -r) of
30; without, one line says so and they run at normal priority. Kernel RT
throttling is left on: a service that spins leaves 5 % of each CPU to the rest,
and the watchdog still kills it. --no-realtime runs everything at normal priority.

A service found stopped (SIGSTOP) when its watchdog fires, or when it is to be
stopped or restarted, gets SIGKILL at once: resumed, a frozen command source
would publish commands again before it died.

The HSM (a service of kind "hsm") asks the launcher to restart services through
the control socket <data_dir>/launcher.sock. See docs/supervision.md.

Before anything starts, the profile is checked as u2sa check does (docs/check.md):
with any error the launcher lists every one and starts nothing. --force starts
anyway (to watch the supervision handle a service that cannot start), except
for [safety] errors, which always refuse: a wrong safety wiring is never run.
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
                   help="seconds a stopping service has to acknowledge (STOPPING=1), and the longest it may go "
                   "without progress after that, before SIGKILL (default 5; every stop ends within 30 s)")
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
    p.add_argument("--watchdog", type=float, default=None, metavar="S",
                   help="restart a service that sends no WATCHDOG=1 for S seconds (default: WatchdogSec of its "
                   "systemd unit, 2 s; 0 = off)")
    add_realtime_option(p)
    p.add_argument("--keep-going", action="store_true",
                   help="keep the other services running when one is given up")
    p.add_argument("--no-color", action="store_true", help="never colour the service names")
    p.add_argument("--force", action="store_true",
                   help="start even when u2sa check finds errors (they are printed); [safety] errors still refuse")
    p.set_defaults(func=cmd_run)


def cmd_run(args: Any) -> int:
    """Run the launcher in the foreground until Ctrl-C/SIGTERM or a failure; return its exit status."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.launcher import PrefixedOutput, RestartPolicy, select_services

    from u2sa_hw.cli.check_cmd import profile_path

    path = profile_path(args, command="run")
    _check_profile(path, force=args.force)   # before loading: the loader stops at the first problem
    profile = profile_from(args)
    only = [n.strip() for item in args.only or [] for n in item.split(",") if n.strip()] or None
    if args.grace < 0:
        raise CliError("run: --grace must be >= 0", 2)
    if args.watchdog is not None and args.watchdog < 0:
        raise CliError("run: --watchdog must be >= 0 (0 turns the watchdog off)", 2)
    try:
        policy = RestartPolicy(initial_backoff_s=args.backoff, max_backoff_s=args.max_backoff,
                               quick_death_s=args.quick_death, give_up_after=args.give_up_after,
                               max_failures=args.max_failures, failure_window_s=args.failure_window)
        names = [s.name for s in select_services(profile, only)]
    except ValueError as exc:
        raise CliError(f"run: {exc}", 2) from None
    _check_safety(profile)
    output = PrefixedOutput(names=names, colour=False if args.no_color else None)
    with _run_key(profile, output):
        return _launch(args, profile, only=only, policy=policy, output=output)


def _launch(args: Any, profile: Any, *, only: list[str] | None, policy: Any, output: Any) -> int:
    from u2sa_hw.cli import CliError
    from u2sa_hw.launcher import Launcher, LauncherError

    from u2sa_hw.realtime import plan

    launcher = Launcher(profile, only=only, grace_s=args.grace, policy=policy, keep_going=args.keep_going,
                        output=output, watchdog_s=args.watchdog, realtime=plan(enabled=args.realtime))
    try:
        code = launcher.run()
    except LauncherError as exc:
        raise CliError(str(exc)) from None
    refused = [s.name for s in launcher.status() if s.name in launcher.failed and s.reason.startswith("refused")]
    given_up = [n for n in launcher.failed if n not in refused]
    if refused:   # exit status 3: not restarted, its own line said why (u2sa_hw.service.bus_handlers)
        output("launcher", f"exit 1: {', '.join(refused)} refused to start (the line above says why)")
    if given_up:
        output("launcher", f"exit 1: given up on {', '.join(given_up)}")
    if not launcher.failed:
        output("launcher", "all services stopped")
    return code


@contextlib.contextmanager
def _run_key(profile: Any, output: Any) -> Iterator[None]:
    """Without an installed bus key, a fresh one for this run in $U2SA_BUS_KEY_FILE (the services inherit it).

    A key that exists but cannot be read, and a ``bus_key`` the profile names that does not
    exist, are errors naming the file and the fix: the profile asked for that key, and a fresh
    one would leave every other computer holding it unheard.
    """
    from u2sa_hw.bus.auth import OPEN, resolve_security
    from u2sa_hw.bus.key import KEY_ENV, BusKeyError, key_path, read_key
    from u2sa_hw.bus.run_keys import fresh_key_file
    from u2sa_hw.cli import CliError

    try:
        if resolve_security(profile.bus_security) == OPEN:
            yield
            return
        path = key_path(profile.bus_key)
        if KEY_ENV not in os.environ and profile.bus_key is not None and not path.exists():
            raise CliError(f"run: {profile.path}: bus_key = \"{path}\" does not exist: make one there with "
                           f"'u2sa key rotate --file {path}' (or copy the vehicle's: 'u2sa key show' there, "
                           f"'u2sa key import FILE --file {path}' here), or remove bus_key from [vehicle] to sign "
                           "this run with a fresh key")
        if path.exists() or KEY_ENV in os.environ:
            read_key(path)
            yield
            return
    except BusKeyError as exc:
        raise CliError(f"run: {exc}") from None
    with tempfile.TemporaryDirectory(prefix="u2sa-run-key-") as tmp:
        key = fresh_key_file(tmp)
        os.environ[KEY_ENV] = str(key)
        output("launcher", f"no bus key at {path}: this run signs with a fresh key {key} "
                           f"(to join: {KEY_ENV}={key} u2sa services)")
        try:
            yield
        finally:
            os.environ.pop(KEY_ENV, None)


def _check_profile(path: Any, *, force: bool) -> None:
    """The offline check (u2sa check): refuse with every error listed, or with --force print them and go on."""
    from u2sa_hw.cli.check_cmd import refuse_on_errors

    refuse_on_errors(path, command="run", force=force)


def _check_safety(profile: Any) -> None:
    """The [safety] table against the profile's actuators and RC channels, before anything starts."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.safety.wiring import check_wiring
    from u2sa_hw.profile.vehicle import ProfileError

    try:
        check_wiring(profile)
    except ProfileError as exc:
        raise CliError(str(exc)) from None
