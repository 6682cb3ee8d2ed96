"""The local launcher: every service of a vehicle profile as its own supervised process.

For a bench or a laptop without systemd (``u2sa run``) and as a library for ``u2sa sim``.
One event-loop thread starts the children (``u2sa service NAME --vehicle FILE``), reads
their output and prefixes it with the service name, restarts crashed ones with the
backoff of :class:`RestartPolicy`, answers the control socket (so the HSM can ask for a
restart), and on stop sends SIGTERM and waits for each child to exit: SIGKILL only for one
that does not acknowledge (``STOPPING=1``) within the grace, one that goes the grace without
progress after acknowledging (hung in its shutdown), and one still alive ``stop_limit_s``
after the SIGTERM (:meth:`~.process.SupervisedProcess.enforce_stop`).

The children report readiness on the launcher's own ``$NOTIFY_SOCKET`` (:mod:`.notify`), as
they do to systemd, and ping its watchdog (:mod:`.watchdog`): a child that stops pinging for
its unit's ``WatchdogSec`` (2 s) is killed with SIGABRT, SIGKILL after ``TimeoutAbortSec``,
and restarted like any dead one, its death counted and logged as a watchdog timeout. Silence is
measured in time the launcher was watching (:class:`~.watchdog.WatchedClock`): when the
launcher's own process stalls (under ``u2sa sim`` it also serves the mock devices a child may
be waiting on), the stall is not counted against the children. A child
found stopped (SIGSTOP) gets SIGKILL at once and is never resumed, on a watchdog timeout or a
stop: resumed, a frozen command source would publish commands before it died.
Services of kind ``recorder`` start first and the others once they are ready (or after
``first_wait_s``), and stop last, once the others have exited: the recording holds every
service's start-up and stop, which replay needs (:mod:`.first`).

A child that exits 3 refused to start (another of its name already answers on the bus, or
its bus cannot be kept on this board): it is not restarted, as ``RestartPreventExitStatus=3``
keeps systemd from restarting the unit, and the launcher stops like for a service given up.
Children get ``$STATE_DIRECTORY`` (the profile's ``data_dir``), as systemd's ``StateDirectory=``
gives the units: the bus clock survives restarts there (``u2sa_hw.bus.clock``).
"""

from __future__ import annotations

import os
import selectors
import signal
import threading
import time
from pathlib import Path
from typing import Any, Callable, Collection

from u2sa_hw.launcher.child_setup import check_cgroup
from u2sa_hw.launcher.children import child_environment, select_services, u2sa_command, watchdog_setting
from u2sa_hw.launcher.control import ControlServer, LauncherError, answer, default_socket_path
from u2sa_hw.launcher.first import FirstServices
from u2sa_hw.launcher.notify import NotifyListener
from u2sa_hw.launcher.output import ChildOutputs, LineSink, PrefixedOutput
from u2sa_hw.launcher.policy import BACKOFF, FAILED, RUNNING, STOP_LIMIT_S, ProcessStatus, RestartPolicy
from u2sa_hw.launcher.process import SupervisedProcess
from u2sa_hw.launcher.watchdog import WatchedClock
from u2sa_hw.realtime import RealtimePlan, describe_plan
from u2sa_hw.registry import RECORDER_KIND
from u2sa_hw.profile.vehicle import ServiceSpec, VehicleProfile

DeathCallback = Callable[[ProcessStatus, str], None]
"""``on_death(status, account)``: a child died; *status* says what happens next (backoff, failed...)."""

LAUNCHER_NAME = "launcher"
_MAX_WAIT = 0.1   # loop wake-up at least this often to notice deaths and deadlines


