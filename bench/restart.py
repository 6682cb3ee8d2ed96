#!/usr/bin/env python3
"""Restart benchmark under a real systemd: kill -> publishing again, and hang -> restart.

Stages a vehicle (``u2sa install --root``) with one service per kind and bytecode mode,
boots systemd as PID 1 of a private namespace (tests/systemd_ns.py) and measures, from
the host, for each service in turn:

- SIGKILL of the main process -> its first Health message from the new process on LCM
  (``start()`` publishes one right after READY), over ``--kills`` kills; also kill ->
  systemd reports it active again (READY received, polled through ``systemctl show``);
- SIGSTOP (a hang: the loop stops pinging the watchdog) -> the watchdog ends it
  (``WatchdogSec=2s``: systemd sends SIGABRT with a SIGCONT, so the stopped process
  wakes, faulthandler writes its stacks to the journal and it dies; SIGKILL follows after
  ``TimeoutAbortSec=1s`` only for a process that cannot act on it) -> publishing again,
  over ``--hangs`` hangs.

Bytecode modes: ``vehicle`` services find the bytecode of u2sa_hw cached (as in the venv
``u2sa install`` builds with pip on the vehicle: a drop-in gives them a writable
``PYTHONPYCACHEPREFIX``, filled by their first start); ``checkout`` services run as in the
tests' shared venv, where the checkout has no ``__pycache__`` (PYTHONDONTWRITEBYTECODE)
and every start compiles u2sa_hw from source.

Between kills ``systemctl reset-failed`` clears the start-limit counter
(``StartLimitBurst=5`` in 60 s would otherwise, rightly, call 20 kills a crash loop).
Prints p50, mean and max of each. Needs root. Usage: ``python bench/restart.py [--quick]``.
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
from staged_code import u2sa_command  # noqa: E402
from systemd_ns import SystemdNamespace, cannot_boot_reason, stage_root, wait_until  # noqa: E402

from u2sa_hw.bus.run_keys import use_run_key  # noqa: E402
from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.client import BusClient  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402

MODES = ("vehicle", "checkout")
PYCACHE = "u2sa-bench-pycache"
BYTECODE_DROPIN = f"""\
# bench/restart.py: bytecode cached as in a pip-installed venv (filled by the first start).
[Service]
CacheDirectory={PYCACHE}
Environment=PYTHONDONTWRITEBYTECODE= PYTHONPYCACHEPREFIX=/var/cache/{PYCACHE}
"""


class FirstHealth:
    """Arrival time of the first Health of each (service, PID)."""

    def __init__(self, url: str) -> None:
        self.client = BusClient(url)
        self.first: dict[tuple[str, int], float] = {}
        self.lock = threading.Lock()
        self.client.transport.subscribe(ch.HEALTH, t.Health, self._on_health)

    def _on_health(self, _channel: str, msg: Any) -> None:
        now = time.monotonic()
        with self.lock:
            self.first.setdefault((msg.name, msg.pid), now)

    def arrival(self, name: str, pid: int) -> float | None:
        """When *name*'s process *pid* was first heard (monotonic), or None."""
        with self.lock:
            return self.first.get((name, pid))


def summary(label: str, values: list[float]) -> str:
    """One line: count, p50, mean and max in milliseconds."""
    ms = [v * 1000 for v in values]
    return (f"  {label:42} n={len(ms):3}  p50 {statistics.median(ms):6.0f} ms  mean {statistics.fmean(ms):6.0f} ms"
            f"  max {max(ms):6.0f} ms")


def gone(host_pid: int) -> bool:
    """True once *host_pid* has exited (or is a zombie)."""
    try:
        return "zombie" in Path(f"/proc/{host_pid}/status").read_text()
    except FileNotFoundError:
        return True


def wait_health(health: FirstHealth, name: str, pid: int) -> float:
    """When the restarted *name* (namespace PID *pid*) first published health."""
    if not wait_until(lambda: health.arrival(name, pid) is not None, timeout=30, interval=0.005):
        raise RuntimeError(f"no health from the restarted {name} (pid {pid})")
    return health.arrival(name, pid)  # type: ignore[return-value]


def unit_of(name: str) -> str:
    """The systemd unit of the staged service *name* (the HSM has a unit of its own, u2sa-hsm.service)."""
    return "u2sa-hsm.service" if name == "hsm" else f"u2sa@{name}.service"


def measure_kill(ns: SystemdNamespace, health: FirstHealth, name: str) -> tuple[float, float]:
    """SIGKILL -> active again, SIGKILL -> first Health of the new process (seconds)."""
    unit = unit_of(name)
    old = ns.wait_active(unit)
    ns.systemctl("reset-failed", unit, check=False)
    t0 = time.monotonic()
    os.kill(ns.host_pid(old), signal.SIGKILL)
    new = ns.wait_active(unit, not_pid=old, timeout=30)
    t_active = time.monotonic()
    return t_active - t0, wait_health(health, name, new) - t0


