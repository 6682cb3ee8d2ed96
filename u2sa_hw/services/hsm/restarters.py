"""How the HSM restarts a service: through systemd, through the local launcher, or not at all.

``choose_restarter("auto", ...)`` picks, in order:

1. systemd, when the HSM itself runs as a unit (``$INVOCATION_ID`` is set by systemd);
2. the local launcher, when its control socket answers (``$U2SA_LAUNCHER_SOCKET``, set by
   ``u2sa run`` for its children, else ``<data_dir>/launcher.sock``);
3. systemd, when the service's unit is installed (``systemctl show`` says it is loaded);
4. none: problems are still detected, escalated and reported, but nothing is restarted.

systemd restarts go through ``systemctl restart --no-block``, which is systemd's D-Bus
``RestartUnit`` call with mode ``replace``; the project ships no D-Bus library, and
``--no-block`` keeps the HSM's loop (and so its own watchdog) from waiting on the job.

Before a restart the HSM asks :meth:`Restarter.started_within`: a service whose process was
started again (by systemd's or the launcher's own watchdog or restart rules) after the HSM
last heard from it is starting up, not hung, and is left alone.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path
from typing import Mapping, Protocol

from u2sa_hw.launcher.control import SOCKET_ENV, LauncherClient, LauncherError, default_socket_path
from u2sa_hw.profile.vehicle import VehicleProfile

RESTARTER_KINDS = ("auto", "systemd", "launcher", "none")
DEFAULT_UNIT_TEMPLATE = "u2sa@{name}.service"


class RestartError(RuntimeError):
    """A restart could not be requested; the message says why and what to do."""


class Restarter(Protocol):
    """Something that can restart a service by name."""

    kind: str

    def restart(self, service: str, *, reason: str) -> str:
        """Request the restart; return a short account, or raise RestartError."""

    def describe(self) -> str:
        """One line for the log: how restarts are done."""

    def started_within(self, service: str, seconds: float) -> bool | None:
        """True when *service*'s process started less than *seconds* ago or is being restarted; None: unknown."""


class SystemdRestarter:
    """Restarts ``u2sa@NAME.service`` (the unit template is configurable) with systemctl."""

    kind = "systemd"

    def __init__(self, *, unit_template: str = DEFAULT_UNIT_TEMPLATE, systemctl: str = "systemctl",
                 timeout_s: float = 10.0) -> None:
        if "{name}" not in unit_template:
            raise ValueError(f"unit_template {unit_template!r} must contain {{name}}, e.g. {DEFAULT_UNIT_TEMPLATE!r}")
        self.unit_template = unit_template
        self.systemctl = systemctl
        self.timeout_s = timeout_s

    def unit(self, service: str) -> str:
        """The unit name of *service*."""
        return self.unit_template.format(name=service)

    def restart(self, service: str, *, reason: str) -> str:
        """``systemctl restart --no-block UNIT``."""
        unit = self.unit(service)
        try:
            done = subprocess.run([self.systemctl, "restart", "--no-block", unit], capture_output=True,
                                  text=True, timeout=self.timeout_s)
        except FileNotFoundError:
            raise RestartError(f"cannot restart {unit}: '{self.systemctl}' not found") from None
        except subprocess.TimeoutExpired:
            raise RestartError(f"systemctl restart {unit} did not return within {self.timeout_s:g} s") from None
        if done.returncode != 0:
            detail = (done.stderr or done.stdout).strip() or f"exit status {done.returncode}"
            raise RestartError(f"systemctl restart {unit} failed: {detail}")
        return f"restart of {unit} queued with systemd"

    def unit_loaded(self, service: str) -> bool:
        """True when systemd knows the unit of *service*."""
        if shutil.which(self.systemctl) is None:
            return False
        try:
            done = subprocess.run([self.systemctl, "show", "--property=LoadState", "--value", self.unit(service)],
                                  capture_output=True, text=True, timeout=self.timeout_s)
        except (OSError, subprocess.TimeoutExpired):
            return False
        return done.returncode == 0 and done.stdout.strip() == "loaded"

    def describe(self) -> str:
        """How restarts are done."""
        return f"systemd ({self.systemctl} restart --no-block {self.unit_template})"

    def started_within(self, service: str, seconds: float) -> bool | None:
        """From ``systemctl show``: restarting (activating, auto-restart), or its main process's start time."""
        props = "ActiveState,SubState,ExecMainStartTimestampMonotonic"
        try:
            done = subprocess.run([self.systemctl, "show", f"--property={props}", self.unit(service)],
                                  capture_output=True, text=True, timeout=self.timeout_s)
        except (OSError, subprocess.TimeoutExpired):
            return None
        if done.returncode != 0:
            return None
        values = dict(line.partition("=")[::2] for line in done.stdout.splitlines())
        if values.get("ActiveState") in ("activating", "deactivating") or values.get("SubState") == "auto-restart":
            return True
        try:
            started_us = int(values.get("ExecMainStartTimestampMonotonic", ""))
        except ValueError:
            return None
        # systemd's CLOCK_MONOTONIC is ours: one clock per machine (and per PID namespace).
        return started_us > 0 and time.monotonic() - started_us / 1e6 < seconds


