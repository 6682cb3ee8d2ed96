"""Findings of the device-address safety review, each against the real parts: profiles on disk read by
``u2sa check``'s own code, drivers built as the service builds them, DeviceLinks opening real (mock) ports,
and mock ODrive axes on a python-can virtual bus.

1. a gpio:// address that does not list every line the driver uses (an e-stop, the mux's enable line);
2. a device name with no [devices] address silently opening can0 / i2c-1;
3. two new-form PWM devices on one output (within a service and across services);
4. a pwm_servo change over the bus (channels, update_hz) saved although the next start would fail;
5. a CAN motor's bus changed live without zero/idle on the old controllers.
"""

from __future__ import annotations

import os
import random
import threading
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until

from u2sa_hw.drivers.gpio.driver import GpioInputDriver
from u2sa_hw.drivers.imu.mpu9250 import Mpu9250ImuDriver
from u2sa_hw.drivers.can_motor.odrive.driver import OdriveCanMotor
from u2sa_hw.drivers.pwm.servo import PwmServoDriver
from u2sa_hw.drivers.rc_mux.driver import RcMuxDriver
from u2sa_hw.mocks.odrive_node import OdriveCanNode
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw import lcmtypes as t
from u2sa_hw.check.offline import check_profile
from u2sa_hw.check.problem import errors_of
from u2sa_hw.config.fields import ConfigError
from u2sa_hw.profile.devices import effective_config, profile_devices
from u2sa_hw.ports import PortUnavailable
from u2sa_hw.ports.device_link import DeviceLink
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.protocols.odrive_cansimple import AxisState
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile
from u2sa_hw.profile.loader import load_profile


