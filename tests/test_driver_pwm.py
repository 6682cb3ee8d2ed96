"""The PWM servo/ESC driver as a real ``u2sa service`` process, against a sysfs-shaped PWM
tree and against a mock PCA9685 on the mock I2C bus, commanded over real LCM multicast."""

from __future__ import annotations

import shutil
import signal
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import ServiceProcesses, wait_until
from serial_driver_harness import DriverProbe, start_driver, write_profile

from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.pca9685_chip import Pca9685Chip
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.ports.tap import raw_channel


def command(bus: BusClient, actuator: str, percent: float) -> None:
    msg = t.PercentageCommand()
    msg.base.actuator_name = actuator
    msg.percentage = percent
    bus.publish(ch.ACTUATOR_CMD, msg)


def failsafe(bus: BusClient, active: bool) -> None:
    msg = t.Failsafe()
    msg.active, msg.reason = active, "test"
    bus.publish(ch.FAILSAFE, msg)


def sysfs(chip: Path, channel: int, name: str) -> int:
    try:
        return int((chip / f"pwm{channel}" / name).read_text())
    except (OSError, ValueError):
        return -1


def wait_duty(chip: Path, channel: int, ns: int, *, message: str = "") -> None:
    wait_until(lambda: sysfs(chip, channel, "duty_cycle") == ns, timeout=10,
               message=message or f"pwm{channel} duty {ns} ns (is {sysfs(chip, channel, 'duty_cycle')})")


def test_sysfs_channels_map_percent_and_go_neutral_on_start_timeout_failsafe_and_stop(
        tmp_path: Path, services: ServiceProcesses, bus: BusClient) -> None:
    chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=4)
    channels = [
        {"name": "rudder"},
        {"name": "throttle", "min_us": 1100, "max_us": 1900, "reverse": True},
        {"name": "esc", "neutral_us": 1400.0},
    ]
    probe = DriverProbe(bus, "servos")
    profile = write_profile(tmp_path, name="servos", kind="pwm_servo",
                            settings={"channels": channels, "command_timeout_s": 0.0, "rc_gating": False},
                            devices={"rudder": f"mock+pwm://{chip}/0", "throttle": f"mock+pwm://{chip}/1",
                                     "esc": f"mock+pwm://{chip}/2"})
    proc = start_driver(services, profile, "servos")
    for channel, neutral in ((0, 1_500_000), (1, 1_500_000), (2, 1_400_000)):  # neutral on start
        wait_until(lambda: sysfs(chip, channel, "enable") == 1, message=f"pwm{channel} enabled")
        assert sysfs(chip, channel, "duty_cycle") == neutral and sysfs(chip, channel, "period") == 20_000_000

    for actuator, percent, channel, ns in (
            ("rudder", 50, 0, 1_750_000), ("rudder", -100, 0, 1_000_000), ("rudder", 250, 0, 2_000_000),
            ("throttle", 50, 1, 1_300_000), ("throttle", -100, 1, 1_900_000),  # reversed
            ("esc", 50, 2, 1_700_000), ("esc", -50, 2, 1_200_000)):  # piecewise through an off-centre neutral
        command(bus, actuator, percent)
        wait_duty(chip, channel, ns, message=f"{actuator} {percent} % -> {ns} ns")
    command(bus, "servos", 80)  # the service name is not an actuator name
    command(bus, "other", 80)

    assert bus.set_config("servos", "command_timeout_s", "0.3").ok
    command(bus, "rudder", 30)
    wait_duty(chip, 0, 1_650_000)
    wait_duty(chip, 0, 1_500_000, message="neutral once commands stop")
    wait_duty(chip, 1, 1_500_000)
    wait_duty(chip, 2, 1_400_000)
    assert bus.set_config("servos", "command_timeout_s", "0").ok

    command(bus, "rudder", 60)
    wait_duty(chip, 0, 1_800_000)
    failsafe(bus, True)
    wait_duty(chip, 0, 1_500_000, message="neutral on failsafe")
    command(bus, "rudder", 60)  # ignored while the failsafe holds
    health = probe.wait_health(lambda d, s: int(d["ignored"]) >= 1, message="the command ignored")
    assert health["failsafe"] == "True" and health["status"] == "degraded"
    assert sysfs(chip, 0, "duty_cycle") == 1_500_000
    failsafe(bus, False)
    probe.wait_health(lambda d, s: s == "ok", message="failsafe cleared")
    command(bus, "rudder", -40)
    wait_duty(chip, 0, 1_300_000)
    assert health["rudder.port"] == "open"

    command(bus, "esc", 100)
    wait_duty(chip, 2, 2_000_000)
    bus.stop(name="servos")
    assert proc.wait(timeout=10) == 0
    for channel, neutral in ((0, 1_500_000), (1, 1_500_000), (2, 1_400_000)):  # held after the stop
        assert sysfs(chip, channel, "duty_cycle") == neutral and sysfs(chip, channel, "enable") == 1


