"""Real-time priority for the safety chain: which services, at what priority, and whether we may.

The safety chain (the RC mux, the actuator drivers, the HSM; DESIGN.md 5a) runs under
``SCHED_FIFO`` where the system allows it, so a board saturated by normal-priority work
(a camera pipeline, a planner) cannot delay the mux's hand-over or an actuator's dead-man
timer. The same table feeds the units' drop-ins (``CPUSchedulingPolicy=fifo``,
:mod:`u2sa_hw.install.units`) and the launcher (``u2sa run``, ``u2sa sim``), so a service
runs at the same priority on the bench as on the vehicle.

Priorities are well below the kernel's own real-time threads (threaded IRQs at 50,
migration and watchdog at 99) and the RC mux is the highest of ours. Kernel RT throttling
(``sched_rt_runtime_us``, 950000 of every 1000000 us by default) is never changed: it keeps
5 % of every CPU for normal tasks, the launcher and systemd among them, so a service that
spins cannot hang the board and its watchdog still kills it. With throttling turned off
(-1) the launcher does not raise anyone, and says so.

The system calls are injectable (:class:`SchedCalls`) so tests fake them.
"""

from __future__ import annotations

import os
import resource
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

from u2sa_hw.registry import ACTUATOR_KINDS

ACTUATOR_PRIORITY = 25   # every actuator driver (u2sa_hw.registry.ACTUATOR_KINDS): dead-man timers, neutral on no signal
SAFETY_CHAIN_PRIORITIES: Mapping[str, int] = {
    **dict.fromkeys(sorted(ACTUATOR_KINDS), ACTUATOR_PRIORITY),
    "rc_mux": 30,       # the pilot's hand-over and the manual path: highest of ours
    "hsm": 20,          # freshness judgements and the failsafe escalation
}
"""Service kind -> ``SCHED_FIFO`` priority (1-99). Kinds not listed run at normal priority. The actuator
drivers come from the registry, so a new one (a CAN motor family) is in the safety chain without a line here."""

SIM_DEVICES_PRIORITY = 10
"""``u2sa sim``'s own process (the mock devices, the simulated RC receiver): below the safety chain."""

DOC = "docs/safety.md"
CAP_SYS_NICE = 23
THROTTLE_FILE = Path("/proc/sys/kernel/sched_rt_runtime_us")


@dataclass(frozen=True)
class Schedule:
    """A scheduling policy for one process: ``SCHED_FIFO`` at *priority*, or normal (priority 0)."""

    priority: int = 0

    @property
    def realtime(self) -> bool:
        """True for ``SCHED_FIFO``."""
        return self.priority > 0

    @property
    def policy(self) -> int:
        """The ``os.SCHED_*`` constant. No SCHED_RESET_ON_FORK: it would also demote the service's own threads."""
        return os.SCHED_FIFO if self.realtime else os.SCHED_OTHER

    def describe(self) -> str:
        """``SCHED_FIFO 30`` / ``normal``."""
        return f"SCHED_FIFO {self.priority}" if self.realtime else "normal"


NORMAL = Schedule(0)


def _cap_sys_nice() -> bool:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return bool(int(line.split()[1], 16) >> CAP_SYS_NICE & 1)
    except (OSError, ValueError):
        pass
    return False


def _rlimit_rtprio() -> int:
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return 99 if soft == resource.RLIM_INFINITY else int(soft)


def _throttle_us() -> int | None:
    try:
        return int(THROTTLE_FILE.read_text())
    except (OSError, ValueError):
        return None


def _threads() -> list[int]:
    return [int(tid) for tid in os.listdir("/proc/self/task")]


def _set(pid: int, schedule: Schedule) -> None:
    os.sched_setscheduler(pid, schedule.policy, os.sched_param(schedule.priority))


@dataclass(frozen=True)
class SchedCalls:
    """The system calls this module makes; tests pass fakes."""

    cap_sys_nice: Callable[[], bool] = _cap_sys_nice
    rlimit_rtprio: Callable[[], int] = _rlimit_rtprio
    throttle_us: Callable[[], int | None] = _throttle_us   # sched_rt_runtime_us, None if unreadable
    setscheduler: Callable[[int, Schedule], None] = _set   # pid or thread id (0: the calling thread), schedule
    threads: Callable[[], list[int]] = _threads            # the thread ids of this process


def priority_for(kind: str) -> int:
    """The ``SCHED_FIFO`` priority of a service of *kind* (0: normal priority)."""
    return SAFETY_CHAIN_PRIORITIES.get(kind, 0)


