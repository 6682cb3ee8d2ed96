"""`u2sa install` runs the offline check before it loads anything: its refusal is the check's whole list
(file, key, fix), and --force goes past every error but a [safety] one or a profile that does not load."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from u2sa_hw.install.deploy import install
from u2sa_hw.install.system import InstallError

U2SA = Path(sys.executable).with_name("u2sa")

PROFILE = """\
[vehicle]
name = "rover"
origin = { lat = 29.1895, lon = -81.0483, alt = 10.0 }

[services.gps]
kind = "gps_nmea"

[devices.gps]
address = "serial:///dev/u2sa/gps?baud=9600&usb=1546:01a7"

[services.compass]
kind = "compass_serial"
settings = { format = "nmea" }

[devices.compass]
address = "serial:///dev/u2sa/compass?baud=4800&usb=0403:6001"

[services.estimator]
kind = "state_estimator"

[services.hsm]
kind = "hsm"
"""
BAUD = ('settings = { format = "nmea" }', 'settings = { format = "nmea", baudrate = "9600" }')


@pytest.fixture()
def vehicle(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.delenv("U2SA_UDEV_RULES_DIRS", raising=False)   # install points the check at the staged root
    path = tmp_path / "src" / "vehicle.toml"
    (path.parent / "config").mkdir(parents=True)
    path.write_text(PROFILE)
    return path


def change(vehicle: Path, *changes: tuple[str, str]) -> Path:
    text = vehicle.read_text()
    for old, new in changes:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    vehicle.write_text(text)
    return vehicle


def test_a_wrong_setting_is_refused_with_the_checks_line_naming_file_service_and_fix(vehicle: Path,
                                                                                    tmp_path: Path) -> None:
    change(vehicle, BAUD)
    root = tmp_path / "root"
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none")
    text = str(err.value)
    assert "\n" not in text, text
    assert f"error: {vehicle} [services.compass.settings.baudrate]: expects int, got str '9600'" in text
    # the check's fix for it (a type, or the baud rates the driver declares): whatever it is, it is on the line
    assert "fix: write an int like baudrate = " in text or "fix: use one of 1200, 2400, 4800, 9600" in text
    assert "pass --force" in text
    assert not root.exists()


def test_every_problem_is_listed_in_one_refusal(vehicle: Path, tmp_path: Path) -> None:
    """A wrong setting, a wrong address and a [safety] mistake: every one, though the loader stops at [safety]."""
    change(vehicle, BAUD, ("baud=4800&usb=0403:6001", "bud=4800&usb=0403:6001"))
    vehicle.write_text(vehicle.read_text() + '\n[safety]\non_check_lost = "stop"\n')
    root = tmp_path / "root"
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none")
    lines = str(err.value).splitlines()
    assert "3 problem(s)" in lines[0], lines
    assert any("[services.compass.settings.baudrate]" in line for line in lines)
    assert any("[devices.compass]" in line and "did you mean 'baud'?" in line for line in lines)
    assert any("[safety]" in line and "'on_check_lost' = 'stop'" in line for line in lines)
    assert not root.exists()


def test_force_installs_past_a_wrong_setting_and_says_it(vehicle: Path, tmp_path: Path) -> None:
    change(vehicle, BAUD)
    root = tmp_path / "root"
    done = subprocess.run([str(U2SA), "install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "none",
                           "--force"], capture_output=True, text=True, timeout=180, env=dict(os.environ))
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"warning: {vehicle} [services.compass.settings.baudrate]" in done.stderr
    assert "warning: error:" not in done.stderr and "warning: warning:" not in done.stderr
    assert (root / "etc/u2sa/vehicle.toml").is_file()
    rules = (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text()
    assert 'SYMLINK+="u2sa/compass"' in rules and 'SYMLINK+="u2sa/gps"' in rules   # the devices are still read


def test_force_never_goes_past_a_safety_error_or_a_profile_that_does_not_load(vehicle: Path, tmp_path: Path) -> None:
    root = tmp_path / "root"
    vehicle.write_text(PROFILE + '\n[safety]\non_check_lost = "stop"\n')
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none", force=True)
    assert "[safety]: 'on_check_lost' = 'stop'" in str(err.value)
    assert "a vehicle whose [safety] table is wrong is never installed" in str(err.value)
    vehicle.write_text(PROFILE.replace('name = "rover"', 'nmae = "rover"'))
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none", force=True)
    assert f"error: {vehicle} [vehicle.nmae]: unknown key 'nmae' (did you mean 'name'?)" in str(err.value)
    assert "the profile does not load" in str(err.value)
    assert not root.exists()


MISSION = ('\n[services.mission]\nkind = "mission_manager"\nsettings = { mission_file = "missing.xml" }\n')
SPARE = '\n[devices.spare]\naddress = "serial:///dev/u2sa/spare?baud=9600&usb=1a86:7523"\n'


def u2sa_install(vehicle: Path, root: Path, *more: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(U2SA), "install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "none",
                           *more], capture_output=True, text=True, timeout=180, env=dict(os.environ))


def mission_line(vehicle: Path) -> str:
    """The check's line for the missing mission (without its severity)."""
    return (f"{vehicle} [services.mission.settings.mission_file]: file {vehicle.parent / 'missing.xml'} does not "
            "exist (mission_file = 'missing.xml' in the profile's settings); fix: correct the path (relative to the "
            "profile's directory) or add the file")


