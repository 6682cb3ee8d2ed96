"""GPS NMEA driver as a real service process against the mock receiver on a pty, with every fault the
mock can script (its parsing, epoch and fix rules on their own: tests/test_gps_parse_fix.py)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Iterator

import pytest
from conftest import ServiceProcesses, wait_until
from serial_driver_harness import ORIGIN, SIM_ORIGIN, DriverProbe, start_driver, write_profile

from u2sa_hw.drivers.gps_nmea.driver import GpsNmeaDriver
from u2sa_hw.mocks.nmea_gps import NmeaGpsDevice
from u2sa_hw.mocks.pty_serial import LineSettings
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.bus.client import BusClient
from u2sa_hw.config.fields import ConfigError
from u2sa_hw.geo import geodetic_to_ned
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.vehicle import Origin, VehicleProfile

GEO = Origin(**ORIGIN)


# ---------------------------------------------------------------- the service ------------------
RATE_HZ = 5.0
H_SIGMA = 0.3


@pytest.fixture
def vehicle() -> Iterator[SimVehicle]:
    """A rover about 140 m from the origin driving at 0.5 m/s on a heading of 30 degrees."""
    v = SimVehicle(**SIM_ORIGIN, start_north=120.0, start_east=-80.0, start_yaw=math.radians(30.0))
    v.set_wheel_speed("left", 0.5)
    v.set_wheel_speed("right", 0.5)
    v.start(rate_hz=100.0)
    yield v
    v.stop()


def make_gps(vehicle: SimVehicle, tmp_path: Path, **options: object) -> NmeaGpsDevice:
    options = {"rate_hz": RATE_HZ, "horizontal_sigma_m": H_SIGMA, "vertical_sigma_m": 0.5, "seed": 3, **options}
    dev = NmeaGpsDevice(vehicle, link_path=tmp_path / "dev" / "gps", **options)
    dev.start()
    return dev


@pytest.fixture
def gps(vehicle: SimVehicle, tmp_path: Path) -> Iterator[NmeaGpsDevice]:
    dev = make_gps(vehicle, tmp_path, talker="GN")
    yield dev
    dev.stop()


def run_gps(services: ServiceProcesses, bus: BusClient, tmp_path: Path, address: str, vehicle: SimVehicle, *,
            line: str = "baud=38400", devices: dict[str, str] | None = None,
            **settings: object) -> tuple[object, DriverProbe]:
    """The gps service on device ``gps`` at the pty *address* with *line* (baud rate and framing)."""
    profile = write_profile(tmp_path, name="gps", kind="gps_nmea", settings=settings,
                            devices={"gps": f"serial://{address}?{line}", **(devices or {})})
    probe = DriverProbe(bus, "gps", on_state=vehicle.snapshot)
    proc = start_driver(services, profile, "gps")
    return proc, probe


def test_gps_service_publishes_one_ned_fix_per_epoch_matching_the_vehicle(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path, vehicle: SimVehicle, gps: NmeaGpsDevice) -> None:
    proc, probe = run_gps(services, bus, tmp_path, gps.address, vehicle)
    states = probe.wait_states(10, timeout=20)
    for msg, truth in states:
        assert msg.sensor_name == "gps" and msg.reference_frame == "NED" and msg.header.system_id == 7
        # the message left up to one epoch gap before the truth was sampled; 0.5 m/s moves 0.1 m in that time
        assert abs(msg.x - truth.north) < 5 * H_SIGMA + 0.2 and abs(msg.y - truth.east) < 5 * H_SIGMA + 0.2
        assert abs(msg.z - truth.down) < 5 * 0.5
        assert abs(msg.x_dot - truth.v_north) < 0.3 and abs(msg.y_dot - truth.v_east) < 0.3
        assert abs(math.degrees(msg.psi - truth.yaw)) < 1.5                     # HDT true heading
        assert (msg.x_sigma, msg.y_sigma, msg.z_sigma) == (H_SIGMA, H_SIGMA, 0.5)  # from GST
    # the receiver's epochs are alike: after two seconds each ends with its last sentence, not after the silence
    details = probe.wait_health(lambda d, s: int(d["epochs"]) >= 5 and d["epoch_end"] == "on completion")
    assert details["status"] == "ok" and details["degraded_reason"] == ""
    assert details["fix"] == "True" and details["fix_type"] == "3D" and details["fix_quality"] == "1 (gps)"
    assert details["satellites"] == "10" and details["hdop"] == "0.9" and details["talkers"] == "GN"
    assert details["port"] == "open" and details["bad_checksums"] == "0"
    assert details["late_sentences"] == "0" and details["out_of_range"] == "0"
    # one publication per epoch of seven sentences, not one per sentence (health is read on its own thread: an
    # epoch counted and not yet published when it was read is the one behind)
    epochs, published = int(details["epochs"]), int(details["published"])
    assert epochs - published in (0, 1), details
    assert int(details["lines"]) >= 6 * epochs
    lat, lon = float(details["lat"]), float(details["lon"])
    north, east, _ = geodetic_to_ned(lat, lon, origin=GEO)
    assert abs(north - vehicle.snapshot().north) < 3.0 and abs(east - vehicle.snapshot().east) < 3.0

    # the frame is read live: changed over the bus, the next epochs come out geodetic
    reply = bus.set_config("gps", "position_frame", "GEODETIC", timeout=10)
    assert reply is not None and reply.ok, reply and reply.error
    wait_until(lambda: probe.states_since(0)[-1][0].reference_frame == "GEODETIC", message="a GEODETIC message")
    msg, truth = probe.states_since(0)[-1]
    north, east, _ = geodetic_to_ned(msg.x, msg.y, origin=GEO)
    assert abs(north - truth.north) < 5 * H_SIGMA + 0.2 and abs(east - truth.east) < 5 * H_SIGMA + 0.2
    assert proc.poll() is None


def test_gps_says_each_change_of_fix_in_health_at_once(services: ServiceProcesses, bus: BusClient, tmp_path: Path,
                                                       vehicle: SimVehicle, gps: NmeaGpsDevice) -> None:
    """With a 60 s health interval only the start and the change hooks publish health (pre-arm reads it)."""
    proc, probe = run_gps(services, bus, tmp_path, gps.address, vehicle, health_interval_s=60.0, stale_after_s=0.5)

    def said() -> list[dict[str, str]]:
        return [{kv.key: kv.value for kv in h.details} for h in list(probe.health)]

    fixed = wait_until(lambda: [d for d in said() if d["fix_type"] == "3D"], timeout=20, message="a 3D fix in health")
    assert float(fixed[0]["h_sigma_m"]) == pytest.approx(math.hypot(H_SIGMA, H_SIGMA), abs=0.01)   # from GST
    gps.set_fix(False)
    lost = wait_until(lambda: [d for d in said() if d["fix_type"] == "no fix"], message="the lost fix in health")
    assert lost[0]["h_sigma_m"] == "" and lost[0]["fix"] == "False"
    gps.set_fix(True)
    wait_until(lambda: [d["fix_type"] for d in said()][-1] == "3D", message="the fix back in health")
    gps.silence(True)
    wait_until(lambda: said()[-1]["data"] == "stale", message="the silent receiver in health")
    gps.silence(False)
    wait_until(lambda: said()[-1]["data"] == "ok", message="the receiver back in health")
    assert proc.poll() is None


def test_gps_geodetic_frame_hdop_sigmas_and_raw_taps(services: ServiceProcesses, bus: BusClient, tmp_path: Path,
                                                      vehicle: SimVehicle) -> None:
    dev = make_gps(vehicle, tmp_path, talker="GB", sentences=("GGA", "RMC", "VTG", "GSA"))
    try:
        _, probe = run_gps(services, bus, tmp_path, dev.address, vehicle, position_frame="GEODETIC", uere_m=2.0,
                           record_raw=True)
        states = probe.wait_states(5, timeout=20)
        for msg, truth in states:
            assert msg.reference_frame == "GEODETIC"
            north, east, down = geodetic_to_ned(msg.x, msg.y, msg.z, origin=GEO)
            assert abs(north - truth.north) < 5 * H_SIGMA + 0.2 and abs(east - truth.east) < 5 * H_SIGMA + 0.2
            assert msg.x_sigma == pytest.approx(0.9 * 2.0 / math.sqrt(2)) and msg.z_sigma == pytest.approx(1.4 * 2.0)
            assert not msg.has("psi")
        wait_until(lambda: len(probe.raw) >= 5, timeout=10, message="RAW.gps records")
        received = b"".join(r.data for r in list(probe.raw) if r.direction == 0)
        assert all(r.device == "gps" and r.length == len(r.data) for r in probe.raw)
        sent = [line.text.encode() for line in dev.history]
        assert sum(line in received for line in sent) >= 10   # the very bytes the receiver wrote
    finally:
        dev.stop()


def test_gps_survives_garbage_bad_checksums_and_loss_of_fix(services: ServiceProcesses, bus: BusClient,
                                                            tmp_path: Path, vehicle: SimVehicle,
                                                            gps: NmeaGpsDevice) -> None:
    proc, probe = run_gps(services, bus, tmp_path, gps.address, vehicle)
    probe.wait_states(3, timeout=20)

    for _ in range(5):
        gps.inject_garbage(300)
    probe.wait_health(lambda d, s: int(d["malformed"]) + int(d["noise_bytes"]) > 0, message="garbage counted")
    probe.wait_states(3, since=probe.state_count(), message="fixes after the garbage")

    gps.bad_checksums(True)
    details = probe.wait_health(lambda d, s: int(d["bad_checksums"]) >= 14, message="bad checksums counted")
    assert "GGA:" in details["bad_checksum_kinds"] and "RMC:" in details["bad_checksum_kinds"]
    assert proc.poll() is None
    gps.bad_checksums(False)
    probe.wait_states(3, since=probe.state_count(), message="fixes after the bad checksums")

    gps.set_fix(False)
    details = probe.wait_health(lambda d, s: d["fix"] == "False", message="the lost fix in health")
    assert details["status"] == "degraded" and details["degraded_reason"] == "no fix"
    assert details["fix_type"] == "no fix" and details["fix_quality"] == "0 (invalid)"
    mark = probe.state_count()
    epochs = int(details["epochs"])
    probe.wait_health(lambda d, s: int(d["epochs"]) >= epochs + 5, message="five epochs without a fix")
    assert not any(msg.has("x") or msg.has("x_dot") for msg, _ in probe.states_since(mark))
    gps.set_fix(True)
    msg, truth = probe.wait_states(1, since=probe.state_count(), message="a fix again")[-1]
    assert abs(msg.x - truth.north) < 5 * H_SIGMA + 0.2
    assert probe.wait_health(lambda d, s: s == "ok")["fix"] == "True"
    assert proc.poll() is None


def test_gps_reports_silence_and_recovers_from_a_disconnect(services: ServiceProcesses, bus: BusClient,
                                                            tmp_path: Path, vehicle: SimVehicle,
                                                            gps: NmeaGpsDevice) -> None:
    proc, probe = run_gps(services, bus, tmp_path, gps.address, vehicle, stale_after_s=0.5)
    probe.wait_states(3, timeout=20)

    stale_before = int(probe.wait_health(lambda d, s: d["data"] == "ok")["stale_events"])
    gps.silence(True)
    details = probe.wait_health(lambda d, s: d["data"] == "stale", message="stale data in health")
    assert details["status"] == "degraded" and details["degraded_reason"].startswith("no data for")
    assert details["port"] == "open"
    assert int(details["stale_events"]) == stale_before + 1   # one silence, counted once however long it lasts
    assert int(probe.health_after(3)["stale_events"]) == stale_before + 1
    gps.silence(False)
    details = probe.wait_health(lambda d, s: s == "ok" and d["data"] == "ok", message="fresh data again")
    assert int(details["stale_events"]) == stale_before + 1

    gps.disconnect()
    details = probe.wait_health(lambda d, s: d["port"] == "down", message="the port down in health")
    assert details["status"] == "degraded" and "down" in details["degraded_reason"]
    assert int(details["port_losses"]) >= 1 and details["port_error"] and details["last_error"]
    assert proc.poll() is None
    gps.reconnect()
    mark = probe.state_count()
    msg, truth = probe.wait_states(3, since=mark, timeout=20, message="fixes after the reconnect")[-1]
    assert abs(msg.x - truth.north) < 5 * H_SIGMA + 0.2
    assert probe.wait_health(lambda d, s: s == "ok")["port"] == "open"


def test_gps_refuses_an_unsupported_baud_rate_with_a_clear_error(services: ServiceProcesses, tmp_path: Path) -> None:
    profile = write_profile(tmp_path, name="gps", kind="gps_nmea", settings={},
                            devices={"gps": "serial:///dev/u2sa/gps?baud=1234"})
    proc = start_driver(services, profile, "gps")
    assert proc.wait(timeout=20) != 0
    out = (tmp_path / "gps.stderr").read_text()
    assert ("baud 1234 is not a serial rate; use one of 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, "
            "460800, 921600") in out


def test_gps_opens_the_port_with_the_configured_framing_and_changes_it_live(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path, vehicle: SimVehicle, gps: NmeaGpsDevice) -> None:
    _, probe = run_gps(services, bus, tmp_path, gps.address, vehicle, line="baud=19200&bytesize=7&parity=E&stopbits=2",
                       devices={"gps_7e1": f"serial://{gps.address}?baud=19200&bytesize=7&parity=E"})
    probe.wait_states(2, timeout=20)
    details = probe.wait_health(lambda d, s: d["port"] == "open", message="the port open in health")
    assert details["framing"] == "7E2" and details["baudrate"] == "19200"   # as pyserial applied it
    # the kernel's view of the line (a pty forces 8 data bits and no parity, so baud and stop bits show)
    assert gps.link.line_settings() == LineSettings(baudrate=19200, stopbits=2)

    reply = bus.set_config("gps", "device", "gps_8n1", timeout=10)   # no such device: refused, nothing changes
    assert reply is not None and not reply.ok and "[devices.gps_8n1]" in reply.error, reply and reply.error
    reply = bus.set_config("gps", "device", "gps_7e1", timeout=10)   # the same line, another framing
    assert reply is not None and reply.ok, reply and reply.error
    probe.wait_health(lambda d, s: d["framing"] == "7E1" and d["port"] == "open", message="the port reopened 7E1")
    wait_until(lambda: gps.link.line_settings().stopbits == 1, message="one stop bit on the line")
    probe.wait_states(2, since=probe.state_count(), message="fixes after the reopen")


@pytest.mark.parametrize(("framing", "expected"), [
    ("bytesize=9", "bytesize 9 must be 5, 6, 7 or 8"),
    ("parity=X", "parity 'X' must be N, E, O, M or S"),
    ("stopbits=3", "stopbits '3' must be 1, 1.5 or 2"),
])
def test_bad_framing_is_refused_naming_the_field_and_the_allowed_values(tmp_path: Path, lcm_url: str, framing: str,
                                                                       expected: str) -> None:
    transport = Transport(lcm_url, name="test")
    profile = VehicleProfile(path=None, devices={"gps": {"address": f"serial:///dev/u2sa/gps?baud=9600&{framing}"}})
    try:
        with pytest.raises(ConfigError) as err:
            GpsNmeaDriver("gps", profile=profile, config_path=tmp_path / "gps.toml", transport=transport)
        assert expected in str(err.value) and "'gps'" in str(err.value)   # names the service and the parameter
    finally:
        transport.stop()
