"""A CPU budget for a process tree: a cgroup CPU quota (v1 or v2) that also bounds real-time time.

Used by ``bench/sbc.py``. A budget is one group in the cpu controller's hierarchy, named
after the bench's pid (``u2sa-sbc-<pid>``). The services join it (the launcher puts each
child there before exec, restarts included); with ``whole_sim`` the ``u2sa sim`` process
(mock devices, simulator) joins it too, and the services inherit it.

cgroup v1: the quota is ``cpu.cfs_quota_us`` over ``cpu.cfs_period_us``. A CFS quota does not
hold back SCHED_FIFO/RR tasks (the safety chain, and the sim's device threads, run so when
permitted); with CONFIG_RT_GROUP_SCHED their time is bounded by the group's
``cpu.rt_runtime_us`` over ``cpu.rt_period_us`` instead, and a real-time task cannot join a
group whose RT runtime is 0 (a new group's default). So the budget sets both: the same share
of CFS and of RT time. The RT runtime applies per CPU, so the measured usage
(``cpuacct.usage``, which counts both classes) is the figure to read, not the quota. When
cpuacct is mounted apart from cpu, a cpuacct group of the same name holds the ``u2sa sim``
process and, by inheritance, every service it forks: the services' share is that group's
usage less the sim process's own CPU time.

cgroup v2: ``cpu.max``, the cpu controller enabled in the root's ``cgroup.subtree_control``.
v2 has no RT runtime: real-time tasks are not held by ``cpu.max`` (and with
CONFIG_RT_GROUP_SCHED cannot run in a non-root group at all), hence ``--no-realtime``.
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

CFS_PERIOD_US = 100_000
RT_PERIOD_US = 1_000_000
MIN_QUOTA_US = 1_000              # the kernel's smallest CFS quota


class BudgetError(RuntimeError):
    """A budget cannot be set up here (not root, no cpu controller, a write refused)."""


@dataclass(frozen=True)
class Hierarchy:
    """Where the cpu controller's groups live and how their usage is read."""

    version: int                    # 1 or 2
    cpu_root: Path                  # v1: the cpu mount; v2: the cgroup2 mount
    acct_root: Path | None = None   # v1 with cpuacct mounted apart: its mount; else None
    realtime: bool = False          # v1 groups have cpu.rt_runtime_us (CONFIG_RT_GROUP_SCHED)

    def describe(self) -> str:
        """One line: the version, where, RT handling, how usage is read."""
        if self.version == 2:
            return f"cgroup v2 at {self.cpu_root} (cpu.max, no RT budget; usage from cpu.stat)"
        rt = "cfs quota + rt_runtime" if self.realtime else "cfs quota (no RT group scheduling)"
        acct = f"usage from {self.acct_root}" if self.acct_root else "usage from cpuacct.usage"
        return f"cgroup v1 at {self.cpu_root} ({rt}; {acct})"


def parse_budgets(text: str, *, cpus: int | None = None) -> list[float]:
    """``"100,60,40"`` -> ``[100.0, 60.0, 40.0]``: percent of one core, each in (0, 100 x cpus]."""
    limit = 100.0 * (cpus or os.cpu_count() or 1)
    budgets = []
    for part in text.replace(" ", "").split(","):
        if not part:
            continue
        try:
            value = float(part.rstrip("%"))
        except ValueError:
            raise ValueError(f"not a percentage of one core: {part!r}") from None
        if not 0.0 < value <= limit:
            raise ValueError(f"budget {part!r} is outside (0, {limit:g}] % of one core")
        budgets.append(value)
    if not budgets:
        raise ValueError("no budget given")
    return budgets


