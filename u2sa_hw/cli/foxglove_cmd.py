"""``u2sa foxglove``: the live Foxglove view of the bus (the ``foxglove_bridge`` service in the foreground)."""

from __future__ import annotations

import argparse
from typing import Any

from u2sa_hw.cli.common import add_vehicle_option, profile_from

HELP = """\
Serve every LCM channel of the vehicle's bus, decoded, to Foxglove (app.foxglove.dev or the
desktop app: Open connection -> Foxglove WebSocket -> ws://127.0.0.1:8765). Positions show
on the Map (through the profile's origin), the estimate, world objects, waypoints and the
planned navigation point in the 3D panel, service health on /health, service log lines
on /log, and every service's config as parameters (read-only unless
--allow-parameter-writes; a write is a signed ConfigChange, checked by the service).

It listens on 127.0.0.1 only. To reach it from another machine prefer an SSH tunnel
(ssh -L 8765:127.0.0.1:8765 vehicle); --host 0.0.0.0 needs --token-file, and clients then
connect to ws://VEHICLE:8765/?token=TOKEN (wss:// with --tls-cert/--tls-key).
It never slows the bus: beyond --queue-size waiting messages, drops are counted in its
health. The same runs as a unit with kind = "foxglove_bridge". See docs/foxglove.md.
"""


def register(sub: Any) -> None:
    """Add the ``foxglove`` subcommand."""
    p = sub.add_parser("foxglove", help="live Foxglove WebSocket view of the bus", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_vehicle_option(p)
    p.add_argument("--name", default="foxglove", help="service name on the bus (default foxglove)")
    p.add_argument("--host", default="127.0.0.1", help="listen address (default 127.0.0.1; others need --token-file)")
    p.add_argument("--port", type=int, default=8765, help="port (default 8765; 0: any free port)")
    p.add_argument("--token-file", default="", metavar="FILE", help="token clients must send (?token=...)")
    p.add_argument("--tls-cert", default="", metavar="PEM", help="certificate: the network listener speaks wss://")
    p.add_argument("--tls-key", default="", metavar="PEM", help="private key of --tls-cert")
    p.add_argument("--queue-size", type=int, default=5000, metavar="N",
                   help="messages buffered between the bus and the server (default 5000)")
    p.add_argument("--allow-parameter-writes", action="store_true",
                   help="let clients change service configs (as signed ConfigChange messages)")
    p.add_argument("--no-logs", action="store_true", help="do not tail the services' log files onto /log")
    p.add_argument("--log-level", choices=["debug", "info", "warn", "error"], help="log level")
    p.set_defaults(func=cmd_foxglove)


def cmd_foxglove(args: Any) -> int:
    """Build the bridge service from the options and run it until Ctrl-C."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.config.fields import ConfigError
    from u2sa_hw.service.log import setup_service_logging
    from u2sa_hw.bus.lcm_open import TransportError

    try:
        from u2sa_hw.foxglove.service import FoxgloveBridgeService
    except ModuleNotFoundError as exc:
        raise CliError(f"u2sa foxglove needs {exc.name}: pip install 'u2sa-hw[foxglove]'") from None
    profile = profile_from(args)
    settings = {"host": args.host, "port": args.port, "token_file": args.token_file, "tls_cert": args.tls_cert,
                "tls_key": args.tls_key, "queue_size": args.queue_size,
                "allow_parameter_writes": args.allow_parameter_writes, "tail_logs": not args.no_logs}
    logger = setup_service_logging(args.name, log_dir=None, level=args.log_level or profile.log_level)
    try:
        service = FoxgloveBridgeService(args.name, profile=profile, config_path="", settings=settings, logger=logger)
    except (ConfigError, TransportError) as exc:
        raise CliError(str(exc)) from None
    return service.main(log_level=args.log_level)
