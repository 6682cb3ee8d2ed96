"""One supervised child process, libbot2-procman style.

A :class:`SupervisedProcess` keeps the *desired* state (running or stopped) apart from
the *observed* one (running, stopping, backoff, exited, stopped, failed). Every start is
an edge with a new run id. A death is judged by :class:`RestartPolicy`: a quick death
(healthy uptime below ``quick_death_s``; healthy uptime counts from the run's READY=1, so a
run that died before it came up is a quick death however slowly it started) doubles the
respawn delay, healthy uptime makes it decay,
and the process is given up (state ``failed``) after too many quick deaths in a row or
too many failed exits within a window (a service that crashes every few seconds after a
healthy-looking start would otherwise restart forever). An exit status in
``RestartPolicy.final_statuses`` (3: the service refused to start, e.g. another of its name
already runs on the bus) is final at once, as ``RestartPreventExitStatus=3`` makes it under
systemd: a restart would find the same, and each one would print the same line again.

A stop (SIGTERM) waits on the child's exit, not on a clock (:meth:`SupervisedProcess.enforce_stop`):
a child that acknowledges it (``STOPPING=1``, which every service sends as its run loop ends)
within the grace is reaped when it exits, however long a loaded machine makes that, as long as
it keeps showing progress: a ``WATCHDOG=1`` (a service pings while it shuts down), CPU time
spent, or being runnable or in an uninterruptible (disk) wait, from ``/proc/PID/stat``. SIGKILL
is kept for a child that does not acknowledge within the grace, that goes the grace without
progress after acknowledging (hung in its shutdown: blocked, deadlocked, SIGSTOPped), and for
any child still alive ``stop_limit_s`` (30 s) of real time after the SIGTERM: the bound on a
stop. The grace and the silences are measured on the launcher's watched clock, so its own
stalls do not count against a child.

The launcher's event loop drives it: ``spawn`` and ``poll`` run on the loop thread only
(the child's parent-death signal is tied to the thread that forked it).
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections import deque
from pathlib import Path
from typing import Callable

from u2sa_hw.launcher.child_setup import CgroupError, ChildSetup, read_report
from u2sa_hw.launcher.policy import (BACKOFF, EXITED, FAILED, RUNNING, STOP_LIMIT_S, STOPPED, STOPPING,
                                     ProcessStatus, RestartPolicy, StopWait, describe_exit)
from u2sa_hw.launcher.watchdog import WatchdogSetting, WatchdogTimer
from u2sa_hw.realtime import Schedule

def process_sample(pid: int, *, proc: Path = Path("/proc")) -> tuple[str, int] | None:
    """``(state letter, CPU ticks used)`` of *pid* from ``/proc/PID/stat``, None when unreadable.

    The state is the main thread's (R running or runnable, S sleeping, D in a disk wait, T stopped,
    Z dead); the ticks (utime + stime) are the whole process's.
    """
    try:
        stat = (proc / str(pid) / "stat").read_text()
    except OSError:
        return None
    fields = stat.rpartition(")")[2].split()   # the name in (...) may hold spaces
    try:
        return fields[0], int(fields[11]) + int(fields[12])
    except (IndexError, ValueError):
        return None


def process_stopped(pid: int, *, proc: Path = Path("/proc")) -> bool:
    """True when *pid* is stopped (state T, or t: stopped by a tracer), from ``/proc/PID/stat``."""
    sample = process_sample(pid, proc=proc)
    return sample is not None and sample[0] in ("T", "t")


class SupervisedProcess:
    """Desired vs observed state of one child, its run id and its respawn backoff."""

    def __init__(self, name: str, argv: list[str], *, policy: RestartPolicy, env: dict[str, str] | None = None,
                 cwd: str | None = None, clock: Callable[[], float] = time.monotonic,
                 watchdog: WatchdogSetting | None = None, cgroup: Path | None = None,
                 schedule: Schedule | None = None, watch_clock: Callable[[], float] | None = None,
                 stop_limit_s: float = STOP_LIMIT_S,
                 sample: Callable[[int], tuple[str, int] | None] = process_sample) -> None:
        # cgroup: each run joins it before exec (a CPU budget); schedule: its policy, set before exec
        # after joining (None: inherited). See child_setup.py for the order and why.
        # watch_clock: the time the watchdog judges silence by (None: *clock*); the launcher's
        # WatchedClock does not count its own stalls against the child (watchdog.py).
        # stop_limit_s: the bound on a stop (real time from the SIGTERM); sample: reads a pid's state and
        # CPU ticks (process_sample), injectable for tests.
        self.name = name
        self.argv = argv
        self.policy = policy
        self.env = env
        self.cwd = cwd
        self.clock = clock
        self.watch_clock = watch_clock or clock
        self.desired = RUNNING
        self.state = BACKOFF          # not yet started: due at once
        self.proc: subprocess.Popen[bytes] | None = None
        self.run_id = 0
        self.restarts = 0
        self.quick_deaths = 0
        self.failure_times: deque[float] = deque()   # clock() of each failed exit within the window
        self.backoff_s = 0.0
        self.next_start = clock()
        self.started_at = 0.0
        self.kill_at: float | None = None   # SIGKILL at this clock() time: the watchdog's SIGABRT was not enough
        self.stop_limit_s = stop_limit_s
        self.sample = sample
        self.stop_wait: StopWait | None = None   # the current stop's wait (see enforce_stop), None when not stopping
        self.restart_pending = False
        self.last_exit = ""
        self.reason = ""
        self.ready = False            # the current run said READY=1
        self.ready_at = 0.0           # ... at this time: healthy uptime counts from here
        self.status_text = ""         # ... and its latest STATUS=
        self.watchdog = WatchdogTimer(watchdog or WatchdogSetting(timeout_s=0.0))
        self.watchdog_kills = 0
        self.result = ""
        self.setup = ChildSetup(cgroup=cgroup, schedule=schedule)
        self.setup_warning: str | None = None   # the last run's set-up problem it started despite (RT refused)
        self.killed_stopped = False   # this run was found stopped when asked to stop: SIGKILL, never resumed

    # -- observing -----------------------------------------------------------------
    @property
    def pid(self) -> int | None:
        """The live child's pid, or None."""
        return self.proc.pid if self.proc is not None else None

    def status(self) -> ProcessStatus:
        """A snapshot for reports."""
        now = self.clock()
        return ProcessStatus(name=self.name, desired=self.desired, state=self.state, pid=self.pid,
                             run_id=self.run_id, restarts=self.restarts, quick_deaths=self.quick_deaths,
                             failures=self.failures_in_window(), backoff_s=self.backoff_s,
                             uptime_s=now - self.started_at if self.proc else 0.0,
                             last_exit=self.last_exit, reason=self.reason, ready=self.ready,
                             status_text=self.status_text, result=self.result, watchdog_kills=self.watchdog_kills,
                             watchdog_s=self.watchdog.setting.timeout_s)

    def due(self) -> bool:
        """True when the child should be (re)started now."""
        return self.desired == RUNNING and self.state == BACKOFF and self.clock() >= self.next_start

    # -- acting (loop thread) ----------------------------------------------------------
    def spawn(self) -> subprocess.Popen[bytes]:
        """Start the child with its output on a pipe; a new run id. OSError when it cannot start."""
        self.run_id += 1
        if self.run_id > 1:
            self.restarts += 1
        env = dict(self.env if self.env is not None else os.environ)
        env["U2SA_RUN_ID"] = str(self.run_id)
        if self.watchdog.setting.timeout_s > 0:
            env["WATCHDOG_USEC"] = str(self.watchdog.setting.usec)
        else:
            env.pop("WATCHDOG_USEC", None)
        env.pop("WATCHDOG_PID", None)   # the child's pid is unknown before the fork; it is the main process
        report_r, report_w = os.pipe2(os.O_CLOEXEC | os.O_NONBLOCK)
        try:
            preexec = self.setup.preexec(report_w)
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                         stderr=subprocess.STDOUT, env=env, cwd=self.cwd, process_group=0,
                                         preexec_fn=preexec)
        except (OSError, subprocess.SubprocessError, CgroupError) as exc:
            self.proc = None
            os.close(report_w)
            error, _ = read_report(report_r)
            os.close(report_r)
            if error is None and isinstance(exc, OSError):
                raise
            raise OSError(0, error or str(exc)) from None   # the set-up's own words: the cgroup, why, the fix
        os.close(report_w)
        _, self.setup_warning = read_report(report_r)
        os.close(report_r)
        self.started_at = self.clock()
        self.state = RUNNING
        self.kill_at = None
        self.stop_wait = None
        self.reason = ""
        self.ready = False
        self.status_text = ""
        self.killed_stopped = False
        self.watchdog.reset()
        return self.proc

    def failed_to_spawn(self, error: str) -> str:
        """Count a start that could not even exec as a quick death; return what happens next."""
        self.last_exit = f"could not start: {error}"
        self.result = "exit-code"
        return self._judge_death(uptime=0.0)

    def poll(self) -> str | None:
        """If the child died: update the state and return a one-line account of it, else None."""
        if self.proc is None or self.proc.poll() is None:
            return None
        code = self.proc.returncode
        uptime = self.clock() - self.started_at
        self.proc = None
        self.kill_at = None
        self.stop_wait = None
        self.last_exit = describe_exit(code)
        if self.killed_stopped:
            self.last_exit += " (it was stopped: killed without resuming it)"
        self.result = "success" if code == 0 else "signal" if code < 0 else "exit-code"
        if self.watchdog.fired:
            self.result = "watchdog"
            self.watchdog_kills += 1
            self.last_exit = f"watchdog timeout, {self.last_exit}"
        if self.desired != RUNNING:
            self.state = STOPPED
            return f"{self.last_exit} after {uptime:.1f} s (stopped)"
        if self.restart_pending:
            self.restart_pending = False
            self.state, self.next_start, self.backoff_s = BACKOFF, self.clock(), 0.0
            return f"{self.last_exit}; restarting now (requested: {self.reason})"
        if code == 0 and not self.watchdog.fired:
            self.state = EXITED
            return f"{self.last_exit} after {uptime:.1f} s; not restarted (a clean exit is deliberate)"
        if code in self.policy.final_statuses and not self.watchdog.fired:
            self.state = FAILED
            self.reason = f"refused to start ({self.last_exit}; its own line says why)"
            return (f"{self.last_exit} after {uptime:.1f} s: it refused to start (its line above says why: another "
                    "of its name on the bus, or a bus it cannot keep on this board); not restarted")
        # Healthy uptime counts from READY: a run that died before it came up is a quick death however
        # long it took to start (on a loaded machine an import can take seconds).
        healthy = self.clock() - self.ready_at if self.ready else 0.0
        return self._judge_death(uptime=healthy, prefix=f"{self.last_exit} after {uptime:.1f} s"
                                 f"{'' if self.ready else ' (never ready)'}")

    def failures_in_window(self) -> int:
        """Failed exits within the policy's ``failure_window_s`` up to now."""
        horizon = self.clock() - self.policy.failure_window_s
        while self.failure_times and self.failure_times[0] < horizon:
            self.failure_times.popleft()
        return len(self.failure_times)

    def _judge_death(self, *, uptime: float, prefix: str = "") -> str:
        self.quick_deaths, self.backoff_s = self.policy.after_death(self.quick_deaths, uptime)
        self.failure_times.append(self.clock())
        failures = self.failures_in_window()
        prefix = prefix or self.last_exit
        if self.policy.gives_up(self.quick_deaths):
            self.state = FAILED
            self.reason = f"{self.quick_deaths} quick deaths in a row, last {self.last_exit}"
            return f"{prefix}; giving up after {self.quick_deaths} quick deaths in a row"
        if self.policy.too_many_failures(failures):
            self.state = FAILED
            window = self.policy.failure_window_s
            self.reason = f"{failures} failed exits within {window:g} s, last {self.last_exit}"
            return f"{prefix}; giving up after {failures} failed exits within {window:g} s"
        self.state = BACKOFF
        self.next_start = self.clock() + self.backoff_s
        return (f"{prefix}; restarting in {self.backoff_s:.2f} s (quick deaths: {self.quick_deaths}, "
                f"failures: {failures}/{self.policy.max_failures or 'no limit'} within "
                f"{self.policy.failure_window_s:g} s)")

    def on_notify(self, fields: dict[str, str]) -> bool:
        """Apply an sd_notify message from this run (READY, STATUS, WATCHDOG); True when it just became ready."""
        if "STATUS" in fields:
            self.status_text = fields["STATUS"]
        now = self.watch_clock()
        self.watchdog.on_fields(fields, now)
        if self.stop_wait is not None and (fields.get("STOPPING") == "1" or fields.get("WATCHDOG") == "1"):
            self.stop_wait.progress_at = now   # an acknowledgement, or a ping on the way out
        if fields.get("READY") == "1" and not self.ready:
            self.ready = True
            self.ready_at = self.clock()
            return True
        return False

    def check_watchdog(self) -> str | None:
        """Fire the watchdog of a running child that stopped pinging, as systemd does; return an account.

        A running child gets SIGABRT (Python's faulthandler prints its stacks) and SIGKILL after
        the abort timeout. A *stopped* child (state T: SIGSTOP, a debugger) gets SIGKILL at once
        and is never resumed: SIGCONT, so it could act on SIGABRT, would let its other threads run
        while faulthandler prints, and a command source then publishes commands (wheels moved
        ~25 ms in a test). Its death then takes the normal restart path.
        """
        if self.proc is None or self.state != RUNNING:
            return None
        silent = self.watchdog.overdue(self.watch_clock())
        if silent is None:
            return None
        setting = self.watchdog.setting
        what = "WATCHDOG=trigger" if self.watchdog.triggered else f"no WATCHDOG=1 for {silent:.1f} s"
        head = f"watchdog timeout ({what}, limit {setting.timeout_s:g} s)"
        if process_stopped(self.proc.pid):
            self.signal(signal.SIGKILL)
            return f"{head}: it was stopped, so SIGKILL without resuming it (no stack dump)"
        self.kill_at = self.clock() + setting.abort_s
        self.signal(signal.SIGABRT)   # no SIGCONT: one stopped since the check above gets SIGKILL in abort_s
        return f"{head}: SIGABRT, SIGKILL in {setting.abort_s:g} s"

    def signal(self, sig: int) -> None:
        """Send *sig* to the child's process group (it is its own group leader)."""
        if self.proc is None:
            return
        try:
            os.killpg(self.proc.pid, sig)
        except ProcessLookupError:
            pass

    def request_stop(self, grace_s: float) -> None:
        """SIGTERM now; SIGKILL only as :meth:`enforce_stop` decides. A stopped child (state T) gets SIGKILL at once.

        A stopped child is not resumed to act on SIGTERM: a frozen command source would publish
        commands again before it stops (see check_watchdog). A stopped recorder loses its last chunk.
        """
        if self.proc is None:
            if self.state in (BACKOFF, RUNNING) and self.desired != RUNNING:
                self.state = STOPPED
            return
        if self.state != STOPPING:
            self.state = STOPPING
            self.stop_wait = StopWait(grace_s=grace_s, started_at=self.clock())
            if process_stopped(self.proc.pid):
                self.killed_stopped = True
                self.stop_wait.killed = True
                self.signal(signal.SIGKILL)
                return
            self.signal(signal.SIGTERM)

    def stop(self, grace_s: float) -> None:
        """Desired: stopped. A child in backoff is simply not restarted."""
        self.desired = STOPPED
        self.restart_pending = False
        if self.proc is None:
            if self.state == BACKOFF:
                self.state = STOPPED
            return
        self.request_stop(grace_s)

    def restart(self, reason: str, grace_s: float) -> None:
        """Restart as an edge: stop a live child then start at once; start a dead one now.

        Deaths caused by this are not quick deaths nor failures; a failed process gets a fresh start.
        """
        self.desired = RUNNING
        self.reason = reason
        if self.proc is not None:
            self.restart_pending = True
            self.request_stop(grace_s)
            return
        if self.state == FAILED:
            self.quick_deaths = 0
            self.failure_times.clear()
        self.state, self.next_start, self.backoff_s = BACKOFF, self.clock(), 0.0

    def enforce_stop(self) -> str | None:
        """SIGKILL a child whose time is up; return why (for the launcher's line), else None. Loop thread only.

        After the watchdog's SIGABRT: ``abort_s`` of real time. After a stop's SIGTERM, on the watched
        clock: the grace to acknowledge (``STOPPING=1``), then never the grace without progress (a
        ``WATCHDOG=1``, CPU time spent, or the main thread runnable, in a disk wait or already dead). A child that
        acknowledged and keeps progressing is waited for, until ``stop_limit_s`` (at least the grace)
        of real time after the SIGTERM: a loaded machine lengthens the wait, not the verdict.
        """
        if self.proc is None:
            return None
        if self.kill_at is not None and self.clock() >= self.kill_at:
            self.kill_at = None
            self.signal(signal.SIGKILL)
            return f"did not die within {self.watchdog.setting.abort_s:g} s of SIGABRT: SIGKILL"
        wait = self.stop_wait
        if wait is None or wait.killed:
            return None
        watched = self.watch_clock()
        if wait.asked_at is None:   # the first turn since the SIGTERM (request_stop may run on another thread)
            wait.asked_at = watched
        grace = wait.grace_s
        verdict = None
        if self.clock() - wait.started_at >= max(self.stop_limit_s, grace):
            verdict = (f"still stopping {max(self.stop_limit_s, grace):g} s after SIGTERM"
                       f"{' (it acknowledged and kept running)' if self.watchdog.stopping else ''}: SIGKILL")
        elif not self.watchdog.stopping:
            if watched - wait.asked_at >= grace:
                verdict = f"did not acknowledge the stop within {grace:g} s (no STOPPING=1): SIGKILL"
        else:
            if wait.progress_at is None:
                wait.progress_at = watched   # acknowledged before we asked (it was stopping on its own)
            sample = self.sample(self.proc.pid)
            if sample is not None:
                state, ticks = sample
                if state in ("R", "D", "Z") or (wait.ticks is not None and ticks != wait.ticks):
                    wait.progress_at = watched
                wait.ticks = ticks
            silent = watched - wait.progress_at
            if silent >= grace and silent > 0:
                verdict = (f"hung while stopping: acknowledged, then no progress for {silent:.1f} s "
                           f"(no WATCHDOG=1, no CPU time): SIGKILL")
        if verdict is None:
            return None
        wait.killed = True
        self.signal(signal.SIGKILL)
        return verdict

    @property
    def settled(self) -> bool:
        """True when nothing more will happen without a request (dead and not due to restart)."""
        return self.proc is None and (self.state in (EXITED, STOPPED, FAILED) or self.desired != RUNNING)