def write(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "vehicle.toml"
    path.write_text('[vehicle]\nname = "review"\n' + body)
    return path


def problems_about(path: Path, word: str, *, for_sim: bool = False) -> list[Any]:
    return [p for p in check_profile(path, for_sim=for_sim) if word in str(p)]


# ---- 1: every line the driver uses is in its gpio:// address ------------------------------------------
ESTOP = """
[services.estop]
kind = "gpio_input"
settings = { inputs = "bump=5,estop=4", failsafe_on = "estop" }

[devices.estop]
address = "gpio://gpiochip0/5"
"""


def test_an_estop_line_missing_from_the_address_is_an_error_in_check_and_at_start(tmp_path: Path,
                                                                                  lcm_url: str) -> None:
    path = write(tmp_path, ESTOP)
    found = [p for p in errors_of(check_profile(path)) if "line(s) 4" in p.message]
    assert len(found) >= 1, check_profile(path)
    assert all('[devices.estop] address = "gpio://gpiochip0/4,5"' in p.message for p in found)
    with pytest.raises(ConfigError, match=r"service 'estop': device 'estop' address gpio://gpiochip0/5 does not "
                                          r"list line\(s\) 4 .*\[devices.estop\] address = \"gpio://gpiochip0/4,5\""
                       ) as info:
        profile = load_profile(path)
        GpioInputDriver("estop", profile=profile, settings=profile.service("estop").settings)
    assert "\n" not in str(info.value)
    path.write_text(path.read_text().replace("gpiochip0/5", "gpiochip0/4,5"))
    assert not [p for p in errors_of(check_profile(path)) if "line(s)" in p.message]


def test_the_rc_mux_enable_line_missing_from_the_address_is_refused(tmp_path: Path, lcm_url: str) -> None:
    profile = VehicleProfile(path=None, devices={"rc": {"address": "mock+gpio:///run/x/chip.sock/5,13"}})
    with pytest.raises(ConfigError, match=r"line\(s\) 21 .*\[devices.rc\] address = "
                                          r"\"mock\+gpio:///run/x/chip.sock/5,13,21\""):
        RcMuxDriver("rc", profile=profile, settings={"channels": "throttle=5,mode=13", "mode_channel": "mode",
                                                     "enable_line": 21})


class Owner:
    """What a DeviceLink needs of its driver."""

    def __init__(self, profile: VehicleProfile) -> None:
        self.name, self.profile, self.config = "estop", profile, {"record_raw": False}

    def publish(self, channel: str, msg: Any) -> None:
        pass

    def register_publisher(self, channel: str, kind: type) -> None:
        pass


def test_a_line_the_address_refuses_at_open_is_a_port_fault_in_health_not_an_exception(tmp_path: Path) -> None:
    profile = VehicleProfile(path=None, devices={"estop": {"address": f"mock+gpio://{tmp_path}/chip.sock/5"}})
    link: DeviceLink[Any] = DeviceLink(Owner(profile), device=lambda: "estop", raw_type=t.RawGpioEdge,
                                       options=lambda: {"inputs": [4, 5]})
    link.start()
    try:
        with pytest.raises(PortUnavailable, match=r"line\(s\) 4 are used but not listed"):
            link.get()
        health = link.health()
        assert health["port"] == "down" and "line(s) 4" in health["port_error"] and "fix:" in health["port_error"]
        assert link.reason() == "port down"
    finally:
        link.close()


# ---- 2: no address is an error, never a default bus -----------------------------------------------------
WINCH = """
[services.winch]
kind = "odrive_can"
device = "winc"
settings = { actuators = ["winch"], node_ids = [0], directions = [1], wheel_radius_m = [0.05], odometry = false }

[devices.winch]
address = "can://socketcan/can1?bitrate=500000"
"""


def test_a_can_device_without_an_address_is_an_error_not_can0(tmp_path: Path, lcm_url: str) -> None:
    path = write(tmp_path, WINCH)
    profile = load_profile(path)
    assert OdriveCanMotor.used_devices("winch", effective_config(profile, "winch")) == ("winc",)
    with pytest.raises(ProfileError, match=r"device 'winc' of service 'winch' has no address; .*did you mean "
                                           r"device = \"winch\""):
        profile_devices(profile)
    assert [p for p in errors_of(check_profile(path)) if "'winc'" in p.message], check_profile(path)
    svc = OdriveCanMotor("winch", profile=profile, settings={"device": "winc", "actuators": ["winch"],
                                                              "node_ids": [0], "directions": [1],
                                                              "wheel_radius_m": [0.05], "odometry": False})
    try:
        with pytest.raises(ConfigError, match=r"service 'winch': device 'winc': .*no address: add \[devices.winc\] "
                                              r"address = .*did you mean device = \"winch\"") as info:
            svc.check_config()
        assert "\n" not in str(info.value)
    finally:
        svc.transport.stop()


@pytest.mark.parametrize("cls, settings, key, address", [
    (OdriveCanMotor, {"interface": "virtual", "channel": "can1"}, "interface", "can://socketcan/can0?bitrate=500000"),
    (OdriveCanMotor, {"device": "winch", "bitrate": 500000}, "bitrate", "can://socketcan/can0?bitrate=500000"),
    (Mpu9250ImuDriver, {"bus": "3"}, "bus", "i2c://1/0x68"),
    (Mpu9250ImuDriver, {"address": 0x69}, "address", "i2c://1/0x68"),
])
def test_old_form_settings_are_refused_at_start_naming_the_new_form(cls: type, settings: dict[str, object], key: str,
                                                                    address: str) -> None:
    """The old form no longer gives an address (never a silent can0 or i2c-1): the service refuses to start
    with one line naming the key and the device to write instead (the service's device: "device", else NAME)."""
    device = str(settings.get("device", "NAME"))
    with pytest.raises(ConfigError) as info:
        cls("winch", settings=settings)
    assert str(info.value) == (f"service 'winch' settings: '{key}' is the old form: name a device instead: "
                               f"[devices.{device}] address = \"{address}\" and device = \"{device}\" (docs/ports.md)")


def test_an_imu_naming_no_device_with_an_address_is_refused_at_start(tmp_path: Path, lcm_url: str) -> None:
    svc = Mpu9250ImuDriver("imu", profile=VehicleProfile(path=None, devices={"imu2": {"address": "i2c://1/0x68"}}))
    try:
        with pytest.raises(ConfigError, match=r"imu: device 'imu': .*no address: add \[devices.imu\] address"):
            svc.setup()
    finally:
        svc.transport.stop()


def test_an_address_no_service_uses_is_a_warning(tmp_path: Path) -> None:
    path = write(tmp_path, WINCH.replace('device = "winc"', 'device = "winch"')
                 + '\n[devices.winch_spare]\naddress = "can://socketcan/can2"\n')
    found = problems_about(path, "winch_spare")
    assert found and all(not p.is_error for p in found) and "used by no enabled service" in found[0].message
    assert not errors_of(check_profile(path))
    path.write_text(path.read_text() + '\n[services.winch_spare]\nkind = "vesc_can"\nenabled = false\n')
    assert not problems_about(path, "winch_spare"), "a disabled service's own device is no warning"


# ---- 3 and 4: one output per channel; pwm_servo's check_config ------------------------------------------
def pwm_profile(tmp_path: Path, devices: dict[str, str]) -> VehicleProfile:
    return VehicleProfile(path=None, devices={n: {"address": a} for n, a in devices.items()})


@pytest.mark.parametrize("first, second", [
    ("pwm://pwmchip0/1", "pwm://pwmchip0/1"),
    ("pca9685://1/0x40/0", "pca9685://1/64/0"),            # one chip, spelt two ways
])
def test_two_new_form_devices_on_one_output_are_refused(tmp_path: Path, lcm_url: str, first: str,
                                                        second: str) -> None:
    svc = PwmServoDriver("drive", profile=pwm_profile(tmp_path, {"rudder": first, "esc": second}),
                         settings={"channels": [{"name": "rudder"}, {"name": "esc"}]})
    try:
        with pytest.raises(ConfigError, match=r"channels 'rudder' and 'esc' are one output"):
            svc.check_config()
    finally:
        svc.transport.stop()


def test_one_pca9685_frame_per_chip_in_the_new_form(tmp_path: Path, lcm_url: str) -> None:
    svc = PwmServoDriver("drive", profile=pwm_profile(tmp_path, {"a": "pca9685://1/0x40/0", "b": "pca9685://1/0x40/1"}),
                         settings={"channels": [{"name": "a"}, {"name": "b", "frame_hz": 100.0}]})
    try:
        with pytest.raises(ConfigError, match=r"are on one PCA9685 .* share one frame"):
            svc.check_config()
    finally:
        svc.transport.stop()


def test_two_services_on_one_output_are_an_error_in_check(tmp_path: Path) -> None:
    path = write(tmp_path, """
[services.left]
kind = "pwm_servo"
settings = { channels = [{ name = "rudder" }] }

[services.right]
kind = "pwm_servo"
settings = { channels = [{ name = "esc" }] }

[devices.rudder]
address = "pwm://pwmchip0/1"

[devices.esc]
address = "pwm://pwmchip0/1"
""")
    found = [p for p in errors_of(check_profile(path)) if "one output" in p.message]
    assert found and "service 'right'" in found[0].message and "service 'left'" in found[0].message


def test_a_channels_or_update_hz_change_the_next_start_would_refuse_is_not_saved(tmp_path: Path,
                                                                                 lcm_url: str) -> None:
    chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=4)
    profile = pwm_profile(tmp_path, {"rudder": f"mock+pwm://{chip}/0", "spare": f"mock+pwm://{chip}/0"})
    svc = PwmServoDriver("drive", profile=profile, config_path=tmp_path / "drive.toml",
                         settings={"channels": [{"name": "rudder"}]})
    try:
        svc.check_config()
        ok, reason = svc.config.try_set("channels", [{"name": "rudder"}, {"name": "winch"}])
        assert not ok and "channel 'winch'" in reason and "[devices.winch] address" in reason
        ok, reason = svc.config.try_set("channels", [{"name": "rudder"}, {"name": "spare"}])
        assert not ok and "one output" in reason
        ok, reason = svc.config.try_set("update_hz", 5000.0)
        assert not ok and "update_hz" in reason
        assert svc.config["channels"] == [{"name": "rudder"}] and svc.config["update_hz"] == 50.0
        assert not (tmp_path / "drive.toml").exists() or "winch" not in (tmp_path / "drive.toml").read_text()
        ok, _ = svc.config.try_set("update_hz", 200.0)
        assert ok
    finally:
        svc.transport.stop()


