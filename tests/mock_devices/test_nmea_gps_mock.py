"""NmeaGpsDevice through a real pty: pyserial on its symlink, every sentence parsed by pynmeagps."""

from __future__ import annotations

import math
import statistics
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

import pytest
import serial
from conftest import wait_until
from pynmeagps.exceptions import NMEAParseError
from serial_line_reader import SerialLineReader, parse_nmea

from u2sa_hw.mocks.nmea_gps import GPS_SENTENCES, KNOT_MPS, NmeaGpsDevice
from u2sa_hw.mocks.vehicle_sim import SimVehicle, geodetic_to_ned

ORIGIN = dict(origin_lat=29.1895, origin_lon=-81.0483, origin_alt=10.0)
CLOCK = datetime(2026, 3, 14, 15, 9, 26, 530000, tzinfo=timezone.utc)
YAW = math.radians(30.0)
SIGMA = 1.5


@pytest.fixture
def vehicle() -> SimVehicle:
    """A rover 200 m north-east of the origin, driving at 1 m/s on a heading of 30 degrees."""
    v = SimVehicle(**ORIGIN, start_north=150.0, start_east=120.0, start_yaw=YAW)
    v.set_wheel_speed("left", 1.0)
    v.set_wheel_speed("right", 1.0)
    v.step(0.1)
    return v


def make_gps(vehicle: SimVehicle, tmp_path: Path, **options: object) -> NmeaGpsDevice:
    options.setdefault("utc_clock", lambda: CLOCK)
    options.setdefault("rate_hz", 50.0)
    return NmeaGpsDevice(vehicle, link_path=tmp_path / "dev" / "gps", **options)


@pytest.fixture
def gps(vehicle: SimVehicle, tmp_path: Path) -> Iterator[NmeaGpsDevice]:
    dev = make_gps(vehicle, tmp_path, sentences=GPS_SENTENCES, declination_deg=-4.0)
    dev.start()
    yield dev
    dev.stop()


def ned_error(vehicle: SimVehicle, lat: float, lon: float) -> tuple[float, float]:
    truth = vehicle.snapshot()
    n, e, _ = geodetic_to_ned(lat, lon, 0.0, **ORIGIN)
    return n - truth.north, e - truth.east


def test_every_sentence_parses_with_a_valid_checksum_and_matches_truth(gps: NmeaGpsDevice,
                                                                       vehicle: SimVehicle) -> None:
    truth = vehicle.snapshot()
    with SerialLineReader(gps.address, baudrate=4800) as reader:
        gga = reader.next_sentence("GGA")
        rmc = reader.next_sentence("RMC")
        vtg = reader.next_sentence("VTG")
        gsa = reader.next_sentence("GSA")
        gst = reader.next_sentence("GST")
        zda = reader.next_sentence("ZDA")
        hdt = reader.next_sentence("HDT")
        gns = reader.next_sentence("GNS")
        gll = reader.next_sentence("GLL")
    assert gga.talker == "GP" and gga.quality == 1 and gga.numSV == 10 and gga.HDOP == pytest.approx(0.9)
    assert gga.time == CLOCK.time().replace(microsecond=530000)
    for msg in (gga, rmc, gns, gll):
        dn, de = ned_error(vehicle, msg.lat, msg.lon)
        assert abs(dn) < 5 * SIGMA and abs(de) < 5 * SIGMA, f"{msg.msgID} off by {dn:.1f}, {de:.1f} m"
    assert gga.alt == pytest.approx(truth.alt, abs=5 * 3.0)
    assert rmc.status == "A" and rmc.posMode == "A" and rmc.date == CLOCK.date()
    assert rmc.spd * KNOT_MPS == pytest.approx(1.0, abs=0.25)
    assert rmc.cog == pytest.approx(30.0, abs=15.0)
    assert (rmc.mv, rmc.mvEW) == (4.0, "W")
    assert vtg.sogk / 3.6 == pytest.approx(1.0, abs=0.25) and vtg.posMode == "A"
    assert vtg.cogm == pytest.approx((vtg.cogt + 4.0) % 360.0, abs=0.011)  # W declination: magnetic > true
    assert gsa.navMode == 3 and gsa.svid_01 == 2 and gsa.PDOP == pytest.approx(math.hypot(0.9, 1.4), abs=0.01)
    assert (gst.stdLat, gst.stdLong, gst.stdAlt) == (1.5, 1.5, 3.0)
    assert (zda.day, zda.month, zda.year) == (14, 3, 2026)
    assert hdt.headingT == pytest.approx(30.0, abs=5 * 0.2)
    assert gns.posMode == "A" and gll.status == "A"


def test_one_epoch_reports_one_solution(vehicle: SimVehicle, tmp_path: Path) -> None:
    gps = make_gps(vehicle, tmp_path, sentences=("GGA", "RMC", "GLL", "VTG"))
    gga, rmc, gll, vtg = (parse_nmea(line) for line in gps.epoch_lines(vehicle.snapshot()))
    assert gga.lat == rmc.lat == gll.lat and gga.lon == rmc.lon == gll.lon
    assert rmc.cog == vtg.cogt and rmc.spd == vtg.sogn


