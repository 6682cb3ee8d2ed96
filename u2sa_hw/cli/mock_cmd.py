"""``u2sa mock``: the mock devices a vehicle profile names, around one simulated vehicle."""

from __future__ import annotations

import argparse
import shutil
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from u2sa_hw.cli.common import add_vehicle_option, profile_from

HELP = """\
Start the mock devices the vehicle profile's [devices.NAME] tables name, all
sampling and driven by ONE simulated vehicle ([simulation] table), in this
process; print each device's address; run until Ctrl-C.

The mocks live in the run directory (default <data_dir>/sim): pty links for
serial devices, Unix sockets for the I2C buses and GPIO chips, sysfs-shaped
directories (pwmchipN) for sysfs PWM chips; CAN buses are python-can
udp_multicast on the [simulation] can_udp_port. A copy of the profile
whose device addresses point at the mocks is written there too: run the stack on
it in another terminal with the command printed at start.

On a terminal, type a + Enter to flip the pilot's RC mode switch to autonomous,
m + Enter for manual, h + Enter to hold the vehicle still (motors turn, it does
not move; again to release), q + Enter to quit. See docs/simulation.md.
"""


def register(sub: Any) -> None:
    """Add the ``mock`` subcommand."""
    p = sub.add_parser("mock", help="run the mock devices of a vehicle profile (simulation without the stack)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="example:\n  u2sa mock --vehicle examples/ground_vehicle/vehicle.toml\n"
                              "  u2sa run --vehicle examples/ground_vehicle/data/sim/vehicle.toml")
    add_vehicle_option(p)
    p.add_argument("--run-dir", metavar="DIR", help="where the mocks and the simulation profile go "
                   "(default: <data_dir>/sim)")
    p.add_argument("--can-port", type=int, metavar="PORT", help="UDP port of the simulated CAN bus "
                   "(default: [simulation] can_udp_port)")
    p.add_argument("--list-kinds", action="store_true", help="list the mock kinds (and the service settings each "
                   "reads) and exit")
    p.set_defaults(func=cmd_mock)


def _commands(mocks: Any, done: threading.Event) -> None:
    """Read pilot commands from stdin until EOF (a non-interactive stdin simply ends here)."""
    held = False
    for line in sys.stdin:
        word = line.strip().lower()[:1]
        if word == "a":
            mocks.set_mode_switch(True)
            print("pilot: mode switch AUTONOMOUS", flush=True)
        elif word == "m":
            mocks.set_mode_switch(False)
            print("pilot: mode switch MANUAL", flush=True)
        elif word == "h":
            held = not held
            mocks.actuated.hold(held)
            print(f"vehicle {'held still' if held else 'released'}", flush=True)
        elif word == "q":
            done.set()
            return
        elif word:
            print("a: autonomous, m: manual, h: hold/release the vehicle, q: quit", flush=True)


def cmd_mock(args: Any) -> int:
    """Start the mocks, write the simulation profile, print the addresses, wait for Ctrl-C."""
    from u2sa_hw.cli import CliError

    if args.list_kinds:
        from mock_devices.catalog import CATALOG

        for kind, (_build, what) in sorted(CATALOG.items()):
            print(f"{kind:16} {what}")
        return 0
    from mock_devices.launcher import MockLauncher
    from mock_devices.sim_context import DeviceError, device_dir_for
    from u2sa_hw.sim.profile import effective_configs, write_sim_profile
    from u2sa_hw.vehicle import ProfileError

    profile = profile_from(args)
    if profile.path is None:
        raise CliError("mock: give the vehicle profile with --vehicle PATH (or set $U2SA_VEHICLE)", 2)
    run_dir = Path(args.run_dir) if args.run_dir else profile.data_dir / "sim"
    device_dir = device_dir_for(run_dir / "dev")
    try:
        mocks = MockLauncher(profile, device_dir=device_dir,
                             service_configs=effective_configs(profile), can_udp_port=args.can_port)
        mocks.start()
    except (DeviceError, ProfileError, RuntimeError, OSError) as exc:
        raise CliError(f"mock: {exc}") from None
    try:
        sim_profile = write_sim_profile(profile, run_dir=run_dir, overrides=mocks.overrides)
        s = mocks.settings
        print(f"simulated {s.model} vehicle at {profile.origin.lat:.6f}, {profile.origin.lon:.6f} "
              f"(start {s.start_north:g} m N, {s.start_east:g} m E, heading {s.start_heading_deg:g} deg)")
        for line in mocks.describe():
            print(f"  {line}")
        print(f"simulation profile: {sim_profile}")
        print(f"run the stack on it:  u2sa run --vehicle {sim_profile}")
        print("Ctrl-C stops the mocks" + ("; a/m/h/q + Enter: autonomous, manual, hold, quit"
                                          if sys.stdin.isatty() else ""), flush=True)
        done = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: done.set())
        if sys.stdin.isatty():
            threading.Thread(target=_commands, args=(mocks, done), daemon=True).start()
        while not done.wait(0.5):
            pass
    finally:
        mocks.stop()
        if not device_dir.is_relative_to(run_dir.resolve()):   # a short /tmp directory of our own
            shutil.rmtree(device_dir, ignore_errors=True)
    return 0
