"""open_port: one scheme table opens every kind, here against the mock devices (real ptys, sockets, trees)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterator

import can
import pytest

from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Mpu9250Chip
from u2sa_hw.mocks.pca9685_chip import Pca9685Chip
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.ports import PortUnavailable
from u2sa_hw.ports.address import AddressError, make_address
from u2sa_hw.ports.kinds import PORT_KINDS
from u2sa_hw.ports.opener import open_port
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.ports.tap import RX, TX
from u2sa_hw.protocols import mpu9250 as mpu


@pytest.fixture()
def sockets() -> Iterator[Path]:
    """A short directory for Unix sockets (their paths are limited to 108 bytes)."""
    path = Path(tempfile.mkdtemp(prefix="u2o", dir="/tmp"))
    yield path
    for child in path.iterdir():
        child.unlink()
    path.rmdir()


def test_every_kind_has_a_real_and_a_mock_scheme() -> None:
    assert set(PORT_KINDS) == {"serial", "can", "i2c", "gpio", "pwm", "pca9685"}
    for name, kind in PORT_KINDS.items():
        assert kind.example.startswith(f"{name}://") and kind.mock_example.startswith(f"mock+{name}://")
        assert callable(kind.open_real) and callable(kind.open_mock) and kind.real_backend and kind.mock_backend


def test_serial_on_a_pty_with_the_address_framing_and_a_tap(tmp_path: Path) -> None:
    master, slave = os.openpty()
    link = tmp_path / "gps"
    link.symlink_to(os.ttyname(slave))
    records: list = []
    port = open_port(f"mock+serial://{link}?baud=4800&stopbits=2", device="gps", tap=records.append, timeout=1.0)
    try:
        assert port.framing == "8N2" and port.address == str(link)
        os.write(master, b"$GPHDT,1.0,T*00\r\n")
        assert port.readline() == b"$GPHDT,1.0,T*00\r\n"
        port.write(b"hello")
        assert os.read(master, 5) == b"hello"
        assert [(r.device, r.direction) for r in records][-1] == ("gps", TX) and records[0].direction == RX
    finally:
        port.close()
        os.close(master)
        os.close(slave)


def test_serial_pyserial_url_form() -> None:
    port = open_port("serial+loop://?baud=9600", device="loop", timeout=0.5)
    try:
        port.write(b"ping\n")
        assert port.readline() == b"ping\n"
    finally:
        port.close()


def test_a_missing_serial_device_is_unavailable_with_the_fix(tmp_path: Path) -> None:
    with pytest.raises(PortUnavailable, match=r"^gps .*cannot open.*; fix: .*nothing does not exist"):
        open_port(f"serial://{tmp_path / 'nothing'}?baud=9600", device="gps")


def test_can_on_a_virtual_bus_with_bus_options() -> None:
    port = open_port("mock+can://virtual/u2sa-open-test?receive_own_messages=true", device="wheels")
    peer = can.Bus(interface="virtual", channel="u2sa-open-test")
    try:
        peer.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
        msg = port.recv(1.0)
        assert msg is not None and msg.arbitration_id == 0x123 and bytes(msg.data) == b"\x01\x02"
        port.send(can.Message(arbitration_id=0x321, data=b"", is_extended_id=False))
        assert peer.recv(1.0).arbitration_id == 0x321
    finally:
        port.close()
        peer.shutdown()


def test_i2c_on_the_mock_bus_reads_the_chip_the_address_names(sockets: Path) -> None:
    vehicle = SimVehicle(origin_lat=29.19, origin_lon=-81.05)
    bus = MockI2cBus(socket_path=str(sockets / "i2c.sock"))
    bus.add(Mpu9250Chip(vehicle=vehicle, address=0x69, seed=1))
    with bus:
        port = open_port(make_address("i2c", str(sockets / "i2c.sock"), (0x69,), mock=True), device="imu")
        try:
            assert port.read_byte(mpu.WHO_AM_I) == mpu.VARIANTS["mpu9250"].who_am_i
        finally:
            port.close()


def test_gpio_lines_must_be_listed_in_the_address(sockets: Path) -> None:
    with MockGpioChip(socket_path=str(sockets / "chip.sock")) as chip:
        address = f"mock+gpio://{sockets / 'chip.sock'}/4,5"
        port = open_port(address, device="io", inputs=[5], outputs={4: 1})
        try:
            assert chip.read_output(4) == 1
            port.set(4, 0)
            assert chip.read_output(4) == 0
        finally:
            port.close()
        with pytest.raises(AddressError, match=r"line\(s\) 6 are used but not listed.*/4,5,6"):
            open_port(address, device="io", outputs={6: 0})


def test_pwm_on_a_sysfs_shaped_tree(tmp_path: Path) -> None:
    make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=2)
    pwm = open_port(f"mock+pwm://{tmp_path / 'pwmchip0'}/1", device="rudder", period_ns=20_000_000)
    try:
        pwm.set_pulse_us(1500)
        pwm.enable(True)
        assert (tmp_path / "pwmchip0" / "pwm1" / "duty_cycle").read_text().strip() == "1500000"
    finally:
        pwm.close()


def test_pca9685_output_on_the_mock_bus(sockets: Path) -> None:
    bus = MockI2cBus(socket_path=str(sockets / "i2c.sock"))
    chip = bus.add(Pca9685Chip(address=0x41))
    with bus:
        pwm = open_port(f"mock+pca9685://{sockets / 'i2c.sock'}/0x41/3", device="pan")
        try:
            pwm.set_pulse_us(2000)
            pwm.enable(True)
            assert abs(chip.pulse_width_us(3) - 2000) < 10
        finally:
            pwm.close()


def test_an_option_a_kind_does_not_take_is_refused() -> None:
    with pytest.raises(TypeError, match="open_port\\(i2c\\) takes no options, not timeout"):
        open_port("i2c://1/0x68", device="imu", timeout=1.0)