def measure_hang(ns: SystemdNamespace, health: FirstHealth, name: str) -> tuple[float, float]:
    """SIGSTOP -> the process is gone (watchdog), SIGSTOP -> first Health of the new one (seconds)."""
    unit = unit_of(name)
    old = ns.wait_active(unit)
    ns.systemctl("reset-failed", unit, check=False)
    host = ns.host_pid(old)
    t0 = time.monotonic()
    os.kill(host, signal.SIGSTOP)
    if not wait_until(lambda: gone(host), timeout=30, interval=0.005):
        raise RuntimeError(f"the watchdog did not end the hung {name}")
    t_killed = time.monotonic()
    new = ns.wait_active(unit, not_pid=old, timeout=30)
    return t_killed - t0, wait_health(health, name, new) - t0


def stage(base: Path, url: str, services: dict[str, str]) -> Path:
    """Install a profile of *services* (name -> kind) into a staged root; the vehicle-mode drop-ins."""
    profile = base / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "bench"\nlcm_url = "{url}"\n\n' + "".join(
        f'[services.{name}]\nkind = "{kind}"\n\n' for name, kind in services.items()))
    root = stage_root(base / "root")
    subprocess.run([*u2sa_command(root), "install", "--vehicle", str(profile), "--root", str(root),
                    "--venv", "shared"], check=True, stdout=subprocess.DEVNULL)
    for name in services:
        if name.endswith("_vehicle") or name == "hsm":
            dropin = root / f"etc/systemd/system/{unit_of(name)}.d"
            dropin.mkdir(exist_ok=True)
            (dropin / "90-bench-bytecode.conf").write_text(BYTECODE_DROPIN)
    return root


def main() -> int:
    """Run the benchmark; print the figures."""
    use_run_key()   # without an installed key, a fresh one for this run and the services it starts
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kills", type=int, default=20, help="SIGKILLs per service (default 20)")
    parser.add_argument("--hangs", type=int, default=5, help="SIGSTOP hangs per service (default 5)")
    parser.add_argument("--kinds", default="state_estimator,world_modeler,hsm",
                        help="comma-separated service kinds to restart (default state_estimator,world_modeler,hsm: "
                        "the estimator imports numpy, the world modeler does not, the HSM has a unit of its own)")
    parser.add_argument("--modes", default=",".join(MODES),
                        help="comma-separated bytecode modes: vehicle (bytecode cached, as installed on the "
                        "vehicle), checkout (compiled at every start, as in the tests); default both")
    parser.add_argument("--quick", action="store_true", help="5 kills and 2 hangs per service, vehicle mode only")
    args = parser.parse_args()
    if args.quick:
        args.kills, args.hangs, args.modes = 5, 2, "vehicle"
    modes = [m for m in args.modes.split(",") if m]
    if not set(modes) <= set(MODES):
        parser.error(f"--modes: use {', '.join(MODES)}")
    kinds = [k for k in args.kinds.split(",") if k]
    reason = cannot_boot_reason()
    if reason:
        print(f"bench/restart.py: cannot boot systemd here: {reason}", file=sys.stderr)
        return 2
    # The HSM runs as u2sa-hsm.service under the name 'hsm': one of it, with cached bytecode.
    services = {("hsm" if kind == "hsm" else f"{kind}_{mode}"): kind for kind in kinds
                for mode in (["vehicle"] if kind == "hsm" else modes)}
    url = private_lcm_url()
    results: dict[str, tuple[list[tuple[float, float]], list[tuple[float, float]]]] = {}
    with tempfile.TemporaryDirectory(prefix="u2sa-bench-restart-") as tmp:
        root = stage(Path(tmp), url, services)
        health = FirstHealth(url)
        try:
            with SystemdNamespace(root) as ns:
                for name in services:
                    ns.wait_active(unit_of(name))
                for name in services:
                    kills = [measure_kill(ns, health, name) for _ in range(args.kills)]
                    hangs = [measure_hang(ns, health, name) for _ in range(args.hangs)]
                    results[name] = (kills, hangs)
        finally:
            health.client.close()
    print(f"u2sa restart benchmark: systemd {subprocess.getoutput('systemctl --version').split()[1]}, "
          f"{os.cpu_count()} CPUs, WatchdogSec=2s, TimeoutAbortSec=1s, RestartSec=250ms, {len(services)} services")
    for name, (kills, hangs) in results.items():
        kind, _, mode = ("hsm", "", "vehicle") if name == "hsm" else name.rpartition("_")
        print(f"{kind} ({mode} bytecode):")
        if kills:
            print(summary("SIGKILL -> active again (READY)", [k[0] for k in kills]))
            print(summary("SIGKILL -> publishing again (first Health)", [k[1] for k in kills]))
        if hangs:
            print(summary("hang (SIGSTOP) -> ended by the watchdog", [h[0] for h in hangs]))
            print(summary("hang (SIGSTOP) -> publishing again", [h[1] for h in hangs]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
