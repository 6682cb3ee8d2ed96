#!/usr/bin/env python3
"""Driver benchmarks: NMEA sentences/s through the GPS driver, and the CAN command -> status
round trip through a mock ODrive.

Every driver runs as a real ``u2sa service`` process and every mock device as it does in the
tests; this script is the control system and the stopwatch. It prints:

(a) GPS: NMEA sentences/s through the GPS driver (drivers/gps_nmea/driver.py), fed through a pty
    as fast as it reads (blocking writes on the pty master), and the State Information
    messages published against the epochs written (one message per epoch expected);
(b) CAN: the command -> status round trip through a mock ODrive (each axis a node in a
    process of its own, on udp_multicast) with the ODrive driver (drivers/can_motor/odrive/driver.py)
    in between. One Percentage Command on LCM is timed to three points:
      1. the driver's Set_Input_Vel frame on the bus (the command path),
      2. the mock ODrive's status frame showing it: the first Get_Encoder_Estimates whose
         velocity is the new setpoint (the node ticks at 100 Hz, sends estimates at 50 Hz),
      3. the driver's odometry State Information at the new wheel speed (the full round
         trip LCM -> driver -> CAN -> ODrive -> CAN -> driver -> LCM).
    A point not reached within 1 s of the command is counted as missed, per point, and
    left out of that point's figures (a missed Set_Input_Vel is not hidden in a late status).

(c) compass: NMEA sentences/s through the compass driver (drivers/compass/driver.py), bursts
    of XDR, THS and ROT written back to back as fast as it reads, and the State Information
    messages published against the bursts written (one per burst expected).

Usage: ``python bench/drivers.py [--quick] [--only gps|can|compass]``. Not a test: nothing asserts.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
import tty
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, Callable

import can
import tomli_w

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from u2sa_hw.mocks.nmea_gps import NmeaGpsDevice  # noqa: E402
from u2sa_hw.mocks.serial_compass import NmeaCompassDevice  # noqa: E402
from u2sa_hw.mocks.vehicle_sim import SimVehicle  # noqa: E402
from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.client import BusClient  # noqa: E402
from u2sa_hw.protocols import odrive_cansimple as cs  # noqa: E402
from u2sa_hw.protocols.odrive_cansimple import Cmd  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port  # noqa: E402

GROUP = "239.74.163.2"
RADIUS = 0.1  # the mock ODrive's default wheel radius (m)
MAX_TURNS = 2.0
TRACK = 0.5


def percentile(values: list[float], p: float) -> float:
    """The *p*-th percentile (nearest rank) of *values*."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(p / 100.0 * len(ordered)) - 1))]


def ms(values: list[float]) -> str:
    """p50/p99/max of seconds, as milliseconds."""
    if not values:
        return "no samples"
    return (f"p50 {percentile(values, 50) * 1e3:6.2f} ms   p99 {percentile(values, 99) * 1e3:6.2f} ms   "
            f"max {max(values) * 1e3:6.2f} ms   (n={len(values)})")


class Services:
    """``u2sa service`` processes of one vehicle profile in a temp dir, on a private LCM URL."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self.url = private_lcm_url()
        self.procs: list[subprocess.Popen] = []
        self.services: dict[str, Any] = {}
        self.devices: dict[str, Any] = {}

    def start(self, name: str, kind: str, settings: dict[str, Any], address: str) -> subprocess.Popen:
        """``u2sa service NAME`` of *kind* with *settings*, its device (named after it) at *address*."""
        self.services[name] = {"kind": kind, "settings": {"health_interval_s": 0.2, **settings}}
        self.devices[name] = {"address": address}
        profile = self.workdir / "vehicle.toml"
        profile.write_text(tomli_w.dumps({"vehicle": {"name": "bench", "config_dir": "config", "log_dir": "logs"},
                                          "services": self.services, "devices": self.devices}))
        env = dict(os.environ, U2SA_LCM_URL=self.url, PYTHONPATH=str(REPO))
        log = open(self.workdir / f"{name}.log", "wb")
        proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "service", name, "--vehicle", str(profile)],
                                cwd=self.workdir, env=env, stdout=log, stderr=subprocess.STDOUT)
        self.procs.append(proc)
        return proc

    def stop(self) -> None:
        for proc in self.procs:
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()


def wait_for(predicate: Callable[[], object], timeout: float, what: str) -> None:
    """Poll *predicate*; RuntimeError after *timeout* s."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.01)


def health_watch(bus: BusClient, name: str) -> dict[str, str]:
    """A dict kept equal to the latest Health details (and status) of service *name*."""
    latest: dict[str, str] = {}

    def on_health(_c: str, msg: t.Health) -> None:
        if msg.name == name:
            latest.clear()
            latest.update({kv.key: kv.value for kv in msg.details}, status=msg.status)

    bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
    return latest


# ---------------------------------------------------------------- (a) GPS ----------------------
GPS_FLOOR_PER_S = 8500   # sentences/s the GPS driver must keep (issue 13: before range checks and merging)


