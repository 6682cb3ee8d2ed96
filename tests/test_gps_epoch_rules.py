"""Issue 24 (2, 3): GPS epoch rules that failed on real receivers, and the fix-mode policy.

(a) completion is never re-learned from two bursts cut at the same point seconds apart;
(b) an empty satellites-used count is unknown, not zero; (c) a leftover timeless no-fix
GLL never opens (and so splits) the next epoch. Then which rule gave each fix mode
(``GpsFix.fix_rule``, health ``fix_rule``, a debug log line on a change).

Every stream is composed here from the NMEA 0183 sentence definitions (checksums computed
by ``gps_stream_builder.nmea``), with the receive times injected: no sleeps, no timing.
"""

from __future__ import annotations

import datetime as dt
import logging
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import pytest
from gps_stream_builder import START, RecordingGps, serial_profile, Solution, epoch, gga, gll, gns, gsa, nmea, rmc, vtg

from u2sa_hw.drivers.gps_nmea import fix as gf
from u2sa_hw.drivers.gps_nmea.epochs import GpsEpochCollector
from u2sa_hw.drivers.gps_nmea.fix import fix_from_epoch
from u2sa_hw.drivers.nmea_fields import Epoch, parse_sentence, utc_time
from u2sa_hw.bus.transport import Transport

SOL = Solution(when=START, lat=29.19, lon=-81.05, speed=2.0, course=90.0)
# a receiver without a solution and without a time (u-blox before its first fix; NMEA 0183 leaves
# every field empty and sets status V / mode N, GGA quality 0)
VOID_GLL = nmea("GPGLL,,,,,,V,N")
VOID_RMC = nmea("GPRMC,,V,,,,,,,,,,N")
VOID_GGA = nmea("GPGGA,,,,,,0,00,99.99,,,,,,")


def at(k: int, rate_hz: float = 5.0) -> Solution:
    """The solution of epoch *k* at *rate_hz*, moving north (a latitude a 4-decimal GLL rounds)."""
    return replace(SOL, when=START + dt.timedelta(seconds=k / rate_hz), lat=SOL.lat + (k + 1) * 1.234567e-5)


def add(col: GpsEpochCollector, line: bytes, received: float) -> list[Epoch]:
    sentence = parse_sentence(line)
    assert sentence is not None, line
    return col.add(sentence, received=received)


# ------------------------------------------------------------ (a) completion from a split burst -----
def burst(s: Solution) -> list[bytes]:
    return [gga(s), gsa(s), rmc(s), vtg(s)]


def test_two_bursts_cut_at_the_same_point_seconds_apart_are_never_learned_as_complete() -> None:
    """Rule 4: the span is of consecutive epochs. Whole epochs that end on completion between two
    cuts restart it, so the cut content (GGA, GSA) is not learned, the rest of each cut burst is
    one supplement, and completion stays on for the whole receiver content."""
    col = GpsEpochCollector()
    ended: list[Epoch] = []
    cuts = {15, 26, 40}                           # 3.0 s, 5.2 s, 8.0 s: more than learn_span_s apart
    for k in range(60):
        lines, now = burst(at(k)), k / 5.0
        if k in cuts:                             # a loaded machine: a silence after the GSA
            for line in lines[:2]:
                ended += add(col, line, now)
            ended += [e for e in [col.flush()] if e]
            lines, now = lines[2:], now + 0.06
        for line in lines:
            ended += add(col, line, now)
        if k < 11:                                # learning: each burst ends on the silence after it
            ended += [e for e in [col.flush()] if e]
    whole = {("GP", "GGA"): 1, ("GP", "GSA"): 1, ("GP", "RMC"): 1, ("GP", "VTG"): 1}
    assert col.mode == "on completion" and col.expected == whole
    assert col.late == 2 * len(cuts) and not col.varying
    supplements = [e for e in ended if e.supplement]
    assert [e.kinds() for e in supplements] == [["RMC", "VTG"]] * len(cuts)
    # one epoch per burst, each ended by completion after the cuts, never by a cut content
    epochs = [e for e in ended if not e.supplement]
    assert len(epochs) == 60 and len({e.time for e in epochs}) == 60
    assert all(e.kinds() == ["GGA", "GSA", "RMC", "VTG"] for e in epochs if e.time not in
               {at(c).when.time() for c in cuts})


def test_a_receiver_that_really_drops_a_sentence_is_learned_again_after_two_seconds() -> None:
    """What rule 4 still allows: consecutive epochs of a new content (the receiver stopped its VTG)."""
    col = GpsEpochCollector()
    for k in range(12):
        for line in burst(at(k)):
            add(col, line, k / 5.0)
        col.flush()
    assert col.mode == "on completion"
    for k in range(12, 30):
        for line in burst(at(k))[:3]:
            add(col, line, k / 5.0)
        col.flush()
    assert col.mode == "on completion" and ("GP", "VTG") not in (col.expected or {})
    assert col.late == 0