# ---- 5: a live bus change parks the old controllers first ----------------------------------------------
def test_before_close_gets_the_old_port_still_open_and_a_failing_hook_does_not_stop_the_reopen(
        tmp_path: Path) -> None:
    ptys = {name: os.openpty() for name in ("a", "b")}
    for name, (_master, slave) in ptys.items():
        (tmp_path / name).symlink_to(os.ttyname(slave))
    profile = VehicleProfile(path=None, devices={"gps": {"address": f"mock+serial://{tmp_path / 'a'}?baud=9600"}})
    owner = Owner(profile)
    parked: list[tuple[str, bool]] = []

    def park(port: Any) -> None:
        parked.append((port.address, port.is_open))
        port.write(b"neutral\n")
        raise OSError("and then the hook fails")

    link: DeviceLink[Any] = DeviceLink(owner, device=lambda: "gps", raw_type=t.RawSerial, before_close=park)
    link.start()
    try:
        wait_until(lambda: _opened(link), message="the first port open")
        owner.profile = VehicleProfile(path=None, devices={"gps": {"address": f"mock+serial://{tmp_path / 'b'}"}})
        assert link.refresh() is True
        assert parked == [(str(tmp_path / "a"), True)]
        assert os.read(ptys["a"][0], 100).endswith(b"neutral\n")      # written on the old port, before its close
        assert wait_until(lambda: _opened(link), message="the new port open").address == str(tmp_path / "b")
    finally:
        link.close()
        for master, slave in ptys.values():
            os.close(master)
            os.close(slave)