def unit_directives(kind: str) -> str | None:
    """The ``[Service]`` lines of a unit running *kind*, or None for a normal-priority kind."""
    priority = priority_for(kind)
    if not priority:
        return None
    return f"CPUSchedulingPolicy=fifo\nCPUSchedulingPriority={priority}\n"


@dataclass
class RealtimePlan:
    """What this launcher may do: the ceiling on priorities and the one line that says why it is lower.

    ``ceiling`` 0 means not permitted (every service at normal priority); below the table's
    highest it clamps (RLIMIT_RTPRIO), so the chain still runs ahead of normal work.
    """

    ceiling: int
    notice: str | None = None        # said once by whoever launches: None when everything is as asked
    calls: SchedCalls = field(default_factory=SchedCalls)

    def schedule_for(self, kind: str) -> Schedule:
        """The schedule a service of *kind* gets here."""
        return Schedule(min(priority_for(kind), self.ceiling))

    def schedules(self, kinds: Mapping[str, str]) -> dict[str, Schedule]:
        """Service name -> schedule, for every service in *kinds* (name -> kind)."""
        return {name: self.schedule_for(kind) for name, kind in kinds.items()}

    def raise_process(self, priority: int = SIM_DEVICES_PRIORITY) -> ProcessPriority:
        """Put every thread of this process (and so every thread it starts later) at ``SCHED_FIFO`` *priority*.

        For ``u2sa sim``'s process, which hosts the mock devices: real hardware does not stall when the
        board is busy. The whole process, not only the mocks' threads: a real-time thread waiting for the
        GIL held by a normal one that the load preempted would stall all the same (priority inversion).
        """
        schedule = Schedule(min(priority, self.ceiling))
        done = ProcessPriority(self.calls)
        if not schedule.realtime:
            return done
        for tid in self.calls.threads():
            try:
                self.calls.setscheduler(tid, schedule)
            except ProcessLookupError:
                continue   # a thread that ended meanwhile
            except OSError as exc:
                done.refused = f"the simulated devices run at normal priority: {exc.strerror or exc}"
                break
            done.raised = True
        if done.refused:
            done.restore()
        return done


@dataclass
class ProcessPriority:
    """What :meth:`RealtimePlan.raise_process` did: ``refused`` says why not; ``restore()`` undoes it."""

    calls: SchedCalls
    raised: bool = False
    refused: str | None = None

    def restore(self) -> None:
        """Every thread of the process back at normal priority (those started since inherited the raise)."""
        if not self.raised:
            return
        self.raised = False
        for tid in self.calls.threads():
            try:
                self.calls.setscheduler(tid, NORMAL)
            except OSError:
                pass   # ended meanwhile; lowering is always permitted otherwise


def plan(*, enabled: bool = True, calls: SchedCalls | None = None) -> RealtimePlan:
    """Decide whether the launcher may raise the safety chain, and the one line to say when not."""
    calls = calls or SchedCalls()
    if not enabled:
        return RealtimePlan(0, None, calls)   # asked for with --no-realtime: nothing to say
    wanted = max(SAFETY_CHAIN_PRIORITIES.values())
    throttle = calls.throttle_us()
    if throttle is not None and throttle < 0:
        return RealtimePlan(0, "real-time priority not used: kernel RT throttling is off (sched_rt_runtime_us -1), "
                               f"so a spinning service could hang the board; the safety chain runs at normal "
                               f"priority (see {DOC})", calls)
    if calls.cap_sys_nice():
        return RealtimePlan(wanted, None, calls)
    limit = calls.rlimit_rtprio()
    if limit >= wanted:
        return RealtimePlan(wanted, None, calls)
    if limit <= 0:
        return RealtimePlan(0, f"real-time priority not permitted (no CAP_SYS_NICE, RLIMIT_RTPRIO 0): the safety "
                               f"chain runs at normal priority; see {DOC}", calls)
    return RealtimePlan(limit, f"real-time priority capped at {limit} by RLIMIT_RTPRIO (the RC mux asks {wanted}): "
                               f"the safety chain runs real-time but closer together; see {DOC}", calls)


def describe_plan(plan_: RealtimePlan, kinds: Mapping[str, str]) -> str:
    """One line naming the real-time services and their priorities (for the launcher's start-up)."""
    raised = [f"{name} {s.priority}" for name, s in plan_.schedules(kinds).items() if s.realtime]
    return f"real-time (SCHED_FIFO): {', '.join(raised)}" if raised else "real-time: none of these services"
