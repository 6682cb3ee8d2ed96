"""What a child does between fork and exec: die with the launcher, join a cgroup, take its priority.

It runs in the forked child before ``exec`` (``preexec_fn``), so every run of a service,
restarts included, is in the cgroup and at its priority from its first instruction. The
order matters:

1. ``PR_SET_PDEATHSIG``: a SIGKILLed launcher leaves no orphans.
2. If it is to join a cgroup and was forked real-time (``u2sa sim`` runs its own threads
   real-time, and a fork inherits that), it drops to normal priority first: in cgroup v1 a
   ``SCHED_FIFO`` task cannot enter a ``cpu`` group whose ``cpu.rt_runtime_us`` is 0 (EINVAL).
3. It writes ``0`` (itself, in v1 and v2) to ``<cgroup>/cgroup.procs`` (``tasks`` in a v1
   hierarchy without ``cgroup.procs``). Failing is an error: the child does not exec.
4. It sets its scheduling policy. Inside a v1 ``cpu`` group without an RT budget
   (``cpu.rt_runtime_us`` 0) ``SCHED_FIFO`` is refused (EPERM): the child runs at normal
   priority, and the launcher says why.

Failures cross back to the launcher on a pipe (a ``preexec_fn`` exception alone reaches
the parent only as "Exception occurred in preexec_fn"). Only async-signal-safe-ish calls
here: ``os.open``/``os.write``, no Python file objects (their locks may be held by another
thread of the launcher at the fork).
"""

from __future__ import annotations

import ctypes
import errno
import os
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from u2sa_hw.realtime import NORMAL, Schedule

_PR_SET_PDEATHSIG = 1
try:
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):  # not Linux: children simply outlive a killed launcher
    _PRCTL = None

ERROR_MARK, WARNING_MARK = b"E", b"W"


class CgroupError(ValueError):
    """The cgroup given to the launcher cannot take its children; the message names it and the fix."""


def procs_file(cgroup: Path) -> Path:
    """The file a process writes its pid to, to join *cgroup*: ``cgroup.procs`` (v2, and v1 since 3.x) or ``tasks``."""
    for name in ("cgroup.procs", "tasks"):
        if (cgroup / name).exists():
            return cgroup / name
    raise CgroupError(f"{cgroup}: not a cgroup directory (no cgroup.procs or tasks in it); make it first, e.g. "
                      f"mkdir {cgroup} under /sys/fs/cgroup (v2) or /sys/fs/cgroup/cpu (v1)")


def check_cgroup(cgroup: Path) -> Path:
    """The procs file of *cgroup*, after checking that this process may write it; CgroupError otherwise."""
    path = procs_file(cgroup)
    if not os.access(path, os.W_OK):
        raise CgroupError(f"{path}: not writable by uid {os.geteuid()}: the launcher's children cannot join "
                          f"cgroup {cgroup} (run as root, or chown the cgroup to this user)")
    return path


def explain_join(cgroup: Path, err: int) -> str:
    """Why joining *cgroup* failed with *err*, with the fix."""
    text = f"cannot join cgroup {cgroup}: {os.strerror(err)}"
    if err == errno.EINVAL:
        text += " (a real-time task cannot enter a cgroup v1 cpu group with cpu.rt_runtime_us 0: give it an RT budget)"
    elif err == errno.EBUSY:
        text += " (cgroup v2: processes may only join a group with no controllers in its cgroup.subtree_control)"
    return text


def explain_schedule(schedule: Schedule, cgroup: Path | None, err: int) -> str:
    """Why *schedule* was refused with *err*, with the fix."""
    text = f"{schedule.describe()} refused ({os.strerror(err)})"
    if cgroup is not None and err == errno.EPERM:
        text += (f" inside cgroup {cgroup}: in cgroup v1 a cpu group needs an RT budget, e.g. "
                 f"echo 100000 > {cgroup}/cpu.rt_runtime_us")
    return text + "; it runs at normal priority"


@dataclass(frozen=True)
class ChildSetup:
    """The set-up of one child: its cgroup (None: the launcher's) and its schedule (None: inherited)."""

    cgroup: Path | None = None
    schedule: Schedule | None = None

    def preexec(self, report_fd: int) -> Callable[[], None]:
        """The function to run in the child before exec; problems go to *report_fd* (see :func:`read_report`).

        The cgroup's procs file is found here, in the launcher (CgroupError when there is none).
        """
        procs = os.fsencode(procs_file(self.cgroup)) if self.cgroup is not None else None
        schedule, cgroup = self.schedule, self.cgroup

        def run() -> None:
            if _PRCTL is not None:
                _PRCTL(_PR_SET_PDEATHSIG, int(signal.SIGTERM))
            if procs is not None and cgroup is not None:
                if os.sched_getscheduler(0) != os.SCHED_OTHER:
                    os.sched_setscheduler(0, NORMAL.policy, os.sched_param(0))   # step 2 above
                try:
                    fd = os.open(procs, os.O_WRONLY)
                    try:
                        os.write(fd, b"0")
                    finally:
                        os.close(fd)
                except OSError as exc:
                    os.write(report_fd, ERROR_MARK + explain_join(cgroup, exc.errno or 0).encode())
                    raise
            if schedule is not None:
                try:
                    os.sched_setscheduler(0, schedule.policy, os.sched_param(schedule.priority))
                except OSError as exc:
                    os.write(report_fd, WARNING_MARK + explain_schedule(schedule, cgroup, exc.errno or 0).encode())

        return run


def read_report(fd: int) -> tuple[str | None, str | None]:
    """``(error, warning)`` a child's :meth:`ChildSetup.preexec` left on the pipe *fd* (read end, writers closed)."""
    data = b""
    while True:
        try:
            chunk = os.read(fd, 4096)
        except BlockingIOError:
            break
        if not chunk:
            break
        data += chunk
    if data.startswith(ERROR_MARK):
        return data[1:].decode(errors="replace"), None
    if data.startswith(WARNING_MARK):
        return None, data[1:].decode(errors="replace")
    return None, None
