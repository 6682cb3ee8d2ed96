"""A stop waits on the child's exit, not on a clock (issue 26 item 8).

Ctrl-C on ``u2sa run`` at load 18: every service logged "stopped" within 0.6 s, yet each got
"did not stop within 5 s: SIGKILL". The old rule was a wall-clock deadline from the SIGTERM,
whatever the child was doing. Now a child that acknowledges the stop (``STOPPING=1``) is
reaped when it exits as long as it shows progress (a ``WATCHDOG=1``, CPU time, runnable);
SIGKILL is kept for one that does not acknowledge within the grace, one that goes the grace
without progress after acknowledging, and one still alive ``stop_limit_s`` after the SIGTERM.

The unit tests drive :meth:`SupervisedProcess.enforce_stop` with a fake clock and a fake
``/proc`` sample over a real child that ignores SIGTERM (so only the launcher's SIGKILL, or
the test's SIGUSR1, ends it).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Iterator

import pytest
from conftest import wait_until
from supervision_helpers import write_profile
from test_launcher_watchdog import FakeClock

from u2sa_hw.launcher import Launcher, RestartPolicy, SupervisedProcess
from u2sa_hw.launcher.policy import STOP_LIMIT_S, STOPPED
from u2sa_hw.launcher.process import process_sample
from u2sa_hw.launcher.watchdog import WatchdogSetting, WatchedClock
from u2sa_hw.profile.loader import load_profile

# Ignores SIGTERM (its shutdown is the test's to end), exits 0 on SIGUSR1: a clean exit, whenever it comes.
LINGERS = ("import signal, sys, time\n"
           "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
           "signal.signal(signal.SIGUSR1, lambda *_: sys.exit(0))\n"
           "print('up', flush=True)\n"
           "while True:\n"
           "    time.sleep(60)\n")


class FakeProc:
    """What ``/proc/PID/stat`` says: the main thread's state and the CPU ticks, as the test sets them."""

    def __init__(self) -> None:
        self.state, self.ticks = "S", 100

    def __call__(self, _pid: int) -> tuple[str, int]:
        return self.state, self.ticks


@contextlib.contextmanager
def lingering(**kwargs: object) -> Iterator[tuple[SupervisedProcess, FakeClock, FakeProc]]:
    """A started child that ignores SIGTERM, judged on a fake clock (watched through a WatchedClock)."""
    real, proc = FakeClock(), FakeProc()
    p = SupervisedProcess("svc", [sys.executable, "-c", LINGERS], policy=RestartPolicy(), clock=real,
                          watch_clock=WatchedClock(real), sample=proc,
                          watchdog=WatchdogSetting(timeout_s=2.0, abort_s=1.0), **kwargs)  # type: ignore[arg-type]
    child = p.spawn()
    try:
        assert child.stdout is not None and child.stdout.readline() == b"up\n"   # SIGTERM is ignored from here
        p.on_notify({"READY": "1"})
        yield p, real, proc
    finally:
        if child.poll() is None:
            child.kill()
        child.wait()
        if child.stdout is not None:
            child.stdout.close()


def _turns(p: SupervisedProcess, real: FakeClock, seconds: float, *, step: float = 0.1,
           each: object = None) -> list[str]:
    """The launcher's turns over *seconds* of fake time; the verdicts enforce_stop gave."""
    verdicts = []
    for i in range(int(round(seconds / step))):
        real.now += step
        if callable(each):
            each(i)
        verdict = p.enforce_stop()
        if verdict is not None:
            verdicts.append(verdict)
    return verdicts


def _exit_cleanly(p: SupervisedProcess) -> str:
    """Let the child exit 0 now and return the launcher's account of it."""
    assert p.proc is not None
    p.proc.send_signal(signal.SIGUSR1)
    return str(wait_until(p.poll, timeout=30, message="the child's exit"))


