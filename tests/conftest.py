"""Shared fixtures: a private LCM URL per test and real service processes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterator

import pytest

import unprivileged_env
from u2sa_hw.bus.key import KEY_ENV
from u2sa_hw.bus.run_keys import fresh_key_file
from u2sa_hw.bus.udp_ports import private_lcm_url
from u2sa_hw.service.bus_handlers import PROBE_ENV

REPO = Path(__file__).resolve().parent.parent
U2SA = [sys.executable, "-m", "u2sa_hw.cli"]


_SESSION_KEY_DIR: tempfile.TemporaryDirectory | None = None


def pytest_configure(config: pytest.Config) -> None:
    """A fresh bus key for this test session, in $U2SA_BUS_KEY_FILE before any test module is imported.

    Every process a test starts inherits it, so the session's buses are signed with a key of
    their own: another session (or a vehicle) on this machine is heard only as forged packets.
    """
    global _SESSION_KEY_DIR
    _SESSION_KEY_DIR = tempfile.TemporaryDirectory(prefix="u2sa-test-key-")
    key = fresh_key_file(_SESSION_KEY_DIR.name)
    # Some tests run a service as nobody (see unprivileged()): a test key may be world-readable.
    os.chmod(_SESSION_KEY_DIR.name, 0o755)
    os.chmod(key, 0o644)
    os.environ[KEY_ENV] = str(key)
    # A starting service listens 0.3 s for another of its name (u2sa_hw/service/bus_handlers.py); the tests
    # start hundreds, each on a bus of its own, so they listen a little less. The tests of the
    # duplicate check itself give the default back (DUPLICATE_PROBE_S) where they rely on it.
    os.environ.setdefault(PROBE_ENV, "0.25")
    # Simulations at normal priority: two side by side (pytest-xdist) at one SCHED_FIFO priority
    # would not share a CPU by time slices (simulation/runner.py, SIM_REALTIME_ENV). The tests of
    # real-time priority set it up themselves.
    os.environ.setdefault("U2SA_SIM_REALTIME", "off")


def pytest_unconfigure(config: pytest.Config) -> None:
    """Remove the session's key, and what unprivileged() staged."""
    if _SESSION_KEY_DIR is not None:
        _SESSION_KEY_DIR.cleanup()
    unprivileged_env.remove_stage()


def wait_until(predicate: Callable[[], object], *, timeout: float = 10.0, interval: float = 0.02,
               message: str = "condition") -> object:
    """Poll *predicate* until it returns something truthy; fail the test after *timeout*."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {message}")
        time.sleep(interval)


def unprivileged(cmd: list[str]) -> list[str]:
    """*cmd* run as user nobody when we are root (root ignores file permissions); skip without setpriv.

    A *cmd* that starts with ``sys.executable`` runs a Python nobody can run, with this checkout's
    u2sa_hw: this one, or one staged where nobody can read it when the checkout or the interpreter
    is in a directory other users cannot enter (tests/unprivileged_env.py).
    """
    if os.geteuid() != 0:
        return cmd
    if shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: cannot make a file unwritable")
    if cmd and cmd[0] == sys.executable:
        cmd = [*unprivileged_env.python_for_nobody(), *cmd[1:]]
    return [*unprivileged_env.as_nobody(), *cmd]


@pytest.fixture
def lcm_url(monkeypatch: pytest.MonkeyPatch) -> str:
    """A multicast URL on a port of this test's own, exported as $U2SA_LCM_URL."""
    url = private_lcm_url()
    monkeypatch.setenv("U2SA_LCM_URL", url)
    return url


class ServiceProcesses:
    """Starts ``u2sa service`` processes in a working directory and cleans them up."""

    def __init__(self, workdir: Path, url: str) -> None:
        self.workdir = workdir
        self.url = url
        self.procs: list[subprocess.Popen] = []

    def env(self, **extra: str) -> dict[str, str]:
        env = dict(os.environ, U2SA_LCM_URL=self.url, PYTHONUNBUFFERED="1")
        env.update(extra)
        return env

    def start(self, name: str, *args: str, **env: str) -> subprocess.Popen:
        log = open(self.workdir / f"{name}.stderr", "wb")
        proc = subprocess.Popen([*U2SA, "service", name, *args], cwd=self.workdir, env=self.env(**env),
                                stdout=log, stderr=subprocess.STDOUT)
        self.procs.append(proc)
        return proc

    def cli(self, *args: str, timeout: float = 30.0) -> subprocess.CompletedProcess:
        return subprocess.run([*U2SA, *args], cwd=self.workdir, env=self.env(), capture_output=True,
                              text=True, timeout=timeout)

    def stop_all(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.fixture
def services(tmp_path: Path, lcm_url: str) -> Iterator[ServiceProcesses]:
    """Real service processes on this test's LCM URL, stopped at the end."""
    sp = ServiceProcesses(tmp_path, lcm_url)
    yield sp
    sp.stop_all()


@pytest.fixture
def bus(lcm_url: str) -> Iterator[object]:
    """A BusClient on this test's LCM URL."""
    from u2sa_hw.bus.client import BusClient

    client = BusClient(lcm_url)
    yield client
    client.close()
