"""How one GNSS epoch's sentences merge into a fix: several talkers, GLL, too few satellites,
simulator and dead reckoning, speed without course, the geoid table, GSA against GGA, position
precision, and impossible values. Sentences are composed in gps_stream_builder from the
NMEA 0183 definitions."""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import replace

import pytest
from gps_stream_builder import (KNOT_MPS, START, Solution, dm, epoch, gga, gll, gns, gsa, gst, hdt, hhmmss, nmea,
                                printed, rmc, vtg, zda)

from u2sa_hw.drivers.gps_nmea.geoid import geoid_separation
from u2sa_hw.drivers.gps_nmea.fix import StateSettings, fix_from_epoch, state_from_fix
from u2sa_hw.profile.vehicle import Origin

ORIGIN = Origin(lat=29.1895, lon=-81.0483, alt=10.0)
SOL = Solution(when=START, lat=29.19012345, lon=-81.04912345, alt=25.0, sep=-28.3, speed=3.0, course=45.0,
               heading=50.0, sats=11, hdop=0.8, vdop=1.2)


def settings(**kw: object) -> StateSettings:
    return StateSettings(origin=ORIGIN, **kw)  # type: ignore[arg-type]


# ------------------------------------------------------------------ 1: several talkers -----------
def test_per_talker_sentences_of_one_time_make_one_fix_and_a_poorer_later_one_never_downgrades_it() -> None:
    fix = fix_from_epoch(epoch(gga(SOL, talker="GP"), gga(SOL, talker="GA", alt=False, sats="02"),
                               gga(SOL, talker="GL", quality=0), rmc(SOL, talker="GN"),
                               gsa(SOL, talker="GP"), gsa(SOL, talker="GL", mode=2)))
    assert fix.has_fix and fix.fix_name == "3D" and fix.satellites == 11
    assert fix.alt_msl == 25.0 and fix.talkers == {"GP", "GA", "GL", "GN"}
    # the same with the poorer sentence first: the richest wins whatever the order
    fix = fix_from_epoch(epoch(gga(SOL, talker="GA", alt=False, sats="05"), gga(SOL, talker="GP")))
    assert fix.fix_name == "3D" and fix.alt_msl == 25.0 and fix.satellites == 11


def test_gns_with_a_mode_letter_per_constellation() -> None:
    assert fix_from_epoch(epoch(gns(SOL, modes="NA"))).fix_name == "3D"      # GPS no, Galileo autonomous
    assert fix_from_epoch(epoch(gns(SOL, modes="RR"))).fix_name == "3D"
    assert fix_from_epoch(epoch(gns(SOL, modes="NN"))).fix_name == "no fix"
    assert fix_from_epoch(epoch(gns(SOL, modes="EN"))).fix_name == "DR"
    assert fix_from_epoch(epoch(gns(SOL, modes="S"))).fix_name == "simulator"


# ------------------------------------------------------------------ 2: GLL ------------------------
def test_gll_alone_gives_a_2d_fix_with_its_time() -> None:
    fix = fix_from_epoch(epoch(gll(SOL, decimals=4)))
    assert fix.has_fix and fix.fix_name == "2D" and fix.utc_time == SOL.when.time().replace(microsecond=0)
    assert fix.lat == pytest.approx(printed(SOL.lat, decimals=4)) and fix.lon == pytest.approx(printed(SOL.lon, decimals=4))
    msg = state_from_fix(fix, settings())
    assert msg is not None and msg.has("x") and not msg.has("z")
    # status V, or a mode of N, E or S: no GNSS fix
    assert fix_from_epoch(epoch(gll(SOL, status="V", mode="N"))).fix_name == "no fix"
    assert fix_from_epoch(epoch(gll(SOL, mode="E"))).fix_name == "DR"
    # NMEA 2.0 GLL has no mode field: status A is a fix
    la, ns = dm(SOL.lat, lat=True, decimals=4)
    lo, ew = dm(SOL.lon, lat=False, decimals=4)
    assert fix_from_epoch(epoch(nmea(f"GPGLL,{la},{ns},{lo},{ew},{hhmmss(SOL.when)},A"))).has_fix


