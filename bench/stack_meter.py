"""bench/stack.py's meters: CPU (per kind of thread), RSS and PSS of the stack's processes, and channel rates."""

from __future__ import annotations

import os
import threading
import time
from collections import defaultdict

import psutil

from u2sa_hw.bus.transport import Transport

def pss_bytes(pid: int) -> int:
    """The proportional set size of *pid* (shared pages divided among their users), from smaps_rollup."""
    with open(f"/proc/{pid}/smaps_rollup", encoding="ascii") as f:
        for line in f:
            if line.startswith("Pss:"):
                return int(line.split()[1]) * 1024
    return 0


THREAD_KINDS = (("bus ", "bus"), ("health ", "health"))   # kernel names a service gives its threads
CPU_AIM_PCT, PSS_AIM_MB = 10.0, 200.0    # issue 27: the example rover's services at nominal rates


def thread_ticks(pid: int) -> dict[str, int]:
    """CPU clock ticks per kind of thread of *pid*: the service's own loop, its bus handler, health, other."""
    ticks: dict[str, int] = defaultdict(int)
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm", encoding="ascii", errors="replace") as f:
                comm = f.read().strip()
            with open(f"/proc/{pid}/task/{tid}/stat", encoding="ascii") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        kind = "loop" if tid == str(pid) else next((k for prefix, k in THREAD_KINDS if comm.startswith(prefix)),
                                                   "other")
        ticks[kind] += int(fields[11]) + int(fields[12])
    return ticks


class ResourceMeter:
    """CPU time, RSS and PSS of the launcher's children (and this process) over a window."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.procs = {name: psutil.Process(pid) for name, pid in pids.items()}
        self.procs["(u2sa sim: mocks, simulator)"] = psutil.Process()
        self.rss: dict[str, int] = defaultdict(int)
        self.pss: dict[str, int] = defaultdict(int)
        self.threads: dict[str, dict[str, float]] = {}   # name -> thread kind -> CPU % of one core
        self.cpu0 = {n: sum(p.cpu_times()[:2]) for n, p in self.procs.items()}
        self.threads0 = {n: thread_ticks(p.pid) for n, p in self.procs.items()}
        self.t0 = time.monotonic()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._done.wait(1.0):
            for name, proc in self.procs.items():
                self._memory(name, proc)

    def _memory(self, name: str, proc: psutil.Process) -> None:
        try:
            self.rss[name] = max(self.rss[name], proc.memory_info().rss)
            self.pss[name] = max(self.pss[name], pss_bytes(proc.pid))
        except (psutil.Error, OSError):
            pass

    def stop(self) -> dict[str, tuple[float, float, float]]:
        """name -> (CPU % of one core, largest RSS MB, largest PSS MB) over the window."""
        wall = time.monotonic() - self.t0
        result = {}
        for name, proc in self.procs.items():
            try:
                cpu = sum(proc.cpu_times()[:2]) - self.cpu0[name]
            except psutil.Error:
                cpu = float("nan")
            self._memory(name, proc)
            result[name] = (100.0 * cpu / wall, self.rss[name] / 2**20, self.pss[name] / 2**20)
            try:
                ticks = thread_ticks(proc.pid)
            except OSError:
                ticks = {}
            hz = os.sysconf("SC_CLK_TCK")
            self.threads[name] = {k: 100.0 * (v - self.threads0[name].get(k, 0)) / hz / wall for k, v in ticks.items()}
        self._done.set()
        return result


class RateCounter:
    """Messages and bytes per channel on the bus."""

    def __init__(self, url: str) -> None:
        self.counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])
        self.transport = Transport(url, name="bench-rates")
        self.transport.subscribe(".*", None, self._on, raw=True)
        self.transport.start()
        self.t0 = time.monotonic()

    def _on(self, channel: str, data: bytes) -> None:
        c = self.counts[channel]
        c[0] += 1
        c[1] += len(data)

    def stop(self) -> tuple[float, dict[str, list[int]]]:
        self.transport.stop()
        return time.monotonic() - self.t0, dict(self.counts)
