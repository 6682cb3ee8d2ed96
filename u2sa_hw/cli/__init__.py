"""The ``u2sa`` command line.

Each subcommand lives in its own module with a ``register(subparsers)`` function;
``COMMAND_MODULES`` lists them (modules outside ``u2sa_hw`` -- mocks, replay -- are
imported only when their command runs, so ``u2sa_hw`` stays free of them).
Errors are one line on stderr (``u2sa: ...``) with a non-zero exit status.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from u2sa_hw import __version__

COMMAND_MODULES = [
    "u2sa_hw.cli.service_cmd",
    "u2sa_hw.cli.check_cmd",
    "u2sa_hw.cli.bus_cmds",
    "u2sa_hw.cli.param_cmd",
    "u2sa_hw.cli.calibrate_cmd",
    "u2sa_hw.cli.mission_cmd",
    "u2sa_hw.cli.failsafe_cmd",
    "u2sa_hw.cli.record_cmd",
    "u2sa_hw.cli.run_cmd",
    "u2sa_hw.cli.health_cmd",
    "u2sa_hw.cli.foxglove_cmd",
    "u2sa_hw.cli.install_cmd",
    "u2sa_hw.cli.key_cmd",
    "u2sa_hw.cli.mock_cmd",
    "u2sa_hw.cli.sim_cmd",
    "u2sa_hw.cli.replay_cmd",
    "u2sa_hw.cli.replay_check_cmd",
]

EPILOG = """\
examples:
  u2sa service state_estimator --vehicle examples/ground_vehicle/vehicle.toml
  u2sa services                      list live services (discovery)
  u2sa topics                        channels seen on the bus with rate and bandwidth
  u2sa echo STATE_ESTIMATE --count 1 --json
  u2sa pub STATE_INFO StateInformation sensor_name=test x=1.5 psi=0.3
  u2sa param list state_estimator    a service's config; param set changes and persists it
  u2sa mission status                the mission and its current goal; goto/skip/restart/upload change it
  u2sa failsafe raise                every actuator neutral now; status shows who holds one, clear lowers it
  u2sa stop --all

The LCM URL comes from the vehicle profile, else $U2SA_LCM_URL, else
udpm://239.255.76.67:7667?ttl=0 (this board only).
"""


class CliError(Exception):
    """A user-facing failure: printed as one line on stderr, exit status ``code``."""

    def __init__(self, message: str, code: int = 1) -> None:
        super().__init__(message)
        self.code = code


# `u2sa service NAME` is what every unit and the launcher execute: it registers only its own
# subcommand, so a service process does not import every other command's modules (numpy for
# calibration, mcap for recording, ...), which cost each service about 10 MB.
LEAN_COMMANDS = {"service": "u2sa_hw.cli.service_cmd"}


def build_parser(*, only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered (*only*: that one module's)."""
    parser = argparse.ArgumentParser(
        prog="u2sa", description="u2sa-hw: run, inspect and control U2SA services on a vehicle.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"u2sa-hw {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in [only] if only else COMMAND_MODULES:
        importlib.import_module(module_name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``u2sa`` console script."""
    words = sys.argv[1:] if argv is None else argv
    parser = build_parser(only=LEAN_COMMANDS.get(words[0]) if words else None)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"u2sa: {exc}", file=sys.stderr)
        return exc.code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0
    except (OSError, ValueError, LookupError) as exc:
        print(f"u2sa: {exc}", file=sys.stderr)
        return 1