def test_an_acknowledged_stop_is_waited_for_while_the_child_pings_or_works_and_reaped_at_its_exit() -> None:
    with lingering() as (p, real, proc):
        p.stop(grace_s=5.0)
        assert p.enforce_stop() is None
        assert _turns(p, real, 1.0) == []
        p.on_notify({"STOPPING": "1"})                   # acknowledged ("stopping"), then a long shutdown:
        pings = _turns(p, real, 12.0, each=lambda i: i % 10 == 0 and p.on_notify({"WATCHDOG": "1"}))
        assert pings == []                               # 12 s of pings, beyond the 5 s grace: waited for

        def work(_i: int) -> None:                       # "stopped": no more pings, the interpreter's exit works
            proc.ticks += 1
        assert _turns(p, real, 8.0, each=work) == []
        proc.state = "R"                                 # runnable, even without CPU time yet (a loaded machine)
        assert _turns(p, real, 6.0) == []
        account = _exit_cleanly(p)
    assert account.startswith("exited with status 0 after") and account.endswith("(stopped)"), account
    assert (p.state, p.result) == (STOPPED, "success")


def test_the_launchers_own_stall_does_not_use_up_a_childs_grace_or_silence() -> None:
    with lingering() as (p, real, proc):
        p.stop(grace_s=5.0)
        assert p.enforce_stop() is None
        real.now += 8.0                                  # the launcher did not run for 8 s (SIGSTOP, starved)
        assert p.enforce_stop() is None                  # at most STALL_STEP_S of it counted
        p.on_notify({"STOPPING": "1"})
        real.now += 8.0                                  # again, after the acknowledgement
        assert p.enforce_stop() is None
        account = _exit_cleanly(p)
    assert account.startswith("exited with status 0")


def test_no_acknowledgement_within_the_grace_is_sigkill() -> None:
    with lingering() as (p, real, proc):
        proc.state = "R"                                 # busy, but not stopping: busy is no acknowledgement
        p.stop(grace_s=5.0)
        assert p.enforce_stop() is None
        verdicts = _turns(p, real, 4.9)
        assert verdicts == []
        verdicts = _turns(p, real, 0.2)
        assert verdicts == ["did not acknowledge the stop within 5 s (no STOPPING=1): SIGKILL"]
        assert p.proc is not None and p.proc.wait(timeout=30) == -signal.SIGKILL
        account = wait_until(p.poll, timeout=30, message="the kill reaped")
    assert str(account).startswith("killed by SIGKILL")


@pytest.mark.parametrize("state", ["S", "T"])
def test_acknowledged_then_silent_is_sigkill_as_hung_in_its_shutdown(state: str) -> None:
    with lingering() as (p, real, proc):
        p.stop(grace_s=5.0)
        p.enforce_stop()
        p.on_notify({"STOPPING": "1"})
        assert _turns(p, real, 3.0, each=lambda i: i % 10 == 0 and p.on_notify({"WATCHDOG": "1"})) == []
        proc.state = state                               # blocked (S) or SIGSTOPped (T): no pings, no CPU time
        verdicts = _turns(p, real, 6.0)
        assert len(verdicts) == 1 and verdicts[0].startswith("hung while stopping: acknowledged, then no progress "
                                                             "for 5."), verdicts   # 5 s from its last ping
        assert p.proc is not None and p.proc.wait(timeout=30) == -signal.SIGKILL


def test_a_stop_is_bounded_even_for_a_child_that_acknowledged_and_never_stops_working() -> None:
    with lingering(stop_limit_s=20.0) as (p, real, proc):
        proc.state = "R"                                 # spinning after its acknowledgement: progress forever
        p.stop(grace_s=5.0)
        p.enforce_stop()
        p.on_notify({"STOPPING": "1"})
        assert _turns(p, real, 19.8) == []
        verdicts = _turns(p, real, 0.4)
        assert verdicts == ["still stopping 20 s after SIGTERM (it acknowledged and kept running): SIGKILL"]
        assert p.proc is not None and p.proc.wait(timeout=30) == -signal.SIGKILL
    assert STOP_LIMIT_S == 30.0


