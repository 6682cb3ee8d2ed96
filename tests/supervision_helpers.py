"""Helpers shared by the launcher and HSM tests: profiles and `u2sa run` as a real process."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from pathlib import Path
from typing import Any, Iterator

import pytest

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.launcher import LauncherClient, LauncherError
from u2sa_hw.launcher.children import u2sa_command


def write_profile(tmp: Path, url: str, services: dict[str, str], *, health_interval: float = 0.2,
                  extra: str = "") -> Path:
    """A vehicle profile with one service per name -> kind, fast health, and *extra* TOML appended."""
    lines = ["[vehicle]", 'name = "bench"', f'lcm_url = "{url}"', ""]
    for name, kind in services.items():
        lines += [f"[services.{name}]", f'kind = "{kind}"',
                  f"settings = {{ health_interval_s = {health_interval} }}", ""]
    path = tmp / "vehicle.toml"
    path.write_text("\n".join(lines) + extra)
    return path


BROKEN_CONFIG_ERROR = "not valid TOML"


def break_config(tmp: Path, name: str) -> None:
    """Give service *name* (of a profile in *tmp*) a config file that is not TOML: it exits 1 at every start."""
    (tmp / "config").mkdir(exist_ok=True)
    (tmp / "config" / f"{name}.toml").write_text("this is = = not toml\n")


class LauncherProcess:
    """`u2sa run` as a real process with its output in a file."""

    def __init__(self, profile: Path, *args: str) -> None:
        self.out_path = profile.parent / "launcher.out"
        self._out = open(self.out_path, "wb")
        self.proc = subprocess.Popen([*u2sa_command(), "run", "--vehicle", str(profile), "--no-color", *args],
                                     stdout=self._out, stderr=subprocess.STDOUT, cwd=profile.parent,
                                     env=dict(os.environ, PYTHONUNBUFFERED="1"))
        self.client = LauncherClient(profile.parent / "data" / "launcher.sock", timeout=5.0)

    @property
    def output(self) -> str:
        return self.out_path.read_text(errors="replace")

    def status(self) -> dict[str, dict[str, Any]]:
        try:
            return {s["name"]: s for s in self.client.status()}
        except LauncherError:
            return {}

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._out.close()
        print(f"--- output of u2sa run (exit {self.proc.returncode}) ---\n{self.output}")  # shown when a test fails


@pytest.fixture
def launch() -> Iterator[Any]:
    """Start `u2sa run` processes; SIGINT (then SIGKILL) whatever is left at the end."""
    started: list[LauncherProcess] = []

    def start(profile: Path, *args: str) -> LauncherProcess:
        lp = LauncherProcess(profile, *args)
        started.append(lp)
        return lp

    yield start
    for lp in started:
        lp.close()


# Services beat every 0.2 s; 10 missed beats (2 s) before "missing" keeps a loaded CI machine from
# looking like a hang, and the grace covers a slow Python start.
HSM_SETTINGS = ("health_interval_s = 0.2, missed_heartbeats = 10, restart_backoff_s = 0.5, max_restarts = 2, "
                "system_health_interval_s = 0.2")


def hsm_profile(tmp: Path, url: str, services: str, *, startup_grace_s: float,
                hsm_settings: str = HSM_SETTINGS) -> Path:
    """A profile with the TOML *services* and an HSM with fast test settings."""
    path = tmp / "vehicle.toml"
    path.write_text(f'[vehicle]\nname = "bench"\nlcm_url = "{url}"\n\n{services}\n[services.hsm]\nkind = "hsm"\n'
                    f"settings = {{ {hsm_settings}, startup_grace_s = {startup_grace_s} }}\n")
    return path


class Watch:
    """Collects Health pids and newest stamps per service, SystemHealth and Failsafe messages from the bus."""

    def __init__(self, bus: BusClient) -> None:
        self.pids: dict[str, list[int]] = {}
        self.stamps: dict[str, int] = {}   # name -> header.timestamp_us of its newest Health
        self.details: dict[str, dict[str, str]] = {}   # name -> the details of its newest Health
        self.system: list[t.SystemHealth] = []
        self.failsafes: list[t.Failsafe] = []
        self._lock = threading.Lock()
        bus.transport.subscribe(ch.HEALTH, t.Health, self._health)
        bus.transport.subscribe(ch.SYSTEM_HEALTH, t.SystemHealth, lambda _c, m: self._add(self.system, m))
        bus.transport.subscribe(ch.FAILSAFE, t.Failsafe, lambda _c, m: self._add(self.failsafes, m))

    def _add(self, items: list[Any], msg: Any) -> None:
        with self._lock:
            items.append(msg)

    def _health(self, _c: str, msg: t.Health) -> None:
        with self._lock:
            pids = self.pids.setdefault(msg.name, [])
            if not pids or pids[-1] != msg.pid:
                pids.append(msg.pid)
            self.stamps[msg.name] = max(self.stamps.get(msg.name, 0), msg.header.timestamp_us)
            self.details[msg.name] = {kv.key: kv.value for kv in msg.details}

    def latest(self) -> t.SystemHealth | None:
        """The newest SystemHealth."""
        with self._lock:
            return self.system[-1] if self.system else None

    def service_state(self, name: str) -> t.ServiceState | None:
        with self._lock:
            latest = self.system[-1] if self.system else None
        return next((s for s in latest.services if s.name == name), None) if latest else None
