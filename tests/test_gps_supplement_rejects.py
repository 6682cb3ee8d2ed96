"""Health's out-of-range counts in the GPS driver when late sentences are merged into an epoch
already published: each rejected value is counted once, not again with every supplement."""

from __future__ import annotations

import datetime as dt
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import pytest
from gps_stream_builder import START, serial_profile, Solution, gga, hdt, rmc, zda

from u2sa_hw.drivers.gps_nmea.driver import GpsNmeaDriver
from u2sa_hw.bus.transport import Transport

BAD_HDOP = Solution(when=START, lat=29.19, lon=-81.05, speed=2.0, course=90.0, heading=361.5, hdop=-4.0)
NEXT = replace(BAD_HDOP, when=START + dt.timedelta(seconds=1), lat=29.19002)


@pytest.fixture
def driver(tmp_path: Path, lcm_url: str) -> Iterator[GpsNmeaDriver]:
    transport = Transport(lcm_url, name="gps-rejects")
    yield GpsNmeaDriver("gps", config_path=tmp_path / "gps.toml", transport=transport,
                        profile=serial_profile(), settings={"position_frame": "GEODETIC"})
    transport.stop()


def out_of_range(driver: GpsNmeaDriver) -> tuple[int, str]:
    details = driver.sensor_details()
    return details["out_of_range"], details["out_of_range_kinds"]


def test_late_sentences_merged_into_a_published_epoch_do_not_count_its_rejects_again(
        driver: GpsNmeaDriver) -> None:
    driver.handle_line(gga(BAD_HDOP), 10.0)      # HDOP -4: dropped, counted
    driver.handle_idle()
    assert out_of_range(driver) == (1, "hdop:1")
    driver.handle_line(rmc(BAD_HDOP), 10.3)      # late: merged into the epoch with the GGA
    driver.handle_line(zda(BAD_HDOP), 10.31)
    driver.handle_idle()
    driver.handle_line(hdt(BAD_HDOP), 10.5)      # later still, with a heading of 361.5: a new reject
    driver.handle_idle()
    assert driver.supplements >= 2
    assert out_of_range(driver) == (2, "hdop:1,heading:1")
    driver.handle_line(gga(NEXT), 11.0)          # the next epoch's own bad HDOP is a new value
    driver.handle_idle()
    assert out_of_range(driver) == (3, "hdop:2,heading:1")
