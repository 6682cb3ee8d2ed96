"""I2C port contract: one suite over every I2C implementation that runs here -- the mock
bus server in this process, the mock bus server in another process, and the smbus2 backend
(``SmbusI2cPort``) on a mock adapter standing in for ``/dev/i2c-N`` (mock_devices.
smbus_adapter) -- then the mock server's own behaviour and the smbus2 error mapping."""

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
import smbus2

from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Mpu9250Chip
from u2sa_hw.mocks.smbus_adapter import SmbusAdapters
from conftest import REPO, wait_until
from u2sa_hw.ports.errors import PortClosed, PortIOError, PortTimeout, PortUnavailable
from u2sa_hw.ports.i2c.wire import MOCK_BUS_NUMBER, REQUEST, RESPONSE, STATUS_BAD_REQUEST
from u2sa_hw.ports.i2c.port import I2cPort, MockI2cPort, SmbusI2cPort, open_error, open_i2c, transaction_error
from u2sa_hw.protocols import mpu9250 as mpu

WHO_AM_I_9250 = 0x71


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


class MockBusBackend:
    """The mock bus server in this process, an MPU-9250 at 0x68."""

    faults = True

    def __init__(self, sock_dir: Path) -> None:
        self.server = MockI2cBus(socket_path=str(sock_dir / "bus.sock"))
        self.chip: Mpu9250Chip | None = self.server.add(Mpu9250Chip(address=0x68, seed=3))  # type: ignore[assignment]
        self.server.start()
        self.bus: int | str = self.server.address
        self.bus_number = MOCK_BUS_NUMBER
        self.missing: int | str = f"mock:{sock_dir}/nothing.sock"
        self.missing_fix = "start the mock I2C bus server"

    def lose(self) -> None:
        self.server.stop()

    def cleanup(self) -> None:
        self.server.stop()


