"""Helpers shared by the launcher and HSM tests: profiles and `u2sa run` as a real process."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path
from typing import Any, Iterator

import pytest

from u2sa_hw.launcher import LauncherClient, LauncherError
from u2sa_hw.launcher.launcher import u2sa_command


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


