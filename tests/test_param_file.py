"""Parameter files (``u2sa param save/load``) and the did-you-mean for a service name not on the bus (issue 26).

The bus tests run real service processes; the line scanner and the load checks also run on text alone.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Callable

import pytest
from conftest import ServiceProcesses, wait_until

from u2sa_hw.bus.client import BusClient
from u2sa_hw.config.fields import field
from u2sa_hw.config.param_file import LiveService, key_lines, plan_load

EST, WORLD = "state_estimator", "world_modeler"


def _start_two(services: ServiceProcesses, bus: BusClient) -> None:
    services.start(EST)
    services.start(WORLD)
    wait_until(lambda: {r.name for r in bus.discover(timeout=0.5)} >= {EST, WORLD}, timeout=30,
               message="the estimator and the world modeler on the bus")


def _params(services: ServiceProcesses, name: str) -> dict:
    r = services.cli("param", "list", name, "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _line_of(path: Path, text: str) -> int:
    """The 1-based line of *path* that starts with *text* (the test's own search, not the scanner's)."""
    hits = [i for i, line in enumerate(path.read_text().splitlines(), 1) if line.startswith(text)]
    assert len(hits) == 1, hits
    return hits[0]


def _replace(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert text.count(old) == 1, old
    path.write_text(text.replace(old, new))


def _problems(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("u2sa: ")]


def test_save_load_round_trip_diff_and_dry_run(services: ServiceProcesses, bus: BusClient) -> None:
    _start_two(services, bus)
    saved = services.workdir / "rover.params.toml"
    r = services.cli("param", "save", str(saved))
    assert r.returncode == 0, r.stderr
    text = saved.read_text()
    assert text.startswith("# u2sa parameters of ") and "\n# saved " in text
    data = tomllib.loads(text)
    assert list(data) == [EST, WORLD]
    assert data[EST]["kind"] == EST and data[WORLD]["kind"] == WORLD
    # typed values, exactly what param list reports
    assert data[EST]["params"] == _params(services, EST)
    assert data[WORLD]["params"] == _params(services, WORLD)
    assert isinstance(data[EST]["params"]["sensor_timeout_s"], float)
    assert isinstance(data[EST]["params"]["reinit_after"], int)

    # loading what was saved changes nothing
    r = services.cli("param", "load", str(saved))
    assert r.returncode == 0, r.stderr
    assert "no differences" in r.stdout and "->" not in r.stdout

    # one service's file
    one = services.workdir / "est.toml"
    r = services.cli("param", "save", str(one), EST)
    assert r.returncode == 0, r.stderr
    assert list(tomllib.loads(one.read_text())) == [EST]

    # a changed value: --dry-run prints the difference and changes nothing
    before = _params(services, EST)
    _replace(saved, "sensor_timeout_s = 2.0\n", "sensor_timeout_s = 4.5\n")
    _replace(saved, "expiry_s = 5.0\n", "expiry_s = 7\n")   # an int for a float field is that float
    cfg_file = services.workdir / ".u2sa" / "config" / f"{EST}.toml"
    r = services.cli("param", "load", str(saved), "--dry-run")
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[:2] == [f"{EST}.sensor_timeout_s: 2.0 -> 4.5", f"{WORLD}.expiry_s: 5.0 -> 7.0"]
    assert "--dry-run: nothing changed" in r.stdout
    assert _params(services, EST) == before and not cfg_file.exists()

    # loaded: the difference is printed first, then applied and saved by the service
    r = services.cli("param", "load", str(saved))
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[:2] == [f"{EST}.sensor_timeout_s: 2.0 -> 4.5", f"{WORLD}.expiry_s: 5.0 -> 7.0"]
    assert r.stdout.splitlines()[-1].endswith("2 changes to 2 services, 22 fields already equal; applied")
    assert _params(services, EST) == {**before, "sensor_timeout_s": 4.5}
    assert _params(services, WORLD)["expiry_s"] == 7.0
    assert tomllib.loads(cfg_file.read_text()) == {"sensor_timeout_s": 4.5}
    # and again: nothing left to change
    r = services.cli("param", "load", str(saved))
    assert r.returncode == 0 and "no differences" in r.stdout, r.stdout + r.stderr


def test_load_refuses_bad_files_with_file_and_line_and_rolls_back_a_refusal(
        services: ServiceProcesses, bus: BusClient) -> None:
    _start_two(services, bus)
    saved = services.workdir / "p.toml"
    assert services.cli("param", "save", str(saved)).returncode == 0
    good = saved.read_text()
    est_before, world_before = _params(services, EST), _params(services, WORLD)
    cfg_dir = services.workdir / ".u2sa" / "config"

    def refused(edits: list[tuple[str, str]], expected: Callable[[], list[str]]) -> None:
        """Load the saved file with *edits*: refused with the *expected* lines (computed on the edited file)."""
        saved.write_text(good)
        for old, new in edits:
            _replace(saved, old, new)
        want = expected()
        r = services.cli("param", "load", str(saved))
        assert r.returncode == 1, r.stdout + r.stderr
        problems = _problems(r.stderr)
        assert problems[-1] == f"u2sa: {saved}: {len(want)} problem{'s' if len(want) > 1 else ''}; " \
                               "nothing was changed", r.stderr
        assert problems[:-1] == [f"u2sa: {p}" for p in want], r.stderr
        assert "->" not in r.stdout   # refused before any difference is printed or applied
        assert _params(services, EST) == est_before and _params(services, WORLD) == world_before
        assert not cfg_dir.exists() or not list(cfg_dir.iterdir())

    # an out-of-range value (fields have upper bounds) beside a valid change of the same service
    refused([("sensor_timeout_s = 2.0\n", "sensor_timeout_s = 4.5\n"),
             ("publish_rate_hz = 50.0\n", "publish_rate_hz = 1e9\n")],
            lambda: [f"{saved}:{_line_of(saved, 'publish_rate_hz = 1e9')}: {EST}: field 'publish_rate_hz' must be "
                     "> 0 and <= 1000; got 1000000000.0"])

    # an unknown field, with a did-you-mean
    refused([("expiry_s = 5.0\n", "expiry_sec = 6.0\n")],
            lambda: [f"{saved}:{_line_of(saved, 'expiry_sec')}: {WORLD}: unknown field 'expiry_sec'; did you mean "
                     "'expiry_s'? (known: association_radius_m, default_radius_m, expiry_s, health_interval_s, "
                     "log_level, max_pose_age_s, objects_file, publish_rate_hz)"])

    # an unknown service (its table header's line), and a wrong type
    refused([(f"[{WORLD}]\n", "[world_modeller]\n"), (f"[{WORLD}.params]\n", "[world_modeller.params]\n"),
             ("mode = \"ekf\"\n", "mode = 3\n")],
            lambda: [f"{saved}:{_line_of(saved, 'mode = 3')}: {EST}: field 'mode' expects str, got int 3",
                     f"{saved}:{_line_of(saved, '[world_modeller]')}: no service 'world_modeller' on the bus; "
                     f"did you mean '{WORLD}'? (services: {EST}, {WORLD})"])

    # a change only the service can refuse (its check_config: publish_on names an unknown kind): the
    # changes before it are rolled back, so nothing of that service changes; the other service's apply
    saved.write_text(good)
    _replace(saved, "sensor_timeout_s = 2.0\n", "sensor_timeout_s = 4.5\n")
    _replace(saved, "default_position_sigma = 3.0\n", "default_position_sigma = 4.0\n")
    _replace(saved, "publish_on = \"position,heading\"\n", "publish_on = \"position,altitude_of_the_moon\"\n")
    _replace(saved, "expiry_s = 5.0\n", "expiry_s = 6.0\n")
    bad_line = _line_of(saved, "publish_on = ")
    r = services.cli("param", "load", str(saved))
    assert r.returncode == 1, r.stdout + r.stderr
    problems = _problems(r.stderr)
    assert problems[0].startswith(f"u2sa: {saved}:{bad_line}: {EST} refused: field 'publish_on': "), r.stderr
    assert f"u2sa: {EST}: rolled back 1 change; nothing of it changed" in problems, r.stderr
    assert problems[-1] == f"u2sa: {saved}: not loaded into {EST} (see above); applied to {WORLD}", r.stderr
    assert _params(services, EST) == est_before
    assert _params(services, WORLD) == {**world_before, "expiry_s": 6.0}


def test_a_service_name_not_on_the_bus_gets_a_did_you_mean(services: ServiceProcesses, bus: BusClient) -> None:
    _start_two(services, bus)
    expected = (f"u2sa: no service 'state_estimater' on the bus; did you mean '{EST}'? (services: {EST}, {WORLD})")
    for args in (("param", "list", "state_estimater"), ("param", "get", "state_estimater", "mode"),
                 ("param", "set", "state_estimater", "sensor_timeout_s", "3")):
        r = services.cli(*args)
        assert r.returncode == 1 and _problems(r.stderr) == [expected], (args, r.stderr)
    r = services.cli("param", "save", "x.toml", "world_modler")
    assert r.returncode == 1 and _problems(r.stderr) == [
        f"u2sa: no service 'world_modler' on the bus; did you mean '{WORLD}'? (services: {EST}, {WORLD})"], r.stderr
    assert not (services.workdir / "x.toml").exists()
    r = services.cli("stop", "world_modler")
    assert r.returncode == 1 and _problems(r.stderr) == [
        f"u2sa: no service 'world_modler' on the bus; did you mean '{WORLD}'? (services: {EST}, {WORLD}); "
        "nothing to stop"], r.stderr
    # no close name: the services alone
    r = services.cli("stop", "pan")
    assert r.returncode == 1 and _problems(r.stderr) == [
        f"u2sa: no service 'pan' on the bus (services: {EST}, {WORLD}); nothing to stop"], r.stderr
    assert {r.name for r in bus.discover(timeout=1.0)} == {EST, WORLD}   # nothing was stopped
    # the right name still works
    r = services.cli("stop", WORLD)
    assert r.returncode == 0 and r.stdout.strip() == f"stopped {WORLD}", r.stderr


# -- the file alone ------------------------------------------------------------------------------

def test_key_lines_skips_strings_arrays_and_comments() -> None:
    text = ('# header\n'
            '[est]\n'
            'kind = "state_estimator"   # a comment with x = 1\n'
            '\n'
            '[est.params]\n'
            'note = """\n'
            'not_a_key = 1\n'
            '"""\n'
            'rates = [\n'
            '  1, # fake = 2\n'
            '  2,\n'
            ']\n'
            "'quoted key' = 'a = b'\n"
            'inline = { a = 1, b = "}" }\n'
            'last = 3\n'
            '[ "odd.name" . params ]\n'
            'x = 1\n')
    tomllib.loads(text)   # the test's text is TOML
    lines = key_lines(text)
    assert lines == {("est",): 2, ("est", "kind"): 3, ("est", "params"): 5, ("est", "params", "note"): 6,
                     ("est", "params", "rates"): 9, ("est", "params", "quoted key"): 13,
                     ("est", "params", "inline"): 14, ("est", "params", "last"): 15,
                     ("odd.name", "params"): 16, ("odd.name", "params", "x"): 17}