def nmea_epochs(workdir: Path, epochs: int) -> tuple[list[bytes], int]:
    """*epochs* receiver epochs (7 sentences each, distinct UTC times 10 ms apart) as bytes."""
    clock = [datetime(2026, 3, 14, 12, 0, 0, tzinfo=timezone.utc)]
    vehicle = SimVehicle(origin_lat=29.1895, origin_lon=-81.0483)
    gps = NmeaGpsDevice(vehicle, link_path=workdir / "unused", utc_clock=lambda: clock[0])
    out, sentences = [], 0
    for _ in range(epochs):
        lines = gps.epoch_lines(vehicle.snapshot())
        sentences += len(lines)
        out.append(b"".join(lines))
        clock[0] += timedelta(milliseconds=10)
    return out, sentences


def bench_gps(services: Services, bus: BusClient, epochs: int) -> None:
    """Feed the GPS driver as fast as it reads and count what it publishes."""
    chunks, sentences = nmea_epochs(services.workdir, epochs)
    master, slave = os.openpty()
    tty.setraw(slave)  # a UART: no echo, no line discipline
    link = services.workdir / "gps"
    link.symlink_to(os.ttyname(slave))
    published = [0]

    def on_state(_c: str, msg: t.StateInformation) -> None:
        if msg.sensor_name == "gps":
            published[0] += 1

    bus.transport.subscribe(ch.STATE_INFO, t.StateInformation, on_state)
    health = health_watch(bus, "gps")
    services.start("gps", "gps_nmea", {}, f"serial://{link}?baud=115200")
    wait_for(lambda: health.get("port") == "open", 20, "the GPS driver to open its port")
    start = time.monotonic()
    for chunk in chunks:
        os.write(master, chunk)  # blocks while the kernel buffer is full: the driver sets the pace
    written = time.monotonic()
    last, last_change = published[0], time.monotonic()
    while published[0] < epochs and time.monotonic() - last_change < 2.0:
        time.sleep(0.005)
        if published[0] != last:
            last, last_change = published[0], time.monotonic()
    done = time.monotonic() if published[0] >= epochs else last_change
    elapsed = done - start
    print(f"(a) NMEA sentences/s through the GPS driver: {sentences} sentences ({epochs} epochs x "
          f"{sentences // epochs}) in {elapsed:.2f} s")
    rate = sentences / elapsed
    print(f"    {rate:.0f} sentences/s parsed   {published[0] / elapsed:.0f} State Information/s "
          f"published   {published[0]}/{epochs} epochs published   (writer done after {written - start:.2f} s; "
          f"includes one epoch_gap_s for the last epoch)")
    print(f"    floor {GPS_FLOOR_PER_S}/s (issue 13): {'held' if rate >= GPS_FLOOR_PER_S else 'NOT held'}")
    os.close(master)
    os.close(slave)


# ---------------------------------------------------------------- (c) compass -----------------
def bench_compass(services: Services, bus: BusClient, bursts: int) -> None:
    """Feed the NMEA compass driver attitude-first bursts (XDR, THS, ROT) as fast as it reads."""
    vehicle = SimVehicle(origin_lat=29.1895, origin_lon=-81.0483)
    compass = NmeaCompassDevice(vehicle, link_path=services.workdir / "unused-compass", talker="HE",
                                sentences=("XDR", "THS", "ROT"))
    chunks = [b"".join(compass.epoch_lines(vehicle.snapshot())) for _ in range(bursts)]
    sentences = 3 * bursts
    master, slave = os.openpty()
    tty.setraw(slave)
    link = services.workdir / "compass"
    link.symlink_to(os.ttyname(slave))
    published = [0]

    def on_state(_c: str, msg: t.StateInformation) -> None:
        if msg.sensor_name == "compass":
            published[0] += 1

    bus.transport.subscribe(ch.STATE_INFO, t.StateInformation, on_state)
    health = health_watch(bus, "compass")
    services.start("compass", "compass_serial", {}, f"serial://{link}?baud=115200")
    wait_for(lambda: health.get("port") == "open", 20, "the compass driver to open its port")
    start = time.monotonic()
    for chunk in chunks:
        os.write(master, chunk)  # back to back, no pause between bursts: grouped by order, not silence
    last, last_change = published[0], time.monotonic()
    while published[0] < bursts and time.monotonic() - last_change < 2.0:
        time.sleep(0.005)
        if published[0] != last:
            last, last_change = published[0], time.monotonic()
    elapsed = (time.monotonic() if published[0] >= bursts else last_change) - start
    print(f"(c) NMEA sentences/s through the compass driver: {sentences} sentences ({bursts} bursts of XDR, "
          f"THS, ROT, no pause between them) in {elapsed:.2f} s")
    print(f"    {sentences / elapsed:.0f} sentences/s parsed   {published[0] / elapsed:.0f} State Information/s "
          f"published   {published[0]}/{bursts} bursts published")
    os.close(master)
    os.close(slave)