def detect(*, mounts: str | None = None) -> Hierarchy:
    """The hierarchy that carries the cpu controller, from ``/proc/self/mounts`` (or *mounts*)."""
    if mounts is None:
        mounts = Path("/proc/self/mounts").read_text()
    cpu_v1 = acct_v1 = v2 = None
    for line in mounts.splitlines():
        fields = line.split()
        if len(fields) < 4:
            continue
        where, fstype, options = Path(fields[1]), fields[2], fields[3].split(",")
        if fstype == "cgroup" and "cpu" in options:
            cpu_v1 = where
            if "cpuacct" in options:
                acct_v1 = where
        elif fstype == "cgroup" and "cpuacct" in options:
            acct_v1 = where
        elif fstype == "cgroup2":
            v2 = where
    if cpu_v1 is not None:   # a controller is bound to one hierarchy: v1 has it when mounted there
        return Hierarchy(1, cpu_v1, None if acct_v1 == cpu_v1 or acct_v1 is None else acct_v1,
                         (cpu_v1 / "cpu.rt_runtime_us").exists())
    if v2 is not None and "cpu" in _read(v2 / "cgroup.controllers").split():
        if "cpu" not in _read(v2 / "cgroup.subtree_control").split():
            raise BudgetError(f"cgroup v2 at {v2}: the cpu controller is not enabled for its groups "
                              f"(echo +cpu > {v2 / 'cgroup.subtree_control'})")
        return Hierarchy(2, v2)
    raise BudgetError("no cpu controller: neither a cgroup v1 'cpu' mount nor cgroup v2 with 'cpu' in "
                      "cgroup.controllers (is /sys/fs/cgroup mounted, and the controller not disabled?)")


def require_root() -> None:
    """BudgetError unless this process may create groups and move tasks (root)."""
    if os.geteuid() != 0:
        raise BudgetError("a CPU budget needs root (it creates cgroups and moves processes): run with sudo")


def v1_values(percent: float, *, cfs_period_us: int = CFS_PERIOD_US, rt_period_us: int = RT_PERIOD_US,
              rt_available_us: int | None = None) -> dict[str, str]:
    """cgroup v1 files for *percent* of one core, in the order to write them.

    *rt_available_us*: the RT runtime the parent can still give (None: no RT group
    scheduling, no RT file); the share of ``rt_period_us`` is capped at it.
    """
    values = {"cpu.cfs_period_us": str(cfs_period_us),
              "cpu.cfs_quota_us": str(max(MIN_QUOTA_US, round(percent / 100.0 * cfs_period_us)))}
    if rt_available_us is not None:
        values["cpu.rt_runtime_us"] = str(min(rt_available_us, round(percent / 100.0 * rt_period_us)))
    return values


def v2_values(percent: float, *, period_us: int = CFS_PERIOD_US) -> dict[str, str]:
    """cgroup v2 ``cpu.max`` for *percent* of one core."""
    return {"cpu.max": f"{max(MIN_QUOTA_US, round(percent / 100.0 * period_us))} {period_us}"}


def read_usage_ns(path: Path) -> int:
    """CPU time used by a group, in ns, from ``cpuacct.usage`` (v1) or ``cpu.stat`` (v2)."""
    text = _read(path)
    if path.name == "cpu.stat":
        return 1000 * int(_stat(text).get("usage_usec", 0))
    return int(text.strip() or 0)


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""


def _stat(text: str) -> dict[str, int]:
    out = {}
    for line in text.splitlines():
        key, _, value = line.partition(" ")
        if value.strip().lstrip("-").isdigit():
            out[key] = int(value)
    return out


def _write(path: Path, value: str) -> None:
    try:
        with open(path, "w") as f:
            f.write(value)
    except OSError as exc:
        raise BudgetError(f"cannot write {value!r} to {path}: {exc.strerror or exc}") from exc


