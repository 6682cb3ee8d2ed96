"""A composed two-minute receiver stream through a real pty into the GPS service process.

10 Hz GGA with RMC, ZDA and GSA once a second (the stream that used to lose its RMC and ZDA
as "late"), from a multi-constellation receiver (GN GGA, GP and GL GSA), written as fast as
the driver reads it: no silence tells the epochs apart, only their times. Every published
message is checked, in order, against the epoch it must come from (over real LCM multicast).
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import pytest
from conftest import ServiceProcesses, wait_until
from gps_stream_builder import Part, Receiver, epoch_lines, printed, trajectory
from serial_driver_harness import DriverProbe, start_driver, write_profile

from u2sa_hw.mocks.pty_serial import PtySerialDevice
from u2sa_hw.bus.client import BusClient
from u2sa_hw.profile.vehicle import Origin

ORIGIN = Origin(lat=29.1895, lon=-81.0483, alt=10.0)
RATE_HZ = 10.0
EPOCHS = 1200   # two minutes
RECEIVER = Receiver(rate_hz=RATE_HZ, baud=115200, parts=(
    Part("GGA", "GN"), Part("RMC", "GN", every=10), Part("GSA", "GP", every=10), Part("GSA", "GL", every=10),
    Part("ZDA", "GN", every=10)))


def write_all(link: PtySerialDevice, data: bytes) -> None:
    """Write *data* whole: the pty buffer is small, so wait for the driver to read when it is full."""
    pause = threading.Event()
    while data:
        n = link.write(data)
        data = data[n:]
        if data:
            pause.wait(0.002)   # flow control, as a UART's would: the reader empties the buffer


def test_a_two_minute_10_hz_stream_without_pauses_gives_every_epoch_once_with_its_1_hz_velocity(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    link = PtySerialDevice(link_path=tmp_path / "dev" / "gps", name="gps")
    link.start()
    try:
        profile = write_profile(tmp_path, name="gps", kind="gps_nmea",
                                settings={"position_frame": "GEODETIC", "stale_after_s": 30.0},
                                devices={"gps": f"serial://{link.address}?baud=115200"})
        probe = DriverProbe(bus, "gps")
        proc = start_driver(services, profile, "gps")
        probe.wait_health(lambda d, s: d["port"] == "open", timeout=20, message="the port open")
        solutions = [trajectory(ORIGIN, k, RATE_HZ) for k in range(EPOCHS)]
        for k, sol in enumerate(solutions):
            write_all(link, b"".join(line for _, line in epoch_lines(RECEIVER, sol, k)))
        wait_until(lambda: probe.state_count() >= EPOCHS, timeout=60, message=f"{EPOCHS} fixes")
        details = probe.wait_health(lambda d, s: int(d["epochs"]) >= EPOCHS, message="every epoch in health")
        sent = [msg for msg, _ in probe.states_since(0)]
        assert len(sent) == EPOCHS                     # once each: no supplement, no repeat
        for k, (msg, sol) in enumerate(zip(sent, solutions)):
            assert msg.x == pytest.approx(printed(sol.lat), abs=1e-9), k
            assert msg.y == pytest.approx(printed(sol.lon), abs=1e-9), k
            assert msg.has("x_dot") == (k % 10 == 0), k      # each second's RMC with its own GGA
            if msg.has("x_dot") and sol.course is not None:
                c = math.radians(round(sol.course, 2))
                assert msg.x_dot == pytest.approx(sol.speed * math.cos(c), abs=2e-3), k
        assert details["late_sentences"] == "0" and details["supplements"] == "0"
        assert details["out_of_range"] == "0" and details["malformed"] == "0" and details["fix_type"] == "3D"
        assert details["talkers"] == "GL,GN,GP" and details["utc"].startswith("2026-03-15")
        assert proc.poll() is None
    finally:
        link.stop()