@pytest.fixture
def pca_bus() -> Iterator[MockI2cBus]:
    """A mock I2C bus with a PCA9685 at 0x40, on a short socket path."""
    tmp = Path(tempfile.mkdtemp(prefix="pwm", dir="/tmp"))
    i2c = MockI2cBus(socket_path=str(tmp / "bus.sock"))
    i2c.add(Pca9685Chip(address=0x40))
    with i2c:
        yield i2c
    shutil.rmtree(tmp, ignore_errors=True)


class RawPwmProbe:
    """RawPwmWrite records of one channel, as the driver publishes them."""

    def __init__(self, bus: BusClient, device: str) -> None:
        self.records: list[t.RawPwmWrite] = []
        self._lock = threading.Lock()
        bus.transport.subscribe(raw_channel(device), t.RawPwmWrite, self._add)

    def _add(self, _channel: str, msg: t.RawPwmWrite) -> None:
        with self._lock:
            self.records.append(msg)

    def since(self, index: int) -> list[t.RawPwmWrite]:
        with self._lock:
            return list(self.records[index:])


def test_pca9685_channels_slew_limit_taps_reconnect_and_neutral_on_kill(
        tmp_path: Path, services: ServiceProcesses, bus: BusClient, pca_bus: MockI2cBus) -> None:
    pca: Any = pca_bus.chip(0x40)
    address = f"mock+pca9685://{pca_bus.socket_path}/0x40"
    count_us = 20_000 / 4096 + 0.1  # one count at 50 Hz (the chip's frame is the nearest prescale step)
    channels = [
        {"name": "pan"},
        {"name": "winch", "slew_percent_per_s": 100.0},
    ]
    raw = RawPwmProbe(bus, "winch")
    profile = write_profile(tmp_path, name="gimbal", kind="pwm_servo",
                            settings={"channels": channels, "command_timeout_s": 0.0, "rc_gating": False, "record_raw": True},
                            devices={"pan": f"{address}/0", "winch": f"{address}/3"})
    proc = start_driver(services, profile, "gimbal")
    wait_until(lambda: abs(pca.pulse_width_us(0) - 1500) < count_us and abs(pca.pulse_width_us(3) - 1500) < count_us,
               message="neutral on start")
    assert pca.frame_rate_hz() == pytest.approx(50, abs=0.2)
    command(bus, "pan", 100)
    wait_until(lambda: abs(pca.pulse_width_us(0) - 2000) < count_us, message="pan at 100 %")

    start = len(raw.records)
    command(bus, "winch", 100)  # slewed at 100 %/s: about a second from 1500 to 2000 us
    wait_until(lambda: any(r.duty_ns == 2_000_000 for r in raw.since(start)), message="winch at 100 %")
    ramp = [r for r in raw.since(start) if r.enabled]
    duties = [r.duty_ns for r in ramp]
    assert duties == sorted(duties) and len(set(duties)) >= 10  # rising in steps, not a jump
    steps_seconds = (ramp[-1].header.timestamp_us - ramp[0].header.timestamp_us) / 1e6
    assert steps_seconds >= 0.8  # 500 us of travel at 5 us per 1 % and 100 %/s: not faster than 1 s less a step
    assert abs(pca.pulse_width_us(3) - 2000) < count_us

    command(bus, "winch", -100)
    wait_until(lambda: pca.pulse_width_us(3) < 1400, message="winch slewing down")
    before = len(raw.records)
    failsafe(bus, True)  # neutral at once, not slewed (a slew step is 2 % = 10 us)
    wait_until(lambda: any(r.duty_ns == 1_500_000 for r in raw.since(before)), message="neutral on failsafe")
    duties = [r.duty_ns for r in raw.since(0)]
    jump = duties.index(1_500_000, before)
    assert duties[jump - 1] < 1_400_000
    assert abs(pca.pulse_width_us(0) - 1500) < count_us
    failsafe(bus, False)

    probe = DriverProbe(bus, "gimbal")
    before = probe.health_after(1)
    assert (before["pan.errors"], before["winch.errors"]) == ("0", "0")
    pca_bus.disconnect_clients()  # the bus connection drops: the next write finds out, the channel reopens
    command(bus, "pan", -100)
    wait_until(lambda: abs(pca.pulse_width_us(0) - 1000) < count_us, message="pan after the reconnect")
    details = probe.wait_health(lambda d, s: d["pan.errors"] == "1", message="the failed write counted")
    assert details["pan.port"] == "open" and details["status"] == "ok"   # reopened by the retry at once
    assert "went away" in details["pan.last_error"] and details["winch.errors"] == "0"

    pca_bus.stop()                # the bus server dies: the channel cannot be reopened until it is back
    command(bus, "pan", 100)
    details = probe.wait_health(lambda d, s: d["pan.port"] == "down", message="pan down while the bus is gone")
    assert details["status"] == "degraded" and "mock I2C bus" in details["pan.last_error"]
    assert proc.poll() is None
    pca_bus.start()
    wait_until(lambda: abs(pca.pulse_width_us(0) - 2000) < count_us, message="pan at 100 % once the bus is back")
    assert probe.wait_health(lambda d, s: s == "ok")["pan.port"] == "open"

    proc.send_signal(signal.SIGTERM)
    try:   # about 0.2 s on a quiet machine; the bound is for a hang, not a speed (a loaded CI took over 10 s once)
        code = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail(f"gimbal still running 60 s after SIGTERM; its log:\n{(tmp_path / 'gimbal.stderr').read_text()[-3000:]}")
    assert code == 0, (tmp_path / "gimbal.stderr").read_text()[-3000:]
    assert abs(pca.pulse_width_us(0) - 1500) < count_us and abs(pca.pulse_width_us(3) - 1500) < count_us


