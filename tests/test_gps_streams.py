"""The GPS driver on whole receiver streams, minutes long, composed in gps_stream_builder.

Each stream models one receiver family's output (talkers, order, rates, decimals, quirks)
over a trajectory that drives a circle, stops, and crosses midnight; the lines arrive with a
modelled wire timing (the driver's read timeout reports the silences). They are fed to the
real driver class -- line handling, epochs, fixes, publishing over LCM -- in the test
process, and every published message is checked against the epoch it must come from.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Callable, Iterator

import pytest
from gps_stream_builder import RecordingGps, serial_profile, GAP_S, Part, Receiver, Solution, printed, stream, trajectory

from u2sa_hw.drivers.gps_nmea.geoid import geoid_separation
from u2sa_hw.drivers.gps_nmea.limits import SPEED_MPS
from u2sa_hw.drivers.gps_nmea.driver import GpsNmeaDriver
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.vehicle import Origin

ORIGIN = Origin(lat=29.1895, lon=-81.0483, alt=10.0)


@pytest.fixture
def transport(lcm_url: str) -> Iterator[Transport]:
    tr = Transport(lcm_url, name="gps-streams")
    yield tr
    tr.stop()


def make_driver(tmp_path: Path, transport: Transport, **settings: object) -> RecordingGps:
    return RecordingGps("gps", config_path=tmp_path / "gps.toml", transport=transport,
                        profile=serial_profile(), settings={"epoch_gap_s": GAP_S, "position_frame": "GEODETIC",
                                  **settings})


def replay(driver: GpsNmeaDriver, events: Iterator[tuple[float, bytes | None]],
           watch: Callable[[GpsNmeaDriver], None] | None = None) -> int:
    """Feed *events* to *driver* as its read loop would; *watch* runs after each one. Returns the lines."""
    lines = 0
    for at, line in events:
        if line is None:
            driver.handle_idle()
        else:
            driver.handle_line(line, at)
            lines += 1
        if watch is not None:
            watch(driver)
    driver.handle_idle()
    return lines


def epoch_of(msg: t.StateInformation, rate_hz: float) -> int:
    """The epoch a message was stamped for (stamped with the arrival of the epoch's first line)."""
    return int(msg.header.timestamp_us / 1e6 * rate_hz + 1e-6)


def truth(rate_hz: float) -> Callable[[int], Solution]:
    return lambda k: trajectory(ORIGIN, k, rate_hz)


def check_position(msg: t.StateInformation, sol: Solution, *, decimals: int = 5) -> None:
    assert msg.reference_frame == "GEODETIC"
    assert msg.x == pytest.approx(printed(sol.lat, decimals=decimals), abs=1e-9)
    assert msg.y == pytest.approx(printed(sol.lon, decimals=decimals), abs=1e-9)


def check_velocity(msg: t.StateInformation, sol: Solution) -> None:
    if sol.course is None:   # standing: the receiver leaves the course empty
        assert (msg.x_dot, msg.y_dot) == (0.0, 0.0)
        return
    c = math.radians(round(sol.course, 2))
    assert msg.x_dot == pytest.approx(sol.speed * math.cos(c), abs=2e-3)
    assert msg.y_dot == pytest.approx(sol.speed * math.sin(c), abs=2e-3)


def check_sane(sent: list[t.StateInformation]) -> None:
    for msg in sent:
        for name in msg.present_fields():
            assert math.isfinite(msg.get(name)), name
        if msg.has("x"):
            assert -90 <= msg.x <= 90 and -180 <= msg.y <= 180
        if msg.has("x_dot"):
            assert math.hypot(msg.x_dot, msg.y_dot) <= SPEED_MPS.high


UBLOX = Receiver(rate_hz=5.0, baud=115200, parts=(
    Part("RMC", "GN"), Part("VTG", "GN"), Part("GGA", "GN"), Part("GSA", "GN"), Part("GSA", "GN", options={"mode": 3}),
    Part("GST", "GN"), Part("ZDA", "GN")))


def test_a_multi_constellation_receiver_at_5_hz_for_three_minutes_gives_one_exact_fix_per_epoch(
        tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport)
    epochs, sol = 900, truth(5.0)
    fix_types: set[str] = set()
    replay(driver, stream(UBLOX, sol, epochs), lambda d: fix_types.add(d.sensor_details()["fix_type"]))
    sent = driver.sent
    assert len(sent) == epochs and [epoch_of(m, 5.0) for m in sent] == list(range(epochs))
    for msg in sent:
        k = epoch_of(msg, 5.0)
        check_position(msg, sol(k))
        check_velocity(msg, sol(k))
        assert msg.z == pytest.approx(sol(k).alt, abs=0.006) and msg.x_sigma == 0.8
    check_sane(sent)
    details = driver.sensor_details()
    assert details["epoch_end"] == "on completion" and details["late_sentences"] == 0
    assert details["out_of_range"] == 0 and driver.malformed == 0 and fix_types == {"no data", "3D"}
    assert details["utc"].startswith("2026-03-15 00:01")                    # across midnight, the new date


def test_10_hz_gga_with_1_hz_rmc_and_zda_keeps_every_second_its_velocity_and_date(
        tmp_path: Path, transport: Transport) -> None:
    receiver = Receiver(rate_hz=10.0, baud=38400, parts=(
        Part("GGA", "GP"), Part("RMC", "GP", every=10), Part("ZDA", "GP", every=10), Part("GSA", "GP", every=10)))
    driver = make_driver(tmp_path, transport)
    epochs, sol = 1200, truth(10.0)
    replay(driver, stream(receiver, sol, epochs))
    sent = driver.sent
    assert [epoch_of(m, 10.0) for m in sent] == list(range(epochs))
    with_velocity = [epoch_of(m, 10.0) for m in sent if m.has("x_dot")]
    assert with_velocity == list(range(0, epochs, 10))                      # no second lost its RMC
    for msg in sent:
        k = epoch_of(msg, 10.0)
        check_position(msg, sol(k))
        if msg.has("x_dot"):
            check_velocity(msg, sol(k))
    details = driver.sensor_details()
    assert details["late_sentences"] == 0 and details["epoch_end"] == "learning"
    check_sane(sent)


def test_per_system_talkers_and_a_poorer_second_gga_make_one_3d_fix_per_second(
        tmp_path: Path, transport: Transport) -> None:
    receiver = Receiver(rate_hz=1.0, baud=4800, parts=(
        Part("GGA", "GP"), Part("GGA", "GL", options={"alt": False, "sats": "02"}), Part("GSA", "GP"),
        Part("GSA", "GL", options={"mode": 2}), Part("RMC", "GP"), Part("VTG", "GP")))
    driver = make_driver(tmp_path, transport)
    epochs, sol = 240, truth(1.0)
    replay(driver, stream(receiver, sol, epochs))
    assert [epoch_of(m, 1.0) for m in driver.sent] == list(range(epochs))
    assert all(m.has("z") for m in driver.sent)
    details = driver.sensor_details()
    assert details["fix_type"] == "3D" and details["talkers"] == "GL,GP" and details["satellites"] == "9"


def test_a_gll_only_receiver_gives_2d_fixes(tmp_path: Path, transport: Transport) -> None:
    receiver = Receiver(rate_hz=1.0, baud=4800, parts=(Part("GLL", "GP", options={"decimals": 4}), Part("VTG", "GP")))
    driver = make_driver(tmp_path, transport)
    epochs, sol = 180, truth(1.0)
    replay(driver, stream(receiver, sol, epochs))
    assert [epoch_of(m, 1.0) for m in driver.sent] == list(range(epochs))
    for msg in driver.sent:
        check_position(msg, sol(epoch_of(msg, 1.0)), decimals=4)
        assert not msg.has("z")
        check_velocity(msg, sol(epoch_of(msg, 1.0)))
    assert driver.sensor_details()["fix_type"] == "2D"


def test_quirks_blank_lines_ais_duplicate_zda_late_heading_and_empty_geoid_field(
        tmp_path: Path, transport: Transport) -> None:
    """An old receiver on a shared NMEA bus: no geoid separation, blank lines and AIS between the
    sentences, every ZDA sent twice, and a dual-antenna heading that comes 80 ms after the burst."""
    receiver = Receiver(rate_hz=2.0, baud=38400, parts=(
        Part("GGA", "GP", options={"sep": False}), Part("RMC", "GP"), Part("ZDA", "GP"), Part("ZDA", "GP"),
        Part("HDT", "GP", pause_before_s=0.08)),
        extra_lines=(b"\r\n", b"!AIVDM,1,1,,A,15MgK45P3@G?fl0E`JbR0OwT0@MS,0*4E\r\n"))
    driver = make_driver(tmp_path, transport, altitude_datum="ellipsoid")
    epochs, sol = 480, truth(2.0)
    fix_seen: list[bool] = []
    replay(driver, stream(receiver, sol, epochs), lambda d: fix_seen.append(d.sensor_details()["fix"]))
    assert fix_seen[-1] and fix_seen.count(False) == fix_seen.index(True)   # never False after the first fix
    positions = [m for m in driver.sent if m.has("x")]
    headings = [m for m in driver.sent if m.has("psi") and not m.has("x")]
    assert [epoch_of(m, 2.0) for m in positions] == list(range(epochs))
    assert len(headings) == epochs                                           # each heading its own message ...
    for msg in headings:                                                     # ... for the epoch it followed
        k = epoch_of(msg, 2.0)
        assert math.degrees(msg.psi) % 360.0 == pytest.approx(round(sol(k).heading, 2), abs=1e-6)
    for msg in positions:
        s = sol(epoch_of(msg, 2.0))
        assert msg.z == pytest.approx(s.alt + geoid_separation(msg.x, msg.y), abs=0.006)
    assert driver.malformed == 0 and driver.sensor_details()["geoid_source"] == "EGM96 table"
    assert driver.supplements == epochs
    check_sane(driver.sent)


def test_dead_reckoning_and_simulator_epochs_publish_no_position_and_say_so_in_health(
        tmp_path: Path, transport: Transport) -> None:
    def solution(k: int) -> Solution:
        base = trajectory(ORIGIN, k, 1.0)
        if 60 <= k < 90:
            return replace(base, quality=6)      # in a tunnel: dead reckoning
        if 120 <= k < 130:
            return replace(base, quality=8)      # a simulator left on
        return base
    receiver = Receiver(rate_hz=1.0, baud=9600, parts=(Part("GGA", "GN"), Part("VTG", "GN")))
    driver = make_driver(tmp_path, transport)
    reasons: dict[int, str] = {}

    def watch(d: GpsNmeaDriver) -> None:
        reasons[d.epoch_count] = d.problem()
    replay(driver, stream(receiver, solution, 180), watch)
    published = {epoch_of(m, 1.0) for m in driver.sent}
    assert published == set(range(180)) - set(range(60, 90)) - set(range(120, 130))
    assert reasons[70] == "dead reckoning" and reasons[125] == "simulator" and reasons[150] == ""
