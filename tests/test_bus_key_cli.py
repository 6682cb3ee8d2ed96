"""The bus key from the command line and at start (issue 11, "Keys" and "Bad input").

``u2sa key show|import|rotate`` as real processes on real files; a key that cannot be used
(missing, of the wrong length, not hex, unreadable) stops a service and the CLI at start
with one line naming the file and the fix, never a traceback. ``u2sa key`` finds the key through
``$U2SA_VEHICLE`` as the services do; a key pasted into ``bus_key`` is refused without being
printed; a user outside the key's group is told, end to end, how to get access.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import pytest
from conftest import U2SA, unprivileged

from u2sa_hw.bus.key import KEY_ENV, BusKeyError, key_id, key_path, read_key


def u2sa(*args: str, key: Path | None = None, stdin: str | None = None, **env: str) -> subprocess.CompletedProcess:
    full = dict(os.environ, **env)
    if key is not None:
        full[KEY_ENV] = str(key)
    with tempfile.TemporaryDirectory(prefix="u2sa-cli-") as cwd:   # a service without a profile logs in ./.u2sa
        return subprocess.run([*U2SA, *args], env=full, input=stdin, capture_output=True, text=True, timeout=60,
                              cwd=cwd)


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


# ------------------------------------------------- the key the services use (issue 11 audit) ---------
KEY_HEX = "0123456789abcdef" * 4


def profile_naming(tmp: Path, bus_key: str, lcm_url: str = "") -> Path:
    profile = tmp / "vehicle.toml"
    url = f'lcm_url = "{lcm_url}"\n' if lcm_url else ""
    profile.write_text(f'[vehicle]\nname = "rover"\n{url}bus_key = "{bus_key}"\n'
                       '[services.state_estimator]\nkind = "state_estimator"\n')
    return profile


def without_key_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != KEY_ENV}


def run_u2sa(args: list[str], env: dict[str, str], *, stdin: str | None = None,
             as_user: bool = False) -> subprocess.CompletedProcess:
    cmd = [*U2SA, *args]
    if as_user:
        return subprocess.run(unprivileged(cmd), env=env, input=stdin, capture_output=True, text=True, timeout=60)
    with tempfile.TemporaryDirectory(prefix="u2sa-cli-") as cwd:   # a service without a profile logs in ./.u2sa
        return subprocess.run(cmd, env=env, input=stdin, capture_output=True, text=True, timeout=60, cwd=cwd)


def test_the_key_command_acts_on_the_key_of_the_profile_in_U2SA_VEHICLE(tmp_path: Path) -> None:
    # The services find the key through the profile $U2SA_VEHICLE names; so does `u2sa key`,
    # not /etc/u2sa/bus.key (which a test must never touch).
    from u2sa_hw.profile.loader import load_profile

    profile = profile_naming(tmp_path, "keys/rover.key")          # relative to the profile's directory
    env = {**without_key_env(), "U2SA_VEHICLE": str(profile)}
    system_key = Path("/etc/u2sa/bus.key")
    before = system_key.read_bytes() if system_key.exists() else None
    services_use = key_path(load_profile(profile).bus_key, env=env)    # what Transport and bus_client open
    assert services_use == tmp_path / "keys" / "rover.key"

    made = run_u2sa(["key", "rotate"], env)
    assert made.returncode == 0, made.stderr
    assert str(services_use) in made.stdout and services_use.exists()
    shown = run_u2sa(["key", "show", "--id"], env)
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.strip() == key_id(read_key(services_use)).hex()
    imported = run_u2sa(["key", "import", "-"], env, stdin=KEY_HEX + "\n")
    assert imported.returncode == 0, imported.stderr
    assert read_key(services_use) == bytes.fromhex(KEY_HEX)
    assert run_u2sa(["key", "show"], env).stdout.strip() == KEY_HEX
    assert (system_key.read_bytes() if system_key.exists() else None) == before


def test_a_key_pasted_into_bus_key_is_refused_at_load_without_printing_it(tmp_path: Path, lcm_url: str) -> None:
    from u2sa_hw.profile.vehicle import ProfileError
    from u2sa_hw.profile.loader import load_profile

    profile = profile_naming(tmp_path, KEY_HEX, lcm_url)
    with pytest.raises(ProfileError) as err:
        load_profile(profile)
    assert KEY_HEX not in str(err.value) and "\n" not in str(err.value)
    env = {**without_key_env(), "U2SA_VEHICLE": str(profile)}
    for args in (["service", "state_estimator"], ["services"], ["key", "show", "--id"]):
        r = run_u2sa(args, env)
        lines = r.stderr.strip().splitlines()
        assert r.returncode != 0 and "Traceback" not in r.stderr, (args, r.stderr)
        assert len(lines) == 1 and KEY_HEX not in r.stderr + r.stdout, (args, r.stderr)
        assert "bus_key holds a key" in lines[0] and "u2sa key import" in lines[0] and str(profile) in lines[0]
    # The fix the line gives works with the profile still broken (--file names the file, not the profile).
    stored = tmp_path / "stored.key"
    fixed = run_u2sa(["key", "import", "-", "--file", str(stored)], env, stdin=KEY_HEX + "\n")
    assert fixed.returncode == 0, fixed.stderr
    assert read_key(stored) == bytes.fromhex(KEY_HEX)


def test_a_user_outside_the_keys_group_is_told_how_to_get_access(tmp_path: Path, lcm_url: str) -> None:
    # End to end: the key root:root 0640 (as /etc/u2sa/bus.key is root:u2sa), the CLI run as nobody.
    if os.geteuid() != 0:
        pytest.skip("needs root to make a key file another user cannot read")
    with tempfile.TemporaryDirectory(prefix="u2sa-denied-") as tmp:
        directory = Path(tmp)
        directory.chmod(0o755)
        key = directory / "bus.key"
        key.write_text(KEY_HEX + "\n")
        os.chown(key, 0, 0)
        key.chmod(0o640)
        profile = profile_naming(directory, str(key), lcm_url)
        profile.chmod(0o644)
        env = {**without_key_env(), "U2SA_VEHICLE": str(profile)}
        for args in (["key", "show", "--id"], ["services"]):
            r = run_u2sa(args, env, as_user=True)
            lines = r.stderr.strip().splitlines()
            assert r.returncode == 1 and "Traceback" not in r.stderr, (args, r.stderr)
            assert len(lines) == 1, (args, r.stderr)
            assert f"cannot read the bus key {key} (permission denied)" in lines[0], lines[0]
            assert "sudo usermod -aG u2sa $USER" in lines[0] and "or use sudo" in lines[0], lines[0]
            assert KEY_HEX not in r.stdout + r.stderr
        assert run_u2sa(["key", "show", "--id"], env).returncode == 0     # root reads it: the file is fine


def test_operator_and_pilot_keys_are_made_beside_the_bus_key_and_shown(tmp_path: Path) -> None:
    bus = tmp_path / "vehicle" / "bus.key"
    assert u2sa("key", "rotate", "--file", str(bus)).returncode == 0
    pilot_key, pilot_pub = bus.parent / "pilot.key", bus.parent / "pilot.pub"   # rotate made the pair: none was there
    assert pilot_key.is_file() and pilot_pub.is_file()
    assert oct(pilot_key.stat().st_mode & 0o777) == oct(0o600) and pilot_pub.stat().st_mode & 0o044 == 0o044
    shown = u2sa("key", "show", "--pilot", "--file", str(bus))
    assert shown.returncode == 0 and bytes.fromhex(shown.stdout.strip()) == read_key(pilot_pub)
    from u2sa_hw.bus.pilot import pilot_key_id
    assert u2sa("key", "show", "--pilot", "--id", "--file", str(bus)).stdout.strip() == \
        pilot_key_id(read_key(pilot_pub)).hex()

    made = u2sa("key", "operator", "laptop", "--print", "--file", str(bus))
    assert made.returncode == 0, made.stderr
    stored = bus.parent / "operators" / "laptop.key"
    assert read_key(stored) == bytes.fromhex(made.stdout.strip()) and "U2SA_OPERATOR_KEY_FILE" in made.stderr
    again = u2sa("key", "operator", "laptop", "--file", str(bus))
    assert again.returncode == 1 and "exists" in again.stderr and read_key(stored).hex() == made.stdout.strip()
    for bad in ("", "../escape", ".hidden"):
        refused = u2sa("key", "operator", bad, "--file", str(bus))
        assert refused.returncode == 2 and "NAME of letters" in refused.stderr, bad
    assert sorted(p.name for p in (bus.parent / "operators").iterdir()) == ["laptop.key"]

    old_pub = read_key(pilot_pub)
    assert u2sa("key", "pilot", "--file", str(bus)).returncode == 0
    assert read_key(pilot_pub) != old_pub
    missing = u2sa("key", "show", "--pilot", "--file", str(tmp_path / "elsewhere" / "bus.key"))
    assert missing.returncode == 1 and "pilot.pub" in missing.stderr and "Traceback" not in missing.stderr


def test_rotate_says_services_switch_only_when_it_is_their_key(tmp_path: Path) -> None:
    theirs, other = tmp_path / "bus.key", tmp_path / "other.key"
    own = u2sa("key", "rotate", key=theirs)   # no --file: the services' key ($U2SA_BUS_KEY_FILE)
    assert own.returncode == 0 and "running services switch to it" in own.stdout, own.stdout
    again = u2sa("key", "rotate", "--file", str(theirs), key=theirs)
    assert again.returncode == 0 and "running services switch to it" in again.stdout, again.stdout
    elsewhere = u2sa("key", "rotate", "--file", str(other), key=theirs)
    assert elsewhere.returncode == 0 and "running services switch" not in elsewhere.stdout, elsewhere.stdout
    assert "no service uses it yet" in elsewhere.stdout and f"U2SA_BUS_KEY_FILE={other}" in elsewhere.stdout
