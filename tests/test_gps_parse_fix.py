"""GPS NMEA driver's rules on their own (no service, no device): sentence parsing and checksums, how
sentences group into epochs and when an epoch ends, and the fix, state and sigmas an epoch gives. The
driver as a real service process against the mock receiver is tests/test_driver_gps.py."""

from __future__ import annotations

import datetime as dt
import math

import pytest
from pynmeagps.nmeahelpers import calc_checksum
from serial_driver_harness import ORIGIN

from u2sa_hw.drivers.gps_nmea.fix import KNOT_MPS, StateSettings, fix_from_epoch, horizontal_sigma, state_from_fix
from u2sa_hw.drivers.gps_nmea.epochs import GpsEpochCollector
from u2sa_hw.drivers.nmea_fields import BadChecksum, Epoch, MalformedSentence, Sentence, parse_sentence
from u2sa_hw.geo import ned_to_geodetic
from u2sa_hw.profile.vehicle import Origin

GEO = Origin(**ORIGIN)


def nmea(body: str) -> bytes:
    """``$<body>*HH`` CR LF with a correct checksum."""
    return f"${body}*{calc_checksum(body)}\r\n".encode()


def parsed(body: str) -> Sentence:
    s = parse_sentence(nmea(body))
    assert s is not None, body
    return s


def epoch_of(*bodies: str) -> Epoch:
    epoch = Epoch(received=0.0)
    for body in bodies:
        epoch.sentences.append(parsed(body))
    return epoch


def dm(value: float, *, lat: bool) -> tuple[str, str]:
    """Degrees to NMEA ddmm.mmmmm / dddmm.mmmmm and the hemisphere letter."""
    deg = int(abs(value))
    minutes = (abs(value) - deg) * 60.0
    text = f"{deg:02d}{minutes:08.5f}" if lat else f"{deg:03d}{minutes:08.5f}"
    return text, ("N" if value >= 0 else "S") if lat else ("E" if value >= 0 else "W")


def gga(lat: float, lon: float, *, talker: str = "GP", quality: int = 1, alt: str = "12.0", hdop: str = "0.9",
        time: str = "120000.00") -> str:
    la, ns = dm(lat, lat=True)
    lo, ew = dm(lon, lat=False)
    return f"{talker}GGA,{time},{la},{ns},{lo},{ew},{quality},09,{hdop},{alt},M,-30.5,M,,"


# ---------------------------------------------------------------- parsing ----------------------
@pytest.mark.parametrize("talker", ["GP", "GN", "GL", "GA", "GB", "GQ"])
def test_every_talker_and_sentence_kind_parses(talker: str) -> None:
    bodies = {
        "GGA": gga(29.19, -81.05, talker=talker),
        "RMC": f"{talker}RMC,120000.00,A,2911.37000,N,08103.00000,W,1.944,90.00,140326,,,A,V",
        "VTG": f"{talker}VTG,90.00,T,,M,1.944,N,3.600,K,A",
        "GSA": f"{talker}GSA,A,3,02,05,07,09,,,,,,,,,1.70,0.90,1.40",
        "GST": f"{talker}GST,120000.00,1.5,1.50,1.50,0.0,0.80,0.60,2.00",
        "GNS": f"{talker}GNS,120000.00,2911.37000,N,08103.00000,W,AA,09,0.9,12.0,-30.5,,,V",
        "ZDA": f"{talker}ZDA,120000.00,14,03,2026,00,00",
        "HDT": f"{talker}HDT,45.50,T",
    }
    for kind, body in bodies.items():
        s = parsed(body)
        assert (s.talker, s.kind, s.noise_bytes) == (talker, kind, 0)


