"""The replay I2C bus paces a driver's data reads by the player (hil/replay_buses.py): a read of the
data register (the most-read one) is held until the player feeds its recorded read, other reads are
answered at once, ``stop()`` refuses a held read, and the replay address carries the longer client
timeout a held read needs. A real client port (MockI2cPort over the replay bus's socket) does the reads.
"""

from __future__ import annotations

import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import wait_until

from u2sa_hw.hil.replay_buses import I2C_CLIENT_TIMEOUT_S, ReplayI2cDevice
from u2sa_hw.hil.replay_cut import i2c_setup_recorded
from u2sa_hw.messages import RawI2c
from u2sa_hw.ports.address import parse_address
from u2sa_hw.ports.errors import PortClosed, PortError, PortIOError
from u2sa_hw.ports.i2c.wire import OP_READ, OP_WRITE
from u2sa_hw.ports.opener import open_port
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.recording.mcap_log import McapLogWriter

CHIP, WHO_AM_I, CONFIG, DATA = 0x68, 0x75, 0x1A, 0x3B
SAMPLES = [bytes((n, n + 1, n + 2, n + 3)) for n in (10, 20, 30)]


def raw(register: int, data: bytes, *, op: int = OP_READ, address: int = CHIP) -> RawI2c:
    rec = RawI2c()
    rec.device, rec.bus, rec.address, rec.register_address = "imu", -1, address, register
    rec.op, rec.ok, rec.data, rec.length = op, True, data, len(data)
    return rec


RECORDS = [raw(WHO_AM_I, b"\x71"), raw(CONFIG, b"\x03", op=OP_WRITE),
           *[r for sample in SAMPLES for r in (raw(DATA, sample), raw(0x03, sample[:2], address=0x0C))]]


@pytest.fixture
def sockets() -> Iterator[Path]:
    path = Path(tempfile.mkdtemp(prefix="i2cg", dir="/tmp"))   # Unix socket paths must stay short
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def device(sockets: Path) -> Iterator[ReplayI2cDevice]:
    log = McapLogWriter(sockets, path=sockets / "imu.mcap")
    for n, record in enumerate(RECORDS):
        log.write("RAW.imu", record.encode(), 1_000 + n)
    log.close()
    dev = ReplayI2cDevice(name="imu", socket_path=sockets / "bus.sock", fast=True)
    dev.preload(sockets / "imu.mcap", start_ns=0, end_ns=2 ** 63 - 1)
    dev.start()
    yield dev
    dev.stop()


class Reader:
    """``read_block`` on a thread: ``result`` is the answer or the port error, ``done`` once it returned."""

    def __init__(self, port: Any, register: int, length: int) -> None:
        self.result: Any = None
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(port, register, length), daemon=True)
        self.thread.start()

    def _run(self, port: Any, register: int, length: int) -> None:
        try:
            self.result = port.read_block(register, length)
        except PortError as exc:
            self.result = exc
        self.done.set()


def open_imu(device: ReplayI2cDevice, chip: int = CHIP) -> Any:
    address = parse_address(device.mock_address(parse_address("i2c://1/0x68", device="imu")), device="imu")
    return open_port(address.with_chip_address(chip), device="imu")


def test_a_data_read_is_held_until_the_player_feeds_its_record(device: ReplayI2cDevice) -> None:
    port = open_imu(device)
    try:
        assert port.read_byte(WHO_AM_I) == 0x71                    # identification: answered at once
        port.write_byte(CONFIG, 0x03)
        held = Reader(port, DATA, 4)
        wait_until(lambda: device.report()["gated_reads"] == 1, message="the data read held on the replay bus")
        assert not held.done.is_set() and device.pending() == 0
        device.feed(RECORDS[0])   # records of other registers release nothing
        device.feed(RECORDS[1])
        assert device.pending() == 0 and device.report()["reads"] == 1
        device.feed(RECORDS[2])   # the first recorded data read
        assert held.done.wait(10), "the released read did not return"
        assert held.result == SAMPLES[0] and device.pending() == 0
        device.feed(RECORDS[4])
        device.feed(RECORDS[6])
        assert device.pending() == 2                               # released ahead: the --fast backlog
        assert [port.read_block(DATA, 4) for _ in range(2)] == SAMPLES[1:]
        report = device.report()
        assert report["gated_reads"] == 1 and report["divergences"] == 0 and device.pending() == 0, report
    finally:
        port.close()