class LauncherRestarter:
    """Asks the local launcher (``u2sa run``) over its control socket."""

    kind = "launcher"

    def __init__(self, socket_path: Path | str, *, timeout_s: float = 3.0) -> None:
        self.client = LauncherClient(socket_path, timeout=timeout_s)

    def restart(self, service: str, *, reason: str) -> str:
        """Request the restart; the launcher stops the service (if alive) and starts it again."""
        try:
            status = self.client.restart(service, reason=reason)
        except LauncherError as exc:
            raise RestartError(str(exc)) from None
        return f"launcher restarting {service} (was {status.get('state')}, run {status.get('run_id')})"

    def supervised(self) -> set[str] | None:
        """The services the launcher runs, or None when it does not answer."""
        try:
            return {s["name"] for s in self.client.status()}
        except LauncherError:
            return None

    def describe(self) -> str:
        """How restarts are done."""
        return f"launcher (control socket {self.client.path})"

    def started_within(self, service: str, seconds: float) -> bool | None:
        """From the launcher's status: in backoff or stopping (being restarted), or its run's uptime."""
        try:
            status = next((s for s in self.client.status() if s.get("name") == service), None)
        except LauncherError:
            return None
        if status is None:
            return None
        if status.get("state") in ("backoff", "stopping"):
            return True
        return status.get("state") == "running" and float(status.get("uptime_s", 1e9)) < seconds


class NoRestarter:
    """Restarts nothing; says why each time it is asked."""

    kind = "none"

    def __init__(self, why: str) -> None:
        self.why = why

    def restart(self, service: str, *, reason: str) -> str:
        """Always RestartError: there is nothing to restart with."""
        raise RestartError(f"cannot restart {service}: {self.why}")

    def describe(self) -> str:
        """How restarts are done."""
        return f"none ({self.why})"

    def started_within(self, service: str, seconds: float) -> bool | None:
        """Unknown: there is no supervisor to ask."""
        return None


def launcher_socket(profile: VehicleProfile, env: Mapping[str, str]) -> Path:
    """The control socket a launcher of this HSM would listen on."""
    return Path(env.get(SOCKET_ENV) or default_socket_path(profile.data_dir))


def choose_restarter(kind: str, *, profile: VehicleProfile, services: list[str],
                     unit_template: str = DEFAULT_UNIT_TEMPLATE, env: Mapping[str, str] | None = None) -> Restarter:
    """The restarter for *kind* (``auto``, ``systemd``, ``launcher``, ``none``); see the module docstring."""
    env = os.environ if env is None else env
    if kind not in RESTARTER_KINDS:
        raise ValueError(f"the HSM's config field restarter = '{kind}' is not one of {', '.join(RESTARTER_KINDS)}")
    if kind == "none":
        return NoRestarter("restarter = \"none\" in the HSM's config")
    if kind == "systemd":
        return SystemdRestarter(unit_template=unit_template)
    socket_path = launcher_socket(profile, env)
    launcher = LauncherRestarter(socket_path)
    if kind == "launcher":
        return launcher
    if env.get("INVOCATION_ID"):
        return SystemdRestarter(unit_template=unit_template)
    if launcher.supervised() is not None:
        return launcher
    systemd = SystemdRestarter(unit_template=unit_template)
    if services and systemd.unit_loaded(services[0]):
        return systemd
    return NoRestarter(f"not under systemd ($INVOCATION_ID unset, {systemd.unit(services[0]) if services else 'no unit'} "
                       f"not loaded) and no launcher answers on {socket_path}; start the stack with 'u2sa run' "
                       "or install the units with 'u2sa install'")
