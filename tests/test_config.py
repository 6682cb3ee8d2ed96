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

from u2sa_hw.config import ConfigError, Configurator, field

FIELDS = (field("rate_hz", 50.0), field("retries", 3), field("enabled", True), field("port", "/dev/ttyUSB0"))


def test_missing_file_means_defaults_and_is_created_on_first_change(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "svc.toml"
    cfg = Configurator(path, FIELDS)
    assert cfg.get("rate_hz") == 50.0 and not path.exists()
    assert cfg.set("retries", 5)
    assert tomllib.loads(path.read_text()) == {"rate_hz": 50.0, "retries": 5, "enabled": True, "port": "/dev/ttyUSB0"}
    assert Configurator(path, FIELDS).get("retries") == 5


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
        from u2sa_hw.config import Configurator, field
        logging.basicConfig(level=logging.WARNING, stream=sys.stdout, format="%(message)s")
        cfg = Configurator({str(path)!r}, (field("retries", 3),))
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
    fields = (field("level", "info", choices=("debug", "info")), field("retries", 3))
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