def test_checksums_are_enforced_and_bad_input_never_raises_anything_else() -> None:
    good = nmea(gga(29.19, -81.05))
    bad = good[:-4] + (b"00" if good[-4:-2] != b"00" else b"11") + good[-2:]
    with pytest.raises(BadChecksum) as err:
        parse_sentence(bad)
    assert err.value.kind == "GGA"
    for line in (b"\x00\xff\xfe garbage\r\n", b"$GPGGA,120000.00,,,,,0,00,,,,,,,\r\n", b"$GPHDT,1.0,T*zz\r\n",
                 "$GPHDT,\u00e91.0,T*00\r\n".encode("latin-1"), b"*4F$"):
        with pytest.raises(MalformedSentence):
            parse_sentence(line)
    # blank lines and AIS sentences sharing the port are not errors: not for this driver
    for line in (b"", b"\r\n", b"  \r\n", b"!AIVDM,1,1,,B,177KQJ5000G?tO`K>RA1wUbN0TKH,0*5C\r\n"):
        assert parse_sentence(line) is None
    # noise glued to the front of a sentence (a garbage burst without a newline) is dropped, not the sentence
    s = parse_sentence(b"\x8a\x13$$\x02junk" + good)
    assert s is not None and s.kind == "GGA" and s.noise_bytes == 9
    # known to nobody, or proprietary: None (ignored, not an error)
    assert parse_sentence(nmea("GPXYZ,1,2")) is None
    assert parse_sentence(nmea("PGRMZ,246,f,3")) is None


def test_epochs_split_on_a_new_utc_time_or_a_repeated_talker_and_kind_but_not_on_gsa_per_constellation() -> None:
    col = GpsEpochCollector(end_on_complete=False)
    first = [gga(29.19, -81.05, talker="GN"), "GNRMC,120000.00,A,2911.37000,N,08103.00000,W,0.0,,140326,,,A,V",
             "GPGSA,A,3,02,05,,,,,,,,,,,1.70,0.90,1.40", "GLGSA,A,3,70,71,,,,,,,,,,,1.70,0.90,1.40",
             "GNVTG,,T,,M,0.000,N,0.000,K,A"]
    assert all(col.add(parsed(b), received=1.0) == [] for b in first)
    [done] = col.add(parsed(gga(29.19, -81.05, talker="GN", time="120000.20")), received=1.2)
    assert done.kinds() == ["GGA", "RMC", "GSA", "GSA", "VTG"]
    assert done.time == dt.time(12, 0, 0) and done.talkers() == {"GN", "GP", "GL"} and done.received == 1.0
    # a receiver that sends no time: the second VTG of the same talker starts the next epoch
    assert col.add(parsed("GNVTG,10.0,T,,M,1.0,N,1.852,K,A"), received=1.3) == []
    [done] = col.add(parsed("GNVTG,11.0,T,,M,1.0,N,1.852,K,A"), received=1.4)
    assert done.kinds() == ["GGA", "VTG"] and done.time == dt.time(12, 0, 0, 200000)
    assert col.flush().kinds() == ["VTG"] and col.flush() is None


def rmc(time: str) -> str:
    return f"GNRMC,{time},A,2911.37000,N,08103.00000,W,0.0,,140326,,,A,V"


def burst(time: str) -> list[str]:
    """One epoch of a two-constellation receiver: GGA, RMC, two GSA, VTG."""
    return [gga(29.19, -81.05, talker="GN", time=time), rmc(time), "GPGSA,A,3,02,05,,,,,,,,,,,1.70,0.90,1.40",
            "GLGSA,A,3,70,71,,,,,,,,,,,1.70,0.90,1.40", "GNVTG,,T,,M,0.000,N,0.000,K,A"]


def feed(col: GpsEpochCollector, bodies: list[str], *, at: float = 0.0) -> list[list[Epoch]]:
    return [col.add(parsed(b), received=at) for b in bodies]


def stamp(k: int) -> str:
    """Epoch k of a 5 Hz receiver as hhmmss.ss."""
    return f"1200{k // 5:02d}.{(k % 5) * 20:02d}"


def learn(col: GpsEpochCollector, epochs: int = 11, *, rate_hz: float = 5.0) -> None:
    """*epochs* alike bursts, each ended by the silence after it, 1 / rate_hz apart."""
    for k in range(epochs):
        assert feed(col, burst(stamp(k)), at=k / rate_hz) == [[]] * 5
        assert col.flush().kinds() == ["GGA", "RMC", "GSA", "GSA", "VTG"]


