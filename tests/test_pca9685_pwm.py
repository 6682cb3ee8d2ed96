"""The PCA9685 PWM backend driving the mock chip on the mock I2C bus: pulse accuracy,
prescale set once per chip, shared channels (in one process and across processes),
taps, enable/close, errors."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Iterator

import pytest

from conftest import REPO
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.pca9685_chip import Pca9685Chip
from u2sa_hw.ports.errors import PortClosed, PortIOError, PortUnavailable
from u2sa_hw.ports.i2c.wire import OP_WRITE
from u2sa_hw.ports.i2c.port import open_i2c
from u2sa_hw.ports.pwm.pca9685 import open_pca9685_pwm, parse_address
from u2sa_hw.ports.pwm.port import open_pwm
from u2sa_hw.protocols import pca9685 as pca


@pytest.fixture
def bus() -> Iterator[MockI2cBus]:
    """A mock bus with a PCA9685 at 0x40."""
    tmp = Path(tempfile.mkdtemp(prefix="pca", dir="/tmp"))
    mock = MockI2cBus(socket_path=str(tmp / "bus.sock"))
    mock.add(Pca9685Chip(address=0x40))
    with mock:
        yield mock
    shutil.rmtree(tmp, ignore_errors=True)


def chip_of(bus: MockI2cBus) -> Pca9685Chip:
    return bus.chip(0x40)  # type: ignore[return-value]


def address_of(bus: MockI2cBus) -> str:
    return f"pca9685:{bus.address}:0x40"


def writes_to(chip: Pca9685Chip, register: int) -> list[bytes]:
    return [t.data for t in chip.history if t.op == OP_WRITE and t.register == register]


def test_pulse_widths_within_one_count(bus: MockI2cBus) -> None:
    chip = chip_of(bus)
    pwm = open_pca9685_pwm(device="rudder", address=address_of(bus), channel=3)
    assert chip.prescale == 121 and abs(chip.frame_period_us() - 20_000) < 0.5 * 163  # nearest prescale step
    assert pwm.period_ns == round(chip.frame_period_us() * 1000)
    pwm.enable(True)
    one_count_us = chip.frame_period_us() / 4096
    for us in (1000.0, 1234.5, 1500.0, 1750.3, 2000.0, 500.0):
        pwm.set_pulse_us(us)
        assert abs(chip.pulse_width_us(3) - us) <= one_count_us, us
    assert chip.lost_restarts == 0
    pwm.set_pulse_ns(pwm.period_ns)
    assert chip.high_counts(3) == 4096  # full on
    pwm.set_pulse_ns(0)
    assert chip.pulse_width_us(3) == 0.0


def test_enable_tap_and_close(bus: MockI2cBus) -> None:
    chip = chip_of(bus)
    records = []
    pwm = open_pca9685_pwm(device="rudder", address=address_of(bus), channel=0, tap=records.append)
    assert not pwm.enabled
    pwm.set_pulse_us(1500)
    assert chip.pulse_width_us(0) == 0.0  # set while disabled: stored, not output
    pwm.enable(True)
    assert abs(chip.pulse_width_us(0) - 1500) < 5
    pwm.set_pulse_us(1500)  # unchanged: no write, no record
    pwm.enable(False)
    assert chip.pulse_width_us(0) == 0.0
    pwm.enable(True)
    period = pwm.period_ns
    pwm.close()
    assert chip.pulse_width_us(0) == 0.0  # close stops the output, like the sysfs backend
    states = [(r.device, r.channel, r.period_ns, r.duty_ns, r.enabled) for r in records]
    assert states == [("rudder", 0, period, 0, False), ("rudder", 0, period, 1_500_000, False),
                      ("rudder", 0, period, 1_500_000, True), ("rudder", 0, period, 1_500_000, False),
                      ("rudder", 0, period, 1_500_000, True), ("rudder", 0, period, 1_500_000, False)]
    with pytest.raises(PortClosed):
        pwm.set_pulse_us(1600)
    pwm.close()  # idempotent


def test_second_channel_shares_the_chip_without_resetting_it(bus: MockI2cBus) -> None:
    chip = chip_of(bus)
    a = open_pca9685_pwm(device="left", address=address_of(bus), channel=0)
    a.set_pulse_us(1100)
    a.enable(True)
    mode1_writes, prescale_writes = len(writes_to(chip, pca.MODE1)), len(writes_to(chip, pca.PRE_SCALE))
    b = open_pwm(device="right", address=address_of(bus), channel=1)  # through the generic opener
    b.set_pulse_us(1900)
    b.enable(True)
    assert len(writes_to(chip, pca.PRE_SCALE)) == prescale_writes == 1
    assert len(writes_to(chip, pca.MODE1)) == mode1_writes  # nobody slept the chip
    assert abs(chip.pulse_width_us(0) - 1100) < 5 and abs(chip.pulse_width_us(1) - 1900) < 5
    with pytest.raises(PortUnavailable, match="share one period"):
        open_pca9685_pwm(device="led", address=address_of(bus), channel=2, period_ns=5_000_000)
    with pytest.raises(PortUnavailable, match="already open"):
        open_pca9685_pwm(device="left2", address=address_of(bus), channel=0)
    a.close()
    assert abs(chip.pulse_width_us(1) - 1900) < 5  # b still runs
    b.close()


def test_channel_opened_from_another_process_keeps_the_prescale(bus: MockI2cBus) -> None:
    chip = chip_of(bus)
    a = open_pca9685_pwm(device="left", address=address_of(bus), channel=0)
    a.set_pulse_us(1200)
    a.enable(True)
    script = ("from u2sa_hw.ports.pwm.pca9685 import open_pca9685_pwm\n"
              f"p = open_pca9685_pwm(device='other', address={address_of(bus)!r}, channel=5)\n"
              "p.set_pulse_us(1700); p.enable(True)\n")
    subprocess.run([sys.executable, "-c", script], cwd=REPO, check=True, timeout=60)
    assert len(writes_to(chip, pca.PRE_SCALE)) == 1
    assert abs(chip.pulse_width_us(0) - 1200) < 5
    assert abs(chip.pulse_width_us(5) - 1700) < 5  # it exited without close(), as a crash would
    a.close()


def test_open_reprograms_a_wrong_prescale_and_adopts_a_running_pulse(bus: MockI2cBus) -> None:
    chip = chip_of(bus)
    raw = open_i2c(device="setup", bus=bus.address, address=0x40)
    raw.write_byte(pca.MODE1, 0x21)  # awake at the power-on prescale (200 Hz), channel 7 running
    raw.write_block(pca.led_register(7), pca.led_bytes(0, 1229))
    raw.close()
    pwm = open_pca9685_pwm(device="rudder", address=address_of(bus), channel=7)
    assert chip.prescale == 121 and not chip.asleep and not chip.restart_pending
    assert pwm.enabled and abs(pwm.duty_ns - 1229 * 4880) <= 4880  # adopted what the chip outputs
    assert abs(chip.pulse_width_us(7) - 1229 * 4.88) < 5  # restarted after the prescale change
    pwm.close()


def test_chip_faults_surface_and_bus_restart_recovers(bus: MockI2cBus) -> None:
    chip = chip_of(bus)
    pwm = open_pca9685_pwm(device="rudder", address=address_of(bus), channel=2)
    pwm.enable(True)
    chip.nack(True)
    with pytest.raises(PortIOError, match="no ACK from 0x40") as info:
        pwm.set_pulse_us(1500)
    assert info.value.device == "rudder" and info.value.address == address_of(bus) and info.value.fix
    assert str(info.value).count("fix:") == 1
    chip.nack(False)
    pwm.set_pulse_us(1500)
    bus.disconnect_clients()
    with pytest.raises(PortClosed):
        pwm.set_pulse_us(1600)
    pwm.set_pulse_us(1600)  # the next call reopens the bus
    assert abs(chip.pulse_width_us(2) - 1600) < 5
    pwm.close()


def test_missing_bus_is_unavailable(tmp_path: Path) -> None:
    address = f"pca9685:mock:{tmp_path}/none.sock:0x40"
    with pytest.raises(PortUnavailable, match="start the mock I2C bus server") as info:
        open_pca9685_pwm(device="rudder", address=address, channel=0)
    assert info.value.device == "rudder" and info.value.address == address
    with pytest.raises(PortUnavailable, match="dtparam=i2c_arm=on"):
        open_pca9685_pwm(device="rudder", address="pca9685:250:0x40", channel=0)


@pytest.mark.parametrize("address", ["pca9685:", "pca9685:1", "pca9685:1:forty", "pwm:1:0x40", "pca9685:i2c:0x40"])
def test_bad_addresses_are_refused(address: str) -> None:
    with pytest.raises(PortUnavailable, match="rudder"):
        open_pca9685_pwm(device="rudder", address=address, channel=0)


def test_bad_channel_period_and_pulse(bus: MockI2cBus) -> None:
    for channel in (16, -1):
        with pytest.raises(PortUnavailable, match="channel"):
            open_pca9685_pwm(device="rudder", address=address_of(bus), channel=channel)
    with pytest.raises(PortUnavailable, match="outside the PCA9685 range"):
        open_pca9685_pwm(device="rudder", address=address_of(bus), channel=0, period_ns=1000)
    pwm = open_pca9685_pwm(device="rudder", address=address_of(bus), channel=0)
    for ns in (-1, pwm.period_ns + 1):
        with pytest.raises(ValueError, match="rudder"):
            pwm.set_pulse_ns(ns)
    pwm.close()


def test_parse_address() -> None:
    assert parse_address("pca9685:1:0x40", device="d") == (1, 0x40)
    assert parse_address("pca9685:mock:/run/x.sock:0x41", device="d") == ("mock:/run/x.sock", 0x41)
