"""The serial compass driver on whole streams: burst grouping (heading with its own burst's pitch
and roll), the newer sentences (THS, ROT, PASHR, PTNTHTM/HPR, XDR heel/trim) and impossible values.

Streams are composed here from the sentence definitions (checksums computed), minutes long,
with a modelled wire timing (each line takes its characters x 10 bits / baud and arrives with
its last byte; the driver's read timeout reports silence when no byte came for epoch_gap_s). They are fed to the real driver class -- its line handling,
burst grouping and publishing over LCM -- in the test process, so minutes of stream take a
fraction of a second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import pytest
from pynmeagps.nmeahelpers import calc_checksum
from gps_stream_builder import recording_driver

from u2sa_hw.drivers.compass.driver import SerialCompassDriver, char_time_s
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.loader import load_profile
from u2sa_hw.profile.vehicle import VehicleProfile

GAP_S = 0.05  # the driver's epoch_gap_s (its read timeout)


def nmea(body: str) -> bytes:
    return f"${body}*{calc_checksum(body)}\r\n".encode()


@dataclass(frozen=True)
class Truth:
    heading: float
    pitch: float
    roll: float


def truth_of(k: int) -> Truth:
    """Burst k's values, each unique over 3600 bursts: a heading, and a pitch and roll that differ from burst
    to burst (the pitch says k mod 800, the roll k // 800)."""
    return Truth(round((k * 7.3) % 360.0, 1), round(-40.0 + (k % 800) * 0.1, 1),
                 round(-20.0 + (k // 800) * 5.0 + (k % 13) * 0.1, 1))


def sentence(kind: str, v: Truth) -> bytes:
    """One sentence of *kind* carrying *v* (heading sentences give v.heading as the true heading)."""
    bodies = {
        "XDRP": f"HCXDR,A,{v.pitch:.1f},D,PITCH",
        "XDRR": f"HCXDR,A,{v.roll:.1f},D,ROLL",
        "XDR": f"HCXDR,A,{v.pitch:.1f},D,PITCH,A,{v.roll:.1f},D,ROLL",
        "HEELTRIM": f"IIXDR,A,{v.roll:.1f},D,HEEL,A,{v.pitch:.1f},D,TRIM",
        "HDM": f"HCHDM,{v.heading:.1f},M",
        "HDG": f"HCHDG,{v.heading:.1f},0.0,E,0.0,E",
        "HDT": f"HEHDT,{v.heading:.1f},T",
        "THS": f"HETHS,{v.heading:.2f},A",
        "ROT": "HEROT,-12.0,A",
        "PASHR": f"PASHR,120000.00,{v.heading:.2f},T,{v.roll:.2f},{v.pitch:.2f},0.05,0.020,0.030,0.150,1,1",
        "PTNTHTM": f"PTNTHTM,{v.heading:.1f},N,{v.pitch:.1f},N,{v.roll:.1f},N,59.1,3844",
    }
    return nmea(bodies[kind])


def compose(order: tuple[str, ...], *, bursts: int, rate_hz: float, baud: int = 19200, evenly: bool = False,
            skip: int = 0, bits: int = 10) -> Iterator[tuple[float, bytes | None]]:
    """(time, line) as the driver reads them; (time, None) where its read timeout reports silence.

    Each line takes its characters x *bits* (10: 8N1) / *baud* and arrives when its last byte has. Burst k
    starts at k / rate_hz and its lines go back to back; with *evenly* every line is preceded by the
    same pause instead (the bursts cannot be told apart by their timing). The first *skip* lines
    are not sent (the driver starts reading mid-burst). Silence is reported where no byte came for
    GAP_S: between the previous line's last byte and this line's first, not its last.
    """
    lines = [[sentence(kind, truth_of(k)) for kind in order] for k in range(bursts)]
    on_wire = sum(len(line) for line in lines[0]) * bits / baud
    even_pause = (1.0 / rate_hz - on_wire) / len(order)
    assert even_pause > 0, "the burst does not fit its period at this baud rate"
    now, last, n = 0.0, None, 0
    for k, burst in enumerate(lines):
        now = now if evenly else max(now, k / rate_hz)
        for line in burst:
            on_line = len(line) * bits / baud
            now += (even_pause if evenly else 0.0) + on_line
            n += 1
            if n <= skip:
                continue
            if last is not None and now - on_line - last >= GAP_S:
                yield last + GAP_S, None
            yield now, line
            last = now


@pytest.fixture
def transport(lcm_url: str) -> Iterator[Transport]:
    tr = Transport(lcm_url, name="compass-test")
    yield tr
    tr.stop()


RecordingCompass = recording_driver(SerialCompassDriver)


def make_driver(tmp_path: Path, transport: Transport, *, baud: int = 19200, **settings: object) -> RecordingCompass:
    """A compass driver (nothing opened) whose device ``compass`` is at *baud* 8N1."""
    profile = VehicleProfile(path=None, devices={"compass": {"address": f"serial:///dev/u2sa/compass?baud={baud}"}})
    return RecordingCompass("compass", profile=profile, config_path=tmp_path / "compass.toml", transport=transport,
                            settings={"epoch_gap_s": GAP_S, **settings})


def feed(driver: SerialCompassDriver, events: Iterator[tuple[float, bytes | None]]) -> int:
    lines = 0
    for at, line in events:
        if line is None:
            driver.handle_idle()
        else:
            driver.handle_line(line, at)
            lines += 1
    driver.handle_idle()
    return lines


HEADINGS = {truth_of(k).heading: k for k in range(3600)}
ATTITUDES = {(truth_of(k).pitch, truth_of(k).roll): k for k in range(3600)}
PITCHES: dict[float, set[int]] = {}
ROLLS: dict[float, set[int]] = {}
for _k in range(3600):
    PITCHES.setdefault(truth_of(_k).pitch, set()).add(_k)
    ROLLS.setdefault(truth_of(_k).roll, set()).add(_k)


def burst_of(msg: t.StateInformation) -> tuple[int | None, int | None]:
    """(the burst its heading came from, the burst its pitch and roll came from); None where absent."""
    heading = round(math.degrees(msg.psi) % 360.0, 1) % 360.0 if msg.has("psi") else None
    attitude = (round(math.degrees(msg.theta), 1) + 0.0, round(math.degrees(msg.phi), 1) + 0.0) \
        if msg.has("theta") and msg.has("phi") else None
    return (None if heading is None else HEADINGS[heading],
            None if attitude is None else ATTITUDES[attitude])


def bursts_of(msg: t.StateInformation) -> set[int] | None:
    """The bursts whose values the message's heading, pitch and roll all are (None: it holds none of them;
    empty: they come from different bursts)."""
    found = []
    if msg.has("psi"):
        found.append({HEADINGS[round(math.degrees(msg.psi) % 360.0, 1) % 360.0]})
    if msg.has("theta"):
        found.append(PITCHES[round(math.degrees(msg.theta), 1) + 0.0])
    if msg.has("phi"):
        found.append(ROLLS[round(math.degrees(msg.phi), 1) + 0.0])
    return set.intersection(*found) if found else None


def mismatched(sent: list[t.StateInformation]) -> list[int]:
    """Indexes of messages whose values come from more than one burst (a heading with another burst's
    pitch or roll, or a pitch with another burst's roll)."""
    return [i for i, msg in enumerate(sent) if bursts_of(msg) == set()]


def complete(msg: t.StateInformation) -> bool:
    return msg.has("psi") and msg.has("theta") and msg.has("phi")


def in_step_from(sent: list[t.StateInformation]) -> int:
    """The burst from which every message is a whole burst (heading, pitch and roll)."""
    first = max((i + 1 for i, m in enumerate(sent) if not complete(m)), default=0)
    assert first < len(sent), "never in step"
    return burst_of(sent[first])[0]  # type: ignore[return-value]


def one_per_sentence(sent: list[t.StateInformation]) -> list[tuple[str, float]]:
    """Each message's one value (which, degrees); fails on a message holding more than one sentence's."""
    out = []
    for msg in sent:
        held = [name for name in ("psi", "theta", "phi") if msg.has(name)]
        assert len(held) == 1, msg.present_fields()
        degrees = math.degrees(getattr(msg, held[0]))
        out.append((held[0], round(degrees % 360.0, 1) % 360.0 if held[0] == "psi" else round(degrees, 1) + 0.0))
    return out


def check_finite(sent: list[t.StateInformation]) -> None:
    for msg in sent:
        for name in ("psi", "theta", "phi", "psi_dot"):
            if msg.has(name):
                assert math.isfinite(getattr(msg, name)), (name, getattr(msg, name))
        if msg.has("psi"):
            assert -math.pi <= msg.psi < math.pi


# -------------------------------------------------------------- item 11: the right burst ------
@pytest.mark.parametrize("skip", [0, 1])
@pytest.mark.parametrize("order", [("XDRP", "XDRR", "HDM"), ("HDM", "XDRP", "XDRR")])
def test_an_evenly_spaced_stream_without_any_pause_publishes_each_sentence_alone_never_mixed(
        tmp_path: Path, transport: Transport, order: tuple[str, ...], skip: int) -> None:
    """Three minutes at 10 Hz, sentences evenly spaced: neither silence nor timing shows the bursts, and
    heading-first and heading-last look alike. Fail safe: never combined, each sentence its own message
    (joined at a burst's start, or mid-burst)."""
    driver = make_driver(tmp_path, transport)
    bursts = 1800
    feed(driver, compose(order, bursts=bursts, rate_hz=10.0, evenly=True, skip=skip))
    field = {"XDRP": "theta", "XDRR": "phi", "HDM": "psi"}
    wanted = [(field[kind], getattr(truth_of(k), {"theta": "pitch", "phi": "roll", "psi": "heading"}[field[kind]]))
              for k in range(bursts) for kind in order][skip:]
    assert one_per_sentence(driver.sent) == wanted
    assert driver.bursts.first is None and driver.bursts.rule == "complete, learning"
    check_finite(driver.sent)


def test_xdr_xdr_hdm_back_to_back_bursts_are_found_by_their_timing(tmp_path: Path, transport: Transport) -> None:
    """The same at 20 Hz, 38400 baud, each burst's lines back to back: about 30 ms of pause before each
    burst, no silence; the pitch XDR follows the longest pause and is learned as the first sentence."""
    driver = make_driver(tmp_path, transport, baud=38400)
    feed(driver, compose(("XDRP", "XDRR", "HDM"), bursts=20 * 120, rate_hz=20.0, baud=38400, skip=2))
    assert mismatched(driver.sent) == []
    assert driver.bursts.first == "XDR:PITCH" and driver.bursts.first_from == "timing"
    assert in_step_from(driver.sent) <= 12   # one sentence per message until then


def test_a_heading_first_device_without_silence_is_found_by_its_timing(tmp_path: Path, transport: Transport) -> None:
    """HDG then XDR at 20 Hz, 38400 baud: the pause between bursts (about 30 ms) is shorter than
    epoch_gap_s, so no silence; the HDG follows the longest pause and is learned as the first sentence."""
    driver = make_driver(tmp_path, transport, baud=38400)
    bursts = 20 * 150
    feed(driver, compose(("HDG", "XDR"), bursts=bursts, rate_hz=20.0, baud=38400))
    assert mismatched(driver.sent) == []   # not even while learning: each sentence alone until then
    assert driver.bursts.first == "HDG" and driver.bursts.first_from == "timing"
    assert in_step_from(driver.sent) <= 12
    assert [burst_of(m)[0] for m in driver.sent if m.has("psi")] == list(range(bursts))
    check_finite(driver.sent)


def test_a_heading_first_device_with_silence_between_bursts_is_in_step_at_once(tmp_path: Path,
                                                                               transport: Transport) -> None:
    driver = make_driver(tmp_path, transport, baud=4800)
    feed(driver, compose(("HDG", "XDR"), bursts=2 * 180, rate_hz=2.0, baud=4800, skip=1))
    assert mismatched(driver.sent) == []
    assert driver.bursts.first == "HDG" and driver.bursts.first_from == "silence"
    # burst 0: its XDR alone (its HDG was missed); burst 1, before the first sentence is known: HDG and XDR apart
    assert len(driver.sent) == 2 * 180 + 1 and all(m.has("psi") and m.has("theta") for m in driver.sent[3:])


@pytest.mark.parametrize(("rate_hz", "learned_from"), [(2.0, "silence"), (6.0, "timing")])
@pytest.mark.parametrize("order", [("XDRP", "XDRR", "HDM"), ("HDM", "XDRP", "XDRR")])
def test_nmea_standard_4800_baud_bursts_keep_heading_pitch_and_roll_together(
        tmp_path: Path, transport: Transport, order: tuple[str, ...], rate_hz: float, learned_from: str) -> None:
    """At 4800 baud (NMEA 0183's rate) each line is some 50 ms on the wire, as long as epoch_gap_s: the time
    between line arrivals is not silence. Five minutes with a pause between bursts (at 2 Hz ~350 ms:
    silence; at 6 Hz ~17 ms: timing only), attitude-first and heading-first."""
    driver = make_driver(tmp_path, transport, baud=4800)
    bursts = int(300 * rate_hz)
    feed(driver, compose(order, bursts=bursts, rate_hz=rate_hz, baud=4800))
    assert mismatched(driver.sent) == []
    first = {"XDRP": "XDR:PITCH", "HDM": "HDM"}[order[0]]
    assert (driver.bursts.first, driver.bursts.first_from) == (first, learned_from)
    assert in_step_from(driver.sent) <= (1 if learned_from == "silence" else 12)
    assert [burst_of(m)[0] for m in driver.sent if m.has("psi")] == list(range(bursts))
    check_finite(driver.sent)


def test_the_wire_time_of_a_character_comes_from_the_device_address_baud_and_framing(
        tmp_path: Path, transport: Transport) -> None:
    assert char_time_s(baud=4800) == pytest.approx(10 / 4800)                                  # 8N1
    assert char_time_s(baud=9600, bytesize=7, parity="E", stopbits=2.0) == pytest.approx(11 / 9600)
    assert make_driver(tmp_path, transport, baud=4800).char_time_s() == pytest.approx(10 / 4800)  # before setup
    path = tmp_path / "vehicle.toml"
    path.write_text('[vehicle]\nname = "boat"\n[devices.compass]\n'
                    'address = "serial:///dev/u2sa/compass?baud=4800&parity=E"\n')
    driver = RecordingCompass("compass", profile=load_profile(path), config_path=tmp_path / "c.toml",
                              transport=transport, settings={})
    driver.setup()                                                 # resolves the address; opens nothing
    try:
        assert driver.char_time_s() == pytest.approx(11 / 4800)
        # a 42-character XDR is 96 ms on this wire: at the OS5000's factory 19200 it would look like silence
        feed(driver, compose(("HDG", "XDR"), bursts=60, rate_hz=2.0, baud=4800, bits=11))
        assert driver.bursts.char_time_s == pytest.approx(11 / 4800)
        assert len(driver.sent) == 61 and all(m.has("psi") and m.has("theta") for m in driver.sent[2:])
    finally:
        driver.kill()


def test_blank_lines_and_ais_sentences_are_ignored_not_malformed(tmp_path: Path, transport: Transport) -> None:
    """The GPS driver's rule (nmea_fields.is_foreign): a blank line or an encapsulated AIS sentence sharing the
    port is no error."""
    body = "AIVDM,1,1,,A,13aG?P0P00PD;88MD5MTDww@2<0L,0"
    ais = f"!{body}*{calc_checksum(body)}\r\n".encode()
    for fmt in ("nmea", "os5000"):
        driver = make_driver(tmp_path, transport, format=fmt)
        for i, line in enumerate((b"\r\n", b"\n", b"  \r\n", ais)):
            driver.handle_line(line, float(i))
        assert (driver.malformed, driver.ignored) == (0, 4), fmt
        driver.handle_line(b"garbage\r\n", 9.0)
        assert driver.malformed == 1


# -------------------------------------------------------------- item 12: XDR only -------------
def test_an_xdr_only_stream_without_silence_publishes_every_reading(tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport)
    for k in range(10):
        driver.handle_line(sentence("XDR", truth_of(k)), 100.0 + k * 0.02)
    assert [burst_of(m)[1] for m in driver.sent] == list(range(10))   # each published as it arrives
    split = make_driver(tmp_path, transport)   # evenly spaced: pitch and roll apart, the order is not known
    feed(split, compose(("XDRP", "XDRR"), bursts=600, rate_hz=25.0, evenly=True))
    assert one_per_sentence(split.sent) == [(f, v) for k in range(600)
                                            for f, v in (("theta", truth_of(k).pitch), ("phi", truth_of(k).roll))]
    paused = make_driver(tmp_path, transport)  # with silence between bursts: one message per burst
    feed(paused, compose(("XDRP", "XDRR"), bursts=600, rate_hz=10.0))
    assert mismatched(paused.sent) == [] and [burst_of(m)[1] for m in paused.sent[2:]] == list(range(1, 600))


# -------------------------------------------------------------- item 13: more sentences -------
@pytest.mark.parametrize("order", [("PTNTHTM",), ("PASHR",), ("THS", "ROT", "HEELTRIM"), ("HEELTRIM", "HDT")])
def test_tnt_pashr_ths_rot_and_heel_trim_streams(tmp_path: Path, transport: Transport, order: tuple[str, ...]) -> None:
    driver = make_driver(tmp_path, transport)
    feed(driver, compose(order, bursts=600, rate_hz=10.0, baud=19200))
    assert mismatched(driver.sent) == []
    assert [burst_of(m)[0] for m in driver.sent if m.has("psi")] == list(range(600))
    # the first burst, before its first sentence is learned (from the silence after it): one sentence at a time
    assert len(driver.sent) - 600 <= len(order) - 1
    assert all(len(m.present_fields()) >= 4 for m in driver.sent[len(order):])
    if "ROT" in order:
        rates = [m for m in driver.sent if m.has("psi_dot")]
        assert len(rates) == 600 and all(m.psi_dot == pytest.approx(math.radians(-12.0 / 60.0)) for m in rates)
        assert rates[0].psi_dot_sigma == pytest.approx(math.radians(1.0))
    if order == ("PASHR",):   # the device's own accuracies become the sigmas
        m = driver.sent[0]
        assert (m.phi_sigma, m.theta_sigma, m.psi_sigma) == pytest.approx(tuple(map(math.radians, (0.02, 0.03, 0.15))))
    details = driver.sensor_details()
    assert details["out_of_range"] == 0 and details["not_valid"] == 0
    check_finite(driver.sent)


def test_status_letters_drop_what_the_device_marks_not_valid(tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport)
    lines = ["HETHS,10.0,A", "HETHS,20.0,E", "HETHS,30.0,V", "HETHS,40.0,S", "HETHS,50.0,M",
             "HEROT,99.0,V", "PTNTHPR,59.6,N,-0.2,N,-3.0,N", "PTNTHPR,72.9,N,-1.6,N,-29.6,O",
             "PTNTHPR,80.0,N,-1.5,N,50.0,P", "PTNTHPR,81.0,L,0.3,N,0.1,N"]
    for i, body in enumerate(lines):
        driver.handle_line(nmea(body), i * 1.0)
        driver.handle_idle()
    got = [(round(math.degrees(m.psi) % 360, 1) if m.has("psi") else None,
            round(math.degrees(m.phi), 1) if m.has("phi") else None) for m in driver.sent]
    # THS V/S/M and ROT V: nothing; HPR alarm P on roll: no heading, no roll (the pitch stays); alarm L: no heading
    assert got == [(10.0, None), (20.0, None), (59.6, -3.0), (72.9, -29.6), (None, None), (None, 0.1)]
    assert driver.sensor_details()["not_valid_kinds"] == ("PTNTHPR heading alarm L:1,PTNTHPR heading alarm P:1,"
                                                          "PTNTHPR roll alarm P:1,ROT status V:1,THS mode M:1,"
                                                          "THS mode S:1,THS mode V:1")


# -------------------------------------------------------------- impossible values -------------
def test_impossible_values_are_dropped_and_counted_by_kind(tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport, pitch_range_deg=40.0, roll_range_deg=40.0)   # an HMR3000
    bad = ["HCHDG,400.0,0.0,E,0.0,E", "HCHDG,100.0,500.0,E,0.0,E", "HCXDR,A,120.0,D,PITCH",
           "HCXDR,A,45.0,D,PITCH,A,3.0,D,ROLL", "HCXDR,A,2.0,D,PITCH,A,-41.0,D,ROLL",
           "HEROT,20000.0,A", "HCHDM,999999999999999999999999,M", "PASHR,1,10.0,T,0,0,0,500,0.1,0.1,1,1"]
    for i, body in enumerate(bad):
        driver.handle_line(nmea(body), i * 1.0)
        driver.handle_idle()
    details = driver.sensor_details()
    assert details["out_of_range_kinds"] == "deviation:1,heading:2,pitch:2,rate of turn:1,roll:1,roll accuracy:1"
    # what was left of each sentence is still used: HDG's heading with its deviation dropped, XDR's other angle
    kept = [(m.present_fields()) for m in driver.sent]
    assert ["psi", "psi_sigma"] in kept and ["theta", "theta_sigma"] in kept and ["phi", "phi_sigma"] in kept
    check_finite(driver.sent)
    # exponents, inf and nan are no NMEA numbers: the sentence is malformed, not a measurement
    before = driver.malformed
    for body in ("HCHDG,1e308,1e308,E,,", "HCXDR,A,1e306,D,PITCH", "HCHDT,nan,T", "HCHDT,inf,T"):
        driver.handle_line(nmea(body), 50.0)
    assert driver.malformed == before + 4


def test_os5000_values_outside_the_documented_ranges_are_dropped(tmp_path: Path, transport: Transport) -> None:
    driver = make_driver(tmp_path, transport, format="os5000")
    for i, body in enumerate(("C361.0P1.0R2.0T20.0", "C10.0P95.0R200.0T20.0", "C10.0P1.0R2.0T900.0")):
        driver.handle_line(nmea(body), float(i))
    assert driver.sensor_details()["out_of_range_kinds"] == "heading:1,pitch:1,roll:1,temperature:1"
    assert [sorted(m.present_fields()) for m in driver.sent] == [
        ["phi", "phi_sigma", "theta", "theta_sigma"], ["psi", "psi_sigma"],
        ["phi", "phi_sigma", "psi", "psi_sigma", "theta", "theta_sigma"]]


def test_a_corrupted_heading_of_the_next_burst_ends_the_pending_one_at_once(tmp_path: Path,
                                                                          transport: Transport) -> None:
    driver = make_driver(tmp_path, transport)
    feed(driver, compose(("HDG", "XDR"), bursts=4, rate_hz=5.0))   # learned: HDG first, HDG + XDR complete
    assert driver.bursts.rule == "complete, first HDG (silence)"
    before = len(driver.sent)
    driver.handle_line(sentence("HDG", truth_of(10)), 10.0)        # a burst whose XDR is lost ...
    corrupted = sentence("HDG", truth_of(11)).replace(b"*", b"0*", 1)
    driver.handle_line(corrupted, 10.03)                            # ... and the next one's HDG corrupted
    assert [burst_of(m) for m in driver.sent[before:]] == [(10, None)]
    assert driver.bad_checksums == {"HDG": 1}
