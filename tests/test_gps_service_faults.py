"""The GPS driver as a real ``u2sa service`` process on a pty, fed the sentences that used to end it
and the receiver states that are no GNSS fix; checked over real LCM multicast."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Iterator

import pytest
from conftest import ServiceProcesses, wait_until
from gps_stream_builder import nmea
from serial_driver_harness import ORIGIN, SIM_ORIGIN, DriverProbe, start_driver, write_profile

from u2sa_hw.drivers.gps_nmea.geoid import geoid_separation
from u2sa_hw.mocks.nmea_gps import NmeaGpsDevice
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.bus.client import BusClient

CRASHERS = (
    nmea("GPZDA,120000.00,14,03," + "9" * 20 + ",00,00"),                                   # a 20-digit year
    nmea("GNGGA,120000.00,2911.000,N,08103.000,W," + "1" * 400 + ",09,0.9,12.0,M,-30.5,M,,"),   # 400-digit quality
    nmea("GNGGA,120000.00,9940.670,N,18212.000,W,1,09,0.9,12.0,M,-30.5,M,,"),                # lat 99.7, lon 182.2
    # an epoch of its own (another time): an RMC fix whose speed and sigmas are impossible
    nmea("GNRMC,120001.00,A,2911.000,N,08103.000,W," + "9" * 400 + ",,140326,,,A"),            # speed 1e399 knots
    nmea("GNGST,120001.00,1.0,inf,inf,0.0,1e309,1e309,1e309"),                               # sigma inf
)


@pytest.fixture
def vehicle() -> Iterator[SimVehicle]:
    v = SimVehicle(**SIM_ORIGIN, start_north=20.0, start_east=-10.0)
    v.set_wheel_speed("left", 0.5)
    v.set_wheel_speed("right", 0.5)
    v.start(rate_hz=50.0)
    yield v
    v.stop()


def start(services: ServiceProcesses, bus: BusClient, tmp_path: Path, vehicle: SimVehicle,
          **options: object) -> tuple[NmeaGpsDevice, object, DriverProbe]:
    gps = NmeaGpsDevice(vehicle, link_path=tmp_path / "dev" / "gps", rate_hz=5.0, talker="GN", seed=4,
                        horizontal_sigma_m=0.3, **options)  # type: ignore[arg-type]
    gps.start()
    profile = write_profile(tmp_path, name="gps", kind="gps_nmea",
                            settings={"position_frame": "GEODETIC", "altitude_datum": "ellipsoid"},
                            devices={"gps": f"serial://{gps.address}?baud=38400"})
    probe = DriverProbe(bus, "gps", on_state=vehicle.snapshot)
    proc = start_driver(services, profile, "gps")
    return gps, proc, probe


def test_the_sentences_that_ended_the_service_are_dropped_counted_and_it_keeps_publishing(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path, vehicle: SimVehicle) -> None:
    gps, proc, probe = start(services, bus, tmp_path, vehicle)
    try:
        probe.wait_states(3, timeout=20)
        for _ in range(3):
            for line in CRASHERS:
                gps.inject(line)
        details = probe.wait_health(
            lambda d, s: {"date", "quality", "lat", "lon", "speed"} <= set(
                k.split(":")[0] for k in d["out_of_range_kinds"].split(",") if k),
            message="the impossible values counted by kind")
        assert int(details["out_of_range"]) >= 5
        mark = probe.state_count()
        probe.wait_states(10, since=mark, message="fixes after the impossible sentences")
        assert proc.poll() is None                                # still running: nothing escaped
        for msg, _ in probe.states_since(0):
            assert all(math.isfinite(msg.get(name)) for name in msg.present_fields())
            assert -90 <= msg.x <= 90 and -180 <= msg.y <= 180
            if msg.has("x_dot"):
                assert math.hypot(msg.x_dot, msg.y_dot) < 600
        assert "Traceback" not in (tmp_path / "gps.stderr").read_text()
    finally:
        gps.stop()


def test_dead_reckoning_and_simulator_are_no_gnss_fix_and_an_empty_geoid_field_uses_the_table(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path, vehicle: SimVehicle) -> None:
    gps, proc, probe = start(services, bus, tmp_path, vehicle, geoid_separation_m=None, vertical_sigma_m=0.3,
                             sentences=("GGA", "RMC", "VTG", "GSA"))
    try:
        msg, _ = probe.wait_states(3, timeout=20)[-1]
        n = geoid_separation(msg.x, msg.y)
        # the ellipsoid height = the GGA's MSL altitude + the EGM96 separation (about -30.8 m here)
        details = probe.wait_health(lambda d, s: d["geoid_source"] == "EGM96 table", message="the geoid table")
        assert float(details["geoid_sep_m"]) == pytest.approx(n, abs=0.01) and n < -29.0
        assert msg.z == pytest.approx(ORIGIN["alt"] + n, abs=1.5)   # the rover is at the origin's MSL height
        gps.set_quality(6)
        details = probe.wait_health(lambda d, s: d["fix_type"] == "DR", message="dead reckoning in health")
        assert details["fix"] == "False" and details["degraded_reason"] == "dead reckoning"
        epochs = int(details["epochs"])
        mark = probe.state_count()
        probe.wait_health(lambda d, s: int(d["epochs"]) >= epochs + 5, message="five dead-reckoning epochs")
        assert not any(m.has("x") or m.has("x_dot") for m, _ in probe.states_since(mark))
        gps.set_quality(8)
        probe.wait_health(lambda d, s: d["fix_type"] == "simulator" and d["degraded_reason"] == "simulator",
                          message="the simulator in health")
        gps.set_quality(2)
        details = probe.wait_health(lambda d, s: d["fix_type"] == "3D", message="the DGPS fix back")
        assert details["fix"] == "True" and details["fix_quality"] == "2 (dgps)"
        wait_until(lambda: probe.states_since(mark)[-1:] and probe.states_since(mark)[-1][0].has("x"),
                   message="a position again")
        assert proc.poll() is None
    finally:
        gps.stop()
