"""Unknown keys and kinds in a vehicle profile, and a kind's settings checked against its fields."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import pytest

from u2sa_hw.service.validate import kind_problem, validate_config_file, validate_settings
from u2sa_hw.profile.vehicle import ProfileError
from u2sa_hw.profile.loader import SIMULATION_KEYS, SIMULATION_START_KEYS, load_profile

GOOD = """
[vehicle]
name = "bench"
log_level = "info"
origin = { lat = 1.0, lon = 2.0, alt = 0.0 }

[services.gps]
kind = "gps_nmea"
settings = { device = "gnss", uere_m = 3.0 }

[services.gps.supervision]
data_channel = "STATE_INFO"

[services.planner]
kind = "path_planner"

[services.old]
kind = "retired_camera"    # not started: its kind is not looked up
enabled = false

[simulation]
model = "differential"
start = { north = 1.0, east = 0.0, heading_deg = 0.0 }
"""


def _load(tmp_path: Path, text: str) -> object:
    path = tmp_path / "vehicle.toml"
    path.write_text(text)
    return load_profile(path)


def test_a_profile_with_only_known_keys_loads(tmp_path: Path) -> None:
    profile = _load(tmp_path, GOOD)
    assert set(profile.services) == {"gps", "planner", "old"}


@pytest.mark.parametrize("change, line", [
    (("log_level = ", "log_levle = "),
     "vehicle.toml [vehicle]: unknown key 'log_levle'; did you mean 'log_level'?"),
    (("lon = 2.0", "lng = 2.0"), "vehicle.toml [vehicle] origin: unknown key 'lng'; did you mean 'lon'?"),
    (('kind = "path_planner"', 'kind = "path_planer"'),
     "vehicle.toml [services.planner] kind: unknown service kind 'path_planer'; did you mean 'path_planner'?"),
    (('kind = "gps_nmea"', 'kind = "gps_nmea"\nenabeld = false'),
     "vehicle.toml [services.gps]: unknown key 'enabeld'; did you mean 'enabled'?"),
    (("data_channel =", "data_chanel ="),
     "vehicle.toml [services.gps.supervision]: unknown key 'data_chanel'; did you mean 'data_channel'?"),
    (('model = "differential"', 'modle = "differential"'),
     "vehicle.toml [simulation]: unknown key 'modle'; did you mean 'model'?"),
    (("heading_deg = 0.0 }", "heading = 0.0 }"),
     "vehicle.toml [simulation] start: unknown key 'heading'; did you mean 'heading_deg'?"),
    (("[simulation]", "[simluation]"), "vehicle.toml: unknown table 'simluation'; did you mean 'simulation'?"),
])
def test_an_unknown_key_is_one_line_naming_the_file_the_key_and_the_fix(tmp_path: Path, change: tuple[str, str],
                                                                       line: str) -> None:
    with pytest.raises(ProfileError) as err:
        _load(tmp_path, GOOD.replace(*change))
    text = str(err.value)
    assert "\n" not in text and text.startswith(str(tmp_path)) and line in text and "(known: " in text


def test_every_problem_is_reported_at_once(tmp_path: Path) -> None:
    bad = GOOD.replace("log_level = ", "log_levle = ").replace('kind = "path_planner"', 'kind = "path_planer"')
    with pytest.raises(ProfileError) as err:
        _load(tmp_path, bad)
    lines = str(err.value).splitlines()
    assert len(lines) == 2 and "log_levle" in lines[0] and "path_planer" in lines[1]


def test_a_binary_profile_is_an_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "vehicle.toml"
    path.write_bytes(b"[vehicle]\nname = \"\xc3\x28\"\n")
    with pytest.raises(ProfileError, match=r"vehicle\.toml: not a text file \(byte 18 is 0xc3, not UTF-8\)"):
        load_profile(path)


def test_the_simulation_keys_are_those_the_mock_launcher_reads() -> None:
    from u2sa_hw.mocks.launcher import SimulationSettings

    names = {f.name for f in fields(SimulationSettings)}
    assert set(SIMULATION_KEYS) == {n for n in names if not n.startswith("start_")} | {"start"}
    assert {f"start_{k}" for k in SIMULATION_START_KEYS} == {n for n in names if n.startswith("start_")}


@pytest.mark.parametrize("settings, line", [
    ({"uere": 3.0}, "v.toml [services.gps] settings: unknown key 'uere'; did you mean 'uere_m'?"),
    ({"uere_m": "3"}, "v.toml [services.gps] settings: field 'uere_m' expects float, got str '3'; "
                      "fix 'uere_m' (default 3.0)"),
    ({"stale_after_s": -1.0}, "v.toml [services.gps] settings: field 'stale_after_s' must be > 0 and <= 30; "
                              "got -1.0"),
    ({"health_interval_s": float("inf")}, "field 'health_interval_s' must be a finite number > 0 and <= 60; got inf"),
    ({"position_frame": "XYZ"}, 'field \'position_frame\' must be one of "NED", "GEODETIC" (any case); got "XYZ"'),
])
def test_validate_settings_checks_each_setting_against_its_field(settings: dict, line: str) -> None:
    problems = validate_settings("gps_nmea", settings, where="v.toml [services.gps] settings")
    assert len(problems) == 1 and line in problems[0], problems


def test_validate_settings_of_good_settings_and_of_an_unknown_kind() -> None:
    assert validate_settings("gps_nmea", {"device": "gnss", "uere_m": 4.0}, where="w") == []
    problems = validate_settings("path_planer", {}, where="v.toml [services.planner]")
    assert problems == [kind_problem("path_planer", where="v.toml [services.planner]")]
    assert "did you mean 'path_planner'?" in problems[0] and "u2sa service --list-kinds" in problems[0]


def test_validate_config_file_names_a_binary_or_out_of_range_file(tmp_path: Path) -> None:
    path = tmp_path / "estimator.toml"
    assert validate_config_file("state_estimator", path) == []   # no file: defaults
    path.write_text("sensor_timeout_s = -5\n")
    assert validate_config_file("state_estimator", path) == [
        f"{path}: field 'sensor_timeout_s' must be > 0 and <= 3600; got -5.0; fix 'sensor_timeout_s' (default 2.0)"]
    path.write_bytes(b"\x89PNG\r\n")
    assert validate_config_file("state_estimator", path) == [
        f"{path}: not a text file (byte 0 is 0x89, not UTF-8); fix the file or delete it to use defaults"]


def test_unknown_safety_keys_get_a_did_you_mean(tmp_path: Path) -> None:
    from u2sa_hw.safety.prearm_table import parse_prearm

    with pytest.raises(ProfileError, match=r"\[safety\]: unknown key 'hardware_mx'; did you mean 'hardware_mux'\?"):
        _load(tmp_path, GOOD + '\n[safety]\nhardware_mx = { steering = "steering" }\n')
    profile = _load(tmp_path, GOOD + "\n[safety.prearm]\ngsp = false\n")
    with pytest.raises(ProfileError, match=r"gsp.*is not a pre-arm check; did you mean 'gps'\?"):
        parse_prearm(profile)


def test_the_hsm_reads_no_heartbeat_interval_from_a_binary_or_infinite_config(tmp_path: Path) -> None:
    from u2sa_hw.services.hsm.rules import DEFAULT_HEALTH_INTERVAL_S, health_interval_of

    profile = _load(tmp_path, GOOD)
    spec = profile.services["gps"]
    spec.config_path.parent.mkdir(parents=True, exist_ok=True)
    spec.config_path.write_bytes(b"health_interval_s = 0.5\n\xff")
    assert health_interval_of(spec) == DEFAULT_HEALTH_INTERVAL_S
    for text in ("health_interval_s = inf\n", "health_interval_s = nan\n"):
        spec.config_path.write_text(text)
        assert health_interval_of(spec) == DEFAULT_HEALTH_INTERVAL_S
    spec.config_path.write_text("health_interval_s = 0.5\n")
    assert health_interval_of(spec) == 0.5