def _opened(link: DeviceLink[Any]) -> Any:
    try:
        return link.get()
    except PortUnavailable:
        return None


def test_a_bus_change_sends_zero_and_idle_to_the_old_controllers_before_closing(tmp_path: Path,
                                                                               lcm_url: str) -> None:
    old, new = (f"review-{name}-{random.randint(0, 1 << 30)}" for name in ("old", "new"))
    vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0)
    node = OdriveCanNode(vehicle, side="left", node_id=3, interface="virtual", channel=old, vel_limit=10.0)
    profile = VehicleProfile(path=None, devices={"winch_old": {"address": f"can://virtual/{old}"},
                                                 "winch_new": {"address": f"can://virtual/{new}"}})
    svc = OdriveCanMotor("winch", profile=profile, config_path=tmp_path / "winch.toml", settings={
        "device": "winch_old", "actuators": ["winch"], "node_ids": [3], "directions": [1],
        "wheel_radius_m": [0.1], "odometry": False, "status_poll_s": 0.0, "rc_gating": False,
        "hw_watchdog": False, "idle_on_stop": True, "command_timeout_s": 0.5})
    runner = threading.Thread(target=svc.run, daemon=True)
    vehicle.start()
    node.start()
    try:
        svc.start()
        runner.start()
        wait_until(lambda: svc.health_details().get("winch.phase") == "armed", timeout=20, message="axis armed")
        svc.on_percentage("winch", 50.0)
        wait_until(lambda: node.input_vel > 0.0, timeout=10, message="the winch turning")
        assert svc.config.set("device", "winch_new")   # another device: the other bus
        svc.on_config_change("device", "winch_new")
        wait_until(lambda: svc.health_details()["address"].endswith(new), timeout=10, message="the new bus")
        wait_until(lambda: node.input_vel == 0.0 and node.axis_state == AxisState.IDLE, timeout=10,
                   message="zero and IDLE on the old bus (its watchdog is off: nothing else would stop it)")
    finally:
        svc.stop()
        runner.join(timeout=10)
        svc.kill()
        svc.transport.stop()
        node.stop()
        vehicle.stop()
