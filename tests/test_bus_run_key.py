"""``u2sa run`` without any key signs the run with a fresh one and says where (issue 11, "Keys");
a ``bus_key`` the profile names must exist.

Real processes: the launcher and its service on a private bus; the key file the launcher
printed lets ``u2sa services`` in; the test session's own key is a stranger to that run.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
from pathlib import Path

import pytest
from conftest import U2SA, wait_until

from u2sa_hw.bus.key import KEY_ENV, SYSTEM_KEY, read_key

SERVICE = "state_estimator"


def test_run_with_a_missing_bus_key_says_so_in_one_line_and_makes_none(tmp_path: Path, lcm_url: str) -> None:
    missing = tmp_path / "keys" / "rover.key"
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "rover"\nlcm_url = "{lcm_url}"\nbus_key = "{missing}"\n'
                       f'[services.{SERVICE}]\nkind = "{SERVICE}"\n')
    env = {k: v for k, v in os.environ.items() if k != KEY_ENV}
    done = subprocess.run([*U2SA, "run", "--vehicle", str(profile), "--no-color"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    (line,) = [x for x in done.stderr.splitlines() if x.startswith("u2sa: run:")]   # after u2sa check's warnings
    assert f'bus_key = "{missing}" does not exist' in line and str(profile) in line
    assert f"u2sa key rotate --file {missing}" in line and "remove bus_key" in line
    assert "fresh key" not in done.stdout and not missing.exists()
    assert "started, pid" not in done.stdout, "nothing started"


def test_run_without_any_key_makes_one_for_the_run(tmp_path: Path, lcm_url: str) -> None:
    if SYSTEM_KEY.exists():
        pytest.skip(f"{SYSTEM_KEY} is installed here: u2sa run signs with it")
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "bench"\nlcm_url = "{lcm_url}"\n'
                       f'[services.{SERVICE}]\nkind = "{SERVICE}"\n')
    env = {k: v for k, v in os.environ.items() if k != KEY_ENV}    # no key in the environment, no bus_key
    out_path = tmp_path / "run.out"
    with open(out_path, "wb") as out:
        run = subprocess.Popen([*U2SA, "run", "--vehicle", str(profile), "--no-color"], cwd=tmp_path, env=env,
                               stdout=out, stderr=subprocess.STDOUT)
    try:
        said = wait_until(lambda: re.search(r"signs with a fresh key (\S+) ", out_path.read_text(errors="replace")),
                          timeout=60, message="the launcher to say which key the run signs with")
        key = Path(said.group(1))
        assert read_key(key)

        def listed(with_key: str) -> list[dict[str, object]]:
            r = subprocess.run([*U2SA, "services", "--json", "--vehicle", str(profile), "--timeout", "1"],
                               env={**env, KEY_ENV: with_key}, capture_output=True, text=True, timeout=60)
            return json.loads(r.stdout) if r.returncode == 0 else []

        found = wait_until(lambda: listed(str(key)), timeout=60, message="the run's service, with the run's key")
        assert [s["name"] for s in found] == [SERVICE] and str(found[0]["bus"]).startswith("signed")
        assert listed(os.environ[KEY_ENV]) == []    # the session's key is another one
    finally:
        run.send_signal(signal.SIGINT)
        try:
            run.wait(timeout=30)
        except subprocess.TimeoutExpired:
            run.kill()
            run.wait()
    assert not key.exists()    # the run's key goes with the run
