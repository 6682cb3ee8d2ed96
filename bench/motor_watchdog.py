#!/usr/bin/env python3
"""The dead-man below the driver: kill or freeze a CAN motor driver, time the wheels to zero.

A motor driver (``u2sa service``, drivers/can_motor/odrive/driver.py or drivers/can_motor/vesc/driver.py) drives two
mock controllers (ODrive axes or VESCs, in this process, on a udp_multicast bus) at 50 %,
with the controllers' own watchdog turned on and read back by the driver (``hw_watchdog``,
0.3 s). The driver process is then sent SIGKILL (dies) or SIGSTOP (hangs): it sends nothing
more, no neutral and no IDLE, so only the controllers' watchdogs can stop the wheels. The
figure is the time from the signal to the second wheel at zero (the mock's own record of its
watchdog expiry: ``watchdog_trips`` for an ODrive, ``timeouts`` for a VESC), min / median /
max over the runs. Expect about the watchdog timeout minus the time since the driver's last
frame (it re-sends every ``command_period_s``, 50 ms), plus the mock's 10 ms tick.

Usage: ``python bench/motor_watchdog.py [--runs N] [--only odrive|vesc]``. Not a test.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

import tomli_w

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.mocks.odrive_config import ENABLE_WATCHDOG_ENDPOINT, MOCK_FW, WATCHDOG_TIMEOUT_ENDPOINT  # noqa: E402
from u2sa_hw.mocks.odrive_node import OdriveCanNode  # noqa: E402
from u2sa_hw.mocks.vehicle_sim import SimVehicle  # noqa: E402
from u2sa_hw.mocks.vesc_node import VescCanNode  # noqa: E402
from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.client import BusClient  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port  # noqa: E402

GROUP = "239.74.163.2"
TIMEOUT_S = 0.3
SIGNALS = {"SIGKILL": signal.SIGKILL, "SIGSTOP": signal.SIGSTOP}
KINDS: dict[str, dict[str, Any]] = {
    "odrive": {"kind": "odrive_can", "ids": ("node_ids", [1, 2]),
               "settings": {"watchdog_timeout_endpoint": WATCHDOG_TIMEOUT_ENDPOINT,
                            "enable_watchdog_endpoint": ENABLE_WATCHDOG_ENDPOINT, "endpoints_fw": MOCK_FW,
                            "status_poll_s": 0.0}},
    "vesc": {"kind": "vesc_can", "ids": ("controller_ids", [1, 2]), "settings": {"max_duty": 0.1}},
}


def wait_for(predicate: Callable[[], object], timeout: float, what: str) -> None:
    """Poll *predicate*; RuntimeError after *timeout* s."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.005)


