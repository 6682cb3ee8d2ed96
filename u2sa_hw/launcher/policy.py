"""The states of a supervised child and the rules that move it between them.

The states (``RUNNING`` ... ``FAILED``; u2sa_hw/launcher/process.py's docstring tells them), the
:class:`RestartPolicy` that judges each death (backoff, giving up, final exit statuses),
:class:`ProcessStatus` (the snapshot ``status`` and the control socket report),
:func:`describe_exit`, and what a stop waits for (``STOP_LIMIT_S``, :class:`StopWait`). Nothing here touches a process: :class:`~u2sa_hw.launcher.process.SupervisedProcess`
applies them.
"""

from __future__ import annotations

import signal
from dataclasses import dataclass

RUNNING = "running"
STOPPING = "stopping"
BACKOFF = "backoff"
EXITED = "exited"      # exited with status 0 on its own: not restarted (like systemd's on-failure)
STOPPED = "stopped"    # stopped because we asked
FAILED = "failed"      # given up: too many quick deaths in a row, failed exits within the window, a refusal
REFUSED_EXIT = 3       # service_bus.DUPLICATE_EXIT: refused to start (RestartPreventExitStatus=3 in u2sa@.service)
STOP_LIMIT_S = 30.0    # the most a stop waits, in real time from the SIGTERM, for a child that keeps making progress

@dataclass(frozen=True)
class RestartPolicy:
    """Respawn rules: backoff that doubles on quick deaths and decays after healthy uptime; when to give up.

    Two give-up rules: ``give_up_after`` quick deaths in a row, and ``max_failures``
    failed exits (non-zero status, a signal, a failed exec) within ``failure_window_s``,
    whatever the uptime before each. 0 turns a rule off. An exit status in ``final_statuses``
    is never restarted (systemd's ``RestartPreventExitStatus=``).
    """

    initial_backoff_s: float = 0.5
    max_backoff_s: float = 30.0
    quick_death_s: float = 5.0
    give_up_after: int = 5
    max_failures: int = 10
    failure_window_s: float = 300.0
    final_statuses: tuple[int, ...] = (REFUSED_EXIT,)

    def __post_init__(self) -> None:
        if self.initial_backoff_s < 0 or self.max_backoff_s < self.initial_backoff_s:
            raise ValueError(f"restart policy: need 0 <= initial_backoff_s ({self.initial_backoff_s}) "
                             f"<= max_backoff_s ({self.max_backoff_s})")
        if self.quick_death_s <= 0 or self.give_up_after < 0:
            raise ValueError("restart policy: quick_death_s must be > 0 and give_up_after >= 0 (0 = never give up)")
        if self.max_failures < 0 or self.failure_window_s <= 0:
            raise ValueError(f"restart policy: need max_failures >= 0 (0 = no limit, got {self.max_failures}) and "
                             f"failure_window_s > 0 (got {self.failure_window_s})")

    def after_death(self, quick_deaths: int, uptime_s: float) -> tuple[int, float]:
        """``(quick deaths now, respawn delay)`` after a death following *uptime_s* of running.

        A quick death adds one; each full ``quick_death_s`` of uptime forgives one (so the
        delay halves per healthy period). The delay is ``initial * 2**(quick deaths - 1)``,
        capped at ``max_backoff_s``.
        """
        if uptime_s < self.quick_death_s:
            quick = quick_deaths + 1
        else:
            quick = max(0, quick_deaths - int(uptime_s // self.quick_death_s))
        delay = self.initial_backoff_s * 2 ** max(0, quick - 1)
        return quick, min(self.max_backoff_s, delay)

    def gives_up(self, quick_deaths: int) -> bool:
        """True when *quick_deaths* in a row mean the process keeps failing."""
        return self.give_up_after > 0 and quick_deaths >= self.give_up_after

    def too_many_failures(self, failures: int) -> bool:
        """True when *failures* failed exits within ``failure_window_s`` mean the process keeps failing."""
        return self.max_failures > 0 and failures >= self.max_failures


@dataclass(frozen=True)
class ProcessStatus:
    """A snapshot of one supervised process (what ``status`` and the control socket report)."""

    name: str
    desired: str
    state: str
    pid: int | None
    run_id: int
    restarts: int
    quick_deaths: int
    failures: int          # failed exits within the policy's window
    backoff_s: float
    uptime_s: float
    last_exit: str
    reason: str
    ready: bool = False    # this run sent READY=1 (on the launcher's NOTIFY_SOCKET)
    status_text: str = ""  # its latest STATUS=
    result: str = ""       # how the last run ended, in systemd's words: exit-code, signal, watchdog ("" yet)
    watchdog_kills: int = 0   # runs killed because they stopped pinging WATCHDOG=1
    watchdog_s: float = 0.0   # the watchdog timeout (WATCHDOG_USEC), 0 = off

    def as_dict(self) -> dict[str, object]:
        """JSON-ready form."""
        return dict(self.__dict__)


def describe_exit(returncode: int) -> str:
    """``exited with status 1`` / ``killed by SIGKILL``."""
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exited with status {returncode}"


@dataclass
class StopWait:
    """One stop of one run: when it was asked, and the child's latest sign of progress (see enforce_stop)."""

    grace_s: float
    started_at: float                  # clock() of the SIGTERM (real time: the bound)
    asked_at: float | None = None      # watch_clock() at the launcher's first turn after it
    progress_at: float | None = None   # watch_clock() of the latest sign of progress since the acknowledgement
    ticks: int | None = None           # CPU ticks at the latest sample
    killed: bool = False               # SIGKILL sent: nothing more to decide