# ------------------------------------------------------------------ 3: satellites -----------------
@pytest.mark.parametrize(("sats", "name"), [("00", "no fix"), ("02", "no fix"), ("", "2D"), ("03", "2D"),
                                            ("04", "3D")])
def test_gga_with_fewer_than_three_satellites_is_no_fix_and_three_is_2d(sats: str, name: str) -> None:
    """An empty count is unknown, not zero (issue 24 (b)): the quality decides, 2-D without a GSA saying 3-D."""
    fix = fix_from_epoch(epoch(gga(SOL, sats=sats)))
    assert fix.fix_name == name
    assert (state_from_fix(fix, settings()) is None) == (name == "no fix")


# ------------------------------------------------------------------ 4: simulator, dead reckoning ----
@pytest.mark.parametrize(("lines", "name"), [
    ((gga(SOL, quality=8),), "simulator"),
    ((rmc(SOL, mode="S"),), "simulator"),
    ((rmc(SOL, status="V", mode="A"),), "no fix"),
    ((rmc(SOL, mode="N"),), "no fix"),
    ((rmc(SOL, mode="C"),), "no fix"),                      # Quectel "caution"
    ((gga(SOL, quality=6), rmc(SOL, mode="E")), "DR"),
    ((gga(SOL, quality=7),), "manual"),
    ((gga(SOL, quality=9),), "no fix"),                     # not defined
])
def test_simulator_and_dead_reckoning_are_no_gnss_fix_and_say_what_they_are(lines: tuple[bytes, ...],
                                                                            name: str) -> None:
    fix = fix_from_epoch(epoch(*lines, vtg(SOL)))
    assert not fix.has_fix and fix.fix_name == name
    assert fix.speed_mps is None                            # no velocity either
    assert state_from_fix(fix, settings()) is None


# ------------------------------------------------------------------ 5: speed without course --------
def test_speed_and_course_are_separate_fields() -> None:
    still = replace(SOL, speed=0.05, course=None)
    fix = fix_from_epoch(epoch(gga(still), rmc(still)))
    assert fix.speed_mps == pytest.approx(0.05, abs=1e-3) and fix.course_deg is None
    msg = state_from_fix(fix, settings(speed_sigma_mps=0.1))
    assert msg is not None and (msg.x_dot, msg.y_dot) == (0.0, 0.0)
    assert msg.x_dot_sigma == pytest.approx(math.hypot(0.1, 0.05 / math.sqrt(2.0)), abs=1e-3)
    # the course from VTG when RMC leaves it empty, the speed from RMC
    fix = fix_from_epoch(epoch(gga(SOL), rmc(replace(SOL, course=None)), vtg(replace(SOL, speed=9.0))))
    assert fix.speed_mps == pytest.approx(3.0, abs=1e-3) and fix.course_deg == 45.0
    msg = state_from_fix(fix, settings())
    assert msg.x_dot == pytest.approx(3.0 / math.sqrt(2.0), abs=1e-3)
    # a VTG with a speed but no course (the SiRF at rest): speed only
    fix = fix_from_epoch(epoch(gga(SOL), vtg(replace(SOL, course=None))))
    assert fix.speed_mps == pytest.approx(3.0, abs=1e-3) and fix.course_deg is None


# ------------------------------------------------------------------ 6: geoid ----------------------
@pytest.mark.parametrize(("lat", "lon", "expected"), [
    (0.0, 0.0, 17.2), (29.19, -81.05, -30.8), (-90.0, 0.0, -29.5), (90.0, 123.0, 13.6), (50.0, 180.0, -5.7),
])
def test_the_geoid_table_gives_egm96_at_the_grid_points_and_between_them(lat: float, lon: float,
                                                                          expected: float) -> None:
    assert geoid_separation(lat, lon) == pytest.approx(expected, abs=0.1)
    assert geoid_separation(lat, lon + 360.0) == pytest.approx(geoid_separation(lat, lon))


