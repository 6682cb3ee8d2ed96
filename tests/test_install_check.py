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
    assert "fix: write an int like baudrate = " in text and "pass --force" in text
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
    assert f"warning: error: {vehicle} [services.compass.settings.baudrate]" in done.stderr
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
