"""The configurator: typed fields, refusals that leave the file intact, atomic writes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
import tomllib
from pathlib import Path

import pytest
from conftest import unprivileged

from u2sa_hw.config.configurator import Configurator
from u2sa_hw.config.fields import ConfigError, field

FIELDS = (field("rate_hz", 50.0, le=1000), field("retries", 3, le=100), field("enabled", True), field("port", "/dev/ttyUSB0"))


def test_missing_file_means_defaults_and_is_created_on_first_change(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "svc.toml"
    cfg = Configurator(path, FIELDS)
    assert cfg.get("rate_hz") == 50.0 and not path.exists()
    assert cfg.set("retries", 5)
    assert tomllib.loads(path.read_text()) == {"retries": 5}    # only what changed: defaults stay defaults
    assert Configurator(path, FIELDS).get("retries") == 5


def test_a_change_never_freezes_the_profiles_values_into_the_file(tmp_path: Path) -> None:
    # A bench profile's setting must not outlive the switch to another profile because of an
    # unrelated change over the bus (the file overrides the profile).
    path = tmp_path / "wheels.toml"
    path.write_text("retries = 4\n")
    bench = Configurator(path, FIELDS, initial={"enabled": False, "rate_hz": 5.0})
    assert bench.get("enabled") is False and bench.get("retries") == 4
    assert bench.set("port", "/dev/ttyACM0")
    assert tomllib.loads(path.read_text()) == {"retries": 4, "port": "/dev/ttyACM0"}
    vehicle = Configurator(path, FIELDS, initial={"enabled": True})
    assert vehicle.get("enabled") is True and vehicle.get("rate_hz") == 50.0 and vehicle.get("port") == "/dev/ttyACM0"


def test_a_trial_value_is_seen_only_by_the_thread_that_validates_it(tmp_path: Path) -> None:
    import threading

    cfg = Configurator(tmp_path / "c.toml", FIELDS)
    seen: list[float] = []
    with cfg.trial("rate_hz", 0.5):
        assert cfg.get("rate_hz") == 0.5
        t = threading.Thread(target=lambda: seen.append(cfg.get("rate_hz")))
        t.start()
        t.join()
    assert seen == [50.0] and cfg.get("rate_hz") == 50.0 and not (tmp_path / "c.toml").exists()


def test_int_accepted_for_float_text_parsed_by_type(tmp_path: Path) -> None:
    cfg = Configurator(tmp_path / "c.toml", FIELDS)
    assert cfg.set("rate_hz", 20) and cfg.get("rate_hz") == 20.0
    assert cfg.set("rate_hz", "12.5") and cfg.get("rate_hz") == 12.5
    assert cfg.set("enabled", "false") and cfg.get("enabled") is False
    assert cfg.set("port", "/dev/ttyACM0") and cfg.get("port") == "/dev/ttyACM0"


@pytest.mark.parametrize("name,value,expected", [
    ("retries", 2.5, "field 'retries' expects int, got float 2.5"),
    ("retries", "2.5", "field 'retries' expects int, got float 2.5"),
    ("enabled", 1, "field 'enabled' expects bool, got int 1"),
    ("rate_hz", "fast", "field 'rate_hz' expects float, got unparseable text 'fast'"),
    ("nope", 1, "no config field 'nope'"),
])
def test_wrong_type_refused_with_message_and_file_intact(tmp_path: Path, name: str, value: object,
                                                         expected: str) -> None:
    path = tmp_path / "c.toml"
    cfg = Configurator(path, FIELDS)
    assert cfg.set("retries", 4)
    before = path.read_bytes()
    ok, reason = cfg.try_set(name, value)
    assert not ok and expected in reason
    assert path.read_bytes() == before
    assert cfg.get("retries") == 4


def test_wrong_type_in_file_is_an_error_naming_file_and_field(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('retries = "three"\n')
    with pytest.raises(ConfigError, match=r"c\.toml: field 'retries' expects int, got str"):
        Configurator(path, FIELDS)


def test_broken_toml_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("retries = = 3\n")
    with pytest.raises(ConfigError, match="c.toml: not valid TOML"):
        Configurator(path, FIELDS)


def test_unknown_fields_in_the_file_are_kept_on_write(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("future_field = 1\n")
    cfg = Configurator(path, FIELDS)
    assert cfg.set("retries", 9)
    assert tomllib.loads(path.read_text())["future_field"] == 1


def _try_set_unprivileged(path: Path, name: str, value: object) -> str:
    code = textwrap.dedent(f"""\
        import logging, sys
        from u2sa_hw.config.configurator import Configurator
        from u2sa_hw.config.fields import field
        logging.basicConfig(level=logging.WARNING, stream=sys.stdout, format="%(message)s")
        cfg = Configurator({str(path)!r}, (field("retries", 3, le=100),))
        ok, reason = cfg.try_set({name!r}, {value!r})
        print("RESULT", ok, cfg.get("retries"))
        print("REASON", reason)
        """)
    src = str(Path(__file__).resolve().parent.parent)
    return subprocess.run(unprivileged([sys.executable, "-c", code]), capture_output=True, text=True, timeout=30,
                          env=dict(os.environ, PYTHONPATH=src), cwd="/").stdout


def test_unwritable_file_set_returns_false_and_file_intact() -> None:
    """Run as an unprivileged user (root ignores permissions) against a read-only directory."""
    workdir = Path(tempfile.mkdtemp(prefix="u2sa-ro-"))
    try:
        cfg_dir = workdir / "cfg"
        cfg_dir.mkdir()
        path = cfg_dir / "svc.toml"
        path.write_text("retries = 4\n")
        os.chmod(workdir, 0o755)
        os.chmod(cfg_dir, 0o555)
        os.chmod(path, 0o444)
        out = _try_set_unprivileged(path, "retries", 7)
        assert "RESULT False 4" in out, out
        assert f"cannot write {path}" in out and "file is unchanged" in out
        assert "config change of 'retries' not saved" in out  # logged
        assert path.read_text() == "retries = 4\n"
        assert sorted(p.name for p in cfg_dir.iterdir()) == ["svc.toml"]  # no temp file left
    finally:
        os.chmod(workdir / "cfg", 0o755)
        shutil.rmtree(workdir)


def test_validator_refuses_before_writing(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    cfg = Configurator(path, FIELDS, validator=lambda n, v: "must be positive" if n == "rate_hz" and v <= 0 else None)
    assert cfg.set("rate_hz", 5)
    before = path.read_bytes()
    ok, reason = cfg.try_set("rate_hz", -1.0)
    assert not ok and reason == "field 'rate_hz': must be positive"
    assert path.read_bytes() == before and cfg.get("rate_hz") == 5.0


def test_directory_sync_failure_after_the_rename_says_the_file_changed() -> None:
    """A directory we may write but not read: the rename succeeds, opening it to fsync fails."""
    workdir = Path(tempfile.mkdtemp(prefix="u2sa-wx-"))
    try:
        cfg_dir = workdir / "cfg"
        cfg_dir.mkdir()
        path = cfg_dir / "svc.toml"
        path.write_text("retries = 4\n")
        os.chmod(workdir, 0o755)
        os.chmod(path, 0o644)
        os.chmod(cfg_dir, 0o333)  # write + search, no read
        out = _try_set_unprivileged(path, "retries", 7)
        assert "RESULT True 7" in out, out  # the value is in effect, as in the file
        assert f"saved to {path}, but syncing its directory" in out and "unchanged" not in out
        assert tomllib.loads(path.read_text()) == {"retries": 7}
        os.chmod(cfg_dir, 0o755)
        assert sorted(p.name for p in cfg_dir.iterdir()) == ["svc.toml"]  # no temp file left
    finally:
        os.chmod(workdir / "cfg", 0o755)
        shutil.rmtree(workdir)


def test_string_field_takes_a_toml_string_literal_or_a_bare_word(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    cfg = Configurator(path, FIELDS)
    for text, stored in (('"/dev/ttyS1"', "/dev/ttyS1"), ("'/dev/tty S2'", "/dev/tty S2"), ("/dev/ttyS3", "/dev/ttyS3"),
                         ("42", "42"), ('""', ""), ('"a"\nretries = 1', '"a"\nretries = 1')):
        assert cfg.set("port", text)
        assert cfg.get("port") == stored, text
        assert tomllib.loads(path.read_text())["port"] == stored


def test_a_value_outside_the_choices_is_refused_naming_the_field_and_the_allowed_values(tmp_path: Path) -> None:
    fields = (field("level", "info", choices=("debug", "info")), field("retries", 3, le=100))
    path = tmp_path / "c.toml"
    cfg = Configurator(path, fields)
    assert cfg.set("level", '"debug"') and cfg.get("level") == "debug"
    before = path.read_bytes()
    ok, reason = cfg.try_set("level", "verbose")
    assert not ok and reason == "field 'level' must be one of \"debug\", \"info\"; got \"verbose\""
    assert path.read_bytes() == before and cfg.get("level") == "debug"
    path.write_text('level = "loud"\n')
    with pytest.raises(ConfigError, match=r"c\.toml: field 'level' must be one of"):
        Configurator(path, fields)
    with pytest.raises(ValueError, match="not one of its choices"):
        field("level", "chatty", choices=("debug", "info"))


def test_a_case_insensitive_choice_is_taken_in_any_case_and_kept_in_its_declared_spelling(tmp_path: Path) -> None:
    # the gps position_frame / compass format rule: "ned" was always accepted, now declared instead of lowered by hand
    fields = (field("frame", "NED", choices=("NED", "GEODETIC"), case_insensitive=True),)
    path = tmp_path / "c.toml"
    cfg = Configurator(path, fields, initial={"frame": "geodetic"})
    assert cfg.get("frame") == "GEODETIC"
    assert cfg.set("frame", "ned") and cfg.get("frame") == "NED" and tomllib.loads(path.read_text())["frame"] == "NED"
    ok, reason = cfg.try_set("frame", "ned2")
    assert not ok and reason == 'field \'frame\' must be one of "NED", "GEODETIC" (any case); got "ned2"'
    with pytest.raises(TypeError, match="case_insensitive needs str choices"):
        field("rate", 9600, choices=(4800, 9600), case_insensitive=True)


# ---------------------------------------------------------------- ranges and non-finite numbers -----
RANGED = (field("timeout_s", 2.0, gt=0, le=3600), field("fraction", 0.5, ge=0, le=1), field("count", 3, ge=1, lt=10),
          field("offset", 0.0, unbounded="a test of the opt-out"),
          field("limit", 1.0, allow_nonfinite=True, unbounded="inf is its off value"),
          field("ids", [1, 2], item_type=int, ge=0, le=62), field("names", ["a"], item_type=str))


@pytest.mark.parametrize("name, text, message", [
    ("timeout_s", "-5", "field 'timeout_s' must be > 0 and <= 3600; got -5.0"),
    ("timeout_s", "0", "field 'timeout_s' must be > 0 and <= 3600; got 0.0"),
    ("timeout_s", "1e308", "field 'timeout_s' must be > 0 and <= 3600; got 1e+308"),
    ("timeout_s", "inf", "field 'timeout_s' must be a finite number > 0 and <= 3600; got inf"),
    ("timeout_s", "-inf", "field 'timeout_s' must be a finite number > 0 and <= 3600; got -inf"),
    ("timeout_s", "nan", "field 'timeout_s' must be a finite number > 0 and <= 3600; got nan"),
    ("offset", "inf", "field 'offset' must be a finite number; got inf"),
    ("fraction", "1.5", "field 'fraction' must be >= 0 and <= 1; got 1.5"),
    ("count", "10", "field 'count' must be >= 1 and < 10; got 10"),
    ("count", "0", "field 'count' must be >= 1 and < 10; got 0"),
    ("ids", "[1, 63]", "field 'ids' item 1 must be >= 0 and <= 62; got 63"),
    ("ids", "[1, 2.0]", "field 'ids' item 1 expects int, got float 2.0"),
    ("names", '["a", 3]', "field 'names' item 1 expects str, got int 3"),
    ("ids", '"1,2"', "field 'ids' expects list, got str '1,2'"),
])
def test_a_value_out_of_range_is_refused_with_the_field_the_bound_and_the_value(
        tmp_path: Path, name: str, text: str, message: str) -> None:
    path = tmp_path / "c.toml"
    cfg = Configurator(path, RANGED)
    assert cfg.set("count", 4)
    before = path.read_bytes()
    ok, reason = cfg.try_set(name, text)
    assert not ok and reason == message
    assert path.read_bytes() == before and cfg.get("count") == 4


def test_values_inside_the_range_and_allowed_non_finite_ones_are_taken(tmp_path: Path) -> None:
    cfg = Configurator(tmp_path / "c.toml", RANGED)
    for name, text, value in (("timeout_s", "1e-3", 0.001), ("fraction", "0", 0.0), ("fraction", "1", 1.0),
                              ("count", "9", 9), ("offset", "-1e3", -1000.0), ("limit", "inf", float("inf")),
                              ("limit", "-inf", float("-inf")), ("ids", "[0, 62]", [0, 62])):
        ok, reason = cfg.try_set(name, text)
        assert ok, reason
        assert cfg.get(name) == value
    assert tomllib.loads((tmp_path / "c.toml").read_text())["limit"] == float("-inf")


def test_an_out_of_range_value_in_the_file_or_the_profile_names_its_source(tmp_path: Path) -> None:
    path = tmp_path / "est.toml"
    path.write_text("timeout_s = inf\n")
    with pytest.raises(ConfigError, match=r"est\.toml: field 'timeout_s' must be a finite number > 0 and <= 3600; got inf"):
        Configurator(path, RANGED)
    path.write_text("timeout_s = -5\n")
    with pytest.raises(ConfigError, match=r"est\.toml: field 'timeout_s' must be > 0 and <= 3600; got -5\.0"):
        Configurator(path, RANGED)
    with pytest.raises(ConfigError, match=r"^v\.toml \[services\.est\] settings: field 'ids' item 0 must be >= 0"):
        Configurator(None, RANGED, initial={"ids": [-1]}, initial_source="v.toml [services.est] settings")
    assert path.read_text() == "timeout_s = -5\n"


def test_an_unknown_key_in_the_profile_settings_is_an_error_with_a_did_you_mean(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"v\.toml \[services\.gps\] settings: unknown key 'prot'; did you mean "
                                          r"'port'\?"):
        Configurator(None, FIELDS, initial={"prot": "/dev/x"}, initial_source="v.toml [services.gps] settings")
    cfg = Configurator(None, FIELDS, initial={"device": "gps"}, passthrough=("device",))
    assert "device" not in cfg


def test_a_declaration_that_breaks_its_own_bounds_fails_at_import() -> None:
    with pytest.raises(ValueError, match="its default breaks its own declaration: field 'x' must be > 0; got 0.0"):
        field("x", 0.0, gt=0)
    with pytest.raises(TypeError, match="bounds need a number"):
        field("x", "text", ge=0)
    with pytest.raises(TypeError, match="bounds must be finite"):
        field("x", 1.0, le=float("inf"))


def test_a_number_without_an_upper_bound_fails_at_import_unless_it_says_why() -> None:
    for declaration in (lambda: field("rate_hz", 50.0, gt=0), lambda: field("count", 3, ge=1),
                        lambda: field("ids", [1], item_type=int, ge=0)):
        with pytest.raises(TypeError, match="a number needs a finite upper bound"):
            declaration()
    assert field("rate_hz", 50.0, gt=0, le=1000).upper_bound == 1000
    assert field("count", 3, ge=1, lt=10).upper_bound == 10
    assert field("baud", 9600, choices=(4800, 9600)).upper_bound == 9600   # choices bound it too
    assert field("offset", 0.0, unbounded="a sum of anything").upper_bound is None
    with pytest.raises(TypeError, match="unbounded is for a number"):
        field("name", "x", unbounded="why")


def test_a_binary_config_file_is_an_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "gps.toml"
    path.write_bytes(b"rate_hz = 5\n\xff\xfe\x00garbage")
    with pytest.raises(ConfigError) as err:
        Configurator(path, FIELDS)
    assert str(err.value).startswith(f"{path}: not a text file (byte 12 is 0xff, not UTF-8)")
    assert "delete it to use defaults" in str(err.value)


def test_a_remote_false_field_is_not_changed_over_the_bus(tmp_path: Path, lcm_url: str) -> None:
    from u2sa_hw.service.contract import U2SAService

    class Gated(U2SAService):
        CONFIG = (field("gating", True, "the pilot's switch", remote=False),)

    svc = Gated("gated", config_path=tmp_path / "gated.toml")
    try:
        ok, reason = svc.config.try_set("gating", "false")
        assert not ok and "gating is not changed over the bus (the pilot's switch)" in reason
        assert not (tmp_path / "gated.toml").exists()
        assert svc.config.try_set("gating", "true")[0]   # the value it has: not a change
    finally:
        svc.transport.stop()


def test_a_configurator_reads_like_a_mapping(tmp_path: Path) -> None:
    cfg = Configurator(tmp_path / "c.toml", FIELDS)
    assert "rate_hz" in cfg and "nope" not in cfg and len(cfg) == 4 and list(cfg)[0] == "rate_hz"
    assert cfg.get("nope", 7) == 7
    with pytest.raises(KeyError, match="no config field 'nope'"):
        cfg.get("nope")


def test_a_file_field_is_declared_and_a_wrong_declaration_fails_at_import() -> None:
    """field(file=True) / file="secret" marks a setting that names a file (install copies it, check looks for it)."""
    plain, secret, word = field("mission_file", "", file=True), field("token_file", "", file="secret"), \
        field("loop", "file")
    assert (plain.names_file, plain.secret_file) == (True, False)
    assert (secret.names_file, secret.secret_file) == (True, True)
    assert (word.names_file, word.secret_file) == (False, False)   # a value "file" is not a file field
    with pytest.raises(ValueError, match="file must be"):
        field("x_file", "", file="yes")
    with pytest.raises(TypeError, match="default must be a str"):
        field("x_file", 0, file=True)
