"""DeviceLink (one device lifecycle) on real ptys, and profile_devices (one address per device, old profiles)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest

from conftest import REPO, wait_until
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import ConfigError
from u2sa_hw.profile.devices import profile_devices
from u2sa_hw.ports import PortClosed, PortUnavailable
from u2sa_hw.ports.address import AddressError
from u2sa_hw.ports.device_link import DeviceLink, device_setting
from u2sa_hw.ports.tap import raw_channel
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile
from u2sa_hw.profile.loader import load_profile


class Pty:
    """A pty whose slave is reached through a symlink, as a mock device or udev makes one."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master, self.slave = os.openpty()
        if link.is_symlink():
            link.unlink()
        link.symlink_to(os.ttyname(self.slave))

    def unplug(self) -> None:
        os.close(self.master)
        os.close(self.slave)
        self.link.unlink()


class Owner:
    """What a DeviceLink needs of its driver: profile, config, publish, register_publisher."""

    def __init__(self, profile: VehicleProfile, *, record_raw: bool = True) -> None:
        self.name = "gps"
        self.profile = profile
        self.config: dict[str, Any] = {"record_raw": record_raw}
        self.published: list[tuple[str, Any]] = []
        self.registered: list[tuple[str, type]] = []

    def publish(self, channel: str, msg: Any) -> None:
        self.published.append((channel, msg))

    def register_publisher(self, channel: str, kind: type) -> None:
        self.registered.append((channel, kind))


def profile_with(tmp_path: Path, devices: dict[str, str]) -> VehicleProfile:
    return VehicleProfile(path=tmp_path / "vehicle.toml", devices={n: {"address": a} for n, a in devices.items()})


def link_for(owner: Owner, device: str = "gps") -> DeviceLink:
    return DeviceLink(owner, device=lambda: device, raw_type=t.RawSerial,
                      options=lambda: {"timeout": 0.2}, initial_backoff=0.05, max_backoff=0.2)


def opened(link: DeviceLink) -> Any:
    """The open port, once the link (re)opened it (pyserial drops what arrived before the open, as a UART does)."""
    def attempt() -> Any:
        try:
            return link.get()
        except PortUnavailable:
            return None
    return wait_until(attempt, timeout=10, message="the link to open its device")


def read_line(link: DeviceLink) -> bytes:
    """The next line through the link, reopening as the link allows."""
    def attempt() -> bytes:
        try:
            return link.call(lambda port: port.readline())
        except (PortUnavailable, PortClosed):
            return b""
    return wait_until(attempt, timeout=10, message="a line through the link")


def test_unplug_and_replug_a_pty_under_the_link(tmp_path: Path) -> None:
    pty = Pty(tmp_path / "gps")
    owner = Owner(profile_with(tmp_path, {"gps": f"mock+serial://{tmp_path / 'gps'}?baud=4800"}))
    link = link_for(owner)
    link.start()
    try:
        assert owner.registered == [(raw_channel("gps"), t.RawSerial)]
        opened(link)
        os.write(pty.master, b"$GPGGA,1*00\r\n")
        assert read_line(link) == b"$GPGGA,1*00\r\n"
        assert link.health()["port"] == "open" and link.health()["address"].endswith("?baud=4800")
        assert [c for c, _ in owner.published] == ["RAW.gps"]     # the tap, under the one naming rule
        pty.unplug()
        with pytest.raises((PortClosed, PortUnavailable)):
            link.call(lambda port: port.readline())
        down = link.health()
        assert down["port"] == "down" and down["port_losses"] == 1 and "fix:" in down["port_error"]
        assert link.reason() == "port down"
        pty = Pty(tmp_path / "gps")                                # replugged: a new pty at the same link
        opened(link)
        os.write(pty.master, b"$GPGGA,3*00\r\n")
        assert read_line(link).startswith(b"$GPGGA,")
        assert link.health()["reconnects"] >= 1 and link.health()["port_error"] == ""
    finally:
        link.close()
        pty.unplug()