def test_process_sample_reads_the_state_and_cpu_ticks_of_a_real_child() -> None:
    child = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        first = process_sample(child.pid)
        assert first is not None and first[0] in ("R", "S")
        wait_until(lambda: (s := process_sample(child.pid)) and s[1] > first[1], timeout=30,
                   message="the spinning child's CPU ticks to grow")
        os.kill(child.pid, signal.SIGSTOP)
        wait_until(lambda: (s := process_sample(child.pid)) and s[0] == "T", timeout=30, message="state T")
    finally:
        child.kill()
        child.wait()
    assert process_sample(child.pid) is None             # reaped: nothing to read


# A real U2SAService whose kill() blocks for several graces (closing a big recording on a busy machine):
# its stopping thread pings the launcher's watchdog meanwhile.
SLOW_SERVICE = textwrap.dedent("""\
    import sys, time
    from u2sa_hw.service.contract import U2SAService
    from u2sa_hw.profile.loader import load_profile

    class SlowStop(U2SAService):
        SERVICE_TYPE = "slow_stop"

        def kill(self):
            super().kill()                   # its health thread ends: what is left waits without CPU time
            print("closing slowly", flush=True)
            time.sleep(4 * {grace})          # blocked (an fsync, a device closing): no CPU time, only the pings

    code = SlowStop("slow", profile=load_profile({vehicle!r})).main()
    print("slow stopped", flush=True)
    sys.exit(code)
    """)

# Acknowledges the stop, then hangs: it stops itself (state T), as a deadlock would leave it without progress.
HANGS = textwrap.dedent("""\
    import os, signal, sys, time
    from u2sa_hw.service.sdnotify import SystemdNotifier
    n = SystemdNotifier()
    signal.signal(signal.SIGTERM, lambda *_: (n.notify("STOPPING=1"), print("acknowledged", flush=True),
                                             os.kill(os.getpid(), signal.SIGSTOP)))
    n.notify("READY=1")
    while True:
        time.sleep(60)
    """)


def test_a_real_service_whose_shutdown_outlasts_the_grace_is_reaped_not_killed(tmp_path: Path, lcm_url: str) -> None:
    grace = 1.5
    vehicle = write_profile(tmp_path, lcm_url, {"slow": "state_estimator"})
    script = SLOW_SERVICE.format(grace=grace, vehicle=str(vehicle))
    lines: list[tuple[str, str]] = []
    launcher = Launcher(load_profile(vehicle), control=False, grace_s=grace, watchdog_s=0.5,
                        output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: [sys.executable, "-c", script])
    launcher.start()
    try:
        wait_until(lambda: all(s.ready for s in launcher.status()), timeout=60, message="the service ready")
    finally:
        launcher.request_stop("test")
        assert launcher.wait(timeout=120)
    said = [line for name, line in lines if name == "launcher"]
    assert any(name == "slow" and "closing slowly" in line for name, line in lines), lines
    assert any(name == "slow" and line.endswith("slow stopped") for name, line in lines), lines
    assert not any(line.endswith(": SIGKILL") or "killed by" in line for line in said), said
    assert any(line.startswith("slow exited with status 0") for line in said), said
    assert launcher.processes["slow"].result == "success"


def test_a_real_child_that_acknowledges_and_then_hangs_is_still_killed(tmp_path: Path, lcm_url: str) -> None:
    vehicle = write_profile(tmp_path, lcm_url, {"hangs": "state_estimator"})
    script = HANGS
    lines: list[tuple[str, str]] = []
    launcher = Launcher(load_profile(vehicle), control=False, grace_s=1.0,
                        output=lambda n, line: lines.append((n, line)),
                        command=lambda spec: [sys.executable, "-c", script])
    launcher.start()
    try:
        wait_until(lambda: all(s.ready for s in launcher.status()), timeout=60, message="the child ready")
    finally:
        launcher.request_stop("test")
        assert launcher.wait(timeout=120)
    said = [line for name, line in lines if name == "launcher"]
    assert ("hangs", "acknowledged") in lines, lines
    assert any(line.startswith("hangs hung while stopping: acknowledged, then no progress") for line in said), said
    assert any(line.startswith("hangs killed by SIGKILL") for line in said), said