# ---------------------------------------------------------------- (b) CAN round trip -----------
def start_mock_odrives(services: Services, port: int) -> list[subprocess.Popen]:
    """Two mock ODrive nodes (1 left, 2 right), each in its own process with its own vehicle."""
    procs = []
    for node, side in ((1, "left"), (2, "right")):
        proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.mocks.odrive_node", "--node-id", str(node), "--side",
                                 side, "--port", str(port)], cwd=REPO, stdout=subprocess.PIPE, text=True,
                                env=dict(os.environ, PYTHONPATH=str(REPO)))
        assert proc.stdout is not None
        if not proc.stdout.readline().startswith("ready"):
            raise RuntimeError("mock ODrive did not start")
        services.procs.append(proc)
        procs.append(proc)
    return procs


POINTS = ("set_input_vel", "status", "state")
POINT_NAMES = {"set_input_vel": "1. Set_Input_Vel on the bus (driver)",
               "status": "2. ODrive status (encoder estimate) at it",
               "state": "3. odometry State Information (round trip)"}


def bench_round_trip(services: Services, bus: BusClient, port: int, count: int) -> None:
    """Percentage Command -> Set_Input_Vel -> ODrive status -> driver odometry, per command."""
    health = health_watch(bus, "motors")
    services.start("motors", "odrive_can", {
        "node_ids": [1, 2], "max_turns_per_s": MAX_TURNS, "command_timeout_s": 0.0, "rc_gating": False,
        "track_width_m": TRACK}, f"can://udp_multicast/{GROUP}?port={port}")
    wait_for(lambda: health.get("left.phase") == "armed" and health.get("right.phase") == "armed", 30,
             "both ODrive axes armed")
    can_bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port)
    vel_id = cs.arbitration_id(1, Cmd.SET_INPUT_VEL)
    estimate_id = cs.arbitration_id(1, Cmd.GET_ENCODER_ESTIMATES)
    lock = threading.Lock()
    pending: dict[str, Any] = {}
    times: dict[str, list[float]] = {point: [] for point in POINTS}
    missed = dict.fromkeys(POINTS, 0)

    def reached(point: str, now: float) -> None:
        if pending and point not in pending:
            pending[point] = now - pending["t0"]

    def on_state(_c: str, msg: t.StateInformation) -> None:
        now = time.monotonic()
        if msg.sensor_name != "motors":
            return
        v_left = msg.x_dot + msg.psi_dot * TRACK / 2.0
        with lock:
            if pending and abs(v_left - pending["v_left"]) < 1e-3:
                reached("state", now)

    def can_reader(stop: threading.Event) -> None:
        while not stop.is_set():
            msg = can_bus.recv(timeout=0.05)
            if msg is None or msg.is_remote_frame or msg.arbitration_id not in (vel_id, estimate_id):
                continue
            now = time.monotonic()
            if msg.arbitration_id == vel_id:
                vel, point = cs.decode_set_input_vel(bytes(msg.data))[0], "set_input_vel"
            else:
                vel, point = cs.decode_encoder_estimates(bytes(msg.data))[1], "status"
            with lock:
                if pending and abs(vel - pending["turns"]) < 1e-3:
                    reached(point, now)

    bus.transport.subscribe(ch.STATE_INFO, t.StateInformation, on_state)
    stop = threading.Event()
    reader = threading.Thread(target=can_reader, args=(stop,), daemon=True)
    reader.start()
    try:
        for i in range(count):
            percent = 10.0 + (i % 40)  # every command differs from the one before
            turns = percent / 100.0 * MAX_TURNS
            cmd = t.PercentageCommand()
            cmd.base.actuator_name, cmd.percentage = "left", percent
            with lock:
                pending.clear()
                pending.update(t0=time.monotonic(), turns=turns, v_left=turns * 2 * math.pi * RADIUS)
            bus.publish(ch.ACTUATOR_CMD, cmd)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline and not all(point in pending for point in POINTS):
                time.sleep(0.0005)
            with lock:
                for point in POINTS:
                    if point in pending:
                        times[point].append(pending[point])
                    else:
                        missed[point] += 1
                pending.clear()
            time.sleep(random.uniform(0.0, 0.02))
    finally:
        stop.set()
        reader.join()
        can_bus.shutdown()
    print(f"(b) CAN command -> status round trip through a mock ODrive (ODrive driver; {count} Percentage Commands "
          "on LCM, each timed to:)")
    for point in POINTS:
        print(f"    {POINT_NAMES[point]:<44} {ms(times[point])}   missed {missed[point]}")


def main() -> None:
    """Run the benchmarks and print the figures."""
    use_run_key()   # without an installed key, a fresh one for this run and the services it starts
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples")
    parser.add_argument("--only", choices=("gps", "can", "compass"), help="run one part")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="u2sa-bench-") as tmp:
        services = Services(Path(tmp))
        bus = BusClient(services.url)
        try:
            if args.only in (None, "gps"):
                bench_gps(services, bus, 300 if args.quick else 2000)
            if args.only in (None, "compass"):
                bench_compass(services, bus, 300 if args.quick else 2000)
            if args.only in (None, "can"):
                port = private_udp_port()
                start_mock_odrives(services, port)
                bench_round_trip(services, bus, port, 60 if args.quick else 300)
        finally:
            bus.close()
            services.stop()


if __name__ == "__main__":
    main()
