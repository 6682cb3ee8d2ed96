"""Serial compass driver: the OS5000 parser and heading arithmetic on their own, then the driver
as a real service process against the mock NMEA and OS5000 compasses on a pty."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Iterator

import pytest
from conftest import ServiceProcesses
from pynmeagps.nmeahelpers import calc_checksum
from serial_driver_harness import SIM_ORIGIN, DriverProbe, start_driver, write_profile

from u2sa_hw.drivers.compass.bursts import CompassReading, reading_from_parts
from u2sa_hw.drivers.compass.sentences import AttitudeLimits, CompassPart, parse_compass_line
from u2sa_hw.drivers.compass.driver import state_from_reading
from u2sa_hw.drivers.value_ranges import ValueDrops
from u2sa_hw.drivers.compass.os5000_format import Os5000BadChecksum, Os5000Error, is_os5000_line, parse_os5000
from u2sa_hw.mocks.serial_compass import NmeaCompassDevice, Os5000CompassDevice
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.bus.client import BusClient


def nmea(body: str) -> bytes:
    return f"${body}*{calc_checksum(body)}\r\n".encode()


def parts_of(*bodies: str) -> list[CompassPart]:
    drops = ValueDrops(logging.getLogger("test"), device="compass")
    parts = [parse_compass_line(nmea(body), limits=AttitudeLimits(), drops=drops, not_valid=drops) for body in bodies]
    assert all(p is not None for p in parts) and not drops.counts, (bodies, drops.counts)
    return parts  # type: ignore[return-value]


def reading_of(*bodies: str, declination_deg: float = 0.0, use_hdg_variation: bool = True) -> CompassReading:
    return reading_from_parts(parts_of(*bodies), declination_deg=declination_deg, use_hdg_variation=use_hdg_variation)


def angle_error_deg(a: float, b: float) -> float:
    """|a - b| in degrees, both in radians, across the wrap."""
    return abs(math.degrees((a - b + math.pi) % (2 * math.pi) - math.pi))


# ---------------------------------------------------------------- OS5000 format ----------------
def test_os5000_examples_from_the_manual_parse_with_their_checksums() -> None:
    reading, noise = parse_os5000(b"$C320.5P0.2R-18.3T19.0*3C\r\n")
    assert (reading.heading, reading.pitch, reading.roll, reading.temperature, noise) == (320.5, 0.2, -18.3, 19.0, 0)
    full, _ = parse_os5000(b"$C212.4P2.5R-14.0T28.4Mx107977.90My-79422.00Mz173.27Ax0.045Ay-0.245Az0.977*3A\r\n")
    assert (full.mag_x, full.mag_y, full.mag_z) == (107977.90, -79422.00, 173.27)
    assert (full.accel_x, full.accel_y, full.accel_z) == (0.045, -0.245, 0.977)
    body = "C328.3P28.4R-12.4T21.1D21.01Q7"
    depth, noise = parse_os5000(b"\x07\xfe" + f"${body}*{calc_checksum(body)}\r\n".encode())
    assert depth.depth == 21.01 and depth.unknown == {"Q": 7.0} and noise == 2
    heading_only, _ = parse_os5000(f"$C7.0*{calc_checksum('C7.0')}\r\n".encode())
    assert heading_only.heading == 7.0 and heading_only.pitch is None


def test_os5000_bad_lines_are_refused_with_the_reason() -> None:
    with pytest.raises(Os5000BadChecksum):
        parse_os5000(b"$C320.5P0.2R-18.3T19.0*3D\r\n")
    for line in (b"garbage\r\n", b"$C320.5P0.2R-18.3T19.0\r\n", b"$P0.2R-18.3*00\r\n",
                 f"$P0.2R1.0*{calc_checksum('P0.2R1.0')}".encode(),            # no heading
                 f"$C1.0P?2*{calc_checksum('C1.0P?2')}".encode(),               # unreadable field
                 "$C1\u00e9*00".encode("latin-1")):
        with pytest.raises(Os5000Error):
            parse_os5000(line)
    assert is_os5000_line(b"$C320.5P0.2*3C") and not is_os5000_line(b"$HCHDT,1.0,T*00")
    assert not is_os5000_line(b"$C") and not is_os5000_line(b"no dollar")


# ---------------------------------------------------------------- heading arithmetic -----------
def test_hdg_applies_deviation_and_its_own_variation_or_the_configured_declination() -> None:
    hdg = "HCHDG,98.3,1.5,W,12.6,W"
    with_variation = reading_of(hdg, declination_deg=3.0, use_hdg_variation=True)
    assert with_variation.magnetic_heading == pytest.approx(96.8)        # sensor + deviation (W negative)
    assert with_variation.true_heading == pytest.approx(96.8 - 12.6)     # + variation (W negative)
    configured = reading_of(hdg, declination_deg=3.0, use_hdg_variation=False)
    assert configured.true_heading == pytest.approx(96.8 + 3.0)
    no_variation = reading_of("HCHDG,98.3,,,,", declination_deg=-2.0, use_hdg_variation=True)
    assert no_variation.true_heading == pytest.approx(96.3)


def test_hdt_wins_over_hdg_over_hdm_and_xdr_gives_pitch_and_roll() -> None:
    xdr = "HCXDR,A,-3.5,D,PITCH,A,12.0,D,ROLL"
    assert reading_of("HCHDM,10.0,M", "HCHDG,20.0,,,,", "HCHDT,30.0,T", xdr,
                      declination_deg=5.0) == CompassReading("HDT", 30.0, None, -3.5, 12.0)
    hdm = reading_of("HCHDM,350.0,M", xdr, declination_deg=15.0)
    assert (hdm.source, hdm.true_heading, hdm.pitch, hdm.roll) == ("HDM", 365.0, -3.5, 12.0)
    msg = state_from_reading(hdm, heading_sigma_deg=2.0, attitude_sigma_deg=0.5)
    assert msg.psi == pytest.approx(math.radians(5.0)) and msg.psi_sigma == pytest.approx(math.radians(2.0))
    assert msg.theta == pytest.approx(math.radians(-3.5)) and msg.phi == pytest.approx(math.radians(12.0))
    assert msg.phi_sigma == pytest.approx(math.radians(0.5)) and msg.reference_frame == "NED"
    attitude_only = reading_of("HCXDR,A,1.0,D,PTCH")
    assert state_from_reading(attitude_only, heading_sigma_deg=1.0, attitude_sigma_deg=1.0).present_fields() == \
        ["theta", "theta_sigma"]
    assert state_from_reading(CompassReading(""), heading_sigma_deg=1.0, attitude_sigma_deg=1.0) is None


@pytest.mark.parametrize("heading, expected", [(0.0, 0.0), (179.9, 179.9), (180.0, -180.0), (359.9, -0.1),
                                               (-190.0, 170.0), (540.0, -180.0)])
def test_psi_is_radians_in_minus_pi_to_pi(heading: float, expected: float) -> None:
    msg = state_from_reading(CompassReading("HDT", heading), heading_sigma_deg=1.0, attitude_sigma_deg=1.0)
    assert -math.pi <= msg.psi < math.pi and msg.psi == pytest.approx(math.radians(expected), abs=1e-9)


# ---------------------------------------------------------------- the service ------------------
YAW_DEG = -100.0
DECLINATION = -7.5


@pytest.fixture
def vehicle() -> Iterator[SimVehicle]:
    """A rover turning slowly to the right from a heading of 260 degrees."""
    v = SimVehicle(**SIM_ORIGIN, start_yaw=math.radians(YAW_DEG))
    v.set_wheel_speed("left", 0.05)
    v.set_wheel_speed("right", -0.05)
    v.start(rate_hz=100.0)
    yield v
    v.stop()


def check_heading(probe: DriverProbe, count: int, *, since: int = 0, attitude: bool = True,
                  rate: bool | None = False) -> None:
    for msg, truth in probe.wait_states(count, since=since, timeout=20):
        assert rate is None or msg.has("psi_dot") == rate
        assert msg.sensor_name == "compass" and msg.reference_frame == "NED"
        # a burst cut short while the driver learns the device's burst order (at the start of a stream) is
        # published with what it holds: attitude only, or a heading without it
        assert msg.has("psi") or msg.has("theta") or msg.has("psi_dot")
        # 0.5 deg noise, 0.1 deg rounding and up to one epoch gap of turning (0.2 rad/s x 0.05 s)
        assert not msg.has("psi") or angle_error_deg(msg.psi, truth.yaw) < 3.5
        assert -math.pi <= msg.psi < math.pi
        if attitude and msg.has("theta"):
            assert abs(msg.phi) < math.radians(1.5) and abs(msg.theta) < math.radians(1.5)
        assert not msg.has("x")


def make_compass(fmt: str, vehicle: SimVehicle, tmp_path: Path) -> NmeaCompassDevice | Os5000CompassDevice:
    """A mock compass in *fmt* ("nmea": HDG + XDR; "os5000": $C lines) at 20 Hz, started."""
    link = tmp_path / "dev" / "compass"
    if fmt == "nmea":
        dev: NmeaCompassDevice | Os5000CompassDevice = NmeaCompassDevice(
            vehicle, link_path=link, rate_hz=20.0, sentences=("HDG", "XDR"), declination_deg=DECLINATION, seed=9)
    else:
        dev = Os5000CompassDevice(vehicle, link_path=link, rate_hz=20.0, declination_deg=DECLINATION, seed=5)
    dev.start()
    return dev


@pytest.mark.parametrize(("fmt", "checksum_kinds"), [("nmea", ("HDG:", "XDR:")), ("os5000", ("$C:",))])
def test_compass_survives_garbage_bad_checksums_silence_and_a_disconnect(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path, vehicle: SimVehicle, fmt: str,
        checksum_kinds: tuple[str, ...]) -> None:
    dev = make_compass(fmt, vehicle, tmp_path)
    try:
        profile = write_profile(tmp_path, name="compass", kind="compass_serial",
                                settings={"format": fmt, "declination_deg": DECLINATION, "stale_after_s": 0.5},
                                devices={"compass": f"serial://{dev.address}?baud=19200"})
        probe = DriverProbe(bus, "compass", on_state=vehicle.snapshot)
        proc = start_driver(services, profile, "compass")
        check_heading(probe, 5)
        details = probe.wait_health(lambda d, s: s == "ok" and d["data"] == "ok")
        assert details["bad_checksums"] == "0" and details["format"] == fmt

        dev.inject_garbage(300)
        probe.wait_health(lambda d, s: int(d["malformed"]) + int(d["noise_bytes"]) > 0, message="garbage counted")
        check_heading(probe, 3, since=probe.state_count())

        dev.bad_checksums(True)
        details = probe.wait_health(lambda d, s: int(d["bad_checksums"]) >= 6, message="bad checksums counted")
        for kind in checksum_kinds:   # counted per sentence kind, HDG included
            assert kind in details["bad_checksum_kinds"], details["bad_checksum_kinds"]
        mark = probe.state_count()
        probe.health_after(3)
        assert probe.state_count() - mark <= 1   # nothing published from corrupted sentences (one may be in flight)
        dev.bad_checksums(False)
        check_heading(probe, 3, since=probe.state_count())

        # only valid sentences keep the data fresh: a run of bad checksums may itself have made it stale
        stale_before = int(probe.wait_health(lambda d, s: d["data"] == "ok")["stale_events"])
        dev.silence(True)
        details = probe.wait_health(lambda d, s: d["data"] == "stale", message="stale data in health")
        assert details["status"] == "degraded" and details["degraded_reason"].startswith("no data for")
        assert int(details["stale_events"]) == stale_before + 1 and details["port"] == "open"
        dev.silence(False)
        check_heading(probe, 3, since=probe.state_count())
        probe.wait_health(lambda d, s: s == "ok" and d["data"] == "ok", message="fresh data again")

        dev.disconnect()
        details = probe.wait_health(lambda d, s: d["port"] == "down" and s == "degraded",
                                    message="the port down in health")
        assert int(details["port_losses"]) >= 1 and details["port_error"]
        assert proc.poll() is None
        dev.reconnect()
        check_heading(probe, 5, since=probe.state_count())
        assert probe.wait_health(lambda d, s: s == "ok")["port"] == "open"
        assert proc.poll() is None
    finally:
        dev.stop()


def test_os5000_compass_service_gives_true_heading_sigma_and_temperature(services: ServiceProcesses, bus: BusClient,
                                                                         tmp_path: Path, vehicle: SimVehicle) -> None:
    dev = make_compass("os5000", vehicle, tmp_path)
    try:
        profile = write_profile(tmp_path, name="compass", kind="compass_serial",
                                settings={"format": "os5000", "declination_deg": DECLINATION, "heading_sigma_deg": 2.0},
                                devices={"compass": f"serial://{dev.address}?baud=19200"})
        probe = DriverProbe(bus, "compass", on_state=vehicle.snapshot)
        start_driver(services, profile, "compass")
        check_heading(probe, 10)
        msg = probe.states_since(0)[-1][0]
        assert msg.psi_sigma == pytest.approx(math.radians(2.0))
        details = probe.wait_health(lambda d, s: s == "ok" and d["source"] == "$C")
        assert details["temperature_c"] == "25.0" and details["format"] == "os5000"
    finally:
        dev.stop()


def test_nmea_compass_service_uses_hdg_variation_deviation_and_xdr(services: ServiceProcesses, bus: BusClient,
                                                                   tmp_path: Path, vehicle: SimVehicle) -> None:
    dev = NmeaCompassDevice(vehicle, link_path=tmp_path / "dev" / "compass", rate_hz=20.0, sentences=("HDG", "XDR"),
                            declination_deg=DECLINATION, deviation_deg=2.5, seed=9)
    dev.start()
    try:
        # the configured declination is wrong on purpose: HDG's own variation field must win
        profile = write_profile(tmp_path, name="compass", kind="compass_serial",
                                settings={"declination_deg": 20.0},
                                devices={"compass": f"serial://{dev.address}?baud=4800"})
        probe = DriverProbe(bus, "compass", on_state=vehicle.snapshot)
        start_driver(services, profile, "compass")
        check_heading(probe, 10)
        # once the burst order is learned (one message per sentence until then): one message per HDG + XDR burst
        learned = probe.wait_health(lambda d, s: s == "ok" and d["source"] == "HDG" and "first" in d["burst_rule"],
                                    message="the burst order learned")
        later = probe.wait_health(lambda d, s: int(d["lines"]) >= int(learned["lines"]) + 40, message="40 more lines")
        lines, published = (int(later[k]) - int(learned[k]) for k in ("lines", "published"))
        assert lines >= 2 * published - 2
    finally:
        dev.stop()


def test_hdm_compass_service_applies_the_configured_declination(services: ServiceProcesses, bus: BusClient,
                                                               tmp_path: Path, vehicle: SimVehicle) -> None:
    dev = NmeaCompassDevice(vehicle, link_path=tmp_path / "dev" / "compass", rate_hz=20.0, sentences=("HDM",),
                            talker="II", declination_deg=DECLINATION, seed=2)
    dev.start()
    try:
        profile = write_profile(tmp_path, name="compass", kind="compass_serial",
                                settings={"declination_deg": DECLINATION},
                                devices={"compass": f"serial://{dev.address}?baud=19200"})
        probe = DriverProbe(bus, "compass", on_state=vehicle.snapshot)
        start_driver(services, profile, "compass")
        check_heading(probe, 5, attitude=False)
        assert not probe.states_since(0)[-1][0].has("phi")
    finally:
        dev.stop()


@pytest.mark.parametrize("sentences", [("XDR", "HDM"), ("XDR", "THS", "ROT"), ("PASHR",), ("PTNTHTM", "ROT")])
def test_attitude_first_tnt_pashr_and_rot_compasses_as_a_service(services: ServiceProcesses, bus: BusClient,
                                                                 tmp_path: Path, vehicle: SimVehicle,
                                                                 sentences: tuple[str, ...]) -> None:
    dev = NmeaCompassDevice(vehicle, link_path=tmp_path / "dev" / "compass", rate_hz=20.0, sentences=sentences,
                            talker="HE", declination_deg=DECLINATION, seed=4)
    dev.start()
    try:
        profile = write_profile(tmp_path, name="compass", kind="compass_serial",
                                settings={"declination_deg": DECLINATION},
                                devices={"compass": f"serial://{dev.address}?baud=19200"})
        probe = DriverProbe(bus, "compass", on_state=vehicle.snapshot)
        start_driver(services, profile, "compass")
        check_heading(probe, 10, rate=None)
        if len(sentences) > 1:   # one message per sentence until the burst order is learned
            probe.wait_health(lambda d, s: "first" in d["burst_rule"], message="the burst order learned")
        since = probe.state_count() + 2   # a burst pending when it was learned is published in parts
        later = probe.wait_states(20, since=since, timeout=20)
        assert all(m.has("psi") and m.has("theta") for m, _ in later)   # in step once the burst order is learned
        if "ROT" in sentences:   # the rover turns right at 0.2 rad/s
            assert all(m.has("psi_dot") and abs(m.psi_dot - truth.yaw_rate) < 0.01 for m, truth in later)
        details = probe.wait_health(lambda d, s: s == "ok" and d["out_of_range"] == "0")
        assert details["source"] in sentences or (details["source"] == "HDM" and "HDM" in sentences)
    finally:
        dev.stop()
