"""Roles on the bus (u2sa_hw.bus.roles): the pilot's Ed25519 signature, operator keys, ``denied``.

In-process, with keys of the test's own in a temporary directory laid out as on a vehicle
(bus.key, pilot.key, pilot.pub, operators/). The same rules between real processes, with an
actuator on a sysfs PWM tree, are tests/test_bus_pilot.py.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import (DENIED, FORGED, OK, PILOT_TAG, PILOT_TRAILER_LEN, TAG, TRAILER_LEN, UNSIGNED, BusAuth,
                              Keyring, strip_trailer)
from u2sa_hw.bus.key import BusKeyError, new_key, write_key
from u2sa_hw.bus.run_keys import fresh_key_file
from u2sa_hw.bus.roles import OPERATOR_CHANNELS, PILOT_CHANNELS, may_publish, table

NOW_US = 1_764_000_000_000_000
MODE = t.RcMode().encode()
STATE = t.StateInformation().set(x=1.0).encode()


@pytest.fixture()
def vehicle(tmp_path: Path) -> Path:
    """A vehicle's key directory: bus.key, the pilot pair, and one operator key."""
    key = fresh_key_file(tmp_path / "vehicle")
    write_key(key.parent / "operators" / "laptop.key", new_key(), group=None)
    return key


def auth(key: Path, **kw: object) -> BusAuth:
    return BusAuth(Keyring(key, **kw), wall_us=lambda: NOW_US)  # type: ignore[arg-type]


def without_pilot_key(vehicle: Path, where: Path) -> Path:
    """A copy of the bus key (and the pilot's public key) without the pilot's private key: a service, a laptop."""
    where.mkdir()
    shutil.copy(vehicle, where / "bus.key")
    shutil.copy(vehicle.parent / "pilot.pub", where / "pilot.pub")
    return where / "bus.key"


def test_only_the_holder_of_the_pilot_key_speaks_on_the_pilot_channels(vehicle: Path, tmp_path: Path) -> None:
    rx = auth(vehicle)
    pilot = auth(vehicle)                                   # the RC mux: it reads pilot.key
    for channel in PILOT_CHANNELS:
        packet = pilot.sign(channel, MODE)
        assert packet.endswith(PILOT_TAG) and len(packet) == len(MODE) + PILOT_TRAILER_LEN
        assert rx.verify(channel, packet) == OK and packet[:rx.end] == MODE
        assert strip_trailer(packet) == MODE
    service = auth(without_pilot_key(vehicle, tmp_path / "service"))
    with pytest.raises(BusKeyError, match="no pilot's private key at .*only the RC mux signs RC_MODE"):
        service.sign(ch.RC_MODE, MODE)
    # The service can still check the pilot, and sign everything else
    assert service.verify(ch.RC_MODE, pilot.sign(ch.RC_MODE, MODE)) == OK
    assert rx.verify(ch.STATE_INFO, service.sign(ch.STATE_INFO, STATE)) == OK


def test_the_bus_key_and_an_operator_key_are_denied_on_the_pilot_channels(vehicle: Path) -> None:
    rx = auth(vehicle)
    forger = BusAuth(Keyring(vehicle), wall_us=lambda: NOW_US)
    operator = auth(vehicle, operator_file=vehicle.parent / "operators" / "laptop.key")
    key = forger.keyring.current
    for channel in PILOT_CHANNELS:
        # what a holder of the bus key could make: an HMAC trailer on RC_MODE (the code before issue 23 signed so)
        from u2sa_hw.bus.auth import _TAIL, MAC_BYTES
        tail = _TAIL.pack(b"forger!!", NOW_US, key.id)
        hmac_signed = MODE + tail + key.mac(channel.encode() + b"\0", MODE + tail)[:MAC_BYTES] + TAG
        assert rx.verify(channel, hmac_signed) == DENIED
        op = operator.keyring.operator
        tail = _TAIL.pack(b"operator", NOW_US, op.id)
        op_signed = MODE + tail + op.mac(channel.encode() + b"\0", MODE + tail)[:MAC_BYTES] + TAG
        assert rx.verify(channel, op_signed) == DENIED


def test_a_forged_or_unknown_pilot_signature_is_forged(vehicle: Path, tmp_path: Path) -> None:
    rx = auth(vehicle)
    good = auth(vehicle).sign(ch.RC_MODE, MODE)
    flipped = bytearray(good)
    flipped[-PILOT_TRAILER_LEN + 30] ^= 1                   # inside the signature
    assert rx.verify(ch.RC_MODE, bytes(flipped)) == FORGED
    assert rx.verify(ch.MANUAL_CMD, good) == FORGED        # signed for another channel
    other = auth(fresh_key_file(tmp_path / "other"))        # another vehicle's (or sim's) pilot
    assert rx.verify(ch.RC_MODE, other.sign(ch.RC_MODE, MODE)) == FORGED
    assert rx.verify(ch.RC_MODE, MODE + bytes(PILOT_TRAILER_LEN - 4) + PILOT_TAG) == FORGED
    assert rx.verify(ch.RC_MODE, MODE[:10] + PILOT_TAG) in (UNSIGNED, FORGED)
    assert rx.verify(ch.RC_MODE, MODE) == UNSIGNED