# ------------------------------------------------------------ (b) an empty satellite count ---------
@pytest.mark.parametrize("beside", [rmc(SOL), gll(SOL)], ids=["RMC A", "GLL A"])
@pytest.mark.parametrize("quality", [1, 2])
def test_an_empty_satellite_count_is_unknown_so_gga_quality_1_or_2_is_a_fix(quality: int, beside: bytes) -> None:
    fix = fix_from_epoch(epoch(gga(SOL, quality=quality, sats=""), beside))
    assert fix.has_fix and fix.satellites is None and fix.lat == pytest.approx(SOL.lat, abs=1e-6)
    assert fix.fix_name == "2D" and fix.fix_rule == gf.RULE_2D_UNKNOWN_SATELLITES    # 4 not shown
    three_d = fix_from_epoch(epoch(gga(SOL, quality=quality, sats=""), gsa(SOL, mode=3), beside))
    assert three_d.fix_name == "3D" and three_d.fix_rule == gf.RULE_3D_GSA and three_d.alt_msl == SOL.alt


def test_an_empty_count_in_gga_alone_or_gns_is_a_fix_but_zero_or_quality_0_is_not() -> None:
    assert fix_from_epoch(epoch(gga(SOL, sats=""))).has_fix
    body = gns(SOL).decode()[1:-5].split(",")       # $, and *HH CR LF off
    assert body[7] == "09"                            # GNS field 7: satellites in use
    no_count_gns = nmea(",".join([*body[:7], "", *body[8:]]))
    assert fix_from_epoch(epoch(no_count_gns)).has_fix
    for lines in ((gga(SOL, quality=0, sats="00"), rmc(SOL)), (gga(SOL, quality=0, sats=""), rmc(SOL)),
                  (gga(SOL, sats="00"), rmc(SOL)), (gga(SOL, sats="02"), gll(SOL))):
        fix = fix_from_epoch(epoch(*lines))
        assert not fix.has_fix and fix.fix_rule == gf.RULE_NONE_GGA, lines


# ------------------------------------------------------------ (c) a leftover timeless no-fix GLL ---
def run(col: GpsEpochCollector, timed: list[tuple[float, bytes | None]]) -> list[Epoch]:
    """Feed (received, line) pairs; None is a silence (the driver's flush)."""
    ended: list[Epoch] = []
    for now, line in timed:
        ended += [e for e in [col.flush()] if e] if line is None else add(col, line, now)
    ended += [e for e in [col.flush()] if e]
    return ended


@pytest.mark.parametrize("before", ["no time", "its own time", "nothing"])
def test_a_leftover_timeless_no_fix_gll_never_splits_the_next_epoch(before: str) -> None:
    """The burst before the first fix ends in a GLL without a time; a silence cut the burst before
    it, so it finds no epoch open. The next burst's own GLL must not open a second epoch."""
    earlier = at(-5)
    head = {"no time": [(0.0, VOID_RMC), (0.0, VOID_GGA)],
            "its own time": [(0.0, rmc(earlier, status="V", mode="N")), (0.0, gga(earlier, quality=0, sats="00"))],
            "nothing": []}[before]
    first = at(0)
    timed = [*head, (0.05, None), (0.06, VOID_GLL),               # left over after the silence
             (1.0, rmc(first)), (1.0, gga(first)), (1.0, gsa(first)), (1.0, gll(first)), (1.1, None)]
    ended = run(GpsEpochCollector(), timed)
    of_first = [e for e in ended if e.time == first.when.time()]
    assert len(of_first) == 1 and not of_first[0].supplement
    assert of_first[0].kinds() == ["RMC", "GGA", "GSA", "GLL"]
    fix = fix_from_epoch(of_first[0])
    assert fix.fix_name == "3D" and fix.alt_msl == SOL.alt
    # the timeless GLL stayed with the burst before it (a supplement of it), or alone at the start
    [void] = [e for e in ended if any(s.kind == "GLL" and utc_time(s.msg) is None for s in e.sentences)]
    assert void.kinds() == ["GLL"] and void.supplement == (before != "nothing")


def test_a_timeless_gll_at_the_end_of_its_own_burst_still_joins_it() -> None:
    """No silence before it: it joins the epoch being collected, as every sentence without a time does."""
    ended = run(GpsEpochCollector(), [(0.0, VOID_RMC), (0.0, VOID_GGA), (0.0, VOID_GLL), (0.1, None),
                                      (1.0, VOID_RMC), (1.0, VOID_GGA), (1.0, VOID_GLL)])
    assert [e.kinds() for e in ended] == [["RMC", "GGA", "GLL"]] * 2
    assert not any(e.supplement for e in ended) and not fix_from_epoch(ended[0]).has_fix


