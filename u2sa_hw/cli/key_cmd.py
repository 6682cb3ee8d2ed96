"""``u2sa key show|import|rotate|operator|pilot``: the vehicle's bus key, operator keys and the pilot's pair (docs/security.md)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from u2sa_hw.cli.common import add_vehicle_option, profile_from

HELP = """\
Every message on the bus is signed with the vehicle's 256-bit key; a process without it
is not heard. The key is found as the services find it: $U2SA_BUS_KEY_FILE, else the
bus_key of the profile (--vehicle, else $U2SA_VEHICLE, else /etc/u2sa/vehicle.toml), else
/etc/u2sa/bus.key (made by 'sudo u2sa install', root:u2sa 0640). --file PATH acts on PATH.

  u2sa key show                 print the key (64 hex digits) to copy to a ground station
  u2sa key show --id            print only its public id (compare two machines without the secret)
  u2sa key import FILE          store the key in FILE ('-': stdin) as this machine's key
  u2sa key rotate               make a new key; running services pick it up within a second
                                and accept the old one for 30 s more

  u2sa key operator NAME        make an operator key for a ground station (operators/NAME.key
                                beside the bus key); the vehicle accepts it at once
  u2sa key pilot                make a new pilot pair (pilot.key, pilot.pub beside the bus key);
                                restart the stack to use it
  u2sa key show --pilot         print the pilot's public key (the pilot.pub to copy to a laptop)

Roles (docs/security.md): the bus key speaks for the vehicle's services; an operator key only
sends missions, stops, parameters, failsafes and discovery (a tool signs with it when
$U2SA_OPERATOR_KEY_FILE names it); RC_MODE and MANUAL_CMD are signed with the pilot's private
key, which only the RC mux reads: no holder of the bus key or an operator key can take over
from the pilot's switch.