def _live(declared: bool) -> dict[str, LiveService]:
    fields = {"rate_hz": ("float", "10.0"), "mode": ("str", '"a"'), "fixed": ("bool", "true")}
    decl = {"rate_hz": field("rate_hz", 10.0, gt=0, le=100), "mode": field("mode", "a", choices=("a", "b")),
            "fixed": field("fixed", True, remote=False)} if declared else None
    return {"svc": LiveService("svc", "thing", "service", fields, decl)}


def test_plan_load_checks_against_the_declared_fields() -> None:
    text = '[svc]\nkind = "thing"\n[svc.params]\nrate_hz = 200\nmode = "c"\nfixed = false\n'
    plan = plan_load("f.toml", text, ["svc"], _live(True))
    assert plan.problems == ["f.toml:4: svc: field 'rate_hz' must be > 0 and <= 100; got 200.0",
                             "f.toml:5: svc: field 'mode' must be one of \"a\", \"b\"; got \"c\"",
                             "f.toml:6: svc: field 'fixed' is not changed over the bus (it is read at start: set it "
                             "in the profile's settings or the service's config file); it is true there, the file "
                             "says false"]
    # without the declarations (a kind this checkout does not have) only the type is checked here; the service
    # checks the rest when it is applied
    plan = plan_load("f.toml", text, ["svc"], _live(False))
    assert plan.problems == []
    assert [(c.field, c.old_text, c.new_text, c.line) for c in plan.changes["svc"]] == [
        ("rate_hz", "10.0", "200.0", 4), ("mode", '"a"', '"c"', 5), ("fixed", "true", "false", 6)]