class Launcher:
    """Starts, watches, restarts and stops the services of a profile (see the module docstring)."""

    def __init__(self, profile: VehicleProfile, *, only: list[str] | None = None, grace_s: float = 5.0,
                 policy: RestartPolicy = RestartPolicy(), keep_going: bool = False,
                 output: LineSink | None = None, on_death: DeathCallback | None = None,
                 control: bool = True, socket_path: Path | None = None,
                 command: Callable[[ServiceSpec], list[str]] | None = None,
                 env: dict[str, str] | None = None, start_first: list[str] | None = None,
                 first_wait_s: float = 15.0, watchdog_s: float | None = None,
                 unwatched: Collection[str] = (), cgroup: Path | None = None,
                 realtime: RealtimePlan | None = None, stop_limit_s: float = STOP_LIMIT_S) -> None:
        # watchdog_s replaces every unit's watchdog timeout (0: off); *unwatched* services run without one
        # (a replay's I2C drivers wait in reads held for the player and cannot ping, hil/replay_i2c.py).
        # cgroup: every run of every child joins it before exec (CgroupError now if it cannot be written);
        # realtime: the safety chain's priorities as permitted (u2sa_hw.realtime), None leaves priorities alone.
        # grace_s: on a stop, the time (watched) to acknowledge it and the most a child may then go without
        # progress; stop_limit_s: the bound on a stop, real time from the SIGTERM (at least grace_s).
        if profile.path is None:
            raise ValueError("the launcher needs a vehicle profile file (--vehicle PATH)")
        specs = select_services(profile, only)
        self.profile = profile
        self.grace_s = grace_s
        self.stop_limit_s = max(stop_limit_s, grace_s)
        self.keep_going = keep_going
        self.output = output or PrefixedOutput(names=[s.name for s in specs])
        self.on_death = on_death
        self.socket_path = (socket_path or default_socket_path(profile.data_dir)) if control else None
        self.notify = NotifyListener()
        child_env = child_environment(profile, notify_socket=self.notify.address, control_socket=self.socket_path,
                                      env=env)
        vehicle = str(profile.path.resolve())
        self.cgroup = cgroup
        if cgroup is not None:
            check_cgroup(cgroup)
        self.realtime = realtime
        self.kinds = {s.name: s.kind for s in specs}
        schedules = realtime.schedules(self.kinds) if realtime is not None else {}
        self._warned: set[str] = set()   # services whose set-up warning (RT refused) was said
        build = command or (lambda spec: [*u2sa_command(), "service", spec.name, "--vehicle", vehicle])
        self.watch_clock = WatchedClock()   # read on the loop thread only
        self.processes: dict[str, SupervisedProcess] = {
            s.name: SupervisedProcess(s.name, build(s), policy=policy, env=child_env,
                                      watchdog=watchdog_setting(s.kind, 0.0 if s.name in unwatched else watchdog_s),
                                      cgroup=cgroup, schedule=schedules.get(s.name), watch_clock=self.watch_clock,
                                      stop_limit_s=self.stop_limit_s)
            for s in specs}
        names = [s.name for s in specs]
        first = start_first if start_first is not None else [s.name for s in specs if s.kind == RECORDER_KIND]
        self.first = FirstServices([n for n in first if n in names], total=len(names), wait_s=first_wait_s,
                                   say=self.say)
        self._lock = threading.RLock()
        self._wake_r, self._wake_w = os.pipe2(os.O_CLOEXEC | os.O_NONBLOCK)
        self._stop_reason: str | None = None
        self._force = False
        self._stopping = False
        self._failed: list[str] = []
        self._thread: threading.Thread | None = None
        self._server: ControlServer | None = None
        self._outputs = ChildOutputs(self.output)
        self.finished = threading.Event()

    # -- public API ----------------------------------------------------------------------
    def start(self) -> None:
        """Open the control socket and start the loop thread (which starts the children).

        Raises LauncherBusy when another launcher runs this vehicle.
        """
        if self._thread is not None:
            return
        if self.socket_path is not None:
            try:
                self._server = ControlServer(self.socket_path, lambda request: answer(self, request))
            except BaseException:
                self.notify.close()   # the loop that would close it never runs
                raise
            self.say(f"control socket {self.socket_path}")
        if self.realtime is not None:
            self.say(self.realtime.notice or describe_plan(self.realtime, self.kinds))
        if self.cgroup is not None:
            self.say(f"every service runs in cgroup {self.cgroup}")
        self._thread = threading.Thread(target=self._loop, name="u2sa-launcher", daemon=True)
        self._thread.start()

    def request_stop(self, reason: str = "stop requested", *, force: bool = False) -> None:
        """Ask the loop to stop every service (safe from a signal handler); *force*: SIGKILL now."""
        self._stop_reason = self._stop_reason or reason
        self._force = self._force or force
        self._wake()

    def stop(self, *, timeout: float | None = None) -> int:
        """Stop every service (SIGTERM, then wait on their exits: the module docstring); return the exit code."""
        self.request_stop()
        self.wait(timeout)
        return self.exit_code

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until every service is down and the loop ended; True if it did within *timeout*."""
        return self.finished.wait(timeout)

    @property
    def exit_code(self) -> int:
        """1 when some service was given up, else 0."""
        return 1 if self._failed else 0

    @property
    def start_first(self) -> list[str]:
        """The services started first and stopped last (the recorders, unless the caller named others)."""
        return self.first.names

    @property
    def failed(self) -> list[str]:
        """Names of the services given up on."""
        return list(self._failed)

    def status(self) -> list[ProcessStatus]:
        """A snapshot of every supervised process."""
        with self._lock:
            return [p.status() for p in self.processes.values()]

    def restart(self, name: str, *, reason: str = "requested") -> ProcessStatus:
        """Restart service *name* now (a failed one gets a fresh start); LauncherError if impossible."""
        with self._lock:
            proc = self._process(name)
            if self._stopping or self._stop_reason:
                raise LauncherError(f"cannot restart {name}: the launcher is stopping")
            self.say(f"restart of {name} requested: {reason}")
            proc.restart(reason, self.grace_s)
            if name in self._failed:
                self._failed.remove(name)
            self._wake()
            return proc.status()

    def stop_service(self, name: str) -> ProcessStatus:
        """Stop service *name* and keep it stopped."""
        with self._lock:
            proc = self._process(name)
            proc.stop(self.grace_s)
            self._wake()
            return proc.status()

    def start_service(self, name: str) -> ProcessStatus:
        """Start service *name* unless it runs (a stopped or failed one gets a fresh start)."""
        with self._lock:
            proc = self._process(name)
            if proc.proc is None:
                return self.restart(name, reason="start requested")
            return proc.status()

    def say(self, text: str) -> None:
        """Write a line of the launcher's own."""
        self.output(LAUNCHER_NAME, text)

    def run(self) -> int:
        """Foreground use (``u2sa run``): start, stop on SIGINT/SIGTERM (twice: kill now), return the exit code."""
        def on_signal(signum: int, _frame: Any) -> None:
            name = signal.Signals(signum).name
            if self._stop_reason:
                self.request_stop(force=True)
            else:
                self.request_stop(f"{name} received")

        previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.start()
            while not self.finished.wait(0.5):
                pass
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
        return self.exit_code

    def __del__(self) -> None:
        if getattr(self, "_thread", None) is None and hasattr(self, "notify"):
            self.notify.close()   # never started: the loop did not close it
        # The wake pipe outlives the loop: other threads may still call _wake() after it ended.
        for fd in (getattr(self, "_wake_r", -1), getattr(self, "_wake_w", -1)):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass

    # -- internals -------------------------------------------------------------------------
    def _process(self, name: str) -> SupervisedProcess:
        try:
            return self.processes[name]
        except KeyError:
            raise LauncherError(f"no service '{name}' under this launcher "
                                f"(it runs: {', '.join(self.processes)})") from None

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass   # the pipe is full (a wake-up is pending anyway) or closed (finished)

    def _loop(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        sel.register(self.notify.sock, selectors.EVENT_READ, "notify")
        if self._server is not None:
            sel.register(self._server.sock, selectors.EVENT_READ, "accept")
        try:
            while True:
                with self._lock:
                    self._tick(sel)
                    if self._done():
                        break
                    timeout = self._next_timeout()
                for key, _ in sel.select(timeout):
                    self._on_ready(sel, key)
            self._outputs.drain(sel)
        finally:
            if self._server is not None:
                self._server.close()
            sel.close()
            self.notify.close()
            self.finished.set()

    def _on_ready(self, sel: selectors.BaseSelector, key: selectors.SelectorKey) -> None:
        kind = key.data
        if kind == "wake":
            try:
                os.read(self._wake_r, 4096)
            except BlockingIOError:
                pass
        elif kind == "notify":
            self._on_notifications()
        elif kind == "accept":
            conn = self._server.accept() if self._server else None
            if conn is not None:
                sel.register(conn, selectors.EVENT_READ, ("conn", conn))
        elif kind[0] == "conn":
            if self._server is not None and self._server.readable(kind[1]):
                sel.unregister(kind[1])
                self._server.drop(kind[1])
        elif kind[0] == "out":
            self._outputs.read(sel, key.fd)

    def _on_notifications(self) -> None:
        by_pid = {p.pid: p for p in self.processes.values() if p.pid is not None}
        for note in self.notify.read():
            p = by_pid.get(note.pid)
            if p is None:
                continue   # a grandchild, or a child already reaped (systemd's NotifyAccess=main)
            if p.on_notify(note.fields) and p.name in self.first.names:
                self.say(f"{p.name} ready after {p.clock() - p.started_at:.1f} s")

    def _tick(self, sel: selectors.BaseSelector) -> None:
        if self._stop_reason and not self._stopping:
            self._stopping = True
            last = self.first.begin_stop()
            self.say(f"{self._stop_reason}: stopping {len(self.processes)} services (SIGTERM; SIGKILL to one "
                     f"that does not acknowledge within {self.grace_s:g} s or then hangs, or is still "
                     f"alive after {self.stop_limit_s:g} s{last})")
            for p in self.processes.values():
                if not self.first.kept_for_last(p.name):
                    p.stop(self.grace_s)
        for name in self.first.due_to_stop(self.processes):
            self.processes[name].stop(self.grace_s)
        if self._force:
            self._force = False
            self.say("stopping now: SIGKILL")
            for p in self.processes.values():
                p.signal(signal.SIGKILL)
        self._on_notifications()   # a READY sent before a death counts before that death is judged
        for p in self.processes.values():
            account = p.poll()
            if account is not None:
                self._on_death(p, account)
            fired = p.check_watchdog()
            if fired is not None:
                self.say(f"{p.name} {fired}")
            verdict = p.enforce_stop()
            if verdict is not None:
                self.say(f"{p.name} {verdict}")
        if self._stopping:
            return
        self.first.still_holding(self.processes)
        for p in self.processes.values():
            if p.due() and not self.first.holds_back(p.name):
                self._spawn(sel, p)

    def _spawn(self, sel: selectors.BaseSelector, p: SupervisedProcess) -> None:
        try:
            child = p.spawn()
        except OSError as exc:   # errno 0: the child's set-up failed, its message names the cgroup
            self._on_death(p, p.failed_to_spawn(f"{p.argv[0]}: {exc.strerror or exc}" if exc.errno
                                                else str(exc.strerror)))
            return
        self._outputs.add(sel, child, p.name)
        self.say(f"{p.name} started, pid {child.pid}, run {p.run_id}")
        if p.setup_warning and p.name not in self._warned:
            self._warned.add(p.name)
            self.say(f"{p.name}: {p.setup_warning}")

    def _on_death(self, p: SupervisedProcess, account: str) -> None:
        self.say(f"{p.name} {account}")
        if p.state == FAILED and p.name not in self._failed:
            self._failed.append(p.name)
            if not self.keep_going and not self._stop_reason:
                self._stop_reason = f"{p.name} keeps failing ({p.reason})"
        if self.on_death is not None:
            try:
                self.on_death(p.status(), account)
            except Exception as exc:  # noqa: BLE001 - a faulty callback must not stop supervision
                self.say(f"on_death callback failed: {type(exc).__name__}: {exc}")
        if self._stop_reason and not self._stopping:
            self._wake()

    def _done(self) -> bool:
        if self._stopping:
            return all(p.proc is None for p in self.processes.values())
        return all(p.settled for p in self.processes.values())

    def _next_timeout(self) -> float:
        now = time.monotonic()
        # A held service is due but waits for the first ones: its deadline is the end of the hold.
        deadlines = [p.next_start for p in self.processes.values() if p.state == BACKOFF and p.desired == RUNNING
                     and not self.first.holds_back(p.name)]
        hold_end = self.first.hold_deadline()
        if hold_end is not None:
            deadlines.append(hold_end)
        deadlines += [p.kill_at for p in self.processes.values() if p.kill_at is not None]
        soonest = min(deadlines, default=now + _MAX_WAIT)
        return max(0.0, min(_MAX_WAIT, soonest - now))
