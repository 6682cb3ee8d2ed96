"""GPS epoch rules on their own and in the driver: supplements (a late RMC, a heading after the
burst, a GSA that began a burst of the epoch already published), a repeated ZDA, a frozen
receiver repeating its last fix, floods, and the fix a lone ZDA or HDT must not change."""

from __future__ import annotations

import datetime as dt
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import pytest
from conftest import wait_until
from gps_stream_builder import RecordingGps, serial_profile, START, Solution, gga, gsa, hdt, rmc, vtg, zda

from u2sa_hw.drivers.gps_nmea.epochs import MAX_EPOCH_SENTENCES, GpsEpochCollector
from u2sa_hw.drivers.nmea_fields import Epoch, parse_sentence
from u2sa_hw.bus.transport import Transport

SOL = Solution(when=START, lat=29.19, lon=-81.05, speed=2.0, course=90.0, heading=91.0)
NEXT = replace(SOL, when=START + dt.timedelta(seconds=1), lat=29.19002)


def add(col: GpsEpochCollector, line: bytes, at: float = 0.0) -> list[Epoch]:
    sentence = parse_sentence(line)
    assert sentence is not None
    return col.add(sentence, received=at)


def test_an_rmc_after_the_silence_that_ended_its_epoch_is_a_supplement_not_a_second_fix() -> None:
    col = GpsEpochCollector()
    assert add(col, gga(SOL)) == []
    first = col.flush()
    assert first is not None and not first.supplement
    assert add(col, rmc(SOL), 0.2) == []
    [late] = add(col, gga(NEXT), 1.0)
    assert late.supplement and late.kinds() == ["RMC"] and late.time == first.time
    assert col.late == 1


def test_a_burst_split_by_silences_at_a_slow_baud_rate_gives_one_epoch_and_supplements() -> None:
    """GSA and VTG (no time) that begin a burst after a silence, then the RMC of the epoch already out."""
    col = GpsEpochCollector()
    add(col, gga(SOL))
    col.flush()
    add(col, gsa(SOL))
    col.flush()                      # a lone GSA: nothing to say about the fix
    add(col, vtg(SOL), 0.3)
    add(col, rmc(SOL), 0.4)          # carries the published epoch's time: the pending epoch belongs to it
    [late] = add(col, gga(NEXT), 1.0)
    assert late.supplement and late.kinds() == ["VTG", "RMC"]


def test_an_hdt_that_finds_no_epoch_open_belongs_to_the_preceding_epoch() -> None:
    col = GpsEpochCollector()
    add(col, gga(SOL))
    add(col, rmc(SOL))
    assert col.flush().kinds() == ["GGA", "RMC"]
    add(col, hdt(SOL), 0.08)        # 80 ms after the burst: the heading engine is slower
    [heading] = add(col, gga(NEXT), 1.0)
    assert heading.supplement and heading.kinds() == ["HDT"] and heading.time == SOL.when.time()
    assert col.pending is not None and col.pending.kinds() == ["GGA"]


def test_a_repeated_zda_never_starts_an_epoch() -> None:
    col = GpsEpochCollector()
    for line in (gga(SOL), zda(SOL), zda(SOL), rmc(SOL)):
        assert add(col, line) == []
    assert col.flush().kinds() == ["GGA", "ZDA", "ZDA", "RMC"]
    [again] = [e for e in (add(col, zda(SOL)), [col.flush()]) if e][0]
    assert again.supplement and again.kinds() == ["ZDA"]


def test_a_flood_of_one_repeatable_sentence_is_cut_into_bounded_epochs() -> None:
    col = GpsEpochCollector()
    ended: list[Epoch] = []
    for _ in range(3 * MAX_EPOCH_SENTENCES):
        ended += add(col, gsa(SOL))
    assert [len(e.sentences) for e in ended] == [MAX_EPOCH_SENTENCES, MAX_EPOCH_SENTENCES]


# ------------------------------------------------------------------- in the driver ---------------
@pytest.fixture
def transport(lcm_url: str) -> Iterator[Transport]:
    tr = Transport(lcm_url, name="gps-epochs")
    yield tr
    tr.stop()


def make_driver(tmp_path: Path, transport: Transport, **settings: object) -> RecordingGps:
    return RecordingGps("gps", config_path=tmp_path / "gps.toml", transport=transport,
                        profile=serial_profile(), settings={"position_frame": "GEODETIC", **settings})


def test_a_late_rmc_publishes_its_velocity_once_and_never_the_position_again(
        tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport)
    driver.handle_line(gga(SOL), 10.0)
    driver.handle_idle()
    driver.handle_line(rmc(SOL), 10.3)
    driver.handle_line(zda(SOL), 10.31)
    driver.handle_line(gga(NEXT), 11.0)
    driver.handle_idle()
    first, late, second = driver.sent
    assert first.has("x") and not first.has("x_dot")
    assert late.present_fields() == ["x_dot", "y_dot", "x_dot_sigma", "y_dot_sigma"]
    assert late.header.timestamp_us == first.header.timestamp_us          # stamped like its epoch
    assert late.y_dot == pytest.approx(2.0, abs=1e-3) and second.has("x")
    details = driver.sensor_details()
    assert details["supplements"] == 1 and details["utc"].startswith("2026-03-14")


def test_a_lone_zda_or_hdt_epoch_never_flips_the_fix_but_the_fix_expires_without_position_sentences(
        tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport, stale_after_s=0.3)
    driver.handle_line(gga(SOL), 10.0)
    driver.handle_idle()
    assert driver.sensor_details()["fix"] is True
    for k in range(5):
        later = replace(SOL, when=SOL.when + dt.timedelta(seconds=k + 1))
        driver.handle_line(zda(later), 11.0 + k)
        driver.handle_idle()
        driver.handle_line(hdt(later), 11.5 + k)
        driver.handle_idle()
        assert driver.sensor_details()["fix"] is True and driver.problem() == ""
    # still only ZDA and HDT: the receiver says nothing about a fix any more, and after stale_after_s
    # the last one no longer counts
    wait_until(lambda: driver.problem() == "no fix", timeout=5.0, message="the fix expired")
    assert driver.sensor_details()["fix"] is False


def test_a_frozen_receiver_repeating_its_last_fix_is_not_published_again_and_loses_the_fix(
        tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport, stale_after_s=0.3)
    for k in range(6):
        driver.handle_line(gga(SOL), 10.0 + k)                            # time and position never change
        driver.handle_idle()
    assert len(driver.sent) == 1 and driver.sensor_details()["repeated_fixes"] == 5
    wait_until(lambda: driver.problem() == "no fix", timeout=5.0, message="the fix expired")
    # a receiver stamping whole seconds at 5 Hz repeats the time, not the position: every epoch counts
    moved = [replace(SOL, lat=SOL.lat + k * 1e-5) for k in range(1, 6)]
    for k, sol in enumerate(moved):
        driver.handle_line(gga(sol), 20.0 + k * 0.2)
        driver.handle_idle()
    assert len(driver.sent) == 6 and driver.problem() == ""