def test_an_epoch_ends_with_its_last_sentence_once_alike_epochs_spanned_two_seconds() -> None:
    col = GpsEpochCollector()
    assert col.mode == "learning"
    learn(col, 10)                                        # 0 .. 1.8 s: not yet
    assert col.mode == "learning"
    learn_more = burst(stamp(10))
    assert feed(col, learn_more, at=2.0) == [[]] * 5 and col.flush() is not None
    assert col.mode == "on completion"
    assert col.expected == {("GN", "GGA"): 1, ("GN", "RMC"): 1, ("GP", "GSA"): 1, ("GL", "GSA"): 1, ("GN", "VTG"): 1}
    *early, last = feed(col, burst(stamp(11)), at=3.0)
    assert early == [[]] * 4 and len(last) == 1           # the second GSA alone does not complete it
    assert last[0].kinds() == ["GGA", "RMC", "GSA", "GSA", "VTG"] and last[0].received == 3.0
    assert col.pending is None and col.flush() is None and col.completed == 1
    # a sentence missing from an epoch (a bad checksum): it ends the ordinary way, on the next epoch's time
    partial = burst(stamp(12))
    del partial[1]
    assert feed(col, partial) == [[]] * 4
    done = feed(col, burst(stamp(13)))
    assert done[0][0].kinds() == ["GGA", "GSA", "GSA", "VTG"]
    assert done[-1][0].kinds() == ["GGA", "RMC", "GSA", "GSA", "VTG"] and col.mode == "on completion"
    # back-to-back bursts (no silence between them) still end on completion
    assert feed(col, burst(stamp(14)))[-1] and feed(col, burst(stamp(15)))[-1]
    assert col.late == 0


def test_epochs_whose_content_varies_within_two_seconds_are_never_learned() -> None:
    """10 Hz GGA with RMC and ZDA once a second: every epoch ends on the next time, none loses a sentence."""
    col = GpsEpochCollector()
    ended: list[Epoch] = []
    for k in range(60):
        time = f"1200{k // 10:02d}.{k % 10}0"
        bodies = [gga(29.19, -81.05, talker="GN", time=time)]
        if k % 10 == 0:
            bodies += [rmc(time), f"GNZDA,{time},14,03,2026,00,00"]
        for b in bodies:
            ended += col.add(parsed(b), received=k / 10)
    assert col.mode == "learning" and col.late == 0
    assert len(ended) == 59 and all(not e.supplement for e in ended)
    assert [e.kinds() for e in ended[:2]] == [["GGA", "RMC", "ZDA"], ["GGA"]]


def test_a_dropped_sentence_of_a_talker_and_kind_already_held_ends_the_pending_epoch() -> None:
    col = GpsEpochCollector()
    assert feed(col, burst("120000.00")) == [[]] * 5
    assert col.dropped("GSA", "GP") is None          # repeatable: a second GSA belongs to the same epoch
    assert col.dropped("ZDA", "GN") is None          # not in the epoch yet: it may still belong to it
    assert col.dropped("GGA", "GA") is None          # another talker's GGA of the same epoch
    done = col.dropped("GGA", "GN")                  # a corrupted GGA: the receiver has started the next epoch
    assert done is not None and done.kinds() == ["GGA", "RMC", "GSA", "GSA", "VTG"]
    assert col.pending is None and col.dropped("GGA", "GN") is None and col.flush() is None


def test_a_sentence_after_its_epoch_completed_is_a_supplement_and_switches_completion_off() -> None:
    col = GpsEpochCollector()
    learn(col)
    ended = feed(col, [*burst("120003.00"), "GNZDA,120003.00,14,03,2026,00,00", "GNVTG,,T,,M,0.000,N,0.000,K,A"],
                 at=4.0)
    assert ended[4] and ended[5] == []
    assert col.varying and col.mode == "on time or silence"
    # the ZDA carries the ended epoch's time: it opened a supplement, which the next epoch's VTG (no time,
    # a talker and kind the epoch already held) ended
    [supplement] = ended[6]
    assert supplement.supplement and supplement.kinds() == ["ZDA"] and supplement.time == dt.time(12, 0, 3)
    assert col.late == 1
    assert col.add(parsed(gga(29.19, -81.05, talker="GN", time="120003.20")), received=4.2) == []
    assert col.flush().kinds() == ["VTG", "GGA"]
    col.reset()                                                # a reopened port learns again
    assert col.mode == "learning" and col.late == 1


