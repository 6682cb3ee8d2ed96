"""The HSM under a real systemd: booted as PID 1 of a private namespace (tests/systemd_ns.py).

`u2sa install --root` stages a vehicle of three services and the HSM (``kind = "hsm"``,
installed as u2sa-hsm.service): ``est``, a state estimator in passthrough mode that only
publishes STATE_ESTIMATE while this test feeds it STATE_INFO, watched for stale data;
``broken``, a required estimator whose ``mode`` its own check refuses, so it exits 1 at
every start; systemd boots straight into u2sa.target. Checked, all through real LCM:

- est alive but silent (the feed stops) -> the HSM, which runs as a unit and so restarts
  through ``systemctl restart``, restarts u2sa@est.service: a new MainPID, the HSM's
  SystemHealth shows the restart and why, the new process publishes health again;
- broken crash-loops -> systemd's start limit leaves the unit failed, the HSM marks it
  failed and publishes an active Failsafe on FAILSAFE naming it;
- the HSM SIGKILLed -> systemd restarts it (Restart=always), the new HSM publishes
  SystemHealth and, still seeing broken down, raises the failsafe again;
- the HSM (root) and the services (u2sa) share no systemd-managed directory, which
  systemd would hand from one user to the other at every start.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Iterator

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from conftest import wait_until  # noqa: E402
from staged_code import u2sa_command  # noqa: E402
from systemd_ns import SystemdNamespace, cannot_boot_reason, stage_root  # noqa: E402

from u2sa_hw import channels as ch  # noqa: E402
from u2sa_hw import lcmtypes as t  # noqa: E402
from u2sa_hw.bus.client import BusClient  # noqa: E402
from u2sa_hw.bus.udp_ports import private_lcm_url  # noqa: E402

REASON = cannot_boot_reason()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"systemd cannot boot here: {REASON}")

MAX_RESTARTS = 2
# Beats every 0.2 s, 10 may be missed (2 s): a loaded 2-core machine must not look like a hang.
# The grace covers the estimators' imports while the crash loop competes for the CPU.
HSM_SETTINGS = ("health_interval_s = 0.2, missed_heartbeats = 10, startup_grace_s = 20.0, "
                f"restart_backoff_s = 0.5, max_restarts = {MAX_RESTARTS}, system_health_interval_s = 0.2")


def write_profile(path: Path, url: str) -> Path:
    """est (fed by the test, watched for stale data), broken (refuses its mode at start), the HSM."""
    path.write_text(f"""\
[vehicle]
name = "systemd-hsm-test"
system_id = 9
lcm_url = "{url}"

[services.est]
kind = "state_estimator"
settings = {{ health_interval_s = 0.2, mode = "passthrough" }}

[services.est.supervision]
data_channel = "STATE_ESTIMATE"
stale_after_s = 2.0
startup_grace_s = 10.0

[services.broken]
kind = "state_estimator"
required = true
settings = {{ health_interval_s = 0.2, mode = "no_such_mode" }}

[services.broken.supervision]
startup_grace_s = 3.0

[services.hsm]
kind = "hsm"
settings = {{ {HSM_SETTINGS} }}
""")
    return path


class Watch:
    """Health pids per service, every SystemHealth and Failsafe, from real LCM."""

    def __init__(self, url: str) -> None:
        self.client = BusClient(url)
        self.pids: dict[str, list[int]] = {}
        self.system: list[t.SystemHealth] = []
        self.failsafes: list[t.Failsafe] = []
        # (service, pid) -> how many SystemHealth/Failsafe messages had arrived when that pid first spoke
        self.marks: dict[tuple[str, int], tuple[int, int]] = {}
        self._lock = threading.Lock()
        self.client.transport.subscribe(ch.HEALTH, t.Health, self._health)
        self.client.transport.subscribe(ch.SYSTEM_HEALTH, t.SystemHealth, lambda _c, m: self._add(self.system, m))
        self.client.transport.subscribe(ch.FAILSAFE, t.Failsafe, lambda _c, m: self._add(self.failsafes, m))

    def _add(self, items: list[Any], msg: Any) -> None:
        with self._lock:
            items.append(msg)

    def _health(self, _channel: str, msg: t.Health) -> None:
        with self._lock:
            pids = self.pids.setdefault(msg.name, [])
            if not pids or pids[-1] != msg.pid:
                pids.append(msg.pid)
                self.marks[(msg.name, msg.pid)] = (len(self.system), len(self.failsafes))

    def pid(self, name: str) -> int:
        """The PID in the latest health of *name* (0 before any)."""
        with self._lock:
            return self.pids.get(name, [0])[-1]

    def service_state(self, name: str) -> t.ServiceState | None:
        """*name*'s row in the latest SystemHealth."""
        with self._lock:
            latest = self.system[-1] if self.system else None
        return next((s for s in latest.services if s.name == name), None) if latest else None

    def system_since(self, start: int) -> list[t.SystemHealth]:
        """SystemHealth messages from index *start* on."""
        with self._lock:
            return self.system[start:]

    def failsafes_since(self, start: int) -> list[t.Failsafe]:
        """Failsafe messages from index *start* on."""
        with self._lock:
            return self.failsafes[start:]

    def close(self) -> None:
        """Release the bus."""
        self.client.close()