class ProcessBusBackend:
    """The mock bus server in another process (``python -m u2sa_hw.mocks.i2c_bus``)."""

    faults = False  # its chips live in the other process

    def __init__(self, sock_dir: Path) -> None:
        path = sock_dir / "bus.sock"
        self.proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.mocks.i2c_bus", "--socket", str(path),
                                      "--chip", "mpu9250@0x68", "--chip", "bno055@0x28"], cwd=REPO,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.chip = None
        self.bus = f"mock:{path}"
        self.bus_number = MOCK_BUS_NUMBER
        self.missing = f"mock:{sock_dir}/nothing.sock"
        self.missing_fix = "start the mock I2C bus server"

        def listening() -> bool:
            try:
                open_i2c(device="probe", bus=self.bus, address=0x68).close()
            except PortUnavailable:
                return False
            return True

        wait_until(listening, timeout=20, message="the mock I2C bus process to listen")

    def lose(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=10)

    def cleanup(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()


class SmbusBackend:
    """smbus2 on adapter /dev/i2c-7, a mock adapter whose chips are mock bus models (no kernel here)."""

    faults = True
    NUMBER = 7

    def __init__(self, sock_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        self.adapters = SmbusAdapters()
        self.server = MockI2cBus(socket_path=str(sock_dir / "unused.sock"))  # its chips are called directly
        self.chip = self.server.add(Mpu9250Chip(address=0x68, seed=3))  # type: ignore[assignment]
        self.adapters.attach(self.NUMBER, self.server)
        monkeypatch.setattr(smbus2, "SMBus", self.adapters.smbus_class())
        self.bus = self.NUMBER
        self.bus_number = self.NUMBER
        self.missing = 8
        self.missing_fix = "dtparam=i2c_arm=on"

    def lose(self) -> None:
        self.adapters.unplug(self.NUMBER)

    def cleanup(self) -> None:
        pass


@pytest.fixture(params=["mock", "mock-process", "smbus2"])
def backend(request: pytest.FixtureRequest, sock_dir: Path,
            monkeypatch: pytest.MonkeyPatch) -> Iterator[MockBusBackend | ProcessBusBackend | SmbusBackend]:
    """Each I2C implementation that runs on this machine."""
    if request.param == "mock":
        b: MockBusBackend | ProcessBusBackend | SmbusBackend = MockBusBackend(sock_dir)
    elif request.param == "mock-process":
        b = ProcessBusBackend(sock_dir)
    else:
        b = SmbusBackend(sock_dir, monkeypatch)
    yield b
    b.cleanup()


class TestI2cContract:
    """What every I2C implementation must do."""

    def test_the_chip_answers_and_a_burst_is_one_sample(self, backend) -> None:
        port = open_i2c(device="imu", bus=backend.bus, address=0x68)
        if backend.bus_number >= 0:
            assert isinstance(port, SmbusI2cPort) and port.address == f"/dev/i2c-{backend.bus_number}:0x68"
        assert port.read_byte(mpu.WHO_AM_I) == WHO_AM_I_9250
        port.write_byte(mpu.PWR_MGMT_1, 0x01)   # awake
        sample = mpu.decode_burst(port.read_block(mpu.BURST_START, mpu.BURST_LENGTH))
        assert abs(sample.az - 16384) < 400 and abs(sample.ax) < 400 and abs(sample.ay) < 400   # +1 g at rest
        port.close()

    def test_byte_and_block_transactions_are_tapped(self, backend) -> None:
        records = []
        port = open_i2c(device="imu", bus=backend.bus, address=0x68, tap=records.append)
        port.write_byte(mpu.SMPLRT_DIV, 9)
        assert port.read_byte(mpu.SMPLRT_DIV) == 9
        port.write_block(mpu.SMPLRT_DIV, bytes([4, 3, 0x18]))  # SMPLRT_DIV, CONFIG, GYRO_CONFIG in one go
        assert port.read_block(mpu.SMPLRT_DIV, 3) == bytes([4, 3, 0x18])
        assert [(r.op, r.register_address, r.ok) for r in records[:4]] == [
            (1, mpu.SMPLRT_DIV, True), (0, mpu.SMPLRT_DIV, True), (1, mpu.SMPLRT_DIV, True), (0, mpu.SMPLRT_DIV, True)]
        assert records[3].data == bytes([4, 3, 0x18]) and records[3].length == 3
        assert all(r.device == "imu" and r.address == 0x68 and r.bus == backend.bus_number for r in records)
        port.close()

    def test_transfers_longer_than_an_smbus_block_work_both_ways(self, backend) -> None:
        port = open_i2c(device="imu", bus=backend.bus, address=0x68)
        data = bytes(range(1, 41))                    # 40 bytes into 0x00..0x27 (self-test and offset registers)
        port.write_block(0x00, data)
        assert port.read_block(0x00, 40) == data
        assert len(port.read_block(0x00, 200)) == 200
        port.close()

    def test_an_absent_chip_does_not_acknowledge(self, backend) -> None:
        records = []
        port = open_i2c(device="mag", bus=backend.bus, address=0x69, tap=records.append)
        with pytest.raises(PortIOError) as info:
            port.read_byte(0x00)
        assert "no ACK from 0x69" in str(info.value) and "mag" in str(info.value) and info.value.fix
        assert records[-1].ok is False and records[-1].op == 0
        assert port.is_open
        port.close()

    def test_chip_nack_and_eio_are_io_errors_and_the_port_lives_on(self, backend) -> None:
        if not backend.faults:
            pytest.skip("the chip runs in another process: its faults are scripted in-process only")
        chip = backend.chip
        port = open_i2c(device="imu", bus=backend.bus, address=0x68)
        chip.nack(True)
        with pytest.raises(PortIOError, match="no ACK"):
            port.read_byte(mpu.WHO_AM_I)
        chip.nack(False)
        assert port.read_byte(mpu.WHO_AM_I) == WHO_AM_I_9250
        chip.eio_every(2)
        outcomes = []
        for _ in range(4):
            try:
                port.read_byte(mpu.WHO_AM_I)
                outcomes.append("ok")
            except PortIOError as exc:
                assert "imu" in str(exc) and exc.fix
                outcomes.append("io error")
        assert outcomes == ["ok", "io error", "ok", "io error"] and port.is_open
        chip.eio_every(0)
        assert port.read_byte(mpu.WHO_AM_I) == WHO_AM_I_9250
        port.close()

    def test_losing_the_bus_closes_the_port(self, backend) -> None:
        port = open_i2c(device="imu", bus=backend.bus, address=0x68)
        assert port.read_byte(mpu.WHO_AM_I) == WHO_AM_I_9250
        backend.lose()
        with pytest.raises(PortClosed) as info:
            port.read_byte(mpu.WHO_AM_I)
        assert "imu" in str(info.value) and info.value.fix
        assert not port.is_open
        with pytest.raises(PortClosed):
            port.read_byte(mpu.WHO_AM_I)
        with pytest.raises(PortUnavailable):
            open_i2c(device="imu", bus=backend.bus, address=0x68)

    def test_a_missing_bus_is_unavailable_naming_device_and_fix(self, backend) -> None:
        with pytest.raises(PortUnavailable) as info:
            open_i2c(device="imu", bus=backend.missing, address=0x68)
        assert "imu" in str(info.value) and backend.missing_fix in str(info.value)

    def test_a_closed_port_and_bad_arguments_are_refused(self, backend) -> None:
        port = open_i2c(device="imu", bus=backend.bus, address=0x68)
        for call in (lambda: port.read_byte(256), lambda: port.read_block(0, 0), lambda: port.write_byte(0, 300),
                     lambda: port.write_block(0, b""), lambda: port.read_block(0, 5000)):
            with pytest.raises(ValueError, match="imu"):
                call()
        assert port.read_byte(mpu.WHO_AM_I) == WHO_AM_I_9250
        port.close()
        port.close()
        with pytest.raises(PortClosed):
            port.read_byte(mpu.WHO_AM_I)


def test_stale_socket_without_server_is_unavailable(sock_dir: Path) -> None:
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sock_dir / "stale.sock"))
    stale.close()  # the file stays, nobody listens: connection refused
    with pytest.raises(PortUnavailable, match="imu"):
        open_i2c(device="imu", bus=f"mock:{sock_dir}/stale.sock", address=0x68)


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