def test_epoch_learning_ignores_a_split_burst_and_handles_whole_second_time_stamps() -> None:
    col = GpsEpochCollector()
    head, tail = burst("120000.00")[:2], burst("120000.00")[2:]
    feed(col, head)
    col.flush()                                                # a stall mid-burst: the silence split it
    feed(col, tail)
    assert col.flush().kinds() == ["GSA", "GSA", "VTG"]
    feed(col, burst("120000.20"), at=3.0)
    assert col.flush().kinds() == ["GGA", "RMC", "GSA", "GSA", "VTG"]
    assert col.mode == "learning"                              # the halves and the whole: no two alike yet
    # a receiver that stamps whole seconds at 5 Hz: the next epoch's first sentence repeats the time
    col = GpsEpochCollector()
    for k in range(11):
        feed(col, burst("120000"), at=k / 5)
        assert not col.flush().supplement
    assert feed(col, burst("120000"), at=3.0)[-1] and feed(col, burst("120000"), at=3.2)[-1]
    assert col.late == 0 and col.mode == "on completion"


# ---------------------------------------------------------------- fixes -------------------------
def test_a_full_epoch_gives_ned_position_velocity_heading_and_gst_sigmas() -> None:
    lat, lon, alt = ned_to_geodetic(123.4, -56.7, 1.5, origin=GEO)
    la, ns = dm(lat, lat=True)
    lo, ew = dm(lon, lat=False)
    fix = fix_from_epoch(epoch_of(
        gga(lat, lon, alt=f"{alt:.2f}"),
        f"GPRMC,120000.00,A,{la},{ns},{lo},{ew},{2.0 / KNOT_MPS:.4f},90.00,140326,,,A,V",
        "GPGSA,A,3,02,05,07,09,,,,,,,,,1.70,0.90,1.40",
        "GPGST,120000.00,1.5,1.50,1.50,0.0,0.80,0.60,2.00",
        "GPZDA,120000.00,14,03,2026,00,00",
        "GPHDT,359.90,T"))
    assert fix.has_fix and fix.fix_dim == 3 and fix.quality == 1 and fix.satellites == 9 and fix.hdop == 0.9
    assert fix.utc_date == dt.date(2026, 3, 14) and fix.utc_time == dt.time(12, 0)
    msg = state_from_fix(fix, StateSettings(origin=GEO))
    assert msg is not None and msg.reference_frame == "NED"
    assert msg.x == pytest.approx(123.4, abs=0.02) and msg.y == pytest.approx(-56.7, abs=0.02)
    assert msg.z == pytest.approx(1.5, abs=0.01)
    assert msg.x_dot == pytest.approx(0.0, abs=1e-9) and msg.y_dot == pytest.approx(2.0, abs=1e-3)
    assert (msg.x_sigma, msg.y_sigma, msg.z_sigma) == (0.80, 0.60, 2.00)
    assert msg.psi == pytest.approx(math.radians(-0.1)) and -math.pi <= msg.psi < math.pi
    assert msg.get("phi") is None and msg.get("psi_dot") is None   # only what a GPS measures


