"""Signing and verification (u2sa_hw.bus.auth) and the key file (u2sa_hw.bus.key), with injected clocks.

The window rules are checked here with clocks the test sets (a minute later, a board without
RTC); the same code over real multicast between processes is tests/test_bus_security.py.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import pytest

from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import (FORGED, MAX_COUNTER, OK, REPLAYED, TAG, TRAILER_LEN, UNSIGNED, WINDOW_US, BusAuth,
                              Keyring, strip_trailer)
from u2sa_hw.bus.key import BusKeyError, key_path, new_key, parse_key, read_key, write_key
from u2sa_hw.bus.transport import Transport
from u2sa_hw.bus.lcm_open import TransportError

NOW_US = 1_764_000_000_000_000      # November 2025
PAYLOAD = t.StateInformation().set(x=1.0).encode()


class Clock:
    """A wall clock in µs the test moves."""

    def __init__(self, us: int = NOW_US) -> None:
        self.us = us

    def __call__(self) -> int:
        return self.us


@pytest.fixture
def key_file(tmp_path: Path) -> Path:
    path = tmp_path / "bus.key"
    write_key(path, new_key(), group=None)
    return path


def auth(path: Path, clock: Clock | None = None, **kw: object) -> BusAuth:
    return BusAuth(Keyring(path), wall_us=clock or Clock(), **kw)  # type: ignore[arg-type]


def test_a_signed_packet_verifies_once_and_is_the_payload_with_a_trailer(key_file: Path) -> None:
    tx, rx = auth(key_file), auth(key_file)
    packet = tx.sign("STATE_INFO", PAYLOAD)
    assert packet[:len(PAYLOAD)] == PAYLOAD and len(packet) == len(PAYLOAD) + TRAILER_LEN
    assert t.StateInformation.decode(packet).get("x") == 1.0   # LCM's own decoder ignores the trailer
    assert rx.verify("STATE_INFO", packet) == OK
    assert rx.last_sender == tx.sender
    assert rx.verify("STATE_INFO", packet) == REPLAYED
    assert strip_trailer(packet) == PAYLOAD and strip_trailer(PAYLOAD) == PAYLOAD


def test_the_mac_is_the_standard_hmac_sha256_of_channel_nul_payload_and_the_signed_trailer(key_file: Path) -> None:
    """What docs/security.md specifies, checked against the standard library's hmac (a ground station in
    another language computes the same)."""
    import hashlib
    import hmac

    packet = auth(key_file).sign("STATE_INFO", PAYLOAD)
    mac_at = len(packet) - TRAILER_LEN + 20           # sender (8), counter (8), key id (4) are signed
    expected = hmac.new(read_key(key_file), b"STATE_INFO\0" + packet[:mac_at], hashlib.sha256).digest()[:16]
    assert packet[mac_at:mac_at + 16] == expected and packet.endswith(TAG)


def test_the_channel_is_signed_too(key_file: Path) -> None:
    packet = auth(key_file).sign("U2SA_CONFIG_SET", PAYLOAD)
    assert auth(key_file).verify("U2SA_STOP", packet) == FORGED


@pytest.mark.parametrize("damage", ["unsigned", "truncated", "garbage", "flipped payload", "flipped mac",
                                    "wrong key id", "empty"])
def test_damaged_packets_are_dropped_with_a_reason_never_raised(key_file: Path, damage: str) -> None:
    good = auth(key_file).sign("STATE_INFO", PAYLOAD)
    bad = {
        "unsigned": PAYLOAD,
        "truncated": good[:-7],
        "garbage": os.urandom(TRAILER_LEN - len(TAG)) + TAG,
        "flipped payload": bytes([good[0] ^ 1]) + good[1:],
        "flipped mac": good[:-5] + bytes([good[-5] ^ 1]) + good[-4:],
        "wrong key id": good[:-TRAILER_LEN + 16] + b"\0\0\0\0" + good[-TRAILER_LEN + 20:],
        "empty": b"",
    }[damage]
    expected = UNSIGNED if damage in ("unsigned", "truncated", "empty") else FORGED
    assert auth(key_file).verify("STATE_INFO", bad) == expected


def test_a_wrong_key_is_forged(key_file: Path, tmp_path: Path) -> None:
    other = tmp_path / "other.key"
    write_key(other, new_key(), group=None)
    assert auth(key_file).verify("U2SA_STOP", auth(other).sign("U2SA_STOP", PAYLOAD)) == FORGED


def test_a_packet_replayed_a_minute_later_is_refused_by_a_receiver_that_never_heard_its_sender(key_file: Path) -> None:
    clock = Clock()
    packet = auth(key_file, clock).sign("U2SA_STOP", PAYLOAD)
    fresh = auth(key_file, Clock(NOW_US + 60_000_000))
    assert fresh.verify("U2SA_STOP", packet) == REPLAYED
    late_but_live = auth(key_file, Clock(NOW_US + WINDOW_US // 2))
    assert late_but_live.verify("U2SA_STOP", packet) == OK


def test_a_restarted_sender_is_accepted_at_once(key_file: Path) -> None:
    clock = Clock()
    rx = auth(key_file, clock)
    before = auth(key_file, clock)
    for _ in range(3):
        clock.us += 1000
        assert rx.verify("U2SA_HEALTH", before.sign("U2SA_HEALTH", PAYLOAD)) == OK
    # The restarted process has a new sender id, even if its clock stepped back a little.
    clock.us -= 5_000_000
    after = auth(key_file, clock)
    assert after.sender != before.sender
    assert rx.verify("U2SA_HEALTH", after.sign("U2SA_HEALTH", PAYLOAD)) == OK


def test_counters_grow_per_sender_even_when_the_clock_stands_still(key_file: Path) -> None:
    tx, rx = auth(key_file), auth(key_file)
    packets = [tx.sign("A", PAYLOAD) for _ in range(5)]
    assert [rx.verify("A", p) for p in packets] == [OK] * 5
    assert rx.verify("A", packets[2]) == REPLAYED


def test_a_board_without_rtc_adopts_the_vehicle_clock_from_the_first_packet_it_verifies(key_file: Path) -> None:
    vehicle = auth(key_file, Clock(NOW_US))
    booted_in_1970 = auth(key_file, Clock(30_000_000))
    # Before it heard anyone, what it signs is too old for the vehicle.
    assert vehicle.verify("X", booted_in_1970.sign("X", PAYLOAD)) == REPLAYED
    assert booted_in_1970.verify("X", vehicle.sign("X", PAYLOAD)) == OK
    assert booted_in_1970.now() >= NOW_US
    assert vehicle.verify("X", booted_in_1970.sign("X", PAYLOAD)) == OK


def _signed_with_counter(tx: BusAuth, channel: str, counter: int) -> bytes:
    key = tx.keyring.current
    signed = PAYLOAD + tx.sender + struct.pack(">Q", counter) + key.id
    return signed + key.mac(channel.encode() + b"\0", signed) + TAG


@pytest.mark.parametrize("counter", [MAX_COUNTER + 1, 2 ** 64 - 1, NOW_US + 400 * 86_400_000_000])
def test_huge_counters_are_dropped_even_when_signed(key_file: Path, counter: int) -> None:
    rx = auth(key_file)
    assert rx.verify("X", _signed_with_counter(auth(key_file), "X", counter)) == REPLAYED
    assert rx.now() == NOW_US   # and the receiver's clock did not move


def test_rotation_is_picked_up_and_the_old_key_lasts_only_the_overlap(key_file: Path) -> None:
    mono = [1000.0]
    ring = Keyring(key_file, overlap_s=30.0, clock=lambda: mono[0])
    rx = BusAuth(ring, wall_us=Clock())
    old_sender = auth(key_file)     # a process that still has the old key
    write_key(key_file, new_key(), group=None)
    ring.poll()                     # within the reload interval: nothing yet
    assert rx.verify("X", auth(key_file).sign("X", PAYLOAD)) == FORGED
    mono[0] += 1.5
    ring.poll()
    assert rx.verify("X", auth(key_file).sign("X", PAYLOAD)) == OK
    assert rx.verify("X", old_sender.sign("X", PAYLOAD)) == OK
    mono[0] += 31.0
    assert rx.verify("X", old_sender.sign("X", PAYLOAD)) == FORGED


def test_a_broken_key_file_after_start_keeps_the_loaded_key(key_file: Path, caplog: pytest.LogCaptureFixture) -> None:
    mono = [0.0]
    ring = Keyring(key_file, clock=lambda: mono[0])
    before = ring.current.id
    key_file.write_text("not a key\n")
    mono[0] += 2
    ring.poll()
    assert ring.current.id == before
    assert "still signing with the key loaded before" in caplog.text


@pytest.mark.parametrize("content, says", [
    (None, "no bus key at"),
    ("abc\n", "a bus key is 64 hex digits (256 bits), this one has 3 characters"),
    ("zz" * 32 + "\n", "this one has other characters"),
    (b"\xff\xfe" * 32, "not a bus key"),
])
def test_a_bad_key_file_is_one_line_naming_the_file_and_the_fix(tmp_path: Path, content: str | bytes | None,
                                                                says: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("U2SA_BUS_KEY_FILE")   # the profile's bus_key is used only without it
    path = tmp_path / "bus.key"
    if isinstance(content, str):
        path.write_text(content)
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(BusKeyError) as err:
        read_key(path)
    text = str(err.value)
    assert says in text and str(path) in text and "\n" not in text and "u2sa key" in text
    with pytest.raises(TransportError) as terr:
        Transport("memq://", name="t", key_file=path, security="signed")
    assert str(terr.value) == text


def test_the_key_is_found_the_same_way_everywhere(tmp_path: Path) -> None:
    assert key_path(None, env={}) == Path("/etc/u2sa/bus.key")
    assert key_path(tmp_path / "p.key", env={}) == tmp_path / "p.key"
    assert key_path(tmp_path / "p.key", env={"U2SA_BUS_KEY_FILE": str(tmp_path / "e.key")}) == tmp_path / "e.key"


def test_a_written_key_is_private_and_reads_back(tmp_path: Path) -> None:
    key = new_key()
    path = tmp_path / "deep" / "bus.key"
    write_key(path, key, group=None)
    assert read_key(path) == key and parse_key(key.hex().upper(), source="x") == key
    assert path.stat().st_mode & 0o777 == 0o600


def test_an_open_transport_needs_no_key(tmp_path: Path) -> None:
    tr = Transport("memq://", name="t", security="open", key_file=tmp_path / "none.key")
    assert tr.auth is None and tr.sender == "" and tr.key_id() == ""
    with pytest.raises(TransportError, match="bus_security must be"):
        Transport("memq://", name="t", security="loose")
