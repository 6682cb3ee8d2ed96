"""`u2sa check` says every problem, and nothing false: one mistake never hides another or invents one.

Each test starts from the ground vehicle example (copied, with its files) and changes a few
lines of its profile; the real registry, the real safety modules and the mock catalog read it.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from conftest import REPO
from u2sa_hw.check import WARNING, check_profile, errors_of

EXAMPLE = REPO / "examples" / "ground_vehicle"


def example(tmp_path: Path, *changes: tuple[str, str]) -> Path:
    """The example copied into *tmp_path*, each (old, new) of *changes* made once in its profile."""
    copy = tmp_path / "vehicle"
    shutil.copytree(EXAMPLE, copy)
    path = copy / "vehicle.toml"
    text = path.read_text()
    for old, new in changes:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path.write_text(text)
    return path


@pytest.fixture(autouse=True)
def _no_host_rules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rules = tmp_path / "rules.d"
    rules.mkdir()
    monkeypatch.setenv("U2SA_UDEV_RULES_DIRS", str(rules))   # this machine's own udev rules do not matter


def keys(problems: list) -> list[str]:
    return [p.key for p in problems]


DEVICE_TYPO = ('mock = "mpu9250"', 'mokc = "mpu9250"')
SAFETY_TYPO = ("rc_mode_timeout_ms = 250", "rc_mode_timout_ms = 250")
ADDRESS_TYPO = ("can://socketcan/can0?bitrate=500000", "can://socketcan/can0?bitrat=500000")


def test_a_device_typo_and_a_safety_typo_are_both_reported_and_the_addresses_still_checked(tmp_path: Path) -> None:
    path = example(tmp_path, DEVICE_TYPO, SAFETY_TYPO, ADDRESS_TYPO)
    problems = check_profile(path)
    errors = errors_of(problems)
    text = "\n".join(map(str, problems))
    assert "devices.imu.mokc" in keys(errors) and "did you mean 'mock'" in text
    assert any(p.key == "safety" and "rc_mode_timout_ms" in p.message for p in errors), text
    # the bad table did not stop the address check: another device's misspelt parameter is found too
    assert any(p.key == "devices.wheels" and "unknown parameter 'bitrat' (did you mean 'bitrate'?)" in p.message
               for p in errors), text
    assert len(errors) == 3, text


def test_a_profile_the_loader_refuses_still_gets_its_safety_and_devices_checked(tmp_path: Path) -> None:
    """The loader stops at the vehicle typo and at [safety]; the lenient copy leaves both out and checks on."""
    path = example(tmp_path, ('log_level = "info"', 'log_levle = "info"'), DEVICE_TYPO, SAFETY_TYPO, ADDRESS_TYPO,
                   ("gps = { max_sigma_m = 5.0 }", "gps = { max_sigm_m = 5.0 }"))
    errors = errors_of(check_profile(path))
    text = "\n".join(map(str, errors))
    for key, word in (("vehicle.log_levle", "log_level"), ("devices.imu.mokc", "mock"),
                      ("safety", "rc_mode_timout_ms"), ("safety.prearm", "max_sigm_m"), ("devices.wheels", "bitrat")):
        assert any(p.key == key and word in str(p) for p in errors), f"{key} {word}:\n{text}"


def test_every_safety_problem_is_its_own_line(tmp_path: Path) -> None:
    path = example(tmp_path, SAFETY_TYPO,
                   ('on_check_lost = "neutral"', 'on_check_lost = "stop"'),
                   ("gps = { max_sigma_m = 5.0 }", 'gps = { max_sigm_m = 5.0 }\nimu = { services = ["gps"] }'),
                   ("hardware_mux = {}", 'hardware_mux = { pann = "steering", pan = "stering" }'),
                   ('throttle_channel = "throttle"', 'throttle_channel = "throtle"'),
                   ('right = "right_wheel"\nthrottle_channel', 'right = "rigth_wheel"\nthrottle_channel'))
    errors = errors_of(check_profile(path))
    text = "\n".join(map(str, errors))
    for word in ("'rc_mode_timout_ms'", "'on_check_lost' = 'stop'", "'gps.max_sigm_m'", "names service 'gps' of kind",
                 "actuator 'pann'", "'stering' is not a channel", "'throtle' is not a channel",
                 "right = 'rigth_wheel' is not an actuator"):
        assert sum(word in str(p) for p in errors) == 1, f"{word}:\n{text}"
    assert all(p.key.startswith("safety") for p in errors), text
    assert len(errors) == 8, text


def test_a_simulation_typo_is_one_line_with_the_did_you_mean(tmp_path: Path) -> None:
    path = example(tmp_path, ("seed = 1 ", "sede = 1 "))
    for for_sim in (False, True):
        errors = errors_of(check_profile(path, for_sim=for_sim))
        assert [(p.key, p.message) for p in errors] == \
            [("simulation.sede", "unknown key 'sede' (did you mean 'seed'?)")], "\n".join(map(str, errors))


def test_a_service_setting_error_does_not_make_every_device_lack_a_mock(tmp_path: Path) -> None:
    path = example(tmp_path, ('settings = { format = "nmea" }', 'settings = { format = "nmea", heading_sigma_deg = "1" }'))
    errors = errors_of(check_profile(path, for_sim=True))
    assert keys(errors) == ["services.compass.settings.heading_sigma_deg"], "\n".join(map(str, errors))


def test_with_a_service_setting_error_a_device_that_truly_has_no_mock_is_still_named(tmp_path: Path) -> None:
    path = example(tmp_path, ('settings = { format = "nmea" }', 'settings = { format = "nmea", heading_sigma_deg = "1" }'),
                   ('mock = "mpu9250"\n', ""))
    errors = errors_of(check_profile(path, for_sim=True))
    assert keys(errors) == ["services.compass.settings.heading_sigma_deg", "devices.imu"], "\n".join(map(str, errors))
    assert "device 'imu' of service 'imu' (imu_mpu9250) has no mock" in errors[1].message
    assert 'mock = "mpu9250"' in errors[1].fix


def test_a_socketcan_address_without_a_bitrate_is_a_warning_on_the_vehicle(tmp_path: Path) -> None:
    path = example(tmp_path, ("can://socketcan/can0?bitrate=500000", "can://socketcan/can0"))
    problems = check_profile(path)
    assert errors_of(problems) == []
    (warning,) = [p for p in problems if "bitrate" in p.message]
    assert (warning.severity, warning.key) == (WARNING, "devices.wheels.address")
    assert "can0 does not come up at boot" in warning.message
    assert "can://socketcan/can0?bitrate=500000" in warning.fix
    assert not [p for p in check_profile(path, for_sim=True) if "bitrate" in p.message]   # a mock stands in
    assert not [p for p in check_profile(EXAMPLE / "vehicle.toml") if "bitrate" in p.message]
