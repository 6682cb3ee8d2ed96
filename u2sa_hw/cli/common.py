"""Options and helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import contextlib
from typing import Any, Iterator

from u2sa_hw.bus.multicast_check import check_multicast
from u2sa_hw.bus.lcm_open import TransportError
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile
from u2sa_hw.profile.loader import load_profile


def add_vehicle_option(parser: argparse.ArgumentParser) -> None:
    """``--vehicle PATH`` (default: $U2SA_VEHICLE, then /etc/u2sa/vehicle.toml)."""
    parser.add_argument("--vehicle", metavar="PATH",
                        help="vehicle profile (default: $U2SA_VEHICLE, then /etc/u2sa/vehicle.toml)")


def add_timeout_option(parser: argparse.ArgumentParser, default: float = 1.0) -> None:
    """``--timeout S`` for bus requests."""
    parser.add_argument("--timeout", type=float, default=default, metavar="S",
                        help=f"seconds to wait for answers (default {default:g})")


def profile_from(args: Any) -> VehicleProfile:
    """The vehicle profile named by ``--vehicle`` (or the default), CliError on a bad one."""
    from u2sa_hw.cli import CliError

    try:
        return load_profile(getattr(args, "vehicle", None))
    except ProfileError as exc:
        raise CliError(str(exc)) from None


@contextlib.contextmanager
def bus_client(args: Any, *, name: str | None = None) -> Iterator[Any]:
    """A BusClient on the profile's LCM URL for a ``with`` block, closed after it (*name*: its source name).

    A TransportError (LCM cannot open or receive) becomes a one-line CliError with the fix.
    """
    from u2sa_hw.bus.client import BusClient
    from u2sa_hw.cli import CliError

    profile = profile_from(args)
    try:
        # Without a profile file the CLI is no vehicle: system id 0, which every vehicle accepts (docs/security.md).
        client = BusClient(profile.lcm_url, system_id=profile.system_id if profile.path else 0,
                           security=profile.bus_security,
                           key_file=profile.bus_key, interface=profile.bus_interface,
                           **({"name": name} if name else {}))
    except TransportError as exc:
        raise CliError(str(exc)) from None
    try:
        yield client
    except TransportError as exc:
        raise CliError(str(exc)) from None
    finally:
        client.close()


def no_answer_error(args: Any, text: str) -> Exception:
    """The CliError for a request nobody answered: *text*, or why multicast fails here and the fix.

    Multicast that loops nothing back looks like an empty bus; one probe packet tells them apart.
    """
    from u2sa_hw.cli import CliError

    profile = profile_from(args)
    try:
        check_multicast(profile.lcm_url)
    except TransportError as exc:
        return CliError(f"{text}, and {exc}")
    return CliError(text)
