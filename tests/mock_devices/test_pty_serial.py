"""PtySerialDevice seen from a driver's side: pyserial opening the symlink like a USB adapter."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import pytest
import serial
from conftest import wait_until

from u2sa_hw.mocks.pty_serial import RX, TX, PtySerialDevice, corrupt_checksum


@pytest.fixture
def device(tmp_path: Path) -> Iterator[PtySerialDevice]:
    dev = PtySerialDevice(link_path=tmp_path / "dev" / "gps", name="gps", seed=7)
    dev.start()
    yield dev
    dev.stop()


def open_port(dev: PtySerialDevice, baudrate: int = 9600) -> serial.Serial:
    return serial.Serial(dev.address, baudrate, timeout=0.05)


def read_until(port: serial.Serial, expected: bytes, *, timeout: float = 5.0) -> bytes:
    got = bytearray()
    wait_until(lambda: got.extend(port.read(256)) or expected in got, timeout=timeout,
               message=f"{expected!r} from the pty")
    return bytes(got)


@pytest.mark.parametrize("baudrate", [4800, 115200])
def test_driver_opens_the_symlink_and_bytes_flow_both_ways(device: PtySerialDevice, baudrate: int) -> None:
    assert os.readlink(device.address) == device.port_name
    assert device.port_name.startswith("/dev/pts/")
    with open_port(device, baudrate) as port:
        assert device.write(b"$GPZDA,1*00\r\n") == 13
        assert read_until(port, b"\r\n") == b"$GPZDA,1*00\r\n"  # raw mode: nothing translated
        port.write(b"\x1bR10\r")
        wait_until(lambda: device.received() == b"\x1bR10\r", message="the driver's bytes at the device")
    kinds = [(r.direction, r.data) for r in device.history]
    assert kinds == [(TX, b"$GPZDA,1*00\r\n"), (RX, b"\x1bR10\r")]
    assert device.history[0].t <= device.history[1].t


def test_bytes_written_before_the_driver_opens_are_flushed_by_pyserial(device: PtySerialDevice) -> None:
    device.write(b"stale\r\n")
    with open_port(device) as port:
        device.write(b"fresh\r\n")
        assert read_until(port, b"fresh\r\n") == b"fresh\r\n"


def test_garbage_reaches_the_driver_verbatim(device: PtySerialDevice) -> None:
    with open_port(device) as port:
        garbage = device.inject_garbage(40)
        device.write(b"\r\n$OK\r\n")
        got = read_until(port, b"$OK\r\n")
    assert len(garbage) == 40 and got == garbage + b"\r\n$OK\r\n"
    assert device.history[0].note == "garbage"
    assert PtySerialDevice(link_path="/unused", seed=7).inject_garbage(40) == garbage  # seeded


def test_silence_stops_the_stream_until_lifted(device: PtySerialDevice) -> None:
    with open_port(device) as port:
        device.silence(True)
        assert device.silenced
        assert device.write(b"lost\r\n") == 0
        device.inject_garbage(3)  # faults still get through a silenced device
        device.silence(False)
        device.write(b"back\r\n")
        got = read_until(port, b"back\r\n")
    assert b"lost" not in got and got.endswith(b"back\r\n") and len(got) == 3 + 6


def test_disconnect_fails_the_open_port_and_reconnect_brings_a_new_one(device: PtySerialDevice) -> None:
    port = open_port(device)
    device.disconnect()
    assert not device.connected and device.port_name is None
    assert not os.path.lexists(device.address)  # unplugged: the path is gone
    with pytest.raises(serial.SerialException):
        port.read(10)
    with pytest.raises(serial.SerialException, match="write failed"):
        port.write(b"x")
    port.close()
    with pytest.raises(serial.SerialException, match="No such file"):
        open_port(device)
    assert device.write(b"nobody hears\r\n") == 0

    device.reconnect()
    assert device.connected and os.readlink(device.address) == device.port_name
    with open_port(device) as port:
        device.write(b"again\r\n")
        assert read_until(port, b"again\r\n") == b"again\r\n"
        port.write(b"hi")
        wait_until(lambda: device.received().endswith(b"hi"), message="bytes after reconnect")


def test_reconnect_while_connected_replugs(device: PtySerialDevice) -> None:
    port = open_port(device)
    device.reconnect()
    with pytest.raises(serial.SerialException):
        port.read(10)
    port.close()
    with open_port(device) as port:
        device.write(b"ok\r\n")
        assert read_until(port, b"ok\r\n") == b"ok\r\n"


def test_full_kernel_buffer_drops_and_counts_instead_of_blocking(device: PtySerialDevice) -> None:
    with open_port(device):  # open but never read
        chunk = b"x" * 65536
        accepted = sum(device.write(chunk) for _ in range(16))
    assert accepted < 16 * len(chunk)
    assert device.dropped_bytes == 16 * len(chunk) - accepted


def test_a_failing_receive_handler_does_not_kill_the_link(tmp_path: Path) -> None:
    calls: list[bytes] = []

    def handler(data: bytes) -> None:
        calls.append(data)
        raise RuntimeError("model bug")

    dev = PtySerialDevice(link_path=tmp_path / "cmp", on_receive=handler)
    dev.start()
    try:
        with open_port(dev) as port:
            port.write(b"a")
            wait_until(lambda: calls, message="the handler to run")
            port.write(b"b")
            wait_until(lambda: dev.received() == b"ab", message="bytes after the handler failed")
    finally:
        dev.stop()
        dev.stop()  # idempotent
    assert not os.path.lexists(tmp_path / "cmp")


def test_unusable_link_path_is_reported_with_the_path(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    dev = PtySerialDevice(link_path=blocker / "gps", name="gps")
    with pytest.raises(OSError, match=r"gps: cannot create the device link .*file/gps.*writable link_path"):
        dev.start()
    assert not dev.connected


def test_corrupt_checksum_changes_only_the_checksum() -> None:
    good = b"$GPHDT,22.90,T*3C\r\n"
    bad = corrupt_checksum(good)
    assert bad != good and bad[:-4] == good[:-4] and bad.endswith(b"\r\n")
    assert corrupt_checksum(b"no checksum\r\n") == b"no checksum\r\n"