def _write_retrying(path: Path, value: str, *, within_s: float = 3.0) -> None:
    """Write an RT runtime: a group removed just before still holds its runtime until the kernel frees it."""
    deadline = time.monotonic() + within_s
    while True:
        try:
            return _write(path, value)
        except BudgetError as exc:
            if not isinstance(exc.__cause__, OSError) or exc.__cause__.errno != errno.EINVAL or \
                    time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class CpuBudget:
    """One budget group (see the module docstring); a context manager that removes it.

    *whole_sim*: the ``u2sa sim`` process joins the group too (:meth:`runner_join`), not only
    the services. *rmdir* is injectable for a fake root made of plain files (tests).
    """

    def __init__(self, hierarchy: Hierarchy, percent: float, *, whole_sim: bool = False, name: str | None = None,
                 rmdir: Callable[[Path], None] = os.rmdir) -> None:
        self.h = hierarchy
        self.percent = percent
        self.whole_sim = whole_sim
        self.name = name or f"u2sa-sbc-{os.getpid()}"
        self.group = hierarchy.cpu_root / self.name
        self.acct = hierarchy.acct_root / self.name if hierarchy.acct_root else None
        self.rt_runtime_us: int | None = None
        self._rmdir = rmdir
        self._made: list[Path] = []

    def create(self) -> CpuBudget:
        """Make the group(s) and write the budget; on any error remove what was made."""
        try:
            for path in (self.group, *([self.acct] if self.acct else [])):
                path.mkdir()
                self._made.append(path)
            if self.h.version == 2:
                for key, value in v2_values(self.percent).items():
                    _write(self.group / key, value)
            else:
                self._write_v1()
        except BaseException:
            self.remove()
            raise
        return self

    def _write_v1(self) -> None:
        rt = None
        if self.h.realtime:   # the parent's RT runtime less what its other groups hold
            root = self.h.cpu_root
            held = sum(int(_read(d / "cpu.rt_runtime_us") or 0) for d in root.iterdir()
                       if d.is_dir() and d != self.group)
            total = int(_read(root / "cpu.rt_runtime_us") or -1)
            rt = max(0, (total if total >= 0 else RT_PERIOD_US) - held)   # -1: unlimited
        period = int(_read(self.group / "cpu.rt_period_us") or RT_PERIOD_US)
        values = v1_values(self.percent, rt_period_us=period, rt_available_us=rt)
        rt_value = values.pop("cpu.rt_runtime_us", None)
        if rt_value is not None:
            self.rt_runtime_us = int(rt_value)
            _write_retrying(self.group / "cpu.rt_runtime_us", rt_value)
        for key, value in values.items():
            _write(self.group / key, value)

    def runner_join(self) -> None:
        """A ``preexec_fn`` for the ``u2sa sim`` process: into the cpuacct group, and the budget when whole_sim."""
        for group in ([self.group] if self.whole_sim else []) + ([self.acct] if self.acct else []):
            _write(group / "cgroup.procs", str(os.getpid()))

    def stack_join(self) -> None:
        """A ``preexec_fn``: the calling process into the budget (and the cpuacct group)."""
        for group in (self.group, *([self.acct] if self.acct else [])):
            _write(group / "cgroup.procs", str(os.getpid()))

    def usage_file(self) -> tuple[Path, bool]:
        """(the file counting the budget's CPU time, whether it includes the ``u2sa sim`` process)."""
        if self.acct is not None:
            return self.acct / "cpuacct.usage", True
        return self.group / ("cpu.stat" if self.h.version == 2 else "cpuacct.usage"), self.whole_sim

    def throttling(self) -> tuple[int, int]:
        """(CFS periods, periods throttled) of the group so far."""
        stat = _stat(_read(self.group / "cpu.stat"))
        return stat.get("nr_periods", 0), stat.get("nr_throttled", 0)

    def remove(self) -> list[str]:
        """Move any remaining task to the hierarchy's root, remove the group(s); what could not be done."""
        problems = []
        for path in reversed(self._made):
            root = path.parent
            for pid in _read(path / "cgroup.procs").split():
                try:
                    _write(root / "cgroup.procs", pid)
                except BudgetError as exc:
                    if not _gone(pid):
                        problems.append(str(exc))
            for attempt in range(40):   # a task that just exited can hold its group for a moment
                try:
                    self._rmdir(path)
                    break
                except FileNotFoundError:
                    break
                except OSError as exc:
                    if exc.errno != errno.EBUSY or attempt == 39:
                        problems.append(f"cannot remove {path}: {exc.strerror}")
                        break
                    time.sleep(0.05)
        self._made.clear()
        return problems

    def __enter__(self) -> CpuBudget:
        return self.create()

    def __exit__(self, *_exc: object) -> None:
        for problem in self.remove():
            print(f"bench: {problem}", file=sys.stderr)


