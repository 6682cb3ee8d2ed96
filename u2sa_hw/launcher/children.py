"""The launcher's children: which services it runs, with which command, environment and watchdog.

:func:`select_services` picks the profile's services, :func:`u2sa_command` is how a child runs
(``u2sa service NAME --vehicle FILE``, with this interpreter), :func:`child_environment` what it
gets as a systemd unit would (``$NOTIFY_SOCKET``, ``$STATE_DIRECTORY``, the launcher's control
socket), and :func:`watchdog_setting` its unit's watchdog.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from u2sa_hw.bus.clock import STATE_ENV
from u2sa_hw.launcher.control import SOCKET_ENV
from u2sa_hw.launcher.watchdog import WatchdogSetting, watchdog_for
from u2sa_hw.profile.vehicle import ServiceSpec, VehicleProfile


def u2sa_command() -> list[str]:
    """The argv prefix that runs the ``u2sa`` command with this very interpreter."""
    return [sys.executable, "-m", "u2sa_hw.cli"]


def select_services(profile: VehicleProfile, only: list[str] | None = None) -> list[ServiceSpec]:
    """The services to start: those named in *only* (even if disabled), else every enabled one."""
    if only:
        unknown = [n for n in only if n not in profile.services]
        if unknown:
            raise ValueError(f"{profile.path}: no service {', '.join(unknown)} "
                             f"(services: {', '.join(profile.services) or 'none'})")
        return [profile.services[n] for n in only]
    specs = [s for s in profile.services.values() if s.enabled]
    if not specs:
        raise ValueError(f"{profile.path or 'the vehicle profile'}: no enabled services to run; "
                         "add [services.NAME] tables with kind = \"...\"")
    return specs


def watchdog_setting(kind: str, override_s: float | None) -> WatchdogSetting:
    """The unit file's watchdog for *kind*, its timeout replaced by *override_s* when given (0: off)."""
    setting = watchdog_for(kind)
    if override_s is None:
        return setting
    return WatchdogSetting(max(0.0, override_s), setting.abort_s, "override")


def child_environment(profile: VehicleProfile, *, notify_socket: str, control_socket: Path | None,
                      env: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of every child: this one's, *env* over it, and what systemd gives a unit."""
    # PYTHONFAULTHANDLER as in the units: a child killed by the watchdog's SIGABRT prints its stacks.
    # STATE_DIRECTORY as systemd's StateDirectory= gives it: the bus clock is saved there (u2sa_hw.bus.clock).
    child_env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1",
                 STATE_ENV: str(Path(profile.data_dir).resolve()), **(env or {}),
                 "NOTIFY_SOCKET": notify_socket}
    if control_socket is not None:
        child_env[SOCKET_ENV] = str(control_socket)
    return child_env
