"""The mock launcher: a profile's [devices] built around one SimVehicle, read by the real drivers.

Real parts throughout: pty links, the mock I2C bus and GPIO chip sockets, driver processes
started by the launcher on the simulation copy of the profile, LCM multicast on a port of
the test's own.
"""

from __future__ import annotations

import math
import signal
import subprocess
import threading
from pathlib import Path

import pytest

from conftest import U2SA, wait_until
from u2sa_hw.mocks.launcher import MockLauncher
from u2sa_hw.mocks.sim_context import DeviceError
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.launcher import Launcher
from u2sa_hw.simulation.profile import effective_configs, write_sim_profile
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.loader import load_profile
from u2sa_hw.bus.udp_ports import private_udp_port

SENSORS = """
[vehicle]
name = "bench"
origin = { lat = 29.1895, lon = -81.0483, alt = 10.0 }

[services.gps]
kind = "gps_nmea"

[services.imu]
kind = "imu_mpu9250"
settings = { rate_hz = 20.0, calibrate_samples = 10 }

[simulation]
start = { north = 5.0, east = -3.0, heading_deg = 90.0 }
can_udp_port = 43000

[devices.gps]
address = "serial:///dev/u2sa/gps?baud=9600"
mock = "nmea_gps"
options = { horizontal_sigma_m = 0.1, rate_hz = 5 }

[devices.imu]
address = "i2c://1/0x69"
mock = "mpu9250"
"""

def profile_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "vehicle.toml"
    path.write_text(text)
    return path


def test_drivers_read_the_mocks_through_the_simulation_profile(tmp_path: Path, lcm_url: str) -> None:
    profile = load_profile(profile_file(tmp_path, SENSORS))
    mocks = MockLauncher(profile, device_dir=tmp_path / "dev", service_configs=effective_configs(profile))
    assert mocks.addresses == {"gps": f"mock+serial://{tmp_path / 'dev' / 'gps'}?baud=9600",
                               "imu": f"mock+i2c://{tmp_path / 'dev' / 'i2c-1.sock'}/0x69"}
    sim_path = write_sim_profile(profile, run_dir=tmp_path / "run", addresses=mocks.addresses, lcm_url=lcm_url)
    seen: dict[str, t.StateInformation] = {}
    bus = Transport(lcm_url, name="test")
    bus.subscribe(ch.STATE_INFO, t.StateInformation, lambda _c, m: seen.__setitem__(m.header.source, m))
    bus.start()
    mocks.start()
    launcher = Launcher(load_profile(sim_path), grace_s=3.0, output=lambda _n, _l: None)
    try:
        launcher.start()
        gps = wait_until(lambda: seen.get("gps"), timeout=30, message="STATE_INFO from the GPS driver")
        assert math.hypot(gps.x - 5.0, gps.y + 3.0) < 1.0   # the mock's start position, NED about the origin
        imu = wait_until(lambda: seen.get("imu"), timeout=30, message="STATE_INFO from the IMU driver")
        assert imu.has("psi_dot")
        chip = mocks.context.i2c_buses[str(tmp_path / "dev" / "i2c-1.sock")].chip(0x69)
        assert chip.samples > 0   # the driver burst-read the chip the profile's address names
    finally:
        launcher.stop(timeout=10)
        bus.stop()
        mocks.stop()
    assert not (tmp_path / "dev" / "gps").exists()


def test_u2sa_mock_prints_the_addresses_and_cleans_up_on_ctrl_c(tmp_path: Path) -> None:
    vehicle = profile_file(tmp_path, SENSORS)
    run_dir = tmp_path / "sim"
    proc = subprocess.Popen([*U2SA, "mock", "--vehicle", str(vehicle), "--run-dir", str(run_dir),
                             "--can-port", str(private_udp_port())],
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        wait_until(lambda: any(line.startswith("run the stack on it") for line in lines), timeout=30,
                   message="u2sa mock to print its addresses")
        text = "".join(lines)
        assert f"mock+serial://{run_dir / 'dev' / 'gps'}?baud=9600  (pty for /dev/u2sa/gps)" in text
        assert f"mock+i2c://{run_dir / 'dev' / 'i2c-1.sock'}/0x69" in text
        assert (run_dir / "dev" / "gps").is_symlink()
        sim_profile = load_profile(run_dir / "vehicle.toml")   # only the device's address changes
        assert sim_profile.devices["gps"]["address"] == f"mock+serial://{run_dir / 'dev' / 'gps'}?baud=9600"
        assert sim_profile.services["gps"].settings == {}   # the services' settings stay as they were
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15) == 0
    assert not (run_dir / "dev" / "gps").exists()


