"""``u2sa sim``: the whole stack on simulated hardware, driving a mission."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

DEFAULT_VEHICLE = Path("examples/ground_vehicle/vehicle.toml")
EXIT_FAILED, EXIT_TIMEOUT = 1, 3

HELP = """\
Start the mock devices of the vehicle profile around one simulated vehicle (it
moves under the motor commands the mocks receive), run every service of the
profile through the launcher, let the simulated pilot switch the RC mux to
autonomous once the stack is ready, and follow the mission on one progress line
(goal k of N, distance to it, speed, heading, mode).

Exit status: 0 when the mission completes (for a looping mission: one full
loop), 3 on timeout, 1 when a service keeps failing, a failsafe is raised or
autonomy is lost more than 3 times (the simulated safety pilot re-engages after
each loss); the reason is printed. Written to --out:
summary.json and summary.txt (time, distance, per-goal arrival times, largest
cross-track error, closest approach to each obstacle, estimate error), track.csv,
track.png (the driven track, the waypoints, the obstacles), services.log (every
service's output), logs/ (one log per service), run/ (the simulation's copy of
the profile, the mock device nodes), recording/ with --record. summary.json's
"outputs" has every actuator output's final state as the mock devices saw it.

--scenario FILE plays a failsafe scenario instead of waiting for the mission's
end: its events at their times (after autonomy engaged), then summary.json's
"scenario" says, per event, when each output (CAN setpoint, PWM pulse, GPIO
level) went neutral and moved again, and the RC_MODE states heard.

As under u2sa run, the safety chain (RC mux, actuator drivers, HSM) runs
SCHED_FIFO when permitted (root, CAP_SYS_NICE, ulimit -r), and so does this
process, which hosts the mock devices, below it (priority 10): real hardware
does not stall when the board is busy, and a stalled simulated RC receiver is a
false NO RC SIGNAL. When not permitted, one line says so (docs/safety.md).
--no-realtime (or U2SA_SIM_REALTIME=off in the environment, as the test suite
sets it): everything at normal priority.

The pilot hands over only once the IMU has calibrated at rest. A profile whose
devices do not drive every input of its [simulation] model is refused.

Before anything starts the profile is checked as u2sa check --sim does
(docs/check.md): every error is listed and nothing starts. A service that
drives a device needs a mock ([devices.NAME] mock = "..."); the error names the
device, its service and the mock kind to add. A service that reports a device or config
error while starting is named on the console with its error text.