def test_sigmas_fall_back_to_hdop_and_the_geodetic_frame_keeps_lat_lon() -> None:
    fix = fix_from_epoch(epoch_of(gga(-33.85, 151.21, hdop="1.2", alt="40.0"),
                                  "GPGSA,A,3,02,05,07,09,,,,,,,,,2.00,1.20,1.60"))
    assert fix.lat == pytest.approx(-33.85, abs=1e-6) and fix.lon == pytest.approx(151.21, abs=1e-6)
    msg = state_from_fix(fix, StateSettings(origin=GEO, position_frame="GEODETIC", uere_m=4.0,
                                            altitude_datum="ellipsoid"))
    assert msg.reference_frame == "GEODETIC"
    assert (msg.x, msg.y) == (pytest.approx(-33.85, abs=1e-6), pytest.approx(151.21, abs=1e-6))
    assert msg.z == pytest.approx(40.0 - 30.5)          # ellipsoid height = MSL + geoid separation
    assert msg.x_sigma == pytest.approx(1.2 * 4.0 / math.sqrt(2.0)) and msg.z_sigma == pytest.approx(1.6 * 4.0)
    assert not msg.has("x_dot") and not msg.has("psi")  # no RMC/VTG, no HDT in this epoch


def test_2d_fix_has_no_altitude_and_vtg_gives_velocity_in_kmh() -> None:
    fix = fix_from_epoch(epoch_of(gga(29.19, -81.05, alt=""), "GPGSA,A,2,02,05,07,,,,,,,,,,3.00,2.00,2.20",
                                  "GPVTG,180.0,T,,M,,N,7.200,K,D"))
    assert fix.fix_dim == 2 and fix.alt_msl is None
    msg = state_from_fix(fix, StateSettings(origin=GEO))
    assert not msg.has("z") and not msg.has("z_sigma")
    assert msg.x_dot == pytest.approx(-2.0) and msg.y_dot == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(("bodies", "name"), [
    ((gga(29.19, -81.05, quality=0),), "no fix"),                  # invalid
    ((gga(29.19, -81.05, quality=6),), "DR"),                      # dead reckoning is no measurement
    (("GPGGA,120000.00,,,,,0,00,99.99,,,,,,",), "no fix"),         # empty position
    (("GPRMC,120000.00,V,,,,,,,140326,,,N,V", "GPVTG,,T,,M,,N,,K,N"), "no fix"),
    (("GNGNS,120000.00,2911.37000,N,08103.00000,W,NN,00,99.9,,,,,V",), "no fix"),
])
def test_no_fix_gives_no_position_and_no_velocity(bodies: tuple[str, ...], name: str) -> None:
    fix = fix_from_epoch(epoch_of(*bodies))
    assert not fix.has_fix and fix.fix_name == name
    assert state_from_fix(fix, StateSettings(origin=GEO)) is None
    with_heading = fix_from_epoch(epoch_of(*bodies, "GPHDT,90.0,T"))
    msg = state_from_fix(with_heading, StateSettings(origin=GEO))
    assert msg.present_fields() == ["psi", "psi_sigma"]


def test_gns_and_rmc_alone_give_a_fix() -> None:
    gns = fix_from_epoch(epoch_of("GNGNS,120000.00,2911.37000,N,08103.00000,W,RN,14,0.7,12.0,-30.5,,,V"))
    assert gns.has_fix and gns.satellites == 14 and gns.fix_dim == 3
    rmc = fix_from_epoch(epoch_of("GPRMC,120000.00,A,2911.37000,S,08103.00000,E,0.0,,140326,,,A,V"))
    assert rmc.has_fix and rmc.fix_dim == 2 and rmc.lat < 0 < rmc.lon
    assert rmc.speed_mps == 0.0 and rmc.course_deg is None   # speed and course are separate fields
    assert rmc.utc_date == dt.date(2026, 3, 14)


def test_horizontal_sigma_is_the_drms_from_gst_else_hdop() -> None:
    with_gst = fix_from_epoch(epoch_of(gga(29.19, -81.05), "GPGST,120000.00,1.5,1.50,1.50,0.0,0.80,0.60,2.00"))
    assert horizontal_sigma(with_gst, 3.0) == pytest.approx(1.0)
    assert horizontal_sigma(fix_from_epoch(epoch_of(gga(29.19, -81.05, hdop="1.2"))), 4.0) == pytest.approx(4.8)
    assert horizontal_sigma(fix_from_epoch(epoch_of(gga(29.19, -81.05, quality=0))), 4.0) is None