def test_without_the_pilots_public_key_pilot_messages_are_dropped_and_the_fix_named(
        vehicle: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    laptop = tmp_path / "laptop"
    laptop.mkdir()
    shutil.copy(vehicle, laptop / "bus.key")                # the bus key, but no pilot.pub beside it
    rx = auth(laptop / "bus.key")
    assert rx.verify(ch.RC_MODE, auth(vehicle).sign(ch.RC_MODE, MODE)) == FORGED
    assert "copy the vehicle's /etc/u2sa/pilot.pub" in caplog.text


def test_the_pilot_key_signs_nothing_but_the_pilot_channels(vehicle: Path) -> None:
    rx, pilot = auth(vehicle), auth(vehicle)
    packet = pilot.sign(ch.RC_MODE, STATE)
    from u2sa_hw.bus.auth import SIGNED_TAIL
    signer = pilot.keyring.pilot_signer()
    end = len(STATE)
    tail = packet[end:end + SIGNED_TAIL]
    resigned = STATE + tail + signer.sign(ch.STATE_INFO.encode() + b"\0" + STATE + tail) + PILOT_TAG
    assert rx.verify(ch.STATE_INFO, resigned) == DENIED


def test_an_operator_key_may_send_commands_only(vehicle: Path) -> None:
    rx = auth(vehicle)
    operator = auth(vehicle, operator_file=vehicle.parent / "operators" / "laptop.key")
    assert operator.keyring.signing.role == "operator"
    for channel in OPERATOR_CHANNELS:
        assert rx.verify(channel, operator.sign(channel, STATE)) == OK, channel
    for channel in (ch.STATE_INFO, ch.ACTUATOR_CMD, ch.HEALTH, ch.STATE_ESTIMATE, ch.GOALS, "RAW.gps"):
        assert rx.verify(channel, operator.sign(channel, STATE)) == DENIED, channel


def test_an_operator_key_not_on_the_vehicle_is_forged_and_a_new_one_is_picked_up(vehicle: Path,
                                                                               tmp_path: Path) -> None:
    mono = [0.0]
    rx = BusAuth(Keyring(vehicle, clock=lambda: mono[0]), wall_us=lambda: NOW_US)
    stranger = tmp_path / "stranger.key"
    write_key(stranger, new_key(), group=None)
    tool = auth(vehicle, operator_file=stranger)
    assert rx.verify(ch.STOP, tool.sign(ch.STOP, STATE)) == FORGED
    shutil.copy(stranger, vehicle.parent / "operators" / "stranger.key")   # u2sa key operator on the vehicle
    mono[0] += 2.0
    rx.keyring.poll()
    assert rx.verify(ch.STOP, tool.sign(ch.STOP, STATE)) == OK


def test_the_table_gives_each_channel_its_roles() -> None:
    rows = {row[0]: row[1:] for row in table()}
    assert rows[ch.RC_MODE] == rows[ch.MANUAL_CMD] == ("no", "no", "yes")
    assert rows[ch.ACTUATOR_CMD] == rows[ch.STATE_INFO] == ("yes", "no", "no")
    assert rows[ch.STOP] == rows[ch.FAILSAFE] == rows[ch.MISSION_CMD] == ("yes", "yes", "no")
    assert not may_publish("nobody", ch.STOP)
    assert len(TAG) == len(PILOT_TAG) and TRAILER_LEN < PILOT_TRAILER_LEN


def test_a_service_signs_as_the_vehicle_even_where_an_operator_key_is_set(vehicle: Path, lcm_url: str,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from u2sa_hw.bus.key import KEY_ENV
    from u2sa_hw.bus.keyring import OPERATOR_KEY_ENV
    from u2sa_hw.bus.transport import Transport

    monkeypatch.setenv(KEY_ENV, str(vehicle))
    monkeypatch.setenv(OPERATOR_KEY_ENV, str(vehicle.parent / "operators" / "laptop.key"))  # a ground station's shell
    tool, service = Transport(lcm_url, name="tool"), Transport(lcm_url, name="svc", vehicle=True)
    try:
        assert tool.auth is not None and service.auth is not None
        assert tool.auth.keyring.signing.role == "operator"
        assert service.auth.keyring.signing.role == "vehicle"
    finally:
        tool.stop()
        service.stop()