def test_a_missing_mission_is_refused_once_in_the_checks_line(vehicle: Path, tmp_path: Path) -> None:
    """The check and install's own file check both find it: the refusal says it once, the check's way."""
    vehicle.write_text(PROFILE + MISSION)
    root = tmp_path / "root"
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none")
    assert str(err.value) == (f"refusing to install {vehicle}: error: {mission_line(vehicle)} (u2sa check --vehicle "
                              f"{vehicle}; pass --force to install anyway)")
    change(vehicle, BAUD)
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none")
    lines = str(err.value).splitlines()
    assert lines[0] == (f"refusing to install {vehicle}: 2 problem(s); fix them (u2sa check --vehicle {vehicle}) or "
                        "pass --force to install anyway:")
    assert len(lines) == 3 and lines[1].startswith(f"  error: {vehicle} [services.compass.settings.baudrate]: ")
    assert lines[2] == f"  error: {mission_line(vehicle)}"
    assert not root.exists()


def test_force_says_each_problem_once_with_one_severity(vehicle: Path, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The check's errors and warnings are "warning: FILE [KEY]: ..." (never "warning: error: ..."), and what
    install could not do is "not done:" in the check's line, not also a warning."""
    from u2sa_hw.check import check_profile
    from u2sa_hw.install.preflight import unlabelled

    change(vehicle, BAUD)
    vehicle.write_text(vehicle.read_text() + MISSION + SPARE)
    root = tmp_path / "root"
    done = u2sa_install(vehicle, root, "--force")
    assert done.returncode == 1, done.stdout + done.stderr
    monkeypatch.setenv("U2SA_UDEV_RULES_DIRS", ":".join(str(root / d) for d in (
        "etc/udev/rules.d", "run/udev/rules.d", "lib/udev/rules.d", "usr/lib/udev/rules.d")))
    problems = check_profile(vehicle)   # as install's check saw it
    baudrate = next(p for p in problems if p.key == "services.compass.settings.baudrate")
    assert done.stderr.splitlines() == [
        f"warning: {unlabelled(baudrate)}",
        f"warning: {vehicle} [devices.spare]: address serial:///dev/u2sa/spare?baud=9600&usb=1a86:7523 is used by no "
        "enabled service; fix: set device = \"spare\" in the service that drives it, or remove the table (services "
        "with devices: gps (device 'gps'), compass (device 'compass'))",
        f"u2sa install: not done: {mission_line(vehicle)}",
        "u2sa install: 1 thing(s) the profile asks for could not be done; the vehicle will not run as the profile "
        "says until they are fixed"]
    assert (root / "etc/u2sa/vehicle.toml").is_file()


def test_an_old_form_device_is_said_once(vehicle: Path, tmp_path: Path) -> None:
    """The check's old-form warning; install reads the same device and does not say it again."""
    vehicle.write_text(PROFILE + '\n[services.imu]\nkind = "imu_mpu9250"\nsettings = { bus = "1" }\n')
    done = u2sa_install(vehicle, tmp_path / "root")
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stderr.splitlines() == [
        f"warning: {vehicle} [services.imu]: device 'imu' is given in the old form (service settings); fix: write "
        '[devices.imu] address = "i2c://1/0x68"']


def test_an_old_form_bus_written_as_a_number_is_one_warning_with_the_new_form_under_force(vehicle: Path,
                                                                                        tmp_path: Path) -> None:
    """bus = 1: the check's type error (fix: the new form) is the one line; install reads the device as the check
    does, so the other devices' rules are still written and nothing says "no address"."""
    vehicle.write_text(PROFILE + '\n[services.imu]\nkind = "imu_mpu9250"\nsettings = { bus = 1 }\n')
    root = tmp_path / "root"
    done = u2sa_install(vehicle, root, "--force")
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stderr.splitlines() == [
        f"warning: {vehicle} [services.imu.settings.bus]: expects str, got int 1; fix: write the device\'s address in "
        'the profile in the new form: [devices.imu] address = "i2c://1/0x68" (in the old form: bus = "1")']
    rules = (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text()
    assert 'SYMLINK+="u2sa/compass"' in rules and 'SYMLINK+="u2sa/gps"' in rules
