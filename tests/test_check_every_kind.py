"""`u2sa check` runs every registered kind's own checks offline, and a choice typo is reported for each.

Issue 12: the serial and CAN drivers' ``check_config`` read their device link, which the
offline check's bare instance does not have, and the check skipped them without a word, so
``format = "nmae"`` passed ``u2sa check`` and failed only at start. Now every kind's hook runs
(a spy on it says so), a hook that cannot run offline is a warning line, and each kind's
choice fields refuse a typo with a did-you-mean.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from u2sa_hw.check import ERROR, WARNING, Problem, check_profile
from u2sa_hw.config.fields import ConfigError, to_text
from u2sa_hw.registry import known_kinds, resolve_kind

KINDS = sorted(known_kinds())
SKIPPED = "could not run offline"


def _profile(tmp_path: Path, kind: str, settings: dict[str, Any] | None = None) -> Path:
    lines = ['[vehicle]', 'name = "every_kind"', '', '[services.svc]', f'kind = "{kind}"']
    if settings:
        lines.append("settings = { " + ", ".join(f"{k} = {to_text(v)}" for k, v in settings.items()) + " }")
    path = tmp_path / "vehicle.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def _service_problems(path: Path) -> list[Problem]:
    """The problems on the service's own table (the device checks, which want an address, are not the point)."""
    return [p for p in check_profile(path) if p.key == "services.svc" or p.key.startswith("services.svc.")]


def _choice_fields(kind: str) -> list[Any]:
    """The fields of *kind* itself (not the base's log_level) that declare choices."""
    return [f for f in resolve_kind(kind).config_fields() if f.choices]


def _bad_value(f: Any) -> Any:
    """A value close to the first choice but none of them: a typo for text, one past the largest for numbers."""
    if f.type is str:
        return f"{f.choices[0]}x"
    return max(f.choices) + 1


@pytest.mark.parametrize("kind", KINDS)
def test_each_kinds_own_checks_run_offline_on_its_defaults(tmp_path: Path, kind: str,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    cls = resolve_kind(kind)
    ran: list[str] = []
    original = cls.check_config

    def spy(self: Any) -> None:
        try:
            original(self)
        except (ConfigError, ValueError):
            ran.append("refused")   # its defaults may lack a required setting (gpio_output's outputs): it ran
            raise
        except Exception as exc:
            ran.append(f"skipped: {type(exc).__name__}: {exc}")
            raise
        ran.append("passed")

    monkeypatch.setattr(cls, "check_config", spy)
    problems = _service_problems(_profile(tmp_path, kind))
    assert ran and not ran[0].startswith("skipped"), f"{kind}: {ran}"
    assert not [p for p in problems if p.severity == WARNING], [str(p) for p in problems]
    if ran == ["passed"]:
        assert not problems, [str(p) for p in problems]


@pytest.mark.parametrize("kind, name", [(k, f.name) for k in KINDS for f in _choice_fields(k)])
def test_a_bad_choice_of_every_kind_is_reported_with_its_choices(tmp_path: Path, kind: str, name: str) -> None:
    f = next(f for f in _choice_fields(kind) if f.name == name)
    bad = _bad_value(f)
    problems = _service_problems(_profile(tmp_path, kind, {name: bad}))
    [problem] = [p for p in problems if p.key == f"services.svc.settings.{name}"]
    assert problem.severity == ERROR
    assert "must be one of" in problem.message and f"got {to_text(bad)}" in problem.message
    assert problem.fix.startswith("use one of ") and to_text(f.choices[0]) in problem.fix
    if f.type is str:
        assert "did you mean" in problem.message
    assert not [p for p in problems if SKIPPED in p.message]


def test_every_kind_with_a_choice_field_is_covered() -> None:
    # the serial and CAN drivers are the ones that used to be skipped: each has a choice field now
    with_choices = {k for k in KINDS if _choice_fields(k)}
    assert {"gps_nmea", "compass_serial", "odrive_can", "vesc_can"} <= with_choices


@pytest.mark.parametrize("kind, settings, words", [
    ("gps_nmea", {"position_frame": "ned2"}, "(did you mean 'ned'?)"),
    ("gps_nmea", {"altitude_datum": "elipsoid"}, "(did you mean 'ellipsoid'?)"),
    ("compass_serial", {"format": "nmae"}, "(did you mean 'nmea'?)"),
    ("compass_serial", {"baudrate": 9601}, "'baudrate' is the old form"),   # the new form in its fix
    ("compass_serial", {"pitch_range_deg": 0.0}, "must be > 0 and <= 90; got 0.0"),
    ("compass_serial", {"mag_offset": [1.0]}, "mag_offset"),            # the kind's own check: a combination
    ("odrive_can", {"node_ids": [1, 1]}, "node_ids must be distinct"),  # the kind's own check
    ("odrive_can", {"watchdog_timeout_endpoint": 70000}, "must be >= 0 and <= 65535; got 70000"),
    ("vesc_can", {"host_id": 0}, "host_id must be a CAN id 0..254 that no VESC uses"),
    ("vesc_can", {"hw_watchdog_timeout_s": 0.1}, "more than twice command_period_s"),
])
def test_the_drivers_that_were_skipped_report_their_mistakes(tmp_path: Path, kind: str, settings: dict,
                                                             words: str) -> None:
    problems = _service_problems(_profile(tmp_path, kind, settings))
    assert [p for p in problems if p.severity == ERROR and words in p.message], [str(p) for p in problems]
    assert not [p for p in problems if p.severity == WARNING]


@pytest.mark.parametrize("kind, settings", [
    ("gps_nmea", {"position_frame": "geodetic", "altitude_datum": "ELLIPSOID"}),
    ("compass_serial", {"format": "OS5000"}),
])
def test_a_choice_in_another_case_is_still_accepted(tmp_path: Path, kind: str, settings: dict) -> None:
    assert not _service_problems(_profile(tmp_path, kind, settings))


def test_a_kind_whose_checks_cannot_run_offline_is_a_warning_line_not_a_silent_pass(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cls = resolve_kind("state_estimator")

    def needs_a_running_service(self: Any) -> None:
        raise AttributeError(f"'{type(self).__name__}' object has no attribute '_link'")

    monkeypatch.setattr(cls, "check_config", needs_a_running_service)
    [problem] = _service_problems(_profile(tmp_path, "state_estimator"))
    assert problem.severity == WARNING and problem.key == "services.svc"
    assert SKIPPED in problem.message and "_link" in problem.message and cls.__name__ in problem.message
