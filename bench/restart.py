#!/usr/bin/env python3
"""Restart benchmark under a real systemd: kill -> publishing again, and hang -> restart.

Stages a vehicle with one state estimator (``u2sa install --root``), boots systemd as
PID 1 of a private namespace (tests/systemd_ns.py) and measures, from the host:

- SIGKILL of the service's main process -> its first Health message from the new
  process on LCM (``start()`` publishes one right after READY), over ``--kills`` kills;
  also kill -> systemd reports it active again (READY received);
- SIGSTOP (a hang: the loop stops pinging the watchdog) -> systemd kills it
  (``WatchdogSec=2s``, then SIGKILL after ``TimeoutAbortSec=1s`` since a stopped process
  cannot act on SIGABRT) -> publishing again, over ``--hangs`` hangs.

Between kills ``systemctl reset-failed`` clears the start-limit counter
(``StartLimitBurst=5`` in 60 s would otherwise, rightly, call 20 kills a crash loop).
Prints p50, mean and max of each. Needs root. Usage: ``python bench/restart.py``.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from systemd_ns import SystemdNamespace, cannot_boot_reason, stage_root, wait_until  # noqa: E402

from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus_client import BusClient  # noqa: E402
from u2sa_hw.udp_ports import private_udp_port  # noqa: E402

UNIT = "u2sa@bench.service"


class FirstHealth:
    """Arrival time of the first Health of service 'bench' from each PID."""

    def __init__(self, url: str) -> None:
        self.client = BusClient(url)
        self.first: dict[int, float] = {}
        self.lock = threading.Lock()
        self.client.transport.subscribe(ch.HEALTH, t.Health, self._on_health)

    def _on_health(self, _channel: str, msg: Any) -> None:
        now = time.monotonic()
        if msg.name == "bench":
            with self.lock:
                self.first.setdefault(msg.pid, now)

    def arrival(self, pid: int) -> float | None:
        with self.lock:
            return self.first.get(pid)


def summary(label: str, values: list[float]) -> str:
    ms = [v * 1000 for v in values]
    return (f"{label:44} n={len(ms):3}  p50 {statistics.median(ms):7.0f} ms  mean {statistics.fmean(ms):7.0f} ms"
            f"  max {max(ms):7.0f} ms")


def gone(host_pid: int) -> bool:
    try:
        return "zombie" in Path(f"/proc/{host_pid}/status").read_text() or False
    except FileNotFoundError:
        return True


def measure_kill(ns: SystemdNamespace, health: FirstHealth) -> tuple[float, float]:
    old = ns.wait_active(UNIT)
    ns.systemctl("reset-failed", UNIT, check=False)
    host = ns.host_pid(old)
    t0 = time.monotonic()
    os.kill(host, signal.SIGKILL)
    new = ns.wait_active(UNIT, not_pid=old, timeout=30)
    t_active = time.monotonic()
    if not wait_until(lambda: health.arrival(new) is not None, timeout=30, interval=0.005):
        raise RuntimeError(f"no health from the restarted service (pid {new})")
    return t_active - t0, health.arrival(new) - t0  # type: ignore[operator]


def measure_hang(ns: SystemdNamespace, health: FirstHealth) -> tuple[float, float]:
    old = ns.wait_active(UNIT)
    ns.systemctl("reset-failed", UNIT, check=False)
    host = ns.host_pid(old)
    t0 = time.monotonic()
    os.kill(host, signal.SIGSTOP)
    if not wait_until(lambda: gone(host), timeout=30, interval=0.005):
        raise RuntimeError("the watchdog did not kill the hung service")
    t_killed = time.monotonic()
    new = ns.wait_active(UNIT, not_pid=old, timeout=30)
    if not wait_until(lambda: health.arrival(new) is not None, timeout=30, interval=0.005):
        raise RuntimeError(f"no health from the restarted service (pid {new})")
    return t_killed - t0, health.arrival(new) - t0  # type: ignore[operator]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--hangs", type=int, default=5)
    parser.add_argument("--kind", default="state_estimator",
                        help="service kind to restart (default state_estimator, whose filterpy/scipy imports "
                        "take about a second; world_modeler imports ten times less)")
    args = parser.parse_args()
    reason = cannot_boot_reason()
    if reason:
        print(f"bench/restart.py: cannot boot systemd here: {reason}", file=sys.stderr)
        return 2
    port = private_udp_port()
    url = f"udpm://239.255.76.67:{port}?ttl=0"
    with tempfile.TemporaryDirectory(prefix="u2sa-bench-restart-") as tmp:
        base = Path(tmp)
        profile = base / "vehicle.toml"
        profile.write_text(f'[vehicle]\nname = "bench"\nlcm_url = "{url}"\n\n'
                           f'[services.bench]\nkind = "{args.kind}"\n')
        root = stage_root(base / "root")
        u2sa = Path(sys.executable).with_name("u2sa")
        subprocess.run([str(u2sa), "install", "--vehicle", str(profile), "--root", str(root)], check=True,
                       stdout=subprocess.DEVNULL)
        health = FirstHealth(url)
        with SystemdNamespace(root) as ns:
            ns.wait_active(UNIT)
            kills = [measure_kill(ns, health) for _ in range(args.kills)]
            hangs = [measure_hang(ns, health) for _ in range(args.hangs)]
        health.client.close()
    print(f"u2sa restart benchmark: systemd {subprocess.getoutput('systemctl --version').split()[1]}, "
          f"{os.cpu_count()} CPUs, service kind {args.kind}, WatchdogSec=2s, TimeoutAbortSec=1s, RestartSec=250ms")
    print(summary("SIGKILL -> active again (READY)", [k[0] for k in kills]))
    print(summary("SIGKILL -> publishing again (first Health)", [k[1] for k in kills]))
    print(summary("hang (SIGSTOP) -> killed by the watchdog", [h[0] for h in hangs]))
    print(summary("hang (SIGSTOP) -> publishing again", [h[1] for h in hangs]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