class Feeder:
    """A sensor on STATE_INFO at 10 Hz: while it feeds, est publishes STATE_ESTIMATE."""

    def __init__(self, url: str) -> None:
        self.client = BusClient(url, name="test_sensor")
        self.feeding = threading.Event()
        self.feeding.set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feeder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            if self.feeding.is_set():
                info = t.StateInformation().set(x=1.0, y=2.0)
                info.sensor_name = "test_sensor"
                self.client.publish(ch.STATE_INFO, info)

    def close(self) -> None:
        """Stop feeding and release the bus."""
        self._stop.set()
        self._thread.join()
        self.client.close()


@pytest.fixture(scope="module")
def url() -> str:
    """This module's own LCM port."""
    return private_lcm_url()


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory, url: str) -> Path:
    base = tmp_path_factory.mktemp("systemd_hsm")
    profile = write_profile(base / "vehicle.toml", url)
    staged = stage_root(base / "root")
    # --force: the check rightly refuses the service 'broken', which is there to crash-loop.
    done = subprocess.run([*u2sa_command(staged), "install", "--vehicle", str(profile), "--root", str(staged),
                           "--venv", "shared", "--force"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert (staged / "etc/systemd/system/u2sa.target.wants/u2sa-hsm.service").is_symlink()
    return staged


@pytest.fixture(scope="module")
def watch(url: str) -> Iterator[Watch]:
    w = Watch(url)
    yield w
    w.close()


@pytest.fixture(scope="module")
def feeder(url: str) -> Iterator[Feeder]:
    f = Feeder(url)
    yield f
    f.close()


@pytest.fixture(scope="module")
def ns(root: Path, watch: Watch, feeder: Feeder) -> Iterator[SystemdNamespace]:
    """Booted with the feed already running, so est has data from its first moment."""
    namespace = SystemdNamespace(root, unit="u2sa.target")
    namespace.boot()
    yield namespace
    namespace.poweroff()


def hsm_log(root: Path) -> str:
    """The HSM's log file (the staged /var is the namespace's /var)."""
    path = root / "var/log/u2sa/hsm.log"
    return path.read_text(errors="replace") if path.exists() else ""


DIRECTORY_KINDS = ("StateDirectory", "LogsDirectory", "CacheDirectory", "RuntimeDirectory")


def test_the_hsm_and_the_services_do_not_fight_over_their_directories(ns: SystemdNamespace) -> None:
    """Units that share a systemd-managed directory must run as one user.

    systemd chowns a unit's StateDirectory=/LogsDirectory= (recursively, when the top owner
    differs) to the unit's User= at every start. If the HSM (root, no capabilities, so no
    CAP_DAC_OVERRIDE) and the services (u2sa) share /var/log/u2sa, every start hands the
    directory and all its logs to the other: a process that opens its log while the other
    owns it dies with "Permission denied", which at boot (all start together) costs the HSM
    restarts from its start limit and can leave the vehicle with no HSM at all.
    """
    users: dict[str, dict[str, str]] = {}          # "LogsDirectory=u2sa" -> unit -> its User=
    for unit in ("u2sa-hsm.service", "u2sa@est.service", "u2sa@broken.service"):
        props = ns.show(unit, "User", *DIRECTORY_KINDS)
        for kind in DIRECTORY_KINDS:
            for directory in props.get(kind, "").split():
                users.setdefault(f"{kind}={directory}", {})[unit] = props.get("User") or "root"
    shared = {d: by_unit for d, by_unit in users.items() if len(set(by_unit.values())) > 1}
    if shared:
        restarts = ns.show("u2sa-hsm.service", "NRestarts")["NRestarts"]
        pytest.fail(f"units of different users share systemd-managed directories, so each start takes them from "
                    f"the other: {shared}; the HSM already restarted {restarts} times at boot")


def test_alive_but_silent_service_is_restarted_by_the_hsm_through_systemd(
        ns: SystemdNamespace, root: Path, watch: Watch, feeder: Feeder) -> None:
    unit = "u2sa@est.service"
    wait_until(lambda: (s := watch.service_state("est")) and s.state == "ok" and 0 <= s.data_age_s < 1.0,
               timeout=40, message="the HSM to see est ok with fresh data")
    old = ns.wait_active(unit)
    assert watch.pid("est") == old
    host_old = ns.host_pid(old)
    seen = len(watch.system)

    feeder.feeding.clear()              # est stays alive and keeps beating, but its data stops
    try:
        new = ns.wait_active(unit, not_pid=old, timeout=30)
        wait_until(lambda: watch.pid("est") == new, timeout=20,
                   message=f"health from the restarted est (pid {new}); last pid {watch.pid('est')}")
    finally:
        feeder.feeding.set()            # the sensor is back: the new est has data again
    assert not Path(f"/proc/{host_old}").exists(), "the silent est process is still alive"

    # The HSM said why while it restarted it, and counts the restart once est is ok again.
    why = [s for m in watch.system_since(seen) for s in m.services if s.name == "est" and s.state == "restarting"]
    assert why and why[0].last_error.startswith("no data on STATE_ESTIMATE for"), why[:1]
    wait_until(lambda: (s := watch.service_state("est")) and s.state == "ok" and s.restarts == 1
               and 0 <= s.data_age_s < 1.0, timeout=20, message="the HSM to report est ok after one restart")
    log = hsm_log(root)
    assert "restarts via systemd (systemctl restart --no-block u2sa@{name}.service)" in log, log[-2000:]
    assert f"restarting est (restart 1 of {MAX_RESTARTS}): no data on STATE_ESTIMATE for" in log, log[-2000:]
    assert "restart of u2sa@est.service queued with systemd" in log, log[-2000:]


def test_crash_loop_ends_failed_and_the_hsm_raises_the_failsafe(ns: SystemdNamespace, root: Path,
                                                                watch: Watch) -> None:
    unit = "u2sa@broken.service"
    # systemd gave up (start limit), not "activating (auto-restart)".
    wait_until(lambda: ns.state(unit) == "failed/failed", timeout=60,
               message=f"{unit} failed at the start limit ({ns.journal_hint(unit)})")
    props = ns.show(unit, "ExecMainCode", "ExecMainStatus", "ExecMainStartTimestampMonotonic")
    # Its last run either exited 1 (the refused mode) or was stopped by SIGTERM when the HSM's
    # restart of it came while it was still starting up.
    assert (props["ExecMainCode"], props["ExecMainStatus"]) in {("1", "1"), ("2", "15")}, props
    # At the start limit systemd refuses any further start (the HSM's too) without running anything.
    # (Result stays "exit-code": systemd keeps the first failure's result.)
    probe = ns.systemctl("start", unit, check=False)
    assert probe.returncode != 0, probe.stdout
    assert ns.show(unit, "ExecMainStartTimestampMonotonic") == \
        {"ExecMainStartTimestampMonotonic": props["ExecMainStartTimestampMonotonic"]}, "a start was not refused"
    failsafe = wait_until(lambda: next((f for f in watch.failsafes_since(0) if f.active), None), timeout=60,
                          message="an active Failsafe on FAILSAFE")
    assert failsafe.service == "broken" and failsafe.header.source == "hsm", (failsafe.service, failsafe.reason)
    assert failsafe.reason.startswith("required service broken failed: no heartbeat"), failsafe.reason
    assert f"after {MAX_RESTARTS} restarts" in failsafe.reason, failsafe.reason
    wait_until(lambda: (s := watch.service_state("broken")) and s.state == "failed", timeout=10,
               message="SystemHealth to show broken failed")
    latest = watch.system_since(0)[-1]
    assert latest.failsafe and latest.summary.startswith("FAILSAFE held by hsm -- hsm: required service broken failed"), latest.summary
    assert watch.service_state("est").state == "ok"
    log = hsm_log(root)
    assert f"restarting broken (restart 1 of {MAX_RESTARTS}): no heartbeat" in log, log[-2000:]
    assert "broken FAILED (required -> failsafe)" in log, log[-2000:]


def test_sigkilled_hsm_is_restarted_by_systemd_and_reports_again(ns: SystemdNamespace, watch: Watch) -> None:
    unit = "u2sa-hsm.service"
    old = ns.wait_active(unit)
    # Active through READY (Type=notify), under the watchdog like the services.
    props = ns.show(unit, "Type", "WatchdogUSec", "Restart")
    assert props == {"Type": "notify", "WatchdogUSec": "2s", "Restart": "always"}, props
    wait_until(lambda: watch.pid("hsm") == old, timeout=10, message=f"health from the HSM (pid {old})")
    restarts = int(ns.show(unit, "NRestarts")["NRestarts"])
    os.kill(ns.host_pid(old), signal.SIGKILL)

    new = ns.wait_active(unit, not_pid=old, timeout=30)
    assert int(ns.show(unit, "NRestarts")["NRestarts"]) == restarts + 1   # systemd's own restart
    wait_until(lambda: watch.pid("hsm") == new, timeout=20, message=f"health from the restarted HSM (pid {new})")
    system_mark, failsafe_mark = watch.marks[("hsm", new)]
    # Everything from here on comes from the new HSM: the old one was dead before it started.
    fresh = wait_until(lambda: watch.system_since(system_mark), timeout=10,
                       message="SystemHealth from the restarted HSM")
    assert {s.name for s in fresh[0].services} >= {"est", "broken"}
    # It starts from nothing, sees broken still down and raises the failsafe again.
    again = wait_until(lambda: next((f for f in watch.failsafes_since(failsafe_mark) if f.active), None),
                       timeout=40, message="the restarted HSM to raise the failsafe again")
    assert again.service == "broken" and again.reason.startswith("required service broken failed"), again.reason
    assert watch.service_state("est").state == "ok"