Move the key between machines over a channel you trust, for instance:
  ssh pi@rover sudo u2sa key show | sudo u2sa key import -
  ssh pi@rover cat /etc/u2sa/pilot.pub > ~/.u2sa/pilot.pub     (beside the laptop's bus key)
  ssh pi@rover sudo u2sa key operator laptop --print > ~/.u2sa/operator.key
"""


def register(sub: Any) -> None:
    """Add the ``key`` subcommand."""
    p = sub.add_parser("key", help="show, import or rotate the vehicle's bus key", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("action", choices=("show", "import", "rotate", "operator", "pilot"))
    p.add_argument("source", nargs="?", metavar="FILE|NAME",
                   help="import: the key file ('-': standard input); operator: the operator's name")
    p.add_argument("--file", type=Path, metavar="PATH",
                   help="the key file to act on (default: $U2SA_BUS_KEY_FILE, the profile's bus_key, "
                   "/etc/u2sa/bus.key)")
    p.add_argument("--id", action="store_true", help="show: print only the key's public id")
    p.add_argument("--pilot", action="store_true", help="show: the pilot's public key (pilot.pub) instead")
    p.add_argument("--print", dest="print_key", action="store_true",
                   help="operator: also print the new key on standard output (to pipe to the ground station)")
    add_vehicle_option(p)
    p.set_defaults(func=cmd_key)


def cmd_key(args: Any) -> int:
    """Run ``u2sa key ACTION``; every failure is one CliError line naming the file and the fix."""
    from u2sa_hw.bus.key import BusKeyError, key_id, new_key, read_key, write_key
    from u2sa_hw.cli import CliError

    path = args.file or _service_key_path(args)
    try:
        if args.action == "show" and args.pilot:
            return _show_pilot(path, only_id=args.id)
        if args.action == "show":
            key = read_key(path)
            print(key_id(key).hex() if args.id else key.hex())
            return 0
        if args.action == "operator":
            return _make_operator(path, args.source, print_key=args.print_key)
        if args.action == "pilot":
            from u2sa_hw.bus.pilot import write_pilot_pair
            kid = write_pilot_pair(path, system=os.geteuid() == 0 and path.parent == Path("/etc/u2sa"))
            print(f"new pilot key {kid.hex()} beside {path}; restart the stack to use it "
                  "('sudo systemctl restart u2sa.target'), and copy pilot.pub to every laptop that shows RC_MODE")
            return 0
        if args.action == "import":
            key = _read_source(args.source)
            write_key(path, key)
            print(f"imported key {key_id(key).hex()} into {path}")
            return 0
        key = new_key()
        write_key(path, key)
        print(f"new key {key_id(key).hex()} in {path}; " + _who_uses(path, args))
        _ensure_pilot_pair(path)
        return 0
    except BusKeyError as exc:
        raise CliError(f"key {args.action}: {exc}") from None


def _who_uses(path: Path, args: Any) -> str:
    """What a rotated key at *path* changes: the services' key switches them; any other file changes nothing yet."""
    from u2sa_hw.bus.key import KEY_ENV

    try:
        used = _service_key_path(args)
    except Exception:   # noqa: BLE001 - a profile that cannot load: no service uses *path* through it
        used = None
    if used is not None and Path(os.path.abspath(used)) == Path(os.path.abspath(path)):
        return ("running services switch to it within a second (copy it to every other computer of the vehicle: "
                "u2sa key show | ... u2sa key import -)")
    return (f"no service uses it yet (theirs is {used or 'not found'}): point them at it with "
            f"{KEY_ENV}={path} or bus_key = \"{path}\" in the vehicle profile, or import it into theirs "
            f"(u2sa key show --file {path} | u2sa key import -)")


def _service_key_path(args: Any) -> Path:
    """The key file the services of this profile use: the resolution of ``bus_client`` and ``Transport``.

    ``$U2SA_BUS_KEY_FILE``, else the ``bus_key`` of the profile ``--vehicle`` names, or
    ``$U2SA_VEHICLE``, or /etc/u2sa/vehicle.toml (:func:`~u2sa_hw.cli.common.profile_from`),
    else /etc/u2sa/bus.key. With the variable set the profile is not read: it would not change
    the file, and a profile that cannot load must not keep ``u2sa key`` from the key.
    """
    from u2sa_hw.bus.key import KEY_ENV, key_path

    if os.environ.get(KEY_ENV):
        return key_path(None)
    return key_path(profile_from(args).bus_key)


def _read_source(source: str | None) -> bytes:
    from u2sa_hw.bus.key import parse_key
    from u2sa_hw.cli import CliError

    if not source:
        raise CliError("key import: name the key file to import (or '-' to read it from standard input)", 2)
    if source == "-":
        return parse_key(sys.stdin.read(), source="standard input")
    try:
        text = Path(source).read_bytes()
    except OSError as exc:
        raise CliError(f"key import: cannot read {source}: {exc.strerror or exc}") from None
    return parse_key(text, source=source)


NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_.")


def _make_operator(bus_key: Path, name: str | None, *, print_key: bool) -> int:
    """operators/NAME.key beside *bus_key*: a new operator key the vehicle's services accept within a second."""
    from u2sa_hw.bus.key import key_id, new_key, write_key
    from u2sa_hw.bus.keyring import OPERATORS_DIR
    from u2sa_hw.cli import CliError

    if not name or not set(name) <= NAME_CHARS or name.startswith("."):
        raise CliError("key operator: give the operator a NAME of letters, digits, '-', '_' or '.' "
                       "(u2sa key operator laptop)", 2)
    path = bus_key.parent / OPERATORS_DIR / f"{name}.key"
    if path.exists():
        raise CliError(f"key operator: {path} exists; remove it first to replace operator {name!r} "
                       "(the vehicle stops accepting the old key within a second)")
    key = new_key()
    write_key(path, key)
    print(f"operator key {key_id(key).hex()} for {name!r} in {path}; the services accept it within a second. "
          f"On the ground station: store it (0600) and export {_operator_env()}=PATH; it may send missions, "
          "stops, parameters, failsafes and discovery, nothing else", file=sys.stderr if print_key else sys.stdout)
    if print_key:
        print(key.hex())
    return 0


def _operator_env() -> str:
    from u2sa_hw.bus.keyring import OPERATOR_KEY_ENV
    return OPERATOR_KEY_ENV


def _show_pilot(bus_key: Path, *, only_id: bool) -> int:
    from u2sa_hw.bus.pilot import pilot_paths, read_verifier

    verifier = read_verifier(pilot_paths(bus_key)[1])
    print(verifier.id.hex() if only_id else verifier.public.hex())
    return 0


def _ensure_pilot_pair(bus_key: Path) -> None:
    """A pilot pair beside a rotated bus key when there is none (a key of the user's own, or an old install)."""
    from u2sa_hw.bus.pilot import pilot_paths, write_pilot_pair

    private, public = pilot_paths(bus_key)
    if private.exists() or public.exists():
        return
    kid = write_pilot_pair(bus_key, system=os.geteuid() == 0 and bus_key.parent == Path("/etc/u2sa"))
    print(f"new pilot key {kid.hex()} beside it ({private.name}, {public.name}): only the RC mux signs RC_MODE "
          "and MANUAL_CMD with it")
