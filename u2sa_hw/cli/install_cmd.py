"""``u2sa install``, ``u2sa uninstall`` and ``u2sa status``: deployment under systemd."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from u2sa_hw.cli.common import add_timeout_option, add_vehicle_option, profile_from

INSTALL_HELP = """\
Deploy the vehicle profile FILE on this SBC: the user u2sa and the device groups, a
venv under /opt/u2sa, the profile and configs under /etc/u2sa (a config you changed is
never overwritten; a newer default goes beside it as .new) with every file the services
name (missions, a-priori objects...) beside the profile, the systemd units and udev rules,
then enable u2sa.target and one u2sa@NAME.service per service of the profile. The units
run `u2sa service NAME --unit`: the profile alone decides bus security.

Keys, made unless they are there (then only their owners and modes are put back), kept
by uninstall: the bus key /etc/u2sa/bus.key (root:u2sa 0640) and the pilot's pair,
/etc/u2sa/pilot.key (root:u2sa-pilot 0040) and pilot.pub (0644). Only the RC mux's unit
(kind rc_mux) gets the group u2sa-pilot (drop-in 32-pilot-key.conf); the user u2sa is not
in it, and every other unit, the HSM's too, has the key in InaccessiblePaths=.

First the offline check (u2sa check) runs on the file as written; install refuses, writing
nothing and listing every problem with its file, key and fix, when it finds errors or when
the vehicle could not run (a /dev/u2sa/NAME that nothing creates, a named file that is
missing). --force installs anyway: the check's errors are printed as warnings, and install
exits 1 when something the profile asks for could not be done. Not even --force installs a
profile that does not load (every service would refuse it) or one with a [safety] error.

From the device addresses: a serial address /dev/u2sa/NAME with usb=VID:PID (and
serial=...) gets a udev rule making that link; a SocketCAN address with bitrate= gets its
interface set to that bitrate and brought up whenever it appears (at boot, on replug); a
sysfs PWM address gets its service a 50-pwm-sysfs.conf drop-in. Every service of kind
recorder gets u2sa@NAME.service.d/10-recorder.conf (lower CPU and I/O priority, a longer
stop). Running it again changes only what differs, and says so. Needs root, unless
--root DIR stages everything into DIR instead (made if missing; for packages, images and
tests). u2sa uninstall undoes it.