def test_plan_load_refuses_another_kind_and_stray_keys() -> None:
    text = '[svc]\nkind = "gps_nmea"\n[svc.params]\nrate_hz = 20\n'
    plan = plan_load("f.toml", text, ["svc"], _live(True))
    assert plan.problems == ["f.toml:2: [svc]: the file's kind is 'gps_nmea', but 'svc' on the bus is a thing; "
                             "nothing of it is loaded"] and not plan.changes
    plan = plan_load("f.toml", '[svc]\nrate_hz = 20\n', ["svc"], _live(True))
    assert plan.problems == ["f.toml:2: [svc]: unknown key 'rate_hz' (a service's table holds kind and params; "
                             "its fields go under [svc.params])"]
    plan = plan_load("f.toml", '[svc.params]\nrate_hz = 20\n', ["svc"], _live(True), only=["sv"])
    assert plan.problems == ["f.toml: no table [sv] in the file; did you mean 'svc'? (tables: svc)"]


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_plan_load_refuses_non_finite_values(value: str) -> None:
    plan = plan_load("f.toml", f"[svc.params]\nrate_hz = {value}\n", ["svc"], _live(True))
    assert plan.problems == [f"f.toml:2: svc: field 'rate_hz' must be a finite number > 0 and <= 100; got {value}"]