# ------------------------------------------------------------ 3: which rule gave the fix mode ------
@pytest.mark.parametrize(("lines", "name", "rule"), [
    ((rmc(SOL), vtg(SOL)), "2D", gf.RULE_2D_NO_GGA),                     # gpsd keeps its last 3D
    ((gll(SOL),), "2D", gf.RULE_2D_NO_GGA),
    ((gga(SOL, alt=False),), "2D", gf.RULE_2D_NO_ALTITUDE),
    ((gga(SOL), gsa(SOL, mode=2)), "3D", gf.RULE_3D_OVER_GSA_2D),
    ((gga(SOL), gsa(SOL, mode=3)), "3D", gf.RULE_3D_SATELLITES),
    ((gga(SOL),), "3D", gf.RULE_3D_SATELLITES),
    ((gga(SOL, sats="03"),), "2D", gf.RULE_2D_FEW_SATELLITES),           # 3 satellites, an altitude, no GSA
    ((gga(SOL, sats="03"), gsa(SOL, mode=2)), "2D", gf.RULE_2D_FEW_SATELLITES),
    ((gga(SOL, sats="03"), gsa(SOL, mode=3)), "3D", gf.RULE_3D_GSA),
    ((gga(SOL, sats=""),), "2D", gf.RULE_2D_UNKNOWN_SATELLITES),
    ((gga(SOL, quality=0), rmc(SOL)), "no fix", gf.RULE_NONE_GGA),
    ((gga(SOL, quality=6), rmc(SOL, mode="E")), "DR", gf.RULE_NONE_GGA),
    ((rmc(SOL, status="V", mode="N"),), "no fix", gf.RULE_NONE_STATUS),
    ((gga(SOL), gsa(SOL, mode=1)), "no fix", gf.RULE_NONE_GSA),
    ((nmea("GPZDA,235900.00,14,03,2026,00,00"),), "no fix", ""),         # says nothing about the fix
])
def test_each_fix_mode_names_the_rule_that_gave_it(lines: tuple[bytes, ...], name: str, rule: str) -> None:
    fix = fix_from_epoch(epoch(*lines))
    assert (fix.fix_name, fix.fix_rule) == (name, rule)
    assert (fix.alt_msl is not None) == (name == "3D")


# ------------------------------------------------------------ in the driver -----------------------
@pytest.fixture
def transport(lcm_url: str) -> Iterator[Transport]:
    tr = Transport(lcm_url, name="gps-epoch-rules")
    yield tr
    tr.stop()


def make_driver(tmp_path: Path, transport: Transport) -> RecordingGps:
    return RecordingGps("gps", config_path=tmp_path / "gps.toml", transport=transport,
                        profile=serial_profile(), settings={"position_frame": "GEODETIC"})


def test_the_driver_publishes_one_3d_fix_after_a_leftover_gll_and_says_which_rule_gave_each_mode(
        tmp_path: Path, transport: Transport, caplog: pytest.LogCaptureFixture) -> None:
    driver = make_driver(tmp_path, transport)
    caplog.set_level(logging.DEBUG, logger=driver.logger.name)
    for line in (VOID_RMC, VOID_GGA):
        driver.handle_line(line, 10.0)
    driver.handle_idle()
    assert driver.sensor_details()["fix_rule"] == gf.RULE_NONE_GGA
    driver.handle_line(VOID_GLL, 10.06)
    for k in range(3):
        for line in (rmc(at(k)), gga(at(k)), gsa(at(k)), gll(at(k))):
            driver.handle_line(line, 11.0 + k / 5)
        driver.handle_idle()
    assert len(driver.sent) == 3 and all(m.has("z") for m in driver.sent)    # no second, 2-D message
    details = driver.sensor_details()
    assert details["fix_type"] == "3D" and details["fix_rule"] == gf.RULE_3D_SATELLITES
    for line in (rmc(at(3)), vtg(at(3))):                                      # the receiver stops its GGA
        driver.handle_line(line, 12.0)
    driver.handle_idle()
    assert driver.sensor_details()["fix_rule"] == gf.RULE_2D_NO_GGA and not driver.sent[-1].has("z")
    said = [r.getMessage() for r in caplog.records if "by rule" in r.getMessage()]
    assert said == [f"gps: no fix by rule: {gf.RULE_NONE_GGA}", f"gps: 3D by rule: {gf.RULE_3D_SATELLITES}",
                    f"gps: 2D by rule: {gf.RULE_2D_NO_GGA}"]                  # once per change


def test_the_driver_keeps_completion_through_two_cuts_seconds_apart(tmp_path: Path, transport: Transport) -> None:
    """(a) through the driver: each cut burst adds one supplement (its velocity), nothing more."""
    driver = make_driver(tmp_path, transport)
    for k in range(60):
        lines, now = burst(at(k)), 10.0 + k / 5.0
        if k in (15, 26, 40):
            for line in lines[:2]:
                driver.handle_line(line, now)
            driver.handle_idle()
            lines, now = lines[2:], now + 0.06
        for line in lines:
            driver.handle_line(line, now)
        if k < 11:
            driver.handle_idle()
    driver.handle_idle()
    details = driver.sensor_details()
    assert details["epoch_end"] == "on completion"
    assert details["late_sentences"] == 6 and details["supplements"] == 3
    assert len(driver.sent) == 60 + 3