@pytest.mark.parametrize("change, error", [
    (('mock = "nmea_gps"', 'mock = "sextant"'), r"\[devices.gps\]: mock = 'sextant' is not a mock kind; known: .*nmea_gps"),
    (('[devices.gps]\n', '[devices.gps]\nservice = "gnss"\n'), r"service = 'gnss' is not a service of the profile"),
    (('i2c://1/0x69', 'i2c://1/0x40'), None),
    (('options = { horizontal_sigma_m = 0.1, rate_hz = 5 }', 'options = { sigma = 1 }'),
     r"unknown option\(s\) sigma for NmeaGpsDevice; valid: .*horizontal_sigma_m"),
])
def test_bad_device_tables_name_the_table_and_the_fix(tmp_path: Path, change: tuple[str, str],
                                                      error: str | None) -> None:
    text = SENSORS.replace(*change)
    if error is None:   # a second chip on the IMU's address
        text += '\n[services.pan]\nkind = "pwm_servo"\nsettings = { channels = [ { name = "pan" } ] }\n' \
                '[devices.pan]\naddress = "pca9685://1/0x40/0"\nmock = "pca9685"\n'
        error = r"devices.pan: I2C address 0x40 on mock:.*i2c-1.sock is already taken by devices.imu"
    profile = load_profile(profile_file(tmp_path, text))
    with pytest.raises(DeviceError, match=error):
        MockLauncher(profile, device_dir=tmp_path / "dev")


def test_simulation_copy_points_config_files_at_the_mocks_and_keeps_the_originals(tmp_path: Path) -> None:
    config = tmp_path / "config"
    config.mkdir()
    (config / "gps.toml").write_text('device = "usb3"\nuere_m = 4.0\n')   # the device named in the config file
    (config / "mission.toml").write_text('mission_file = "missions/loop.xml"\n')
    text = SENSORS + '\n[devices.usb3]\naddress = "serial:///dev/ttyUSB3?baud=9600"\nmock = "nmea_gps"\n' \
        '\n[services.mission]\nkind = "mission_manager"\n' \
        '\n[services.view]\nkind = "foxglove_bridge"\nsettings = { token_file = "keys/view.token" }\n'
    profile = load_profile(profile_file(tmp_path, text))
    mocks = MockLauncher(profile, device_dir=tmp_path / "dev", service_configs=effective_configs(profile))
    mock_gps = f"mock+serial://{tmp_path / 'dev' / 'ttyUSB3'}?baud=9600"   # named after the real device
    assert mocks.addresses["usb3"] == mock_gps
    sim = load_profile(write_sim_profile(profile, run_dir=tmp_path / "run", addresses=mocks.addresses,
                                         lcm_url="udpm://239.255.76.67:7001?ttl=0"))
    copied = effective_configs(sim)
    assert sim.devices["usb3"]["address"] == mock_gps and copied["gps"]["uere_m"] == 4.0
    assert copied["mission"]["mission_file"] == str(tmp_path / "missions" / "loop.xml")
    # every setting declared a file (field(file=...)) follows the profile, not only the mission's
    assert copied["view"]["token_file"] == str(tmp_path / "keys" / "view.token")
    assert sim.lcm_url == "udpm://239.255.76.67:7001?ttl=0" and sim.data_dir == tmp_path / "run" / "data"
    assert (config / "gps.toml").read_text() == 'device = "usb3"\nuere_m = 4.0\n'   # the user's file untouched