An SD-card image: u2sa install --vehicle FILE --root DIR builds the venv inside DIR
(--venv build, the default), where the booted image has it as /opt/u2sa/venv; nothing in
it points at this checkout. Its python links to this machine's interpreter by path
(e.g. /usr/bin/python3.11): build on a machine of the vehicle's architecture whose
interpreter the image has at the same path (or pass --python). pip shows its progress and
reads its usual settings (PIP_INDEX_URL, PIP_FIND_LINKS...) and cache.
"""

VENV_HELP = ("how to make /opt/u2sa/venv: build (the default, also with --root: a venv and pip install of a "
             "wheel of the checkout with its dependencies, pip's output shown; with --root DIR built inside DIR "
             "and made correct at /opt/u2sa/venv, so the image boots without this checkout), shared (seconds: a "
             "venv using this environment's packages, for a development board; a staged image boots only where "
             "that environment is), none (leave it to the package)")


def register(sub: Any) -> None:
    """Add the ``install``, ``uninstall`` and ``status`` subcommands."""
    p = sub.add_parser("install", help="install the vehicle's services under systemd", description=INSTALL_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vehicle", metavar="FILE", required=True, help="the vehicle profile to deploy")
    p.add_argument("--root", metavar="DIR", default="/", help="stage into DIR instead of this system (made if "
                   "missing)")
    p.add_argument("--venv", choices=["build", "shared", "none"], help=VENV_HELP)
    p.add_argument("--python", metavar="PATH", help="interpreter for the venv (default: this one's, or "
                   "/usr/bin/python3.X when this one lives under /root or /home)")
    p.add_argument("--source", metavar="DIR", help="the u2sa-hw checkout to deploy (default: the one this "
                   "u2sa runs from)")
    p.add_argument("--force", action="store_true", help="install even when the offline check finds errors (they "
                   "are printed as warnings; install still exits 1 when something could not be done); never "
                   "past a [safety] error or a profile that does not load")
    p.add_argument("-v", "--verbose", action="store_true", help="also list what was already up to date")
    p.set_defaults(func=cmd_install)

    p = sub.add_parser("uninstall", help="remove what u2sa install added",
                       description="Undo what u2sa install did, as it recorded in /opt/u2sa/install-manifest.json "
                       "and nothing else: stop the services, remove the units, udev rules (so the /dev/u2sa links "
                       "and CAN bitrates go too), venv, links and the directories install made. Configs and the "
                       "files the services name (/etc/u2sa), logs (/var/log/u2sa) and recordings (/var/lib/u2sa) "
                       "stay, unless --purge.")
    p.add_argument("--root", metavar="DIR", default="/", help="the staging directory install used")
    p.add_argument("--purge", action="store_true", help="also delete configs, logs, recordings, and the user "
                   "and groups that install created")
    p.add_argument("-v", "--verbose", action="store_true", help="also list what was kept")
    p.set_defaults(func=cmd_uninstall)

    p = sub.add_parser("status", help="each unit's systemd state next to the HSM's view",
                       description="Show every U2SA unit as systemd sees it (systemctl show) next to what "
                       "the HSM reports for the same service (its SystemHealth message).")
    add_vehicle_option(p)
    add_timeout_option(p, default=2.5)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=cmd_status)


def _print_changes(tree: Any, *, verbose: bool, done: str) -> None:
    for change in tree.changes:
        if verbose or change.action != "unchanged":
            print(change)
    if not tree.changed:
        print(f"nothing to do: {done}")


def _progress(line: str) -> None:
    """Where install's slow step (pip) says what it does: stderr, so stdout keeps only the changes."""
    print(line, file=sys.stderr, flush=True)


def cmd_install(args: Any) -> int:
    """Run install and print what changed."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.install.deploy import install
    from u2sa_hw.install.system import InstallError
    from u2sa_hw.profile.vehicle import ProfileError

    try:
        tree = install(vehicle=args.vehicle, root=Path(args.root), venv=args.venv, python=args.python,
                       source=args.source, force=args.force, progress=_progress)
    except (InstallError, ProfileError) as exc:
        raise CliError(str(exc)) from None
    for warning in tree.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    _print_changes(tree, verbose=args.verbose, done="everything is already installed as this profile wants")
    if tree.failures:
        for failure in tree.failures:
            print(f"u2sa install: not done: {failure}", file=sys.stderr)
        print(f"u2sa install: {len(tree.failures)} thing(s) the profile asks for could not be done; the vehicle "
              "will not run as the profile says until they are fixed", file=sys.stderr)
        return 1
    if tree.changed and tree.root == Path("/"):
        print("start the services with: systemctl start u2sa.target   (they start at boot from now on)")
    return 0


def cmd_uninstall(args: Any) -> int:
    """Run uninstall and print what was removed."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.install.deploy import uninstall
    from u2sa_hw.install.system import InstallError

    try:
        tree = uninstall(root=Path(args.root), purge=args.purge)
    except InstallError as exc:
        raise CliError(str(exc)) from None
    _print_changes(tree, verbose=args.verbose, done="nothing was installed")
    return 0


def cmd_status(args: Any) -> int:
    """Print the status table (or JSON); exit 1 when a unit of the profile is not active."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.install.status import collect_status, format_status
    from u2sa_hw.install.system import InstallError

    profile = profile_from(args)
    try:
        report = collect_status(profile, timeout=args.timeout)
    except InstallError as exc:
        raise CliError(str(exc)) from None
    print(json.dumps(report, indent=2) if args.json else format_status(report))
    down = [u for u in report["units"] if u["service"] and u["active"] != "active"]
    return 1 if down or report["systemd_error"] else 0
