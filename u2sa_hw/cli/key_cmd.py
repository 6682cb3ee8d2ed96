"""``u2sa key show|import|rotate``: the vehicle's bus key (docs/security.md)."""

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

Move the key between machines over a channel you trust, for instance:
  ssh pi@rover sudo u2sa key show | sudo u2sa key import -
"""


def register(sub: Any) -> None:
    """Add the ``key`` subcommand."""
    p = sub.add_parser("key", help="show, import or rotate the vehicle's bus key", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("action", choices=("show", "import", "rotate"))
    p.add_argument("source", nargs="?", metavar="FILE", help="for import: the key file ('-': standard input)")
    p.add_argument("--file", type=Path, metavar="PATH",
                   help="the key file to act on (default: $U2SA_BUS_KEY_FILE, the profile's bus_key, "
                   "/etc/u2sa/bus.key)")
    p.add_argument("--id", action="store_true", help="show: print only the key's public id")
    add_vehicle_option(p)
    p.set_defaults(func=cmd_key)


def cmd_key(args: Any) -> int:
    """Run ``u2sa key ACTION``; every failure is one CliError line naming the file and the fix."""
    from u2sa_hw.bus_key import BusKeyError, key_id, key_path, new_key, read_key, write_key
    from u2sa_hw.cli import CliError

    path = args.file or _service_key_path(args)
    try:
        if args.action == "show":
            key = read_key(path)
            print(key_id(key).hex() if args.id else key.hex())
            return 0
        if args.action == "import":
            key = _read_source(args.source)
            write_key(path, key)
            print(f"imported key {key_id(key).hex()} into {path}")
            return 0
        key = new_key()
        write_key(path, key)
        print(f"new key {key_id(key).hex()} in {path}; running services switch to it within a second "
              "(copy it to every other computer of the vehicle: u2sa key show | ... u2sa key import -)")
        return 0
    except BusKeyError as exc:
        raise CliError(f"key {args.action}: {exc}") from None


def _service_key_path(args: Any) -> Path:
    """The key file the services of this profile use: the resolution of ``bus_client`` and ``Transport``.

    ``$U2SA_BUS_KEY_FILE``, else the ``bus_key`` of the profile ``--vehicle`` names, or
    ``$U2SA_VEHICLE``, or /etc/u2sa/vehicle.toml (:func:`~u2sa_hw.cli.common.profile_from`),
    else /etc/u2sa/bus.key. With the variable set the profile is not read: it would not change
    the file, and a profile that cannot load must not keep ``u2sa key`` from the key.
    """
    from u2sa_hw.bus_key import KEY_ENV, key_path

    if os.environ.get(KEY_ENV):
        return key_path(None)
    return key_path(profile_from(args).bus_key)


def _read_source(source: str | None) -> bytes:
    from u2sa_hw.bus_key import parse_key
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