def test_noise_is_gaussian_with_the_configured_sigma_and_seeded(vehicle: SimVehicle, tmp_path: Path) -> None:
    gps = make_gps(vehicle, tmp_path, sentences=("GGA",), horizontal_sigma_m=SIGMA, seed=3)
    errors = [ned_error(vehicle, m.lat, m.lon) for m in
              (parse_nmea(gps.epoch_lines(vehicle.snapshot())[0]) for _ in range(2000))]
    for axis in zip(*errors):
        assert statistics.fmean(axis) == pytest.approx(0.0, abs=0.15)
        assert statistics.stdev(axis) == pytest.approx(SIGMA, rel=0.08)
    a, b, c = (make_gps(vehicle, tmp_path, sentences=("GGA",), seed=seed).epoch_lines(vehicle.snapshot())
               for seed in (3, 3, 4))
    assert a == b != c


def test_gn_talker_and_zero_noise_give_the_exact_position(vehicle: SimVehicle, tmp_path: Path) -> None:
    gps = make_gps(vehicle, tmp_path, talker="GN", sentences=("GNS",), horizontal_sigma_m=0.0,
                   vertical_sigma_m=0.0)
    gns = parse_nmea(gps.epoch_lines(vehicle.snapshot())[0])
    assert gns.talker == "GN"
    dn, de = ned_error(vehicle, gns.lat, gns.lon)
    assert abs(dn) < 0.02 and abs(de) < 0.02  # 1e-5 arc-minute resolution is about 2 cm


def test_bad_checksums_are_rejected_by_pynmeagps_until_switched_off(gps: NmeaGpsDevice) -> None:
    with SerialLineReader(gps.address) as reader:
        gps.bad_checksums(True)
        bad = reader.next_matching(lambda l: l.startswith(b"$") and not _checksum_ok(l))
        with pytest.raises(NMEAParseError, match="invalid checksum"):
            parse_nmea(bad)
        assert any(not s.valid for s in gps.history)
        gps.bad_checksums(False)
        good = reader.next_matching(lambda l: _checksum_ok(l))
        assert parse_nmea(good).talker == "GP"


def _checksum_ok(line: bytes) -> bool:
    try:
        parse_nmea(line)
        return True
    except NMEAParseError:
        return False


def test_garbage_arrives_between_sentences_and_valid_ones_follow(gps: NmeaGpsDevice) -> None:
    with SerialLineReader(gps.address) as reader:
        reader.next_sentence("GGA")
        garbage = gps.inject_garbage(64)
        reader.skip_past(garbage)  # arrives whole, between two sentences
        assert reader.next_sentence("GGA").quality == 1


def test_silence_stops_all_output_and_resumes(gps: NmeaGpsDevice) -> None:
    with SerialLineReader(gps.address) as reader:
        reader.next_sentence("GGA")
        gps.silence(True)
        e0 = gps.epochs
        wait_until(lambda: gps.epochs >= e0 + 2, message="an epoch to finish after silence")
        reader.drain()
        sent = len(gps.history)
        e1 = gps.epochs
        wait_until(lambda: gps.epochs >= e1 + 3, message="three silent epochs")
        assert reader.pending() == 0 and len(gps.history) == sent
        gps.silence(False)
        assert reader.next_sentence("GGA").quality == 1


def test_losing_the_fix_is_reported_and_regained(gps: NmeaGpsDevice) -> None:
    with SerialLineReader(gps.address) as reader:
        gps.set_fix(False)
        assert not gps.has_fix
        gga = parse_nmea(reader.next_matching(lambda l: l.startswith(b"$GPGGA") and b",0,00," in l))
        assert gga.quality == 0 and gga.lat == ""
        rmc = reader.next_sentence("RMC")
        assert rmc.status == "V" and rmc.posMode == "N" and rmc.lat == ""
        assert reader.next_sentence("GSA").navMode == 1
        assert reader.next_sentence("HDT").headingT == ""
        gps.set_fix(True)
        assert parse_nmea(reader.next_matching(lambda l: l.startswith(b"$GPGGA") and b",1,10," in l)).quality == 1


def test_disconnect_fails_the_driver_and_reconnect_resumes(gps: NmeaGpsDevice) -> None:
    reader = SerialLineReader(gps.address)
    reader.next_sentence("GGA")
    gps.disconnect()
    with pytest.raises(serial.SerialException):
        for _ in range(100):  # the bytes already queued may come first
            reader.port.read(4096)
    reader.close()
    with pytest.raises(serial.SerialException):
        SerialLineReader(gps.address)
    gps.reconnect()
    with SerialLineReader(gps.address) as reader:
        assert reader.next_sentence("RMC").status == "A"


def test_unknown_sentence_and_bad_options_are_refused(vehicle: SimVehicle, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"unsupported NMEA sentence\(s\) \['XYZ'\]; choose from GGA"):
        make_gps(vehicle, tmp_path, sentences=("GGA", "XYZ"))
    with pytest.raises(ValueError, match="talker must be two letters"):
        make_gps(vehicle, tmp_path, talker="GPS")
    with pytest.raises(ValueError, match="rate_hz must be > 0"):
        make_gps(vehicle, tmp_path, rate_hz=0)
    with pytest.raises(ValueError, match="horizontal_sigma_m must be >= 0"):
        make_gps(vehicle, tmp_path, horizontal_sigma_m=-1.0)
