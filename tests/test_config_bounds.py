"""Every number a service or the vehicle profile accepts has a finite upper bound, and all three
ways in (the loader, `u2sa check`, `u2sa param set`) refuse a value above it.

A user's `u2sa param set state_estimator publish_rate_hz 1e9` used to be saved and spin the
estimator at 97 % of a core; `sensor_timeout_s 1e308` meant "never". The walk below fails
naming each field without a bound, so the next field cannot forget it.
"""

from __future__ import annotations

import dataclasses
import importlib
import subprocess
from pathlib import Path
from typing import Any

import pytest

from conftest import REPO, U2SA
from u2sa_hw.config.configurator import Configurator
from u2sa_hw.config.fields import MAX_RATE_HZ, MAX_TIMEOUT_S, ConfigError, ConfigField
from u2sa_hw.profile.numbers import PROFILE_NUMBERS, SUPERVISION
from u2sa_hw.registry import SERVICE_KINDS, resolve_kind
from u2sa_hw.service.base_config import BASE_CONFIG

DRIVER_MODULES = sorted("u2sa_hw.drivers." + ".".join(p.relative_to(REPO / "drivers").with_suffix("").parts)
                        for p in (REPO / "drivers").rglob("*.py") if p.stem != "__init__")


def _unbounded(fields: dict[str, ConfigField]) -> list[str]:
    return [f"{where}: {f.name} ({f.type_name}, {f.range_text() or 'no bounds'})"
            for where, f in fields.items() if f.numeric and f.upper_bound is None]


def _service_fields() -> dict[str, ConfigField]:
    """Every declared field of every registered kind and every ConfigField a driver module holds."""
    found = {f"base {f.name}": f for f in BASE_CONFIG}
    for kind in SERVICE_KINDS:
        for f in resolve_kind(kind).config_fields():
            found[f"{kind} {f.name}"] = f
    for name in DRIVER_MODULES:
        module = importlib.import_module(name)
        for attr, value in vars(module).items():
            holders = [value]
            if isinstance(value, type):
                holders = [value.__dict__.get("CONFIG", ())]
            for holder in holders:
                items = holder if isinstance(holder, (tuple, list)) else (holder,)
                for f in items:
                    if isinstance(f, ConfigField):
                        found[f"{name}.{attr} {f.name}"] = f
    return found


def test_every_numeric_service_and_driver_field_has_a_finite_upper_bound() -> None:
    fields = _service_fields()
    assert len([f for f in fields.values() if f.numeric]) > 150   # the walk reached the services and drivers
    missing = _unbounded(fields)
    assert not missing, "numbers without a finite upper bound (give le= or lt=):\n" + "\n".join(missing)


def test_rates_and_timeouts_stay_under_the_central_ceilings() -> None:
    for where, f in _service_fields().items():
        if not f.numeric or f.upper_bound is None:
            continue
        if f.name.endswith("_hz"):
            assert f.upper_bound <= MAX_RATE_HZ, where
        if f.name.endswith("_ms"):
            assert f.upper_bound <= MAX_TIMEOUT_S * 1000, where
        if f.name.endswith("_s") and not f.name.endswith(("_pct_s", "_deg_s", "_rad_s")) \
                and f.name != "rotate_duration_s":   # a rate of change is not a time; a file period: a day
            assert f.upper_bound <= MAX_TIMEOUT_S, where


def test_every_number_of_the_profile_has_a_finite_upper_bound() -> None:
    missing = _unbounded(PROFILE_NUMBERS)
    assert not missing, "profile numbers without a finite upper bound:\n" + "\n".join(missing)


def _profile_dataclasses() -> list[tuple[type, str, dict[str, str]]]:
    """(dataclass a profile parser builds, its table's key prefix, attribute -> key where they differ)."""
    from u2sa_hw.mocks.launcher import SimulationSettings
    from u2sa_hw.safety.config import ManualMixerSpec, SafetyConfig
    from u2sa_hw.safety.prearm_table import EstimatorCheck, GpsCheck, PrearmTable
    from u2sa_hw.services.hsm.rules import WatchRule
    from u2sa_hw.profile.vehicle import Origin, VehicleProfile

    return [(VehicleProfile, "vehicle", {}), (Origin, "vehicle.origin", {}),
            (SafetyConfig, "safety", {"rc_mode_timeout_s": "rc_mode_timeout_ms"}),
            (ManualMixerSpec, "safety.manual_mixer", {}), (PrearmTable, "safety.prearm", {}),
            (GpsCheck, "safety.prearm.gps", {}), (EstimatorCheck, "safety.prearm.estimator", {}),
            (WatchRule, SUPERVISION, {}),
            (SimulationSettings, "simulation", {f"start_{k}": f"start.{k}" for k in ("north", "east", "heading_deg")})]


def test_every_numeric_field_the_profile_parsers_build_is_in_the_table_of_profile_numbers() -> None:
    missing = []
    for cls, prefix, renames in _profile_dataclasses():
        for f in dataclasses.fields(cls):
            if str(f.type).split(" |")[0] in ("int", "float"):
                key = f"{prefix}.{renames.get(f.name, f.name)}"
                if key not in PROFILE_NUMBERS:
                    missing.append(f"{cls.__name__}.{f.name} -> {key}")
    assert not missing, "profile numbers missing from u2sa_hw/profile/numbers.py:\n" + "\n".join(missing)


