"""Seeded mutation fuzzing of the GPS driver (bounded: a few seconds; bench/fuzz_gps.py runs longer).

The real driver class reads mutated sentences (most with a recomputed, valid checksum) in
the test process: no exception may escape its line or silence handling, and every message
it publishes must be finite and within the physical ranges.
"""

from __future__ import annotations

import random
import time
from pathlib import Path
from typing import Iterator

import pytest
from gps_fuzzing import check_message, feed, fuzz_cases
from gps_stream_builder import RecordingGps, nmea, serial_profile

from u2sa_hw.drivers.gps_nmea.fix import fix_from_epoch
from u2sa_hw.drivers.nmea_fields import Epoch, SentenceError, parse_sentence
from u2sa_hw.bus.transport import Transport

CASES_PER_SEED = 1500
SEEDS = (1, 2, 3)
BUDGET_S = 6.0   # all seeds together stop by then on a loaded machine (the count is the normal bound)


@pytest.fixture
def transport(lcm_url: str) -> Iterator[Transport]:
    tr = Transport(lcm_url, name="gps-fuzz")
    yield tr
    tr.stop()


def make_driver(tmp_path: Path, transport: Transport) -> RecordingGps:
    return RecordingGps("gps", config_path=tmp_path / "gps.toml", transport=transport,
                        profile=serial_profile(), settings={"position_frame": "GEODETIC",
                                  "altitude_datum": "ellipsoid"})


@pytest.mark.parametrize(("line", "kind"), [
    (nmea("GPZDA,120000.00,14,03," + "9" * 20 + ",00,00"), "date"),
    (nmea("GPGGA,120000.00,2911.000,N,08103.000,W," + "1" * 400 + ",09,0.9,12.0,M,-30.5,M,,"), "quality"),
    (nmea("GPGGA," + "9" * 40 + ",2911.000,N,08103.000,W,1,09,0.9,12.0,M,-30.5,M,,"), "time"),
    (nmea("GPRMC,120000.00,A,2911.000,N,08103.000,W," + "9" * 400 + ",,140326,,,A"), "speed"),
    (nmea("GPGST,120000.00,1.0,inf,inf,0.0,1e309,nan,-0"), "sigma lat"),
    (nmea("GPGSA,A," + "3" * 300 + ",02,05,07,09,,,,,,,,,1.7,0.9,1.4"), "gsa mode"),
])
def test_the_sentences_that_crashed_the_service_are_read_without_an_exception(
        line: bytes, kind: str, tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport)
    before = nmea("GPGGA,120000.00,2911.000,N,08103.000,W,1,09,0.9,12.0,M,-30.5,M,,")
    after = nmea("GPGGA,120001.00,2911.100,N,08103.000,W,1,09,0.9,12.0,M,-30.5,M,,")
    for received, data in enumerate((before, line, line, after)):
        driver.handle_line(data, float(received))
        driver.handle_idle()
    positions = [round(msg.x, 6) for msg in driver.sent if msg.has("x")]
    # the fixes around it, each once; a GGA whose time is unreadable is a fix of no known time (once)
    assert positions == [29.183333, 29.183333, 29.185] if kind == "time" else [29.183333, 29.185]
    for msg in driver.sent:
        check_message(msg)
    if kind != "time":
        assert driver.drops.counts.get(kind, 0) >= 1, driver.drops.counts


def test_seeded_mutations_never_escape_the_parser_and_fix_logic() -> None:
    rng = random.Random(7)
    for line in fuzz_cases(rng, 3000):
        try:
            sentence = parse_sentence(line)
        except SentenceError:
            continue
        if sentence is not None:
            epoch = Epoch(received=0.0, sentences=[sentence])
            fix_from_epoch(epoch)


def test_seeded_mutations_through_the_driver_publish_only_finite_in_range_values(
        tmp_path: Path, transport: Transport) -> None:
    deadline = time.monotonic() + BUDGET_S
    published = dropped = 0
    for seed in SEEDS:
        if time.monotonic() > deadline:
            break
        rng = random.Random(seed)
        driver = make_driver(tmp_path, transport)
        feed(driver.handle_line, driver.handle_idle, rng, fuzz_cases(rng, CASES_PER_SEED))
        for msg in driver.sent:
            check_message(msg)
        details = driver.health_details()
        published += len(driver.sent)
        dropped += details["out_of_range"]
    # the mutations reached the field checks: positions were published and impossible values dropped
    assert published > 50 and dropped > 50
