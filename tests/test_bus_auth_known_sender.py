"""A sender a receiver already heard is held to every rule of the window (u2sa_hw.bus.auth).

tests/test_bus_auth.py checks a sender's first packet against the window; these check the
packets after it: the same or an older counter is a replay, a counter out of range is refused
without moving the clock, and a counter ahead of the receiver's clock is accepted and moves it.
"""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import MAX_COUNTER, OK, REPLAYED, TAG, BusAuth, Keyring
from u2sa_hw.bus.key import new_key, write_key

NOW_US = 1_764_000_000_000_000
PAYLOAD = t.StateInformation().set(x=1.0).encode()


@pytest.fixture
def key_file(tmp_path: Path) -> Path:
    path = tmp_path / "bus.key"
    write_key(path, new_key(), group=None)
    return path


def _signed(tx: BusAuth, counter: int) -> bytes:
    key = tx.keyring.current
    signed = PAYLOAD + tx.sender + struct.pack(">Q", counter) + key.id
    return signed + key.mac(b"X\0", signed) + TAG


def test_a_known_sender_is_held_to_every_rule_after_its_first_packet(key_file: Path) -> None:
    tx = BusAuth(Keyring(key_file), wall_us=lambda: NOW_US)
    rx = BusAuth(Keyring(key_file), wall_us=lambda: NOW_US)
    assert rx.verify("X", _signed(tx, NOW_US - 10)) == OK
    assert rx.verify("X", _signed(tx, NOW_US - 10)) == REPLAYED          # the same counter again
    assert rx.verify("X", _signed(tx, NOW_US - 20)) == REPLAYED          # an older one
    assert rx.verify("X", _signed(tx, MAX_COUNTER + 1)) == REPLAYED      # out of range, known sender or not
    assert rx.now() == NOW_US
    assert rx.verify("X", _signed(tx, NOW_US + 5_000_000)) == OK         # ahead of this clock: it moves the clock
    assert rx.now() == NOW_US + 5_000_000
    assert rx.verify("X", _signed(tx, NOW_US + 5_000_001)) == OK and rx.last_sender == tx.sender
    assert rx.verify("X", _signed(tx, NOW_US + 5_000_001)) == REPLAYED