def test_a_held_read_does_not_keep_another_chip_off_the_bus(device: ReplayI2cDevice) -> None:
    port, mag = open_imu(device), open_imu(device, 0x0C)   # the AK8963 on a connection of its own
    try:
        held = Reader(port, DATA, 4)
        wait_until(lambda: device.report()["gated_reads"] == 1, message="the data read held on the replay bus")
        assert mag.read_block(0x03, 2) == SAMPLES[0][:2]           # answered while the MPU's read is held
        assert not held.done.is_set()
        device.feed(RECORDS[2])
        assert held.done.wait(10) and held.result == SAMPLES[0]
    finally:
        port.close()
        mag.close()


def test_stop_refuses_a_held_read(device: ReplayI2cDevice) -> None:
    port = open_imu(device)
    try:
        held = Reader(port, DATA, 4)
        wait_until(lambda: device.report()["gated_reads"] == 1, message="the data read held on the replay bus")
        device.stop()
        assert held.done.wait(10), "stop() left the read held"
        assert isinstance(held.result, (PortIOError, PortClosed)), held.result
        wait_until(lambda: device.report()["refused_at_stop"] == 1, message="the held read counted as refused")
        assert device.report()["reads"] == 0
    finally:
        port.close()


def test_the_replay_address_carries_the_long_client_timeout_and_ready_is_the_open_port(
        device: ReplayI2cDevice) -> None:
    address = parse_address(device.mock_address(parse_address("i2c://1/0x68", device="imu")), device="imu")
    assert address.i2c_timeout == I2C_CLIENT_TIMEOUT_S >= 30.0 and address.chip_address == CHIP
    port = open_imu(device)
    try:
        assert port._sock.gettimeout() == I2C_CLIENT_TIMEOUT_S
    finally:
        port.close()
    assert device.ready(None, {"port": "open"}) and not device.ready(None, {"port": "closed"})
    assert device.backlog_limit > 0 and device.streamed


def write_log(path: Path, records: list[RawI2c]) -> LogFile:
    log = McapLogWriter(path.parent, path=path)
    for n, record in enumerate(records):
        log.write("RAW.imu", record.encode(), 1_000 + n)
    log.close()
    return LogFile(path)


def test_a_log_begun_after_the_chip_set_up_is_told_from_one_that_holds_it(sockets: Path) -> None:
    """A recording started while the stack ran holds data reads only: the replay cannot identify the chip or
    calibrate as the live driver did, so the plan leaves the service out with a note (hil/replay_plan.py)."""
    assert i2c_setup_recorded(write_log(sockets / "whole.mcap", RECORDS), "imu")
    mid_run = [r for sample in SAMPLES for r in (raw(DATA, sample), raw(0x03, sample[:2], address=0x0C))]
    assert not i2c_setup_recorded(write_log(sockets / "mid-run.mcap", mid_run), "imu")
    # begun inside the set-up, after the identity read: its first record is a write
    assert not i2c_setup_recorded(write_log(sockets / "inside.mcap", RECORDS[1:]), "imu")
    # too few reads to tell: replayed as before
    assert i2c_setup_recorded(write_log(sockets / "short.mcap", mid_run[:2]), "imu")


def test_with_the_drivers_identity_register_only_a_log_that_reads_it_first_holds_the_set_up(sockets: Path) -> None:
    """Begun inside the MPU-9250's set-up after WHO_AM_I: a configuration read, then the writes (issue 24, a
    corpus `mid-run` log built beside two busy processes: the rule without the register took it for a set-up
    and the replayed driver never opened, 'not ready after 30 s: imu'). The driver declares its identity
    register, and the log must begin with a read of it."""
    from u2sa_hw.drivers.imu.bno055 import Bno055ImuDriver
    from u2sa_hw.drivers.imu.mpu9250 import Mpu9250ImuDriver

    assert Mpu9250ImuDriver.IDENTITY_REGISTER == WHO_AM_I and Bno055ImuDriver.IDENTITY_REGISTER == 0x00
    inside = [raw(0x19, b"\x13\x03\x08\x08"), raw(0x6B, b"\x01"), raw(0x37, b"\x02", op=OP_WRITE), *RECORDS[1:]]
    log = write_log(sockets / "inside-after-a-read.mcap", inside)
    assert i2c_setup_recorded(log, "imu"), "the rule without the register cannot tell (why drivers declare it)"
    assert not i2c_setup_recorded(log, "imu", identity_register=WHO_AM_I)
    assert i2c_setup_recorded(write_log(sockets / "whole.mcap", RECORDS), "imu", identity_register=WHO_AM_I)