def test_the_geoid_table_refuses_impossible_coordinates() -> None:
    for lat, lon in ((91.0, 0.0), (math.nan, 0.0), (0.0, math.inf)):
        assert geoid_separation(lat, lon) is None


def test_an_empty_geoid_separation_is_taken_from_the_egm96_table_so_both_heights_are_right() -> None:
    fix = fix_from_epoch(epoch(gga(SOL, sep=False)))
    n = geoid_separation(SOL.lat, SOL.lon)
    assert fix.geoid_source == "EGM96 table" and fix.geoid_sep == pytest.approx(n)
    assert fix.altitude("msl") == 25.0 and fix.altitude("ellipsoid") == pytest.approx(25.0 + n)
    assert -32.0 < n < -29.0                                      # EGM96 near Daytona Beach: about -30.8 m
    fix = fix_from_epoch(epoch(gga(SOL)))
    assert fix.geoid_source == "receiver" and fix.altitude("ellipsoid") == pytest.approx(25.0 - 28.3)


# ------------------------------------------------------------------ 8: disagreeing sentences -------
@pytest.mark.parametrize(("gga_quality", "name"), [(0, "no fix"), (6, "DR"), (8, "simulator")])
def test_an_rmc_saying_valid_beside_a_gga_saying_otherwise_does_not_make_a_fix(gga_quality: int, name: str) -> None:
    """An NMEA 2.0 receiver in dead reckoning: GGA quality 6, RMC status A without a mode letter."""
    la, ns = dm(SOL.lat, lat=True)
    lo, ew = dm(SOL.lon, lat=False)
    old_rmc = nmea(f"GPRMC,{hhmmss(SOL.when)},A,{la},{ns},{lo},{ew},5.8,45.0,140326,,")
    fix = fix_from_epoch(epoch(gga(SOL, quality=gga_quality), old_rmc))
    assert not fix.has_fix and fix.fix_name == name and fix.speed_mps is None
    # one talker's GGA with a fix is enough (another constellation's may say 0)
    assert fix_from_epoch(epoch(gga(SOL, talker="GL", quality=0), gga(SOL), old_rmc)).fix_name == "3D"



def test_gsa_2d_does_not_take_the_altitude_from_a_gga_with_four_satellites() -> None:
    assert fix_from_epoch(epoch(gga(SOL), gsa(SOL, mode=2))).fix_name == "3D"
    # three satellites cannot give 3-D on their own, but the receiver's GSA says it has it
    assert fix_from_epoch(epoch(gga(SOL, sats="03"), gsa(SOL, mode=3))).fix_name == "3D"
    assert fix_from_epoch(epoch(gga(SOL, sats="03"), gsa(SOL, mode=2))).fix_name == "2D"
    # every GSA saying "no fix" vetoes the GGA (fail safe); one constellation saying it does not
    assert fix_from_epoch(epoch(gga(SOL), gsa(SOL, mode=1), gsa(SOL, talker="GL", mode=1))).fix_name == "no fix"
    assert fix_from_epoch(epoch(gga(SOL), gsa(SOL, mode=3), gsa(SOL, talker="GL", mode=1))).fix_name == "3D"


def test_the_position_comes_from_the_sentence_with_more_decimals_of_the_same_position() -> None:
    fine, coarse = printed(SOL.lat, decimals=6), printed(SOL.lat, decimals=3)
    fix = fix_from_epoch(epoch(gga(SOL, decimals=3), rmc(SOL, decimals=6)))
    assert fix.lat == pytest.approx(fine, abs=1e-10) and fix.alt_msl == 25.0     # altitude still from GGA
    fix = fix_from_epoch(epoch(gga(SOL, decimals=6), rmc(SOL, decimals=3)))
    assert fix.lat == pytest.approx(fine, abs=1e-10)
    assert fix.lat != pytest.approx(coarse, abs=1e-9)
    # an RMC whose position is elsewhere is not "more decimals of the same position": the GGA stands
    away = replace(SOL, lat=SOL.lat + 0.01)
    fix = fix_from_epoch(epoch(gga(SOL, decimals=3), rmc(away, decimals=6)))
    assert fix.lat == pytest.approx(coarse, abs=1e-10)


