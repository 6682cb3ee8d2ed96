"""The bus key from the command line and at start (issue 11, "Keys" and "Bad input").

``u2sa key show|import|rotate`` as real processes on real files; a key that cannot be used
(missing, of the wrong length, not hex, unreadable) stops a service and the CLI at start
with one line naming the file and the fix, never a traceback.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from conftest import U2SA

from u2sa_hw.bus_key import KEY_ENV, BusKeyError, key_id, read_key


def u2sa(*args: str, key: Path | None = None, stdin: str | None = None, **env: str) -> subprocess.CompletedProcess:
    full = dict(os.environ, **env)
    if key is not None:
        full[KEY_ENV] = str(key)
    return subprocess.run([*U2SA, *args], env=full, input=stdin, capture_output=True, text=True, timeout=60)


def test_show_import_and_rotate_move_a_key_between_files(tmp_path: Path) -> None:
    rover, ground = tmp_path / "rover.key", tmp_path / "ground.key"
    made = u2sa("key", "rotate", "--file", str(rover))
    assert made.returncode == 0, made.stderr
    shown = u2sa("key", "show", "--file", str(rover))
    assert shown.returncode == 0 and len(shown.stdout.strip()) == 64
    imported = u2sa("key", "import", "-", "--file", str(ground), stdin=shown.stdout)    # ssh ... | u2sa key import -
    assert imported.returncode == 0, imported.stderr
    assert read_key(ground) == read_key(rover) == bytes.fromhex(shown.stdout.strip())
    key_ids = {u2sa("key", "show", "--id", key=path).stdout.strip() for path in (rover, ground)}   # found via the env
    assert key_ids == {key_id(read_key(rover)).hex()}
    rotated = u2sa("key", "rotate", "--file", str(rover))
    assert rotated.returncode == 0 and read_key(rover) != read_key(ground)
    refused = u2sa("key", "import", "-", "--file", str(ground), stdin="not a key\n")
    assert refused.returncode == 1 and "Traceback" not in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and "standard input" in refused.stderr
    assert read_key(ground) == bytes.fromhex(shown.stdout.strip())   # the refused import changed nothing


@pytest.mark.parametrize("kind, says", [
    ("missing", "no bus key at"),
    ("short", "a bus key is 64 hex digits (256 bits), this one has 12 characters"),
    ("not hex", "other characters"),
    ("unreadable", "cannot read the bus key"),
])
def test_a_key_that_cannot_be_used_stops_a_service_and_the_cli_with_one_line(tmp_path: Path, lcm_url: str,
                                                                            kind: str, says: str) -> None:
    key = tmp_path / "bus.key"
    if kind == "short":
        key.write_text("0123456789ab\n")
    elif kind == "not hex":
        key.write_text("zz" * 32 + "\n")
    elif kind == "unreadable":
        key.mkdir()    # as root a mode cannot make a file unreadable; a directory in its place can
    for args in (("service", "state_estimator"), ("services",), ("param", "set", "x", "y", "1")):
        r = u2sa(*args, key=key, U2SA_LCM_URL=lcm_url)
        lines = r.stderr.strip().splitlines()
        assert r.returncode != 0 and "Traceback" not in r.stderr, (args, r.stderr)
        assert len(lines) == 1 and says in lines[0] and str(key) in lines[0], (args, r.stderr)
        assert "u2sa key" in lines[0] or "u2sa install" in lines[0], lines[0]


def test_a_key_without_permission_says_how_to_get_access(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    key = tmp_path / "bus.key"
    key.write_text("00" * 32 + "\n")

    def denied(_self: Path) -> bytes:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Path, "read_bytes", denied)
    with pytest.raises(BusKeyError) as err:
        read_key(key)
    assert str(key) in str(err.value) and "usermod -aG u2sa" in str(err.value) and "\n" not in str(err.value)
