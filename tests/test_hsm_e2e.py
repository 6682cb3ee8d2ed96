"""The HSM end to end under the local launcher: real processes, real LCM multicast, real signals."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from supervision_helpers import Watch, break_config, hsm_profile, launch  # noqa: F401 - launch is a fixture

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.launcher.children import u2sa_command

def u2sa(tmp: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*u2sa_command(), *args], cwd=tmp, capture_output=True, text=True, timeout=60,
                          env=dict(os.environ))


def test_hung_service_is_restarted_through_the_launcher(tmp_path: Path, lcm_url: str, bus: BusClient,
                                                        launch: Any) -> None:
    watch = Watch(bus)
    vehicle = hsm_profile(tmp_path, lcm_url, '[services.est_a]\nkind = "state_estimator"\n'
                      "settings = { health_interval_s = 0.2 }\n", startup_grace_s=10.0)
    lp = launch(vehicle, "--grace", "3", "--watchdog", "0")   # the HSM, not the launcher's watchdog, must see it
    wait_until(lambda: (s := watch.service_state("est_a")) and s.state == "ok", timeout=30,
               message="the HSM to see est_a ok")
    old_pid = watch.pids["est_a"][-1]
    assert lp.status()["est_a"]["pid"] == old_pid

    os.kill(old_pid, signal.SIGSTOP)                         # a hang: alive, but no more heartbeats
    wait_until(lambda: len(watch.pids["est_a"]) >= 2, timeout=30, message="health from a new est_a process")
    assert watch.pids["est_a"][-1] != old_pid
    status = lp.status()["est_a"]
    assert status["run_id"] == 2 and status["pid"] == watch.pids["est_a"][-1]
    wait_until(lambda: (s := watch.service_state("est_a")) and s.state == "ok" and s.restarts == 1, timeout=30,
               message="the HSM to report est_a ok after one restart")
    assert "restarting est_a (restart 1 of 2): no heartbeat for" in lp.output
    assert "restart of est_a requested: HSM: no heartbeat" in lp.output

    shown = u2sa(tmp_path, "health", "--vehicle", str(vehicle), "--json")
    assert shown.returncode == 0, shown.stderr
    report = json.loads(shown.stdout)
    est = next(s for s in report["services"] if s["name"] == "est_a")
    assert report["failsafe"] is False and est["state"] == "ok" and est["restarts"] == 1
    assert report["source"] == "hsm" and est["heartbeat_age_s"] is not None and est["data_age_s"] is None
    table = u2sa(tmp_path, "health", "--vehicle", str(vehicle))
    assert table.returncode == 0 and "failsafe off" in table.stdout and "est_a" in table.stdout


def test_crash_looping_required_service_raises_the_failsafe(tmp_path: Path, lcm_url: str, bus: BusClient,
                                                            launch: Any) -> None:
    watch = Watch(bus)
    vehicle = hsm_profile(tmp_path, lcm_url, '[services.est]\nkind = "state_estimator"\n'
                      "settings = { health_interval_s = 0.2 }\n\n"
                      '[services.broken]\nkind = "state_estimator"\n'
                      "[services.broken.supervision]\nstartup_grace_s = 2.0\n", startup_grace_s=10.0)
    break_config(tmp_path, "broken")                         # it exits 1 at every start
    lp = launch(vehicle, "--force", "--give-up-after", "0", "--max-failures", "0", "--backoff", "0.2",
                "--max-backoff", "1")   # --force: past u2sa check, which sees the broken config
    failsafe = wait_until(lambda: next((f for f in list(watch.failsafes) if f.active), None), timeout=60,
                          message="an active FAILSAFE")
    assert failsafe.service == "broken" and failsafe.header.source == "hsm"
    assert "required service broken failed: no heartbeat" in failsafe.reason and "after 2 restarts" in failsafe.reason
    wait_until(lambda: (s := watch.service_state("broken")) and s.state == "failed", timeout=10,
               message="SystemHealth to show broken failed")
    assert watch.system[-1].failsafe and watch.system[-1].summary.startswith("FAILSAFE")
    assert watch.service_state("est").state == "ok"
    assert lp.proc.poll() is None                            # the launcher keeps going: give-up is off
    assert "broken FAILED (required -> failsafe)" in lp.output

    report = json.loads(u2sa(tmp_path, "health", "--vehicle", str(vehicle), "--json").stdout)
    assert report["failsafe"] is True
    assert next(s for s in report["services"] if s["name"] == "broken")["state"] == "failed"

    # Another source raises and clears its own: the HSM reports both, and its own stays up.
    publish_failsafe(bus, source="estop", active=True, reason="pressed")
    wait_until(lambda: (m := watch.latest()) and m.summary.startswith("FAILSAFE held by estop, hsm -- estop: pressed"),
               timeout=10, message="SystemHealth naming both holders")
    wait_until(lambda: watch.details.get("hsm", {}).get("failsafe_sources") == "estop,hsm", timeout=10,
               message="the HSM's health naming both holders")
    assert "estop: pressed" in watch.details["hsm"]["failsafe_reasons"]
    publish_failsafe(bus, source="estop", active=False, reason="released")
    latest = wait_until(lambda: (m := watch.latest()) and m.summary.startswith("FAILSAFE held by hsm --") and m,
                        timeout=10, message="SystemHealth after the e-stop's clear")
    assert latest.failsafe and "hsm: required service broken failed" in latest.summary
    assert not any(not f.active and f.header.source == "hsm" for f in watch.failsafes)
    assert "failsafe clear from estop leaves the HSM's own up" in lp.output

    seen = len(watch.failsafes)
    publish_failsafe(bus, source="operator", active=False, reason="operator", service="hsm")
    wait_until(lambda: "failsafe clear from operator refused" in lp.output
               and any(f.active and f.header.source == "hsm" for f in watch.failsafes[seen + 1:]),
               timeout=10, message="the HSM to refuse the operator's clear and assert the failsafe again")
    assert "refused: broken is still failed" in lp.output


def publish_failsafe(bus: BusClient, *, source: str, active: bool, reason: str, service: str = "") -> None:
    """A Failsafe message as *source* would send it (an e-stop, the operator)."""
    msg = t.Failsafe()
    msg.active, msg.reason, msg.service = active, reason, service
    msg.header.source = source
    bus.publish(ch.FAILSAFE, msg)


def test_hsm_failsafe_is_cleared_only_by_an_operator_and_only_when_all_is_ok(tmp_path: Path, lcm_url: str,
                                                                               bus: BusClient, launch: Any) -> None:
    watch = Watch(bus)
    vehicle = hsm_profile(tmp_path, lcm_url, '[services.est]\nkind = "state_estimator"\n'
                          "settings = { health_interval_s = 0.2 }\n", startup_grace_s=10.0)
    lp = launch(vehicle)
    wait_until(lambda: (s := watch.service_state("est")) and s.state == "ok", timeout=30, message="est ok")
    bus.stop(name="est")                               # a clean stop: the launcher leaves it down
    raised = wait_until(lambda: next((f for f in list(watch.failsafes) if f.active), None), timeout=30,
                        message="the HSM's failsafe for the stopped est")
    assert raised.header.source == "hsm" and raised.reason.startswith("required service est stopped")

    seen = len(watch.failsafes)
    publish_failsafe(bus, source="operator", active=False, reason="try", service="*")
    wait_until(lambda: "refused: est is still stopped" in lp.output
               and any(f.active and f.header.source == "hsm" for f in watch.failsafes[seen + 1:]),
               timeout=10, message="the clear refused while est is stopped, the failsafe asserted again")

    lp.client.request("start", service="est")
    wait_until(lambda: (s := watch.service_state("est")) and s.state == "ok", timeout=30, message="est ok again")
    latest = watch.latest()
    assert latest.failsafe and latest.summary.startswith("FAILSAFE held by hsm"), latest.summary   # latched
    publish_failsafe(bus, source="rc", active=False, reason="not mine to clear")
    publish_failsafe(bus, source="operator", active=False, reason="est is back", service="control")
    wait_until(lambda: lp.output.count("leaves the HSM's own up") >= 2, timeout=10,
               message="the HSM to read both clears that were not aimed at it")
    assert not any(not f.active and f.header.source == "hsm" for f in watch.failsafes)

    done = u2sa(tmp_path, "failsafe", "clear", "--source", "hsm", "--vehicle", str(vehicle))   # the operator
    assert done.returncode == 0, done.stderr
    lowered = wait_until(lambda: next((f for f in list(watch.failsafes) if not f.active and f.header.source == "hsm"),
                                      None), timeout=10, message="the HSM lowering its failsafe")
    assert lowered.reason == "clear from operator accepted: every required service is ok"
    wait_until(lambda: (m := watch.latest()) and not m.failsafe and m.summary.startswith("ok"), timeout=10,
               message="SystemHealth without failsafe")
    assert "failsafe cleared by operator (cleared by the operator); every required service is ok" in lp.output


def test_health_without_an_hsm_names_the_problem(tmp_path: Path, lcm_url: str) -> None:
    done = u2sa(tmp_path, "health", "--timeout", "0.5")
    assert done.returncode == 1
    assert "no HSM answered: nothing on U2SA_SYSTEM_HEALTH within 0.5 s" in done.stderr and 'kind = "hsm"' in done.stderr


def test_alive_but_silent_service_is_restarted(tmp_path: Path, lcm_url: str, bus: BusClient, launch: Any) -> None:
    watch = Watch(bus)
    vehicle = hsm_profile(tmp_path, lcm_url, '[services.est]\nkind = "state_estimator"\n'
                      'settings = { health_interval_s = 0.2, mode = "passthrough" }\n'   # publishes only when fed
                      '[services.est.supervision]\ndata_channel = "STATE_ESTIMATE"\nstale_after_s = 2.0\n',
                      startup_grace_s=10.0)
    lp = launch(vehicle)
    feeding = threading.Event()
    feeding.set()
    stop = threading.Event()

    def feed() -> None:                    # a sensor: while it feeds, est publishes estimates
        while not stop.wait(0.1):
            if feeding.is_set():
                info = t.StateInformation().set(x=1.0)
                info.sensor_name = "test_sensor"
                bus.publish(ch.STATE_INFO, info)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        wait_until(lambda: (s := watch.service_state("est")) and s.state == "ok" and 0 <= s.data_age_s < 1.0,
                   timeout=30, message="est ok with fresh data")
        first_pid = watch.pids["est"][-1]
        feeding.clear()                    # est stays alive and keeps beating, but its data stops
        wait_until(lambda: watch.pids["est"][-1] != first_pid, timeout=30, message="a restarted est")
    finally:
        stop.set()
        feeder.join()
    assert "restarting est (restart 1 of 2): no data on STATE_ESTIMATE for" in lp.output
    assert lp.status()["est"]["run_id"] == 2


def test_hsm_service_in_process_applies_policy_changes_and_drops_garbage(tmp_path: Path, lcm_url: str) -> None:
    from u2sa_hw.services.hsm.service import HealthStatusMonitor
    from u2sa_hw.profile.loader import load_profile

    vehicle = hsm_profile(tmp_path, lcm_url, '[services.gps]\nkind = "gps_nmea"\n'
                      '[services.gps.supervision]\ndata_channel = "STATE_INFO"\nstale_after_s = 2.0\n',
                      startup_grace_s=10.0)
    loaded = load_profile(vehicle)
    hsm = HealthStatusMonitor("hsm", profile=loaded, settings={**loaded.service("hsm").settings, "restarter": "none"})
    try:
        assert [r.name for r in hsm.rules] == ["gps"] and hsm.policy.max_restarts == 2
        ok, _ = hsm.config.try_set("max_restarts", 7)
        assert ok
        hsm.on_config_change("max_restarts", 7)
        assert hsm.monitor.policy.max_restarts == 7
        hsm._on_data("STATE_INFO", b"\x00" * 9)               # garbage: counted, not fatal
        assert hsm.transport.rx["STATE_INFO"].malformed == 1
        beat = t.Health()
        beat.name, beat.pid, beat.status = "gps", 1234, "ok"
        hsm.monitor.on_health(beat, time.monotonic() - 100.0)   # gps started 100 s ago, no data since
        later = time.monotonic() + 5.0
        info = t.StateInformation()
        info.header.source = "someone_else"
        hsm._on_data("STATE_INFO", info.encode())
        assert hsm.monitor.views(later)[0].data_age_s == pytest.approx(105.0, abs=1.0)
        info.header.source = "gps"
        hsm._on_data("STATE_INFO", info.encode())          # only the header is read
        assert hsm.monitor.views(later)[0].data_age_s == pytest.approx(5.0, abs=1.0)
    finally:
        hsm.transport.stop()