class Driver:
    """One ``u2sa service motors`` process on a private LCM URL, and its latest health."""

    def __init__(self, workdir: Path, url: str, kind: str, port: int) -> None:
        spec = KINDS[kind]
        key, ids = spec["ids"]
        settings = {"health_interval_s": 0.2, key: ids, "rc_gating": False, "command_timeout_s": 0.5, "odometry": False,
                    "hw_watchdog": True, "hw_watchdog_timeout_s": TIMEOUT_S, **spec["settings"]}
        profile = workdir / "vehicle.toml"
        profile.write_text(tomli_w.dumps({"vehicle": {"name": "bench", "config_dir": "config", "log_dir": "logs"},
                                          "services": {"motors": {"kind": spec["kind"], "settings": settings}},
                                          "devices": {"motors": {
                                              "address": f"can://udp_multicast/{GROUP}?port={port}"}}}))
        env = dict(os.environ, U2SA_LCM_URL=url, PYTHONPATH=str(REPO))
        self.log = open(workdir / "motors.log", "ab")
        self.proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "service", "motors", "--vehicle",
                                      str(profile)], cwd=workdir, env=env, stdout=self.log, stderr=subprocess.STDOUT)

    def end(self) -> None:
        """Kill it whatever state it is in (a stopped process takes SIGKILL too) and reap it."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)
        self.log.close()


def one_run(kind: str, sig: int, workdir: Path, bus: BusClient, url: str, health: dict[str, str]) -> float:
    """Seconds from the signal to both mock wheels at zero, for one fresh driver process."""
    port = private_udp_port()
    vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0)
    bus_args = {"interface": "udp_multicast", "channel": GROUP, "bus_options": {"port": port}}
    if kind == "odrive":
        nodes = [OdriveCanNode(vehicle, side=side, node_id=i, vel_limit=10.0, **bus_args)
                 for side, i in (("left", 1), ("right", 2))]
    else:
        nodes = [VescCanNode(vehicle, side=side, controller_id=i, timeout_s=1.0, **bus_args)
                 for side, i in (("left", 1), ("right", 2))]
    vehicle.start()
    for node in nodes:
        node.start()
    health.clear()
    driver = Driver(workdir, url, kind, port)
    stop = threading.Event()

    def command() -> None:
        while not stop.wait(0.05):
            for name in ("left", "right"):
                msg = t.PercentageCommand()
                msg.base.actuator_name, msg.percentage = name, 50.0
                bus.publish(ch.ACTUATOR_CMD, msg)

    commander = threading.Thread(target=command, daemon=True)
    try:
        wait_for(lambda: health.get("hw_watchdog") == f"on {TIMEOUT_S:.2f} s (read back)", 30,
                 f"the {kind} watchdogs read back (health: {health.get('hw_watchdog')!r})")
        commander.start()
        wait_for(lambda: all(abs(n.wheel_speed_mps if kind == "odrive" else n.output) > 0.01 for n in nodes), 30,
                 "both wheels turning")
        trips = (lambda n: n.watchdog_trips) if kind == "odrive" else (lambda n: n.timeouts)
        if any(trips(n) for n in nodes):
            raise RuntimeError("a watchdog expired while the driver was alive")
        t0 = time.monotonic()
        os.kill(driver.proc.pid, sig)
        wait_for(lambda: all(trips(n) for n in nodes), 10, "both watchdogs to expire")
        if any(abs(n.wheel_speed_mps if kind == "odrive" else n.output) > 0 for n in nodes):
            raise RuntimeError("a watchdog expired but its wheel still turns")
        return max(trips(n)[0] for n in nodes) - t0
    finally:
        stop.set()
        driver.end()
        for node in nodes:
            node.stop()
        vehicle.stop()


def main() -> None:
    """Run the kills and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="runs per controller and signal (default 7)")
    parser.add_argument("--only", choices=sorted(KINDS), help="one controller kind")
    args = parser.parse_args()
    keys = tempfile.TemporaryDirectory(prefix="u2sa-bench-key-")
    try:  # a signed bus: this run's own key, inherited by the driver processes
        from u2sa_hw.bus.key import KEY_ENV
        from u2sa_hw.bus.run_keys import fresh_key_file
        os.environ.setdefault(KEY_ENV, str(fresh_key_file(keys.name)))
    except ImportError:
        pass
    url = private_lcm_url()
    bus = BusClient(url)
    health: dict[str, str] = {}

    def on_health(_c: str, msg: t.Health) -> None:
        if msg.name == "motors":
            health.update({kv.key: kv.value for kv in msg.details}, status=msg.status)

    bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
    print(f"controller watchdog {TIMEOUT_S} s, driver re-send period 0.05 s; signal -> second wheel at zero, "
          f"{args.runs} runs each")
    try:
        with tempfile.TemporaryDirectory(prefix="u2sa-bench-wd-") as tmp:
            for kind in [args.only] if args.only else sorted(KINDS):
                for sig_name, sig in SIGNALS.items():
                    times = [one_run(kind, sig, Path(tmp), bus, url, health) for _ in range(args.runs)]
                    print(f"{kind:6s} {sig_name}: min {min(times) * 1e3:5.0f} ms   median "
                          f"{statistics.median(times) * 1e3:5.0f} ms   max {max(times) * 1e3:5.0f} ms   "
                          f"(n={len(times)})", flush=True)
    finally:
        bus.close()
        keys.cleanup()


if __name__ == "__main__":
    main()