def remove_stale(hierarchy: Hierarchy) -> list[str]:
    """Remove the empty ``u2sa-sbc-<pid>`` groups of benches no longer running (one killed with SIGKILL)."""
    removed = []
    for root in (hierarchy.cpu_root, *([hierarchy.acct_root] if hierarchy.acct_root else [])):
        for path in root.glob("u2sa-sbc-*"):
            pid = path.name.rsplit("-", 1)[-1]
            if pid.isdigit() and _gone(pid) and not _read(path / "cgroup.procs").split():
                try:
                    path.rmdir()
                    removed.append(str(path))
                except OSError:
                    pass
    return removed


def _gone(pid: str) -> bool:
    return not Path(f"/proc/{pid}").exists()


SPIN = "import os, sys, time\n{setup}end = time.monotonic() + {seconds}\nwhile time.monotonic() < end: pass\n"
FIFO = ("try: os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))\n"
        "except OSError as e: sys.exit(f'SCHED_FIFO refused: {e.strerror}')\n")


def measure_share(budget: CpuBudget, *, spinners: int, seconds: float, realtime: bool = False) -> float | str:
    """Busy loops in ``stack/`` for *seconds*: their CPU as % of one core, or why they could not run."""
    usage, _with_runner = budget.usage_file()
    code = SPIN.format(setup=FIFO if realtime else "", seconds=seconds)
    u0, t0 = read_usage_ns(usage), time.monotonic()
    procs = [subprocess.Popen([sys.executable, "-c", code], preexec_fn=budget.stack_join, stderr=subprocess.PIPE,
                              text=True) for _ in range(spinners)]
    errors = [p.communicate()[1].strip() for p in procs]
    wall = time.monotonic() - t0
    failed = [e for p, e in zip(procs, errors) if p.returncode]
    if failed:
        return failed[0].splitlines()[-1]
    return 100.0 * (read_usage_ns(usage) - u0) / 1e9 / wall


def selftest(hierarchy: Hierarchy, percents: list[float], *, seconds: float = 2.0) -> list[str]:
    """For each budget: the share busy loops get in it (one per CPU; one SCHED_FIFO loop on v1 with RT)."""
    lines = []
    cpus = os.cpu_count() or 1
    for percent in percents:
        with CpuBudget(hierarchy, percent) as budget:
            cfs = measure_share(budget, spinners=cpus, seconds=seconds)
            line = f"budget {percent:5.1f} %: {cpus} busy loops got " + (f"{cfs:5.1f} %" if isinstance(cfs, float)
                                                                           else f"nothing ({cfs})")
            if hierarchy.version == 1 and hierarchy.realtime:
                rt = measure_share(budget, spinners=1, seconds=seconds, realtime=True)
                line += (f"; one SCHED_FIFO loop got {rt:5.1f} % (rt_runtime {budget.rt_runtime_us} us per "
                         f"{RT_PERIOD_US} us, per CPU)" if isinstance(rt, float) else f"; SCHED_FIFO: {rt}")
        lines.append(line)
    return lines


def remove_tree(path: Path) -> None:
    """``rmdir`` for a fake cgroup root made of plain files (tests)."""
    shutil.rmtree(path)
