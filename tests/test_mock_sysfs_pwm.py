"""The sysfs PWM mock: a sysfs-shaped chip directory the PWM port opens like the kernel's and
the simulation reads back, the ``sysfs_pwm`` kind of ``u2sa mock``, and the real pwm_servo
driver (a service process) driving it alongside a PCA9685 mock of the same service."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from conftest import REPO, U2SA, ServiceProcesses, wait_until
from serial_driver_harness import DriverProbe, start_driver, write_profile

from u2sa_hw.mocks.launcher import MockLauncher
from u2sa_hw.mocks.sim_context import DeviceError
from u2sa_hw.mocks.sysfs_pwm import SysfsPwmChip
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.ports import PortClosed, PortUnavailable, open_pwm
from u2sa_hw.simulation.profile import effective_configs
from u2sa_hw.profile.loader import load_profile

SERVOS = """
[vehicle]
origin = { lat = 29.1895, lon = -81.0483 }

[services.servos]
kind = "pwm_servo"
settings = { command_timeout_s = 0.0, rc_gating = false, channels = [
  { name = "rudder" },
  { name = "esc", neutral_us = 1400.0 },
  { name = "pan" },
] }

[devices.rudder]
address = "pwm://pwmchip0/0"
mock = "sysfs_pwm"

[devices.esc]
address = "pwm://pwmchip1/1"
mock = "sysfs_pwm"

[devices.pan]
address = "pca9685://1/0x40/0"
mock = "pca9685"
service = "servos"
"""


def test_the_chip_is_opened_like_the_kernels_and_read_back_by_the_simulation(tmp_path: Path) -> None:
    chip = SysfsPwmChip(path=tmp_path / "pwmchip0", npwm=2).start()
    assert chip.exported() == [] and chip.pulse_widths_us() == [0.0, 0.0]
    pwm = open_pwm(device="rudder", address=chip.address, channel=1)
    assert chip.exported() == [1] and chip.channel_state(1) == (20_000_000, 0, False)
    pwm.set_pulse_us(1500)
    assert chip.pulse_width_us(1) == 0.0          # set but not enabled: no pulse yet
    pwm.enable(True)
    assert chip.pulse_width_us(1) == 1500.0 and chip.frame_period_us(1) == 20_000.0
    assert chip.channel_state(0) is None and chip.pulse_width_us(0) == 0.0
    with pytest.raises(ValueError, match="channel 2 out of range"):
        chip.pulse_width_us(2)

    chip.unbind()                                  # the chip's driver unbound under the open channel
    assert not chip.bound and not Path(chip.address).exists()
    with pytest.raises(PortClosed, match="PWM chip gone"):
        pwm.set_pulse_us(1600)
    with pytest.raises(PortUnavailable, match="no PWM chip here"):
        open_pwm(device="rudder", address=chip.address, channel=1)
    chip.bind()                                    # back, empty
    assert chip.exported() == []
    again = open_pwm(device="rudder", address=chip.address, channel=1)
    again.set_pulse_us(1200)
    again.enable(True)
    assert chip.pulse_width_us(1) == 1200.0
    chip.stop()


def test_list_kinds_names_the_sysfs_pwm_mock() -> None:
    out = subprocess.run([*U2SA, "mock", "--list-kinds"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    line = next(line for line in out.stdout.splitlines() if line.startswith("sysfs_pwm "))
    assert "/sys/class/pwm" in line and "pwm_servo" in line


def test_a_service_with_no_sysfs_channel_is_refused_naming_the_table(tmp_path: Path) -> None:
    text = SERVOS.replace('"pwm://pwmchip0/0"', '"pca9685://1/0x41/0"')
    (tmp_path / "vehicle.toml").write_text(text)
    profile = load_profile(tmp_path / "vehicle.toml")
    with pytest.raises(DeviceError, match=r"\[devices.rudder\]: mock sysfs_pwm stands in for a pwm device, but the "
                                          r"address is pca9685://1/0x41/0"):
        MockLauncher(profile, device_dir=tmp_path / "dev", service_configs=effective_configs(profile))


def command(bus: BusClient, actuator: str, percent: float) -> None:
    msg = t.PercentageCommand()
    msg.base.actuator_name, msg.percentage = actuator, percent
    bus.publish(ch.ACTUATOR_CMD, msg)


def test_the_driver_drives_sysfs_and_pca9685_mocks_of_one_service(tmp_path: Path, services: ServiceProcesses,
                                                                  bus: BusClient) -> None:
    (tmp_path / "vehicle.toml").write_text(SERVOS)
    profile = load_profile(tmp_path / "vehicle.toml")
    dev = tmp_path / "dev"
    mocks = MockLauncher(profile, device_dir=dev, service_configs=effective_configs(profile))
    addresses = mocks.addresses
    # each output is a device; both tables gave their mock to the outputs of their kind
    assert addresses == {"rudder": f"mock+pwm://{dev / 'pwmchip0'}/0", "esc": f"mock+pwm://{dev / 'pwmchip1'}/1",
                         "pan": f"mock+pca9685://{dev / 'i2c-1.sock'}/0x40/0"}
    (sysfs0,), (sysfs1,) = mocks.context.pwm_chips["rudder"], mocks.context.pwm_chips["esc"]
    assert (sysfs0.npwm, sysfs1.npwm) == (1, 2)    # as many channels as the service uses on each
    pca = mocks.context.pwm_chips["pan"][0]
    rudder_line = next(line for line in mocks.describe() if line.startswith("rudder"))
    assert "sysfs_pwm" in rudder_line and str(dev / "pwmchip0") in rudder_line
    channels = [{"name": "rudder"}, {"name": "esc", "neutral_us": 1400.0}, {"name": "pan"}]   # the new form
    mocks.start()
    try:
        assert sysfs0.bound and sysfs1.bound
        probe = DriverProbe(bus, "servos")
        driver_profile = write_profile(tmp_path, name="servos", kind="pwm_servo",
                                       settings={"channels": channels, "command_timeout_s": 0.0, "rc_gating": False},
                                       devices=addresses)
        proc = start_driver(services, driver_profile, "servos")
        wait_until(lambda: sysfs0.pulse_width_us(0) == 1500.0 and sysfs1.pulse_width_us(1) == 1400.0,
                   message="neutral on start on both sysfs chips", timeout=30)
        command(bus, "rudder", 50)
        command(bus, "esc", -100)
        command(bus, "pan", 100)
        wait_until(lambda: (sysfs0.pulse_width_us(0), sysfs1.pulse_width_us(1)) == (1750.0, 1000.0),
                   message="rudder at 50 %, esc at -100 % as the simulation reads them")
        wait_until(lambda: abs(pca.pulse_width_us(0) - 2000) < 5, message="pan at 100 % on the PCA9685")

        sysfs0.unbind()                            # the chip vanishes under the running driver
        command(bus, "rudder", -50)
        probe.wait_health(lambda d, s: d["rudder.port"] == "down", message="the vanished chip in health")
        sysfs0.bind()
        wait_until(lambda: sysfs0.pulse_width_us(0) == 1250.0, message="the command restored on the new chip")
        assert proc.poll() is None
    finally:
        mocks.stop()
    assert not (dev / "pwmchip0").exists()
