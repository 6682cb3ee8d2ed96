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
WRONG = ('settings = { format = "nmea" }', 'settings = { format = "nmea", heading_sigma_deg = "1" }')


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
    change(vehicle, WRONG)
    root = tmp_path / "root"
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none")
    text = str(err.value)
    assert "\n" not in text, text
    assert f"error: {vehicle} [services.compass.settings.heading_sigma_deg]: expects float, got str '1'" in text
    assert "fix: write a float like heading_sigma_deg = " in text   # the check's fix for it, on the line
    assert "pass --force" in text
    assert not root.exists()


def test_every_problem_is_listed_in_one_refusal(vehicle: Path, tmp_path: Path) -> None:
    """A wrong setting, a wrong address and a [safety] mistake: every one, though the loader stops at [safety]."""
    change(vehicle, WRONG, ("baud=4800&usb=0403:6001", "bud=4800&usb=0403:6001"))
    vehicle.write_text(vehicle.read_text() + '\n[safety]\non_check_lost = "stop"\n')
    root = tmp_path / "root"
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none")
    lines = str(err.value).splitlines()
    assert "3 problem(s)" in lines[0], lines
    assert any("[services.compass.settings.heading_sigma_deg]" in line for line in lines)
    assert any("[devices.compass]" in line and "did you mean 'baud'?" in line for line in lines)
    assert any("[safety]" in line and "'on_check_lost' = 'stop'" in line for line in lines)
    assert not root.exists()


def test_force_installs_past_a_wrong_setting_and_says_it(vehicle: Path, tmp_path: Path) -> None:
    change(vehicle, WRONG)
    root = tmp_path / "root"
    done = subprocess.run([str(U2SA), "install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "none",
                           "--force"], capture_output=True, text=True, timeout=180, env=dict(os.environ))
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"warning: {vehicle} [services.compass.settings.heading_sigma_deg]" in done.stderr
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
    change(vehicle, WRONG)
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="none")
    lines = str(err.value).splitlines()
    assert lines[0] == (f"refusing to install {vehicle}: 2 problem(s); fix them (u2sa check --vehicle {vehicle}) or "
                        "pass --force to install anyway:")
    assert len(lines) == 3 and lines[1].startswith(f"  error: {vehicle} [services.compass.settings.heading_sigma_deg]: ")
    assert lines[2] == f"  error: {mission_line(vehicle)}"
    assert not root.exists()


def test_force_says_each_problem_once_with_one_severity(vehicle: Path, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The check's errors and warnings are "warning: FILE [KEY]: ..." (never "warning: error: ..."), and what
    install could not do is "not done:" in the check's line, not also a warning."""
    from u2sa_hw.check import check_profile
    from u2sa_hw.install.preflight import unlabelled

    change(vehicle, WRONG)
    vehicle.write_text(vehicle.read_text() + MISSION + SPARE)
    root = tmp_path / "root"
    done = u2sa_install(vehicle, root, "--force")
    assert done.returncode == 1, done.stdout + done.stderr
    monkeypatch.setenv("U2SA_UDEV_RULES_DIRS", ":".join(str(root / d) for d in (
        "etc/udev/rules.d", "run/udev/rules.d", "lib/udev/rules.d", "usr/lib/udev/rules.d")))
    problems = check_profile(vehicle)   # as install's check saw it
    wrong = next(p for p in problems if p.key == "services.compass.settings.heading_sigma_deg")
    assert done.stderr.splitlines() == [
        f"warning: {unlabelled(wrong)}",
        f"warning: {vehicle} [devices.spare]: address serial:///dev/u2sa/spare?baud=9600&usb=1a86:7523 is used by no "
        "enabled service; fix: set device = \"spare\" in the service that drives it, or remove the table (services "
        "with devices: gps (device 'gps'), compass (device 'compass'))",
        f"u2sa install: not done: {mission_line(vehicle)}",
        "u2sa install: 1 thing(s) the profile asks for could not be done; the vehicle will not run as the profile "
        "says until they are fixed"]
    assert (root / "etc/u2sa/vehicle.toml").is_file()


def test_an_old_form_setting_is_refused_once_with_the_new_form(vehicle: Path, tmp_path: Path) -> None:
    """The old form is retired: the check's one error names the key and the new form; install reads the
    devices as the check does, so nothing also says the device has no address."""
    vehicle.write_text(PROFILE + '\n[services.imu]\nkind = "imu_mpu9250"\nsettings = { bus = "1" }\n')
    line = (f"error: {vehicle} [services.imu.settings.bus]: 'bus' is the old form; fix: name a device instead: "
            '[devices.imu] address = "i2c://1/0x68" and device = "imu" (docs/ports.md)')
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=tmp_path / "root", venv="none")
    assert str(err.value).startswith(f"refusing to install {vehicle}: {line}"), err.value
    assert "no address" not in str(err.value)


def test_an_old_form_setting_is_one_warning_with_the_new_form_under_force(vehicle: Path, tmp_path: Path) -> None:
    """bus = 1 under --force: the check's error is the one line; the other devices' rules are still written."""
    vehicle.write_text(PROFILE + '\n[services.imu]\nkind = "imu_mpu9250"\nsettings = { bus = 1 }\n')
    root = tmp_path / "root"
    done = u2sa_install(vehicle, root, "--force")
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stderr.splitlines() == [
        f"warning: {vehicle} [services.imu.settings.bus]: 'bus' is the old form; fix: name a device instead: "
        '[devices.imu] address = "i2c://1/0x68" and device = "imu" (docs/ports.md)']
    rules = (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text()
    assert 'SYMLINK+="u2sa/compass"' in rules and 'SYMLINK+="u2sa/gps"' in rules
