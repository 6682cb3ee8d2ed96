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

On a terminal the keyboard is the pilot's RC transmitter (no Enter needed):
  w / s     throttle stick up / down (steps of 10 %)
  a / d     steering stick left / right
  space     both sticks back to the centre
  m         flip the mode switch (manual <-> autonomous)
  l         RC link lost / back
  h         hold the vehicle still (motors turn, it does not move; again to release)
  q         quit
The simulated RC mux switches only the PWM outputs the profile's [safety]
hardware_mux lists; every other actuator follows its driver. See
docs/simulation.md.
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


def cmd_mock(args: Any) -> int:
    """Start the mocks, write the simulation profile, print the addresses, wait for Ctrl-C."""
    from u2sa_hw.cli import CliError

    if args.list_kinds:
        from u2sa_hw.mocks.catalog import CATALOG

        for kind, (_build, what) in sorted(CATALOG.items()):
            print(f"{kind:16} {what}")
        return 0
    from u2sa_hw.mocks.launcher import MockLauncher
    from u2sa_hw.mocks.sim_context import MODEL_INPUTS, DeviceError, device_dir_for
    from u2sa_hw.simulation.keys import HELP, StickKeys
    from u2sa_hw.simulation.profile import effective_configs, write_sim_profile
    from u2sa_hw.profile.vehicle import ProfileError

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
    keys = None
    try:
        sim_profile = write_sim_profile(profile, run_dir=run_dir, addresses=mocks.addresses)
        s = mocks.settings
        print(f"simulated {s.model} vehicle at {profile.origin.lat:.6f}, {profile.origin.lon:.6f} "
              f"(start {s.start_north:g} m N, {s.start_east:g} m E, heading {s.start_heading_deg:g} deg)")
        for line in mocks.describe():
            print(f"  {line}")
        print(f"simulation profile: {sim_profile}")
        print(f"run the stack on it:  u2sa run --vehicle {sim_profile}")
        missing = [i for i in MODEL_INPUTS[s.model] if i not in mocks.context.fed]
        if missing:
            print(f"note: no device drives {', '.join(missing)} of the {s.model} model: the vehicle will not move "
                  "(u2sa sim refuses this profile; see docs/simulation.md)")
        done = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: done.set())
        if sys.stdin.isatty():
            held = [False]

            def hold() -> None:
                held[0] = not held[0]
                mocks.actuated.hold(held[0])

            keys = StickKeys(lambda: mocks, say=lambda text: print(text, flush=True),
                             extra={"h": ("vehicle held still / released", hold), "q": ("quit", done.set)})
            keys.start()
        # after the terminal is in cbreak mode, so a key pressed on seeing this needs no Enter
        print("Ctrl-C stops the mocks" + (f"; keys: {HELP}, h hold, q quit" if keys is not None else ""),
              flush=True)
        while not done.wait(0.5):
            pass
    finally:
        if keys is not None:
            keys.stop()
        mocks.stop()
        if not device_dir.is_relative_to(run_dir.resolve()):   # a short /tmp directory of our own
            shutil.rmtree(device_dir, ignore_errors=True)
    return 0