def test_an_address_change_reopens_on_the_new_device(tmp_path: Path) -> None:
    first, second = Pty(tmp_path / "a"), Pty(tmp_path / "b")
    owner = Owner(profile_with(tmp_path, {"gps": f"serial://{tmp_path / 'a'}?baud=9600"}))
    link = link_for(owner)
    link.start()
    try:
        opened(link)
        os.write(first.master, b"from a\n")
        assert read_line(link) == b"from a\n"
        assert link.refresh() is False                             # nothing changed: the port stays
        owner.profile = profile_with(tmp_path, {"gps": f"serial://{tmp_path / 'b'}?baud=9600"})   # a new address
        assert link.refresh() is True and link.address.serial_path == str(tmp_path / "b")
        opened(link)
        os.write(second.master, b"from b\n")
        assert read_line(link) == b"from b\n"
        owner.profile = profile_with(tmp_path, {"gps": f"serial://{tmp_path / 'a'}?baud=9600"})
        assert link.refresh() is True, "back to the first address"
        opened(link)
        os.write(first.master, b"a again\n")
        assert read_line(link) == b"a again\n"
    finally:
        link.close()
        first.unplug()
        second.unplug()


def test_no_address_is_one_line_naming_the_device_and_the_table(tmp_path: Path) -> None:
    link = link_for(Owner(VehicleProfile(path=None)), device="compass")
    assert "device 'compass'" in link.check() and "[devices.compass] address" in link.check()
    with pytest.raises(AddressError):
        link.start()


def test_recording_off_publishes_nothing(tmp_path: Path) -> None:
    pty = Pty(tmp_path / "gps")
    owner = Owner(profile_with(tmp_path, {"gps": f"serial://{tmp_path / 'gps'}"}), record_raw=False)
    link = link_for(owner)
    link.start()
    try:
        opened(link)
        os.write(pty.master, b"x\n")
        assert read_line(link) == b"x\n" and owner.published == [] and owner.registered == []
    finally:
        link.close()
        pty.unplug()


def test_device_setting_order() -> None:
    assert device_setting({"device": " wheels ", "device_name": "x"}, "svc") == "wheels"
    assert device_setting({"device": "", "device_name": "old"}, "svc") == "old"
    assert device_setting({}, "svc") == "svc"


# ---- profile_devices ----------------------------------------------------------------------------
NEW = """
[vehicle]
name = "new"

[services.gps]
kind = "gps_nmea"
settings = { device = "gnss" }

[services.wheels]
kind = "odrive_can"

[services.imu]
kind = "imu_mpu9250"

[services.rc]
kind = "rc_mux"
settings = { channels = "throttle=5,mode=13", mode_channel = "mode", enable_line = 21 }

[services.drive]
kind = "pwm_servo"
settings = { channels = [ { name = "rudder" }, { name = "throttle", device = "esc" } ] }

[devices.gnss]
address = "serial:///dev/ttyUSB0?baud=4800"
mock = "nmea_gps"

[devices.wheels]
address = "can://socketcan/can1?bitrate=250000"

[devices.imu]
address = "i2c://3/0x69"

[devices.rc]
address = "gpio://gpiochip2/5,13,21"

[devices.rudder]
address = "pca9685://1/0x40/2"
mock = "pca9685"

[devices.esc]
address = "pwm://pwmchip0/1"
mock = "sysfs_pwm"
"""


def test_each_device_is_its_own_table_named_by_its_service(tmp_path: Path) -> None:
    (tmp_path / "vehicle.toml").write_text(NEW)
    entries = profile_devices(load_profile(tmp_path / "vehicle.toml"))
    assert {n: (e.address.url, e.service, e.mock) for n, e in entries.items()} == {
        "gnss": ("serial:///dev/ttyUSB0?baud=4800", "gps", "nmea_gps"),
        "wheels": ("can://socketcan/can1?bitrate=250000", "wheels", None),
        "imu": ("i2c://3/0x69", "imu", None),
        "rc": ("gpio://gpiochip2/5,13,21", "rc", None),
        "rudder": ("pca9685://1/0x40/2", "drive", "pca9685"),
        "esc": ("pwm://pwmchip0/1", "drive", "sysfs_pwm"),
    }
    assert all(e.used and e.table == n for n, e in entries.items())


@pytest.mark.parametrize("service, setting", [
    ("gps", 'port = "/dev/ttyUSB0", baudrate = 4800'), ("wheels", 'interface = "socketcan", channel = "can1"'),
    ("imu", 'bus = "3", address = 0x69'), ("rc", 'chip = "/dev/gpiochip2"'),
])
def test_an_old_form_profile_is_refused_naming_the_new_form(tmp_path: Path, service: str, setting: str) -> None:
    """Version 0.1 retires the old form: a setting that spread the address over the service is one error with
    the new form, never an address derived from it."""
    text = NEW.replace(f"[services.{service}]\n", f"[services.{service}]\nconfig = \"{service}.toml\"\n")
    (tmp_path / "vehicle.toml").write_text(text)
    (tmp_path / f"{service}.toml").write_text(setting.replace(", ", "\n") + "\n")
    key = setting.split(" = ")[0]
    with pytest.raises(ConfigError, match=rf"'{key}' is the old form: name a device instead: \[devices\.") as info:
        profile_devices(load_profile(tmp_path / "vehicle.toml"))
    assert "\n" not in str(info.value) and "(docs/ports.md)" in str(info.value)