Keys, when stdin is a terminal (the pilot's RC transmitter):
  w / s     throttle stick up / down (steps of 10 %)
  a / d     steering stick left / right
  space     both sticks back to the centre
  m         flip the mode switch (manual <-> autonomous)
  l         RC link lost / back
See docs/simulation.md.
"""


def register(sub: Any) -> None:
    """Add the ``sim`` subcommand."""
    from u2sa_hw.cli.run_cmd import add_realtime_option

    p = sub.add_parser("sim", help="drive a mission with the whole stack on simulated hardware",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="example:\n  u2sa sim --vehicle examples/boat/vehicle.toml --out boat-out --record")
    p.add_argument("--vehicle", metavar="PATH", type=Path, default=DEFAULT_VEHICLE,
                   help=f"vehicle profile (default: {DEFAULT_VEHICLE})")
    p.add_argument("--mission", metavar="FILE", type=Path, help="mission XML instead of the profile's mission_file")
    p.add_argument("--out", metavar="DIR", type=Path, default=Path("sim-out"),
                   help="where the summary, plot and logs go (default: sim-out)")
    p.add_argument("--timeout", metavar="S", type=float,
                   help="give up after S seconds from start (default: the profile's [simulation] timeout_s)")
    p.add_argument("--record", action="store_true", help="record every channel with the recorder into DIR/recording")
    p.add_argument("--lcm-url", metavar="URL", help="LCM URL of this run (default: a free private port, so "
                   "runs beside other u2sa processes stay apart)")
    p.add_argument("--can-port", type=int, metavar="PORT",
                   help="UDP port of the simulated CAN bus (default: a free private port)")
    p.add_argument("--bus-key", type=Path, metavar="FILE",
                   help="sign the run's bus with this key (default: a fresh one in --out, printed), e.g. to "
                   "record or watch the run from another process; the pilot's pair (pilot.key, pilot.pub) must be "
                   "beside it ('u2sa key pilot --file FILE' makes one)")
    p.add_argument("--scenario", metavar="FILE", type=Path,
                   help="play a failsafe scenario (events at times: RC loss, manual switch, sticks, GPS fix loss, "
                        "a service killed or stopped, a forged command, a failsafe) and record what every actuator "
                        "output did (summary.json 'scenario'); e.g. examples/ground_vehicle/scenarios/rc_loss.toml")
    add_realtime_option(p)
    p.set_defaults(func=cmd_sim)


def cmd_sim(args: Any) -> int:
    """Run the simulation; CliError with the reason unless the mission completed."""
    from u2sa_hw.mocks.sim_context import DeviceError
    from u2sa_hw.simulation.events import ScenarioError
    from u2sa_hw.simulation.runner import SimOptions, SimRun
    from u2sa_hw.cli import CliError

    if args.timeout is not None and args.timeout <= 0:
        raise CliError("sim: --timeout must be > 0 seconds", 2)
    if not args.vehicle.exists():
        raise CliError(f"sim: {args.vehicle}: vehicle profile not found (run from the repository root for the "
                       "default, or pass --vehicle PATH)", 2)
    from u2sa_hw.cli.check_cmd import refuse_on_errors

    refuse_on_errors(args.vehicle, command="sim", for_sim=True)
    lcm_url, can_port = _private_bus(args)
    options = SimOptions(vehicle=args.vehicle, out=args.out, mission=args.mission, timeout_s=args.timeout,
                         record=args.record, lcm_url=lcm_url, can_port=can_port, scenario=args.scenario,
                         realtime=args.realtime)
    keys = None
    try:
        run = SimRun(options)
        if sys.stdin.isatty() and sys.stdout.isatty():
            from u2sa_hw.simulation.keys import StickKeys

            keys = StickKeys(lambda: run.mocks, say=run.progress.event)
            keys.start()
        summary = run.run()
    except (DeviceError, ScenarioError) as exc:   # refused before anything moves: the file, the key, the fix
        raise CliError(f"sim: {exc}", 2) from None
    except RuntimeError as exc:   # the bus or a mock CAN node could not open; the message says why
        raise CliError(f"sim: {exc}") from None
    finally:
        if keys is not None:
            keys.stop()
    if args.record:
        print_recordings(args.out / "recording")
    if summary["result"] in ("completed", "played"):   # played: a scenario ran to its end (goals not all reached)
        return 0
    where = f"(summary: {args.out / 'summary.txt'})"
    if summary["result"] == "timeout":
        raise CliError(f"sim: {summary['reason']} {where}", EXIT_TIMEOUT)
    raise CliError(f"sim failed: {summary['reason']} {where}", EXIT_FAILED)


def print_recordings(directory: Path) -> None:
    """Name the MCAP files the recorder wrote (``u2sa sim --record``), or say that it wrote none."""
    files = sorted(directory.rglob("*.mcap")) if directory.is_dir() else []
    if not files:
        print(f"recording: no MCAP file in {directory} (see the recorder's log under the run directory)",
              file=sys.stderr)
    for f in files:
        print(f"recording: {f} ({f.stat().st_size / 1e6:.1f} MB; u2sa log info {f})")


def _private_bus(args: Any) -> tuple[str, int]:
    """A fresh bus key, and free LCM and CAN ports, for this run (given ones kept); printed so a user can join.

    The key goes to $U2SA_BUS_KEY_FILE, which the services, the mocks and the monitor inherit:
    another run, or a vehicle, on this machine is then only forged packets to this one.
    """
    import os

    from u2sa_hw.bus.key import KEY_ENV
    from u2sa_hw.bus.run_keys import fresh_key_file
    from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port

    lcm_url = args.lcm_url or private_lcm_url()
    lcm_port = int(lcm_url.split("?", 1)[0].rsplit(":", 1)[-1]) if lcm_url.startswith("udpm://") else 0
    can_port = args.can_port or private_udp_port(avoid={lcm_port}, span=4)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.bus_key is not None:
        from u2sa_hw.bus.key import BusKeyError, read_key
        from u2sa_hw.cli import CliError

        try:
            read_key(args.bus_key)
        except BusKeyError as exc:
            raise CliError(f"sim: {exc}", 2) from None
        from u2sa_hw.bus.pilot import pilot_paths
        missing = [p for p in pilot_paths(args.bus_key) if not p.is_file()]
        if missing:   # the sim's RC mux signs RC_MODE with it: without it the vehicle would never leave neutral
            raise CliError(f"sim: no pilot key beside {args.bus_key} ({', '.join(p.name for p in missing)} missing): "
                           f"make a pair with 'u2sa key pilot --file {args.bus_key}'", 2)
    key = args.bus_key.resolve() if args.bus_key is not None else fresh_key_file(args.out).resolve()
    os.environ[KEY_ENV] = str(key)
    print(f"u2sa sim: bus {lcm_url}, CAN port {can_port}, key {key} (to join: U2SA_LCM_URL='{lcm_url}' "
          f"{KEY_ENV}={key} u2sa services)", flush=True)
    return lcm_url, can_port