@pytest.mark.parametrize(("channels", "expected"), [
    ([], "must list at least one channel"),
    ([{"name": "rudder", "min_us": 1600}], "min_us <= neutral_us"),
    ([{"name": "rudder", "chanel": 0}], "unknown key(s) chanel"),
    ([{"name": "a"}, {"name": "b"}], "channels 'a' and 'b' are one output"),
    ([{"name": "rudder", "address": "/tmp/x", "channel": 0}],
     "'address' is the old form: name a device instead: [devices.rudder] address = \"pca9685://1/0x40/0\" and "
     "device = \"rudder\" in the channel's table (docs/ports.md)"),
])
def test_bad_channel_config_stops_the_service_with_the_reason(
        tmp_path: Path, services: ServiceProcesses, channels: list, expected: str) -> None:
    output = "mock+pwm:///tmp/x/0"   # a and b on one output
    profile = write_profile(tmp_path, name="servos", kind="pwm_servo", settings={"channels": channels},
                            devices={"rudder": output, "a": output, "b": output})
    proc = start_driver(services, profile, "servos")
    assert proc.wait(timeout=15) != 0
    assert expected in (tmp_path / "servos.stderr").read_text()


def test_a_vanished_sysfs_chip_is_reported_and_reopened_while_another_chip_keeps_working(
        tmp_path: Path, services: ServiceProcesses, bus: BusClient) -> None:
    chip0 = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=2)
    chip1 = make_sysfs_pwm_tree(tmp_path / "pwmchip1", npwm=2)
    channels = [{"name": "rudder"}, {"name": "esc"}]
    probe = DriverProbe(bus, "servos")
    profile = write_profile(tmp_path, name="servos", kind="pwm_servo",
                            settings={"channels": channels, "command_timeout_s": 0.0, "rc_gating": False},
                            devices={"rudder": f"mock+pwm://{chip0}/0", "esc": f"mock+pwm://{chip1}/1"})
    proc = start_driver(services, profile, "servos")
    wait_until(lambda: sysfs(chip0, 0, "enable") == 1 and sysfs(chip1, 1, "enable") == 1, message="both enabled")
    command(bus, "rudder", 50)
    wait_duty(chip0, 0, 1_750_000)

    shutil.rmtree(chip0)                     # the chip's driver is unbound (overlay removed): its tree is gone
    command(bus, "rudder", -50)
    details = probe.wait_health(lambda d, s: d["rudder.port"] == "down" and "no PWM chip" in d["rudder.last_error"],
                                message="the vanished chip in health")
    assert details["status"] == "degraded" and int(details["rudder.errors"]) >= 1
    assert details["esc.port"] == "open" and details["esc.errors"] == "0"
    command(bus, "esc", 50)                  # the other chip is untouched
    wait_duty(chip1, 1, 1_750_000)
    assert proc.poll() is None

    make_sysfs_pwm_tree(chip0, npwm=2)       # the chip is back: reopened at the output it should have
    wait_until(lambda: sysfs(chip0, 0, "enable") == 1, message="pwm0 exported and enabled again")
    wait_duty(chip0, 0, 1_250_000, message="the last command (-50 %) restored")
    details = probe.wait_health(lambda d, s: s == "ok", message="ok again")
    assert details["rudder.port"] == "open" and int(details["rudder.errors"]) >= 1