@pytest.mark.parametrize("key, value, param", [("usb", '{ vendor = "1546", product = "01a7" }', "usb=1546:01a7"),
                                               ("can", "{ bitrate = 500000 }", "bitrate=500000")])
def test_an_old_form_device_table_key_is_refused_naming_the_address_parameter(tmp_path: Path, key: str, value: str,
                                                                              param: str) -> None:
    (tmp_path / "vehicle.toml").write_text(NEW.replace('[devices.imu]\n', f'[devices.imu]\n{key} = {value}\n'))
    with pytest.raises(ProfileError, match=rf"\[devices.imu\]: '{key}' is the old form: write it into .*{param}"):
        profile_devices(load_profile(tmp_path / "vehicle.toml"))


@pytest.mark.parametrize("table,error", [
    ('address = "serial:///dev/x"\nmokc = "nmea_gps"', r"\[devices.gnss\]: unknown key 'mokc'; did you mean 'mock'\?"),
    ('address = "/dev/ttyUSB0"', r"\[devices.gnss\]: device 'gnss': address '/dev/ttyUSB0': not a URL .*"
                                 r"did you mean 'serial:///dev/ttyUSB0'"),
    ('address = 5', r"\[devices.gnss\]: address must be a str, not int"),
])
def test_a_bad_device_table_is_one_line_with_the_fix(tmp_path: Path, table: str, error: str) -> None:
    text = NEW.replace('[devices.gnss]\naddress = "serial:///dev/ttyUSB0?baud=4800"\nmock = "nmea_gps"\n',
                       f"[devices.gnss]\n{table}\n")
    (tmp_path / "vehicle.toml").write_text(text)
    with pytest.raises(ProfileError, match=error) as info:
        profile_devices(load_profile(tmp_path / "vehicle.toml"))
    assert "\n" not in str(info.value)


def test_a_device_no_address_gives_names_the_line_to_add(tmp_path: Path) -> None:
    (tmp_path / "vehicle.toml").write_text('[vehicle]\nname = "x"\n[services.gps]\nkind = "gps_nmea"\n')
    with pytest.raises(ProfileError, match=r"device 'gps' of service 'gps' has no address; add \[devices.gps\] "
                                           r"address = "):
        profile_devices(load_profile(tmp_path / "vehicle.toml"))


def test_start_imports_what_the_open_will_so_the_first_open_after_ready_is_quick(tmp_path: Path) -> None:
    """CI: a motor driver's first open imported python-can (some 160 modules) in its first loop turn, after
    READY=1 had armed the watchdog; on a loaded machine that took over 2 s without a ping and the launcher
    killed it. ``start()`` runs in setup, before READY: the import is paid there. A fresh interpreter, since
    this one may have imported python-can already; nothing is opened."""
    code = textwrap.dedent("""
        import sys
        from pathlib import Path
        from u2sa_hw import lcmtypes as t
        from u2sa_hw.ports.device_link import DeviceLink
        from u2sa_hw.profile.vehicle import VehicleProfile

        class Owner:
            name = "wheels"
            config = {"record_raw": False}
            profile = VehicleProfile(path=Path(sys.argv[1]),
                                     devices={"wheels": {"address": "mock+can://udp_multicast/239.74.163.2?port=17280"}})
            def publish(self, channel, msg): pass
            def register_publisher(self, channel, kind): pass

        link = DeviceLink(Owner(), device=lambda: "wheels", raw_type=t.RawCanFrame)
        assert "can" not in sys.modules, "python-can imported before start()"
        link.start()
        assert link.holder.state != "open"
        print(sorted(m for m in ("can", "u2sa_hw.ports.can.port") if m in sys.modules))
    """)
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "vehicle.toml")], cwd=REPO,
                          capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[0] == "['can', 'u2sa_hw.ports.can.port']"


def test_every_kind_has_its_preload_and_each_module_exists() -> None:
    from importlib.util import find_spec

    from u2sa_hw.ports.address import KINDS
    from u2sa_hw.ports.kinds import PORT_KINDS

    assert set(PORT_KINDS) == set(KINDS)
    assert all(kind.preload for kind in PORT_KINDS.values())
    assert all(find_spec(module) is not None for kind in PORT_KINDS.values() for module in kind.preload
               if module.startswith("u2sa_hw."))
