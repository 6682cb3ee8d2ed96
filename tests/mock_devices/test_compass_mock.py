"""NMEA and OS5000 compass mocks through real ptys: formats, declination sign, faults."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Callable, Iterator

import pytest
import serial
from conftest import wait_until
from pynmeagps.exceptions import NMEAParseError
from serial_line_reader import SerialLineReader, parse_nmea

from u2sa_hw.mocks.pty_serial import PeriodicSerialDevice
from u2sa_hw.mocks.serial_compass import NmeaCompassDevice, Os5000CompassDevice
from u2sa_hw.mocks.vehicle_sim import SimVehicle

ORIGIN = dict(origin_lat=44.0, origin_lon=-69.0)
OS5000_LINE = re.compile(rb"^\$(C(\d{1,3}\.\d)P(-?\d+\.\d)R(-?\d+\.\d)T(-?\d+\.\d))\*([0-9A-F]{2})\r\n$")


def os5000_fields(line: bytes) -> tuple[float, float, float, float]:
    """(heading, pitch, roll, temperature) of an OS5000 line; AssertionError on a bad line or checksum."""
    m = OS5000_LINE.match(line)
    assert m, f"not an OS5000 $C line: {line!r}"
    checksum = 0
    for byte in m.group(1):
        checksum ^= byte
    assert f"{checksum:02X}".encode() == m.group(6), f"bad checksum in {line!r}"
    return float(m.group(2)), float(m.group(3)), float(m.group(4)), float(m.group(5))


def is_valid_os5000(line: bytes) -> bool:
    try:
        os5000_fields(line)
        return True
    except AssertionError:
        return False


def is_valid_nmea(line: bytes) -> bool:
    try:
        parse_nmea(line)
        return True
    except NMEAParseError:
        return False


def vehicle_heading(deg: float) -> SimVehicle:
    return SimVehicle(**ORIGIN, start_yaw=math.radians(deg))


def test_nmea_compass_sentences_parse_and_apply_deviation_and_variation(tmp_path: Path) -> None:
    v = vehicle_heading(100.0)
    dev = NmeaCompassDevice(v, link_path=tmp_path / "compass", sentences=("HDG", "HDM", "HDT", "XDR"),
                            declination_deg=-15.0, deviation_deg=3.0, rate_hz=50)
    dev.start()
    try:
        with SerialLineReader(dev.address) as reader:
            hdg = reader.next_sentence("HDG")
            hdm = reader.next_sentence("HDM")
            hdt = reader.next_sentence("HDT")
            xdr = reader.next_sentence("XDR")
    finally:
        dev.stop()
    assert hdg.talker == "HC"
    assert hdt.headingT == pytest.approx(100.0, abs=5 * 0.5)
    # 15 deg W declination: magnetic = true + 15; sensor = magnetic - 3 deg E deviation
    assert hdm.headingM == pytest.approx(115.0, abs=5 * 0.5)
    assert hdg.headingM == pytest.approx(112.0, abs=5 * 0.5)
    assert (hdg.deviation, hdg.deviationEW, hdg.variation, hdg.variationEW) == (3.0, "E", 15.0, "W")
    assert (xdr.tdrid_01, xdr.tdrid_02, xdr.dataunit_01) == ("PITCH", "ROLL", "D")
    assert abs(xdr.data_01) < 5 * 0.2 and abs(xdr.data_02) < 5 * 0.2


def test_east_declination_lowers_the_magnetic_reading(tmp_path: Path) -> None:
    v = vehicle_heading(0.0)  # pointing true north
    nmea = NmeaCompassDevice(v, link_path=tmp_path / "a", sentences=("HDM", "HDT"), declination_deg=10.0,
                             heading_sigma_deg=0.0)
    hdm, hdt = (parse_nmea(line) for line in nmea.epoch_lines(v.snapshot()))
    assert (hdm.headingM, hdt.headingT) == (350.0, 0.0)
    os5 = Os5000CompassDevice(v, link_path=tmp_path / "b", declination_deg=10.0, heading_sigma_deg=0.0,
                              attitude_sigma_deg=0.0, temperature_c=21.5)
    line = os5.epoch_lines(v.snapshot())[0]
    assert line.startswith(b"$C350.0P0.0R0.0T21.5*")  # no "-0.0" either
    assert os5000_fields(line) == (350.0, 0.0, 0.0, 21.5)


def test_heading_just_below_north_prints_as_zero_not_360(tmp_path: Path) -> None:
    v = SimVehicle(**ORIGIN, start_yaw=math.radians(-0.02))  # 359.98 deg
    os5 = Os5000CompassDevice(v, link_path=tmp_path / "c", heading_sigma_deg=0.0, attitude_sigma_deg=0.0)
    assert os5.epoch_lines(v.snapshot())[0].startswith(b"$C0.0P")
    nmea = NmeaCompassDevice(v, link_path=tmp_path / "d", sentences=("HDT",), heading_sigma_deg=0.0)
    assert parse_nmea(nmea.epoch_lines(v.snapshot())[0]).headingT == 0.0


def test_os5000_stream_over_the_pty_matches_truth(tmp_path: Path) -> None:
    v = vehicle_heading(250.0)
    dev = Os5000CompassDevice(v, link_path=tmp_path / "os5000", declination_deg=5.0, rate_hz=50, seed=2)
    dev.start()
    try:
        with SerialLineReader(dev.address, baudrate=19200) as reader:
            lines = [reader.next_line() for _ in range(20)]
    finally:
        dev.stop()
    for line in lines:
        heading, pitch, roll, temperature = os5000_fields(line)
        assert heading == pytest.approx(245.0, abs=5 * 0.5)
        assert abs(pitch) < 5 * 0.2 and abs(roll) < 5 * 0.2 and temperature == 25.0
    sent = [s.text.encode() + b"\r\n" for s in dev.history]
    first = sent.index(lines[0])  # lines sent before the port opened were flushed by pyserial
    assert sent[first:first + 20] == lines


def make_nmea(v: SimVehicle, path: Path) -> PeriodicSerialDevice:
    return NmeaCompassDevice(v, link_path=path, sentences=("HDG", "XDR"), rate_hz=50)


def make_os5000(v: SimVehicle, path: Path) -> PeriodicSerialDevice:
    return Os5000CompassDevice(v, link_path=path, rate_hz=50)


CASES = [pytest.param((make_nmea, is_valid_nmea), id="nmea"),
         pytest.param((make_os5000, is_valid_os5000), id="os5000")]


@pytest.fixture(params=CASES)
def compass(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[PeriodicSerialDevice, Callable]]:
    make, valid = request.param
    dev = make(vehicle_heading(45.0), tmp_path / "dev" / "compass")
    dev.start()
    yield dev, valid
    dev.stop()


def test_bad_checksums_fault(compass: tuple[PeriodicSerialDevice, Callable]) -> None:
    dev, valid = compass
    with SerialLineReader(dev.address) as reader:
        reader.next_matching(valid)
        dev.bad_checksums(True)
        reader.next_matching(lambda l: not valid(l))
        dev.bad_checksums(False)
        reader.next_matching(valid)
    assert any(not s.valid for s in dev.history) and dev.history[-1].valid


def test_garbage_fault(compass: tuple[PeriodicSerialDevice, Callable]) -> None:
    dev, valid = compass
    with SerialLineReader(dev.address) as reader:
        reader.next_matching(valid)
        garbage = dev.inject_garbage(50)
        reader.skip_past(garbage)
        assert valid(reader.next_line())  # the line right after the garbage is intact


def test_silence_fault(compass: tuple[PeriodicSerialDevice, Callable]) -> None:
    dev, valid = compass
    with SerialLineReader(dev.address) as reader:
        reader.next_matching(valid)
        dev.silence(True)
        e0 = dev.epochs
        wait_until(lambda: dev.epochs >= e0 + 2, message="the current epoch to finish")
        reader.drain()
        e1 = dev.epochs
        wait_until(lambda: dev.epochs >= e1 + 3, message="three silent epochs")
        assert reader.pending() == 0
        dev.silence(False)
        reader.next_matching(valid)


def test_disconnect_and_reconnect(compass: tuple[PeriodicSerialDevice, Callable]) -> None:
    dev, valid = compass
    reader = SerialLineReader(dev.address)
    reader.next_matching(valid)
    dev.disconnect()
    with pytest.raises(serial.SerialException):
        for _ in range(100):
            reader.port.read(4096)
    reader.close()
    dev.reconnect()
    with SerialLineReader(dev.address) as reader:
        reader.next_matching(valid)


def test_bad_options_are_refused(tmp_path: Path) -> None:
    v = vehicle_heading(0.0)
    with pytest.raises(ValueError, match=r"unsupported sentence\(s\) \['VHW'\]; choose from HDG, HDM, HDT, THS, ROT, XDR, PASHR, PTNTHTM, PTNTHPR"):
        NmeaCompassDevice(v, link_path=tmp_path / "x", sentences=("VHW",))
    with pytest.raises(ValueError, match="declination_deg must be a finite number"):
        Os5000CompassDevice(v, link_path=tmp_path / "x", declination_deg=float("nan"))
    with pytest.raises(ValueError, match="heading_sigma_deg must be >= 0"):
        Os5000CompassDevice(v, link_path=tmp_path / "x", heading_sigma_deg=-0.1)