# ------------------------------------------------------------------------- the three ways in -----
ABSURD = {"publish_rate_hz": (1e9, "must be > 0 and <= 1000; got 1000000000.0"),
          "sensor_timeout_s": (1e308, "must be > 0 and <= 3600; got 1e+308")}


@pytest.mark.parametrize("name", sorted(ABSURD))
def test_the_loader_refuses_an_absurd_value_in_the_profile_or_the_file(tmp_path: Path, name: str) -> None:
    value, text = ABSURD[name]
    fields = [*BASE_CONFIG, *resolve_kind("state_estimator").config_fields()]
    with pytest.raises(ConfigError) as err:
        Configurator(None, fields, initial={name: value}, initial_source="v.toml [services.est] settings")
    assert str(err.value) == f"v.toml [services.est] settings: field '{name}' {text}; fix it there"
    path = tmp_path / "est.toml"
    path.write_text(f"{name} = {value!r}\n")
    with pytest.raises(ConfigError) as err:
        Configurator(path, fields)
    assert str(err.value) == f"{path}: field '{name}' {text}; fix it there"


@pytest.mark.parametrize("name", sorted(ABSURD))
def test_a_change_over_the_bus_above_the_bound_is_refused_and_not_written(tmp_path: Path, name: str) -> None:
    # what `u2sa param set` reaches: the service's Configurator.try_set with the text sent
    value, text = ABSURD[name]
    path = tmp_path / "est.toml"
    cfg = Configurator(path, [*BASE_CONFIG, *resolve_kind("state_estimator").config_fields()])
    ok, reason = cfg.try_set(name, repr(value))
    assert not ok and reason == f"field '{name}' {text}"
    assert not path.exists()


def _refused_profile(table: str, line: str, tmp_path: Path) -> Exception:
    from u2sa_hw.profile.vehicle import ProfileError
    from u2sa_hw.profile.loader import load_profile

    path = tmp_path / "vehicle.toml"
    path.write_text(f"[{table}]\n{line}\n")
    with pytest.raises(ProfileError) as err:
        load_profile(path)
    return err.value


def test_the_profile_loader_refuses_numbers_above_their_bound(tmp_path: Path) -> None:
    assert str(_refused_profile("vehicle", "system_id = 300", tmp_path)).endswith(
        "[vehicle]: 'system_id' = 300 is out of range; give a value >= 0 and <= 255")
    assert str(_refused_profile("vehicle", "origin = { lat = 1e9, lon = 0.0 }", tmp_path)).endswith(
        "[vehicle] origin: 'lat' = 1000000000.0 is out of range; give a value >= -90 and <= 90")
    assert "'rc_mode_timeout_ms' = 1e+308 is out of range" in str(
        _refused_profile("safety", "rc_mode_timeout_ms = 1e308", tmp_path))


CHECKED = """\
[vehicle]
name = "bench"
config_dir = "config"

[services.estimator]
kind = "state_estimator"
settings = { publish_rate_hz = 1e9, sensor_timeout_s = 1e308 }

[services.estimator.supervision]
stale_after_s = 1e308
data_channel = "STATE_ESTIMATE"

[safety.prearm]
health_timeout_s = 1e9

[simulation]
rate_hz = 1e9
"""


def test_u2sa_check_names_each_number_above_its_bound(tmp_path: Path) -> None:
    (tmp_path / "config").mkdir()
    (tmp_path / "vehicle.toml").write_text(CHECKED)
    done = subprocess.run([*U2SA, "check", "--vehicle", "vehicle.toml"], capture_output=True, text=True,
                          timeout=60, cwd=tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    expected = [
        "error: vehicle.toml [services.estimator.settings.publish_rate_hz]: must be > 0 and <= 1000; got "
        "1000000000.0; fix: give a value > 0 and <= 1000 (default 50.0)",
        "error: vehicle.toml [services.estimator.settings.sensor_timeout_s]: must be > 0 and <= 3600; got 1e+308; "
        "fix: give a value > 0 and <= 3600 (default 2.0)",
        "error: vehicle.toml [simulation]: 'rate_hz' = 1000000000.0 is out of range; fix: give a value > 0 and "
        "<= 1000",
        "error: vehicle.toml [safety.prearm]: 'health_timeout_s' = 1000000000.0 is out of range; fix: give a value "
        "> 0 and <= 3600 (s)",
    ]
    for line in expected:
        assert line in lines, done.stdout
    assert any("[services.estimator.supervision.stale_after_s]" in line and "'stale_after_s' = 1e+308 is out of "
               "range; fix: give a value >= 0 and <= 3600" in line for line in lines), done.stdout


def test_the_examples_stay_inside_every_bound() -> None:
    from u2sa_hw.check import check_profile, errors_of

    for path in sorted((REPO / "examples").glob("*/vehicle.toml")):
        problems: Any = errors_of(check_profile(path))
        assert not [p for p in problems if "out of range" in str(p) or "<=" in str(p)], (path, problems)
