"""A stopped child is killed with SIGKILL and never resumed: a frozen command source must not command again.

The child below ignores SIGABRT (as if faulthandler were busy printing its stacks) and
writes a file the moment it runs again after its SIGSTOP: with SIGABRT + SIGCONT it would.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
from pathlib import Path
from typing import Iterator

from conftest import wait_until
from test_launcher_watchdog import SLEEPER, FakeClock

from u2sa_hw.launcher import RestartPolicy, SupervisedProcess
from u2sa_hw.launcher.policy import BACKOFF
from u2sa_hw.launcher.process import process_stopped
from u2sa_hw.launcher.watchdog import WatchdogSetting

FREEZES = ("import os, signal\n"
           "signal.signal(signal.SIGABRT, signal.SIG_IGN)\n"
           "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
           "os.kill(os.getpid(), signal.SIGSTOP)\n"
           "open('resumed', 'w').write('a command published after the freeze')\n")


@contextlib.contextmanager
def _reaped(child: subprocess.Popen[bytes]) -> Iterator[subprocess.Popen[bytes]]:
    """*child*, killed and waited for at the end if the test left it alive."""
    try:
        yield child
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def _frozen(tmp_path: Path, clock: FakeClock) -> SupervisedProcess:
    p = SupervisedProcess("control", [sys.executable, "-c", FREEZES], policy=RestartPolicy(), clock=clock,
                          cwd=str(tmp_path), watchdog=WatchdogSetting(timeout_s=2.0, abort_s=1.0))
    child = p.spawn()
    wait_until(lambda: process_stopped(child.pid), timeout=30, message="the child stopped itself")
    return p


def test_a_stopped_child_gets_sigkill_from_the_watchdog_and_never_runs_again(tmp_path: Path) -> None:
    clock = FakeClock()
    p = _frozen(tmp_path, clock)
    assert p.proc is not None
    with _reaped(p.proc) as child:
        p.on_notify({"READY": "1"})
        clock.now += 2.5
        fired = p.check_watchdog()
        assert fired == ("watchdog timeout (no WATCHDOG=1 for 2.5 s, limit 2 s): it was stopped, so SIGKILL "
                         "without resuming it (no stack dump)")
        assert child.wait(timeout=30) == -signal.SIGKILL
    account = p.poll()
    assert account is not None and account.startswith("watchdog timeout, killed by SIGKILL")
    assert (p.state, p.result, p.watchdog_kills) == (BACKOFF, "watchdog", 1)
    assert not (tmp_path / "resumed").exists()


def test_a_stopped_child_asked_to_stop_or_restart_gets_sigkill_without_being_resumed(tmp_path: Path) -> None:
    clock = FakeClock()
    p = _frozen(tmp_path, clock)
    assert p.proc is not None
    with _reaped(p.proc) as child:
        p.restart("HSM: no heartbeat", grace_s=5.0)      # what the HSM asks for a hung service
        assert child.wait(timeout=30) == -signal.SIGKILL
    account = p.poll()
    assert account == ("killed by SIGKILL (it was stopped: killed without resuming it); restarting now "
                       "(requested: HSM: no heartbeat)")
    assert not (tmp_path / "resumed").exists()


def test_a_running_child_still_gets_sigabrt_for_its_stacks() -> None:
    clock = FakeClock()
    p = SupervisedProcess("est", SLEEPER, policy=RestartPolicy(), clock=clock,
                          watchdog=WatchdogSetting(timeout_s=2.0, abort_s=1.0))
    with _reaped(p.spawn()) as child:
        assert not process_stopped(child.pid)
        p.on_notify({"READY": "1"})
        clock.now += 2.5
        assert (p.check_watchdog() or "").endswith(": SIGABRT, SIGKILL in 1 s")
        assert child.wait(timeout=30) == -signal.SIGABRT
    assert not process_stopped(999_999_999)   # no such process: not stopped
