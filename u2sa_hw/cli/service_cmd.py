"""``u2sa service NAME``: run one service in the foreground (what a systemd unit executes)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from u2sa_hw.cli.common import add_vehicle_option, profile_from

HELP = """\
Run the service NAME in the foreground until SIGTERM/SIGINT or a stop command.
With --vehicle, NAME is a service of the profile and its kind, config file and
settings come from there; without one, NAME is a service kind (see --list-kinds)
and the service is called NAME. Logs go to the profile's log_dir (one file per
service) and to stderr (journald under systemd).

Config file: --config PATH, else the profile's `config` for the service, else
<config_dir>/<NAME>.toml (a missing file means defaults).

Log level: --log-level, else the service's log_level config field (its config
file, or the profile's settings for it), else the profile's log_level, else
info. `u2sa param set NAME log_level debug` changes it while running.

--unit (what the installed systemd units run): the vehicle profile alone decides
bus security. $U2SA_BUS_SECURITY is removed from the environment before anything
reads it (so an "open" set in a drop-in or the manager's environment cannot open
the vehicle's bus), and one warning names it and its ignored value. Without
--unit (u2sa run, benches, tests) the variable still applies when the profile
has no [vehicle] bus_security.
"""


def register(sub: Any) -> None:
    """Add the ``service`` subcommand."""
    p = sub.add_parser("service", help="run one service in the foreground", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", nargs="?", help="service name in the vehicle profile (or a service kind)")
    add_vehicle_option(p)
    p.add_argument("--config", metavar="PATH", help="the service's TOML config (default: from the profile, "
                   "else <config_dir>/<name>.toml)")
    p.add_argument("--kind", help="service kind when NAME is not in the profile")
    p.add_argument("--log-level", choices=["debug", "info", "warn", "error"],
                   help="log level at start (wins over the config field and the profile)")
    p.add_argument("--list-kinds", action="store_true", help="list the service kinds and exit")
    p.add_argument("--unit", action="store_true",
                   help="run as an installed systemd unit: the vehicle profile alone decides bus security "
                        "($U2SA_BUS_SECURITY is ignored, with a warning)")
    p.set_defaults(func=run)


def run(args: Any) -> int:
    """Resolve the service, build it and run it."""
    ignored = _drop_security_env() if args.unit else None   # first: before anything reads it
    from u2sa_hw.cli import CliError
    from u2sa_hw.config.fields import ConfigError
    from u2sa_hw.registry import known_kinds, resolve_kind
    from u2sa_hw.service.log import setup_service_logging
    from u2sa_hw.bus.lcm_open import TransportError

    if args.list_kinds:
        for kind, target in sorted(known_kinds().items()):
            print(f"{kind:24} {target}")
        return 0
    if not args.name:
        raise CliError("service: give the NAME of a service (u2sa service --help)", 2)
    profile = profile_from(args)
    spec = profile.services.get(args.name)
    kind = args.kind or (spec.kind if spec else args.name)
    try:
        cls = resolve_kind(kind)
    except LookupError as exc:
        where = f" in {profile.path}" if profile.path else ""
        raise CliError(f"service '{args.name}'{where}: {exc}") from None
    # Until the service's config is read, log at the command line's or the profile's level.
    logger = setup_service_logging(args.name, log_dir=profile.log_dir, level=args.log_level or profile.log_level)
    if ignored is not None:
        from u2sa_hw.bus.auth import SECURITY_ENV

        decided = f'bus_security = "{profile.bus_security}"' if profile.bus_security else "no bus_security: signed"
        logger.warning("$%s=%r ignored: an installed unit (--unit) follows the vehicle profile alone (%s)",
                       SECURITY_ENV, ignored, decided)
    config_path = Path(args.config) if args.config else profile.config_path_for(args.name)
    try:
        service = cls(args.name, profile=profile, config_path=config_path,
                      settings=spec.settings if spec else None, logger=logger)
    except (ConfigError, TransportError) as exc:
        raise CliError(str(exc)) from None
    return service.main(log_level=args.log_level)


def _drop_security_env() -> str | None:
    """Remove $U2SA_BUS_SECURITY from this process's environment (and its children's); its value, or None."""
    import os

    from u2sa_hw.bus.auth import SECURITY_ENV

    return os.environ.pop(SECURITY_ENV, None)