# ------------------------------------------------------------------ impossible values --------------
@pytest.mark.parametrize(("line", "kind"), [
    (nmea("GPGGA,120000.00,9940.000,N,08103.000,W,1,09,0.9,12.0,M,-30.5,M,,"), "lat"),
    (nmea("GPGGA,120000.00,2911.000,N,18212.000,W,1,09,0.9,12.0,M,-30.5,M,,"), "lon"),
    (nmea("GPGGA,120000.00,2911.000,N,08103.000,W,1,09,0.9,1e308,M,-30.5,M,,"), "altitude"),
    (nmea("GPGGA,120000.00,2911.000,N,08103.000,W,1,09,0.9,12.0,M,-3000.5,M,,"), "geoid separation"),
    (nmea("GPGGA,120000.00,2911.000,N,08103.000,W," + "1" * 400 + ",09,0.9,12.0,M,-30.5,M,,"), "quality"),
    (nmea("GPGGA,120000.00,2911.000,N,08103.000,W,1,09,-4.0,12.0,M,-30.5,M,,"), "hdop"),
])
def test_an_impossible_gga_value_is_dropped_and_named(line: bytes, kind: str) -> None:
    fix = fix_from_epoch(epoch(line))
    assert kind in fix.rejects
    msg = state_from_fix(fix, settings(position_frame="GEODETIC"))
    if msg is not None:
        assert -90 <= msg.x <= 90 and -180 <= msg.y <= 180
        assert not msg.has("z") or -1000 <= msg.z <= 18200


def test_impossible_speed_heading_sigma_and_date_are_dropped_the_rest_is_kept() -> None:
    fast = replace(SOL, speed=5e307 * KNOT_MPS)
    fix = fix_from_epoch(epoch(gga(SOL), rmc(replace(SOL, speed=600.0)), vtg(fast),
                               nmea("GPGST,120000.00,1.0,1e309,1e309,0.0,inf,1e300,-2.0"),
                               nmea("GPHDT,361.5,T"), nmea("GPZDA,235900.00,14,03," + "9" * 20 + ",00,00")))
    assert fix.has_fix and fix.speed_mps is None and fix.heading_deg is None
    assert fix.utc_date == dt.date(2026, 3, 14)                      # from the RMC: the ZDA's year is impossible
    assert {"speed", "heading", "date", "sigma lon", "sigma alt"} <= set(fix.rejects)
    msg = state_from_fix(fix, settings())
    assert msg is not None and not msg.has("x_dot") and not msg.has("psi")
    assert msg.x_sigma == pytest.approx(0.8 * 3.0 / math.sqrt(2.0))   # the GST is unusable: from HDOP
    # 360.0 is north, and a date from RMC when ZDA's is impossible
    fix = fix_from_epoch(epoch(gga(SOL), rmc(SOL), nmea("GPHDT,360.0,T"), nmea("GPZDA,235900.00,31,02,2026,00,00")))
    assert fix.heading_deg == 0.0 and fix.utc_date == dt.date(2026, 3, 14) and "date" in fix.rejects


def test_a_complete_epoch_with_every_sentence() -> None:
    fix = fix_from_epoch(epoch(gga(SOL), rmc(SOL), vtg(SOL), gsa(SOL), gst(SOL), zda(SOL), hdt(SOL)))
    assert fix.fix_name == "3D" and fix.rejects == [] and fix.heading_deg == 50.0
    assert fix.utc_date == dt.date(2026, 3, 14) and fix.std_lat == 0.8
    msg = state_from_fix(fix, settings())
    assert msg is not None and msg.present_fields() == [
        "x", "y", "z", "x_dot", "y_dot", "x_sigma", "y_sigma", "z_sigma", "x_dot_sigma", "y_dot_sigma", "psi",
        "psi_sigma"]
