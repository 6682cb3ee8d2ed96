"""The I2C port against the mock I2C bus server (in this process and in another one) and
the smbus2 backend's error mapping on this machine, which has no /dev/i2c-*."""

from __future__ import annotations

import errno
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Iterator

import pytest

from mock_devices.i2c_bus import MockI2cBus
from mock_devices.mpu9250_chip import Mpu9250Chip
from conftest import REPO, wait_until
from u2sa_hw.ports.errors import PortClosed, PortIOError, PortTimeout, PortUnavailable
from u2sa_hw.ports.i2c_port import (REQUEST, RESPONSE, STATUS_BAD_REQUEST, STATUS_EIO, STATUS_OK, I2cPort, MockI2cPort,
                                    open_error, open_i2c, transaction_error)
from u2sa_hw.protocols import mpu9250 as mpu


@pytest.fixture
def sock_dir() -> Iterator[Path]:
    """A short directory for Unix sockets (sun_path is limited to 108 bytes)."""
    path = Path(tempfile.mkdtemp(prefix="i2c", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def bus(sock_dir: Path) -> Iterator[MockI2cBus]:
    """A mock bus with an MPU-9250 at 0x68."""
    mock = MockI2cBus(socket_path=str(sock_dir / "bus.sock"))
    mock.add(Mpu9250Chip(address=0x68, seed=3))
    with mock:
        yield mock


def test_server_in_another_process_answers_and_its_death_closes_the_port(sock_dir: Path) -> None:
    path = sock_dir / "bus.sock"
    proc = subprocess.Popen([sys.executable, "-m", "mock_devices.i2c_bus", "--socket", str(path),
                             "--chip", "mpu9250@0x68", "--chip", "bno055@0x28"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        def try_open() -> I2cPort | None:
            try:
                return open_i2c(device="imu", bus=f"mock:{path}", address=0x68)
            except PortUnavailable:
                return None

        port = wait_until(try_open, timeout=20, message="the mock I2C bus process to listen")
        assert port.read_byte(mpu.WHO_AM_I) == 0x71
        sample = mpu.decode_burst(port.read_block(mpu.BURST_START, mpu.BURST_LENGTH))
        assert abs(sample.az - 16384) < 400 and abs(sample.ax) < 400 and abs(sample.ay) < 400
        bno = open_i2c(device="ahrs", bus=f"mock:{path}", address=0x28)
        assert bno.read_byte(0x00) == 0xA0
        bno.close()

        proc.terminate()
        proc.wait(timeout=10)
        with pytest.raises(PortClosed) as info:
            port.read_byte(mpu.WHO_AM_I)
        assert "imu" in str(info.value) and "fix:" in str(info.value)
        assert not port.is_open
        with pytest.raises(PortClosed):
            port.read_byte(mpu.WHO_AM_I)
        with pytest.raises(PortUnavailable):
            open_i2c(device="imu", bus=f"mock:{path}", address=0x68)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


def test_missing_socket_is_unavailable_naming_device_and_fix(sock_dir: Path) -> None:
    with pytest.raises(PortUnavailable) as info:
        open_i2c(device="imu", bus=f"mock:{sock_dir}/nothing.sock", address=0x68)
    text = str(info.value)
    assert "imu" in text and "nothing.sock" in text and "start the mock I2C bus server" in text


def test_stale_socket_without_server_is_unavailable(sock_dir: Path) -> None:
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sock_dir / "stale.sock"))
    stale.close()  # the file stays, nobody listens: connection refused
    with pytest.raises(PortUnavailable, match="imu"):
        open_i2c(device="imu", bus=f"mock:{sock_dir}/stale.sock", address=0x68)


def test_byte_and_block_transactions_and_tap(bus: MockI2cBus) -> None:
    records = []
    port = open_i2c(device="imu", bus=bus.address, address=0x68, tap=records.append)
    assert port.address == f"{bus.address}:0x68"
    port.write_byte(mpu.SMPLRT_DIV, 9)
    assert port.read_byte(mpu.SMPLRT_DIV) == 9
    port.write_block(mpu.SMPLRT_DIV, bytes([4, 3, 0x18]))  # SMPLRT_DIV, CONFIG, GYRO_CONFIG in one go
    assert port.read_block(mpu.SMPLRT_DIV, 3) == bytes([4, 3, 0x18])
    assert len(port.read_block(0x00, 200)) == 200  # longer than an SMBus block
    assert [(r.op, r.register, r.ok) for r in records[:4]] == [(1, mpu.SMPLRT_DIV, True), (0, mpu.SMPLRT_DIV, True),
                                                               (1, mpu.SMPLRT_DIV, True), (0, mpu.SMPLRT_DIV, True)]
    assert records[3].data == bytes([4, 3, 0x18]) and records[3].length == 3
    assert all(r.device == "imu" and r.address == 0x68 and r.bus == -1 for r in records)
    port.close()
    with pytest.raises(PortClosed):
        port.read_byte(0)


def test_absent_chip_nacks_as_port_io_error(bus: MockI2cBus) -> None:
    records = []
    port = open_i2c(device="mag", bus=bus.address, address=0x69, tap=records.append)
    with pytest.raises(PortIOError) as info:
        port.read_byte(0x00)
    assert "no ACK from 0x69" in str(info.value) and "mag" in str(info.value)
    assert records[-1].ok is False and records[-1].op == 0
    assert bus.history[-1].address == 0x69


def test_chip_nack_and_eio_faults(bus: MockI2cBus) -> None:
    chip = bus.chip(0x68)
    port = open_i2c(device="imu", bus=bus.address, address=0x68)
    chip.nack(True)
    with pytest.raises(PortIOError, match="no ACK"):
        port.read_byte(mpu.WHO_AM_I)
    chip.nack(False)
    assert port.read_byte(mpu.WHO_AM_I) == 0x71
    chip.eio_every(3)
    outcomes = []
    for _ in range(6):
        try:
            port.read_byte(mpu.WHO_AM_I)
            outcomes.append("ok")
        except PortIOError as exc:
            assert "EIO" in str(exc)
            outcomes.append("eio")
    assert outcomes == ["ok", "ok", "eio", "ok", "ok", "eio"]
    assert port.is_open  # a failed transaction leaves the port usable
    chip.eio_every(0)
    assert port.read_byte(mpu.WHO_AM_I) == 0x71
    assert [t.status for t in list(chip.history)[-7:]] == [STATUS_OK, STATUS_OK, STATUS_EIO, STATUS_OK, STATUS_OK,
                                                           STATUS_EIO, STATUS_OK]


def test_server_dropping_clients_closes_ports(bus: MockI2cBus) -> None:
    port = open_i2c(device="imu", bus=bus.address, address=0x68)
    assert port.read_byte(mpu.WHO_AM_I) == 0x71
    bus.disconnect_clients()
    with pytest.raises(PortClosed, match="went away"):
        port.read_byte(mpu.WHO_AM_I)
    again = open_i2c(device="imu", bus=bus.address, address=0x68)
    assert again.read_byte(mpu.WHO_AM_I) == 0x71


def test_many_clients_at_once(bus: MockI2cBus) -> None:
    errors: list[BaseException] = []

    def worker() -> None:
        try:
            with open_i2c(device="imu", bus=bus.address, address=0x68) as port:
                for _ in range(50):
                    assert port.read_byte(mpu.WHO_AM_I) == 0x71
                    assert len(port.read_block(mpu.BURST_START, 14)) == 14
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert not errors


def test_bad_request_is_answered_counted_and_the_bus_keeps_serving(bus: MockI2cBus) -> None:
    raw = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    raw.settimeout(5)
    raw.connect(bus.socket_path)
    raw.sendall(REQUEST.pack(7, 0x68, 0, 1))
    status, length = RESPONSE.unpack(raw.recv(RESPONSE.size))
    assert (status, length) == (STATUS_BAD_REQUEST, 0)
    assert raw.recv(16) == b""  # the server hung up on the garbled stream
    raw.close()
    assert bus.bad_requests == 1
    assert open_i2c(device="imu", bus=bus.address, address=0x68).read_byte(mpu.WHO_AM_I) == 0x71


def test_silent_server_times_out(sock_dir: Path) -> None:
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(sock_dir / "silent.sock"))
    listener.listen(1)
    try:
        port = MockI2cPort(device="imu", socket_path=str(sock_dir / "silent.sock"), i2c_address=0x68, tap=None,
                           timeout=0.2)
        with pytest.raises(PortTimeout, match="did not answer"):
            port.read_byte(0x75)
        assert not port.is_open
    finally:
        listener.close()


@pytest.mark.parametrize("kwargs", [dict(bus="i2c-1", address=0x68), dict(bus=-2, address=0x68),
                                    dict(bus="mock:", address=0x68), dict(bus=1, address=0x80),
                                    dict(bus=1, address="0x68")])
def test_bad_bus_or_address_is_refused(kwargs: dict) -> None:
    with pytest.raises(PortUnavailable, match="imu"):
        open_i2c(device="imu", **kwargs)


def test_bad_register_arguments_are_value_errors(bus: MockI2cBus) -> None:
    port = open_i2c(device="imu", bus=bus.address, address=0x68)
    for call in (lambda: port.read_byte(256), lambda: port.read_block(0, 0), lambda: port.write_byte(0, 300),
                 lambda: port.write_block(0, b""), lambda: port.read_block(0, 5000)):
        with pytest.raises(ValueError, match="imu"):
            call()
    assert port.read_byte(mpu.WHO_AM_I) == 0x71


def test_missing_i2c_adapter_names_the_fix() -> None:
    assert not os.path.exists("/dev/i2c-250")
    with pytest.raises(PortUnavailable) as info:
        open_i2c(device="imu", bus=250, address=0x68)
    assert "/dev/i2c-250" in str(info.value) and "dtparam=i2c_arm=on" in str(info.value)
    with pytest.raises(PortUnavailable, match="imu"):
        open_i2c(device="imu", bus="250", address=0x68)


def test_smbus_error_mapping() -> None:
    assert "group i2c" in str(open_error("imu", "/dev/i2c-1:0x68", 1, PermissionError(errno.EACCES, "denied")))
    port = I2cPort(device="imu", address="/dev/i2c-1:0x68", bus_number=1, i2c_address=0x68, tap=None)
    for code in (errno.ENXIO, errno.EREMOTEIO, errno.EIO):
        err = transaction_error(port, OSError(code, os.strerror(code)))
        assert isinstance(err, PortIOError)
        assert "no ACK from 0x68 on /dev/i2c-1" in str(err) and "wiring" in str(err)
    assert isinstance(transaction_error(port, OSError(errno.ETIMEDOUT, "t")), PortTimeout)
    gone = transaction_error(port, OSError(errno.ENODEV, "No such device"))
    assert isinstance(gone, PortClosed) and not port.is_open
