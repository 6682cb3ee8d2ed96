"""The serial device clock of a replay: stamped frames through a real pty (u2sa_hw/ports/serial/clock.py).

The framing survives any data byte and any split, drops garbage, and only a ``mock+serial``
address may turn it on; the port returns the data bytes with the recorded time of each line
and a recorded silence as an empty read, whatever the wall clock did; the replay device
writes recorded chunks and silences that way.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import pytest

from conftest import wait_until
from u2sa_hw.ports.serial.replay import ReplaySerialDevice, StampedChunks
from u2sa_hw.messages import RawSerial
from u2sa_hw.ports.serial import clock as serial_clock
from u2sa_hw.ports.address import AddressError, parse_address
from u2sa_hw.ports.opener import open_port
from u2sa_hw.ports.serial.clock import ESC, FrameDecoder, StampedSerialPort, encode_frame
from u2sa_hw.ports.tap import RX

S = 1_000_000_000  # ns


def decode_all(stream: bytes, *, piece: int) -> tuple[list[tuple[int, bytes]], int]:
    """Frames of *stream* fed *piece* bytes at a time, continuations joined per stamp run."""
    decoder = FrameDecoder()
    frames: list[tuple[int, bytes]] = []
    for i in range(0, len(stream), piece):
        for stamp, data in decoder.feed(stream[i:i + piece]):
            if frames and frames[-1][0] == stamp and data:
                frames[-1] = (stamp, frames[-1][1] + data)
            elif not (frames and frames[-1][0] == stamp and not data):
                frames.append((stamp, data))
    return frames, decoder.garbage


def test_any_data_byte_survives_the_framing_split_anywhere() -> None:
    data = bytes(range(256)) + b"\x1b\x1b\x1bT0123456789abcdef\x1b"
    stream = encode_frame(5, data) + encode_frame(7) + encode_frame(2**63, b"$HDM,1*00\r\n")
    want = [(5, data), (7, b""), (2**63, b"$HDM,1*00\r\n")]
    for piece in (1, 2, 3, 17, 18, 19, len(stream)):
        assert decode_all(stream, piece=piece) == (want, 0), piece


def test_garbage_is_dropped_and_counted_never_handed_on() -> None:
    stream = (b"before any stamp\n" + encode_frame(1, b"a") + bytes((ESC, ord("x"))) + b"b"
              + b"\x1bTnot-hex-digits!!" + b"c" + encode_frame(2, b"d"))
    frames, garbage = decode_all(stream, piece=4)
    assert frames == [(1, b"abc"), (2, b"d")]
    assert garbage == len(b"before any stamp\n") + 2 + 18
    with pytest.raises(ValueError):
        encode_frame(-1)


def test_only_a_mock_serial_address_may_carry_the_device_clock() -> None:
    mock = parse_address("mock+serial:///run/replay/gps?baud=4800&clock=stamped", device="gps")
    assert mock.device_clock and mock.baud == 4800
    assert not parse_address("mock+serial:///run/sim/gps?baud=4800", device="gps").device_clock
    for real in ("serial:///dev/u2sa/gps?clock=stamped", "serial+socket://localhost:7000?clock=stamped"):
        with pytest.raises(AddressError, match="only for mock\\+serial"):
            parse_address(real, device="gps")
    with pytest.raises(AddressError, match="clock=stamped"):
        parse_address("mock+serial:///run/replay/gps?clock=wall", device="gps")


@pytest.fixture
def pty(tmp_path: Path) -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    link = str(tmp_path / "gps")
    os.symlink(os.ttyname(slave), link)
    os.close(slave)
    yield master, link
    os.close(master)


def test_a_real_address_opens_a_port_without_a_device_clock(pty: tuple[int, str]) -> None:
    master, link = pty
    port = open_port(f"mock+serial://{link}", device="gps", timeout=0.05)
    try:
        assert not isinstance(port, StampedSerialPort) and port.device_clock is False
        os.write(master, encode_frame(1, b"x\n"))   # no decoding: the bytes as they came
        line = wait_until(port.readline, timeout=10, message="the line")
        assert line == encode_frame(1, b"x\n") and port.line_time_ns() is None and port.went_quiet()
    finally:
        port.close()


def test_lines_carry_their_frames_stamps_and_a_recorded_silence_is_an_empty_read(
        pty: tuple[int, str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(serial_clock, "DEVICE_CLOCK_GRACE_S", 3600.0)   # the pty stays fresh here
    master, link = pty
    taps: list[RawSerial] = []
    port = open_port(f"mock+serial://{link}?clock=stamped", device="gps", tap=taps.append, timeout=0.05)
    try:
        assert isinstance(port, StampedSerialPort) and port.device_clock
        # one line over two chunks 10 ms apart, then 0.99 s of recorded silence, a line, a tick
        os.write(master, encode_frame(1 * S, b"$GPGGA,1\n$GPRMC") + encode_frame(1 * S + 10**7, b",2\n")
                 + encode_frame(2 * S, b"$HDM,\x1b\n") + encode_frame(2 * S + 10**8))
        got = []
        for _ in range(5):
            line = port.readline()
            got.append((line, port.line_time_ns() if line else None, port.went_quiet()))
        assert got == [(b"$GPGGA,1\n", 1 * S, False), (b"$GPRMC,2\n", 1 * S + 10**7, False),
                       (b"", None, True), (b"$HDM,\x1b\n", 2 * S, False), (b"", None, True)]
        # nothing more: a wall-clock timeout, which is no silence of the device while its clock is fresh
        assert port.readline() == b"" and not port.went_quiet()
        monkeypatch.setattr(serial_clock, "DEVICE_CLOCK_GRACE_S", 0.0)   # the replay stopped: fail safe
        assert port.readline() == b"" and port.went_quiet()
        assert b"".join(bytes(r.data) for r in taps if r.direction == RX) == b"$GPGGA,1\n$GPRMC,2\n$HDM,\x1b\n"
    finally:
        port.close()


def test_the_replay_device_writes_stamped_chunks_and_its_ticks(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(serial_clock, "DEVICE_CLOCK_GRACE_S", 3600.0)   # only the device clock says silence
    device = ReplaySerialDevice(name="compass", link_path=tmp_path / "dev" / "compass", burst_gap_s=0.05,
                                stamped=True)
    real = parse_address("serial:///dev/u2sa/compass?baud=4800&usb=0403:6001", device="compass")
    address = device.mock_address(real)
    assert "clock=stamped" in address and "usb" not in address and "baud=4800" in address
    device.start()
    port = open_port(address, device="compass", timeout=0.05)
    try:
        records = []
        for stamp_us, data in ((1_000_000, b"$XDR,A\n"), (1_005_000, b"$HDM,1\n"), (1_200_000, b"$XDR,B\n")):
            rec = RawSerial()
            rec.header.timestamp_us, rec.direction, rec.data, rec.length = stamp_us, RX, data, len(data)
            records.append(rec)
        burst = device.merge(records[0], records[1])
        assert isinstance(burst, StampedChunks) and burst.length == 14
        device.feed(device.merge(burst, StampedChunks([(1_055_000_000, b"")])))   # the burst and its tick
        device.feed(records[2])
        lines: list[tuple[bytes, int | None]] = []

        def read() -> bool:
            line = port.readline()
            if line or port.went_quiet():
                lines.append((line, port.line_time_ns() if line else None))
            return len(lines) >= 5

        wait_until(read, timeout=10, interval=0.0, message="five reads")
        # a silence after the burst (its tick), and again before the next chunk 0.145 s after the tick,
        # as a live read timing out every 0.05 s would see it
        assert lines == [(b"$XDR,A\n", 1_000_000_000), (b"$HDM,1\n", 1_005_000_000), (b"", None), (b"", None),
                         (b"$XDR,B\n", 1_200_000_000)]
        assert wait_until(lambda: device.pending() == 0, timeout=5)
        assert device.report()["fed_bytes"] == 21
    finally:
        port.close()
        device.stop()


def test_with_recorded_silences_a_long_wall_clock_gap_is_no_silence(pty: tuple[int, str],
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A --fast replay on a loaded machine held the rest of an epoch back for over 2 s (the live driver had
    read the epoch in two parts): in a stream whose silences are recorded, only RECORDED_SILENCES_GRACE_S of
    wall time is one (a replay that stopped), never DEVICE_CLOCK_GRACE_S."""
    monkeypatch.setattr(serial_clock, "DEVICE_CLOCK_GRACE_S", 0.0)   # any wall-clock gap is "long" here
    master, link = pty
    port = open_port(f"mock+serial://{link}?clock=stamped", device="gps", timeout=0.05)
    try:
        os.write(master, encode_frame(1 * S, b"$GPGGA,1\n", silences_recorded=True))
        assert wait_until(port.readline, timeout=10, message="the line") == b"$GPGGA,1\n"
        assert port.readline() == b"" and not port.went_quiet()   # the rest of the burst may still come
        monkeypatch.setattr(serial_clock, "RECORDED_SILENCES_GRACE_S", 0.0)   # the replay stopped: fail safe
        assert port.readline() == b"" and port.went_quiet()
    finally:
        port.close()
