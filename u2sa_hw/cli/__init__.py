"""The ``u2sa`` command line.

Each subcommand lives in its own module with a ``register(subparsers)`` function;
``COMMAND_MODULES`` lists them (modules outside ``u2sa_hw`` -- mocks, replay -- are
imported only when their command runs, so ``u2sa_hw`` stays free of them).
Errors are one line on stderr (``u2sa: ...``) with a non-zero exit status, never a traceback
(a missing bus key or profile included). A command whose reader goes away (``u2sa echo X |
head -3``) exits at once and quietly with status 141, as a process killed by SIGPIPE would.
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
  u2sa service estimator --vehicle examples/ground_vehicle/vehicle.toml
  u2sa services                      list live services (discovery)
  u2sa topics                        channels seen on the bus with rate and bandwidth
  u2sa echo STATE_ESTIMATE --count 1 --json
  u2sa pub STATE_INFO StateInformation sensor_name=test x=1.5 psi=0.3
  u2sa param list estimator          a service's config; param set changes and persists it
  u2sa param save params.toml        every service's parameters to a file; param load FILE restores them
  u2sa mission status                the mission and its current goal; goto/skip/restart/upload change it
  u2sa mission upload field.plan     a QGroundControl plan (import/export convert between .plan and XML)
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
        status = int(args.func(args) or 0)
        sys.stdout.flush()   # here, not at exit, so a reader gone before the last line is seen below
        return status
    except CliError as exc:
        print(f"u2sa: {exc}", file=sys.stderr)
        return exc.code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return output_closed()
    except (OSError, ValueError, LookupError) as exc:
        print(f"u2sa: {exc}", file=sys.stderr)
        return 1
    except RuntimeError as exc:
        if not _user_facing(exc):
            raise
        print(f"u2sa: {exc}", file=sys.stderr)
        return 1


# Errors whose text is the whole story for a user (a missing or unreadable bus key, a bus that cannot
# open): one line, as a CliError, wherever they are raised. Named by module so none is imported here.
USER_FACING_ERRORS = (("u2sa_hw.bus.transport", "TransportError"), ("u2sa_hw.bus.key", "BusKeyError"))


def _user_facing(exc: BaseException) -> bool:
    classes = [getattr(sys.modules.get(module), name, None) for module, name in USER_FACING_ERRORS]
    return any(cls is not None and isinstance(exc, cls) for cls in classes)


SIGPIPE_STATUS = 141   # 128 + SIGPIPE: what a shell reports for `yes | head -1`'s yes


def output_closed() -> int:
    """Our stdout's reader went away (``u2sa echo X | head -3``): exit quietly with the SIGPIPE status.

    stdout is pointed at /dev/null first, so the interpreter's flush at exit does not raise
    again (https://docs.python.org/3/library/signal.html#note-on-sigpipe).
    """
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass
    return SIGPIPE_STATUS
