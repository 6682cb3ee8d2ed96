"""The launcher's watchdog, as systemd's: real children, real signals, the period from the unit files."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO, wait_until
from supervision_helpers import launch, write_profile  # noqa: F401 - launch is a fixture

from u2sa_hw.launcher import Launcher, RestartPolicy, SupervisedProcess
from u2sa_hw.launcher.policy import BACKOFF
from u2sa_hw.launcher.watchdog import (STALL_STEP_S, WatchdogSetting, WatchedClock, parse_timespan, unit_watchdog,
                                       watchdog_for)
from u2sa_hw.profile.loader import load_profile

SLEEPER = [sys.executable, "-c", "import time; time.sleep(120)"]


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_period_comes_from_the_units_watchdogsec(tmp_path: Path) -> None:
    for kind in ("hsm", "gps_nmea"):
        setting = watchdog_for(kind, unit_dir=REPO / "systemd")
        assert (setting.timeout_s, setting.abort_s, setting.usec) == (2.0, 1.0, 2_000_000)
    assert watchdog_for("hsm", unit_dir=REPO / "systemd").source.endswith("u2sa-hsm.service")
    assert watchdog_for("gps_nmea", unit_dir=tmp_path) == WatchdogSetting()       # no units here: the defaults
    unit = tmp_path / "u2sa@.service"
    unit.write_text("[Unit]\nWatchdogSec=9s\n[Service]\nWatchdogSec=1min 30s\nTimeoutAbortSec=250ms\n")
    assert (watchdog_for("imu", unit_dir=tmp_path).timeout_s, unit_watchdog(unit).abort_s) == (90.0, 0.25)
    assert parse_timespan("infinity") == 0.0 and parse_timespan("3") == 3.0
    unit.write_text("[Service]\nWatchdogSec=2 fortnights\n")
    with pytest.raises(ValueError, match=r"u2sa@.service:2: WatchdogSec: '2 fortnights' is not a systemd time span"):
        unit_watchdog(unit)


def test_a_child_that_stops_pinging_is_aborted_and_restarted_as_a_failure() -> None:
    clock = FakeClock()
    p = SupervisedProcess("svc", SLEEPER, policy=RestartPolicy(), clock=clock,
                          watchdog=WatchdogSetting(timeout_s=2.0, abort_s=1.0))
    child = p.spawn()
    try:
        clock.now += 30.0
        assert p.check_watchdog() is None            # silent since the start, but never armed: not judged
        p.on_notify({"READY": "1"})                  # armed
        clock.now += 1.9
        assert p.check_watchdog() is None
        p.on_notify({"WATCHDOG": "1"})
        clock.now += 2.0
        assert p.check_watchdog() is None            # exactly the timeout: not yet
        clock.now += 0.1
        fired = p.check_watchdog()
        assert fired == "watchdog timeout (no WATCHDOG=1 for 2.1 s, limit 2 s): SIGABRT, SIGKILL in 1 s"
        assert p.check_watchdog() is None            # once per run
        assert child.wait(timeout=30) == -signal.SIGABRT
        account = p.poll()
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert account is not None and account.startswith("watchdog timeout, killed by SIGABRT after 34.0 s; restarting")
    status = p.status()
    assert (status.state, status.result, status.watchdog_kills, status.watchdog_s) == (BACKOFF, "watchdog", 1, 2.0)
    assert p.failures_in_window() == 1               # counted as a failed exit, like any crash


def test_watchdog_trigger_fires_at_once_and_a_fresh_run_is_disarmed() -> None:
    clock = FakeClock()
    p = SupervisedProcess("svc", SLEEPER, policy=RestartPolicy(initial_backoff_s=0.0), clock=clock,
                          watchdog=WatchdogSetting(timeout_s=5.0, abort_s=0.0))
    first = p.spawn()
    try:
        p.on_notify({"WATCHDOG": "trigger"})
        assert p.check_watchdog() is None            # not armed yet (no READY=1 or WATCHDOG=1)
        p.on_notify({"WATCHDOG": "1", "STATUS": "busy"})
        assert "WATCHDOG=trigger" in (p.check_watchdog() or "") and p.status_text == "busy"
        first.wait(timeout=30)
        assert p.poll() is not None and p.result == "watchdog"
        second = p.spawn()
        try:
            clock.now += 60.0
            assert p.check_watchdog() is None and p.status().run_id == 2
        finally:
            second.kill()
            second.wait()
        assert p.poll() is not None and p.result == "signal" and p.watchdog_kills == 1
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    leaving = SupervisedProcess("leaving", SLEEPER, policy=RestartPolicy(), clock=clock,
                                watchdog=WatchdogSetting(timeout_s=1.0))
    third = leaving.spawn()
    try:
        leaving.on_notify({"READY": "1"})
        leaving.on_notify({"STOPPING": "1"})        # on its way out: no more pings, and no watchdog
        clock.now += 60.0
        assert leaving.check_watchdog() is None
    finally:
        third.kill()
        third.wait()
    off = SupervisedProcess("off", SLEEPER, policy=RestartPolicy(), clock=clock)
    assert off.status().watchdog_s == 0.0


def test_a_stopped_child_is_restarted_by_the_watchdog_and_a_healthy_one_is_not(tmp_path: Path, lcm_url: str) -> None:
    profile = load_profile(write_profile(tmp_path, lcm_url, {"hung": "state_estimator", "fine": "state_estimator"}))
    lines: list[tuple[str, str]] = []
    launcher = Launcher(profile, control=False, output=lambda n, line: lines.append((n, line)))  # units' 2 s
    launcher.start()
    try:
        before = wait_until(lambda: (s := {x.name: x for x in launcher.status()}) and all(x.ready for x in s.values())
                            and s, timeout=30, message="both services ready")
        assert before["hung"].watchdog_s == before["fine"].watchdog_s == 2.0
        os.kill(before["hung"].pid, signal.SIGSTOP)
        after = wait_until(lambda: (s := {x.name: x for x in launcher.status()}) and s["hung"].run_id == 2
                           and s["hung"].ready and s, timeout=60, message="the stopped service restarted and ready")
    finally:
        launcher.stop(timeout=20)
    hung, fine = after["hung"], after["fine"]
    assert (hung.result, hung.watchdog_kills, hung.restarts) == ("watchdog", 1, 1)
    # found stopped: SIGKILL without resuming it (resumed, a command source would publish again)
    assert hung.last_exit == "watchdog timeout, killed by SIGKILL" and hung.pid != before["hung"].pid
    assert (fine.run_id, fine.restarts, fine.watchdog_kills, fine.pid) == (1, 0, 0, before["fine"].pid)
    said = [line for name, line in lines if name == "launcher"]
    assert any(line.startswith("hung watchdog timeout (no WATCHDOG=1 for") for line in said), said
    assert any(line.startswith("hung watchdog timeout") and "it was stopped, so SIGKILL without resuming it"
               in line for line in said), said
    assert any(line.startswith("hung watchdog timeout, killed by SIGKILL after") and "restarting in" in line
               for line in said), said
    assert not any(line.startswith("fine watchdog") for line in said)
    assert not any(name == "hung" and "Fatal Python error" in line for name, line in lines)  # never resumed


def test_u2sa_run_restarts_a_hung_hsm(tmp_path: Path, lcm_url: str, launch: Any) -> None:
    vehicle = write_profile(tmp_path, lcm_url, {"est": "state_estimator", "hsm": "hsm"})
    lp = launch(vehicle)
    first = wait_until(lambda: (s := lp.status()) and all(x["ready"] for x in s.values()) and s, timeout=30,
                       message="est and the HSM ready")
    assert first["hsm"]["watchdog_s"] == 2.0
    os.kill(first["hsm"]["pid"], signal.SIGSTOP)
    after = wait_until(lambda: (s := lp.status()) and s["hsm"]["run_id"] == 2 and s["hsm"]["ready"] and s,
                       timeout=60, message="the stopped HSM restarted by the launcher's watchdog")
    assert (after["hsm"]["result"], after["hsm"]["watchdog_kills"]) == ("watchdog", 1)
    assert (after["est"]["run_id"], after["est"]["watchdog_kills"]) == (1, 0)
    assert "hsm watchdog timeout (no WATCHDOG=1 for" in lp.output


def test_run_help_documents_the_watchdog_and_refuses_a_negative_one(tmp_path: Path, lcm_url: str) -> None:
    import subprocess

    from u2sa_hw.launcher.children import u2sa_command

    shown = subprocess.run([*u2sa_command(), "run", "--help"], capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0 and "--watchdog S" in shown.stdout and "WatchdogSec" in shown.stdout
    vehicle = write_profile(tmp_path, lcm_url, {"est": "state_estimator"})
    bad = subprocess.run([*u2sa_command(), "run", "--vehicle", str(vehicle), "--watchdog", "-1"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--watchdog must be >= 0 (0 turns the watchdog off)" in bad.stderr


def test_services_named_unwatched_run_without_a_watchdog_and_the_others_keep_theirs(tmp_path: Path) -> None:
    """A replay's I2C drivers wait in reads held for the player and cannot ping (hil/replay_i2c.py)."""
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text('[vehicle]\nname = "w"\n[services.imu]\nkind = "imu_mpu9250"\n'
                       '[services.gps]\nkind = "gps_nmea"\n')
    launcher = Launcher(load_profile(vehicle), control=False, unwatched={"imu"})
    assert {n: p.status().watchdog_s for n, p in launcher.processes.items()} == {"imu": 0.0, "gps": 2.0}
    # every child's silence is judged on the launcher's one watched clock (its own stalls not counted)
    assert all(p.watch_clock is launcher.watch_clock for p in launcher.processes.values())


def test_the_launchers_own_stall_is_not_counted_against_a_child_but_a_hung_child_is_still_killed() -> None:
    """CI: ``u2sa sim`` restarted a healthy imu under load. The sim process both serves the mock devices
    and runs the launcher: while it stalls, a child waiting on a mock (the imu's I2C read, the rc mux's
    GPIO write) cannot ping, and the launcher's next turn counted the whole pause as the child's silence.
    SIGSTOPping the sim process for 2.2-2.5 s reproduced it: the rc service was killed so."""
    real = FakeClock()
    watched = WatchedClock(real)
    p = SupervisedProcess("imu", SLEEPER, policy=RestartPolicy(), clock=real, watch_clock=watched,
                          watchdog=WatchdogSetting(timeout_s=2.0, abort_s=1.0))
    child = p.spawn()
    try:
        p.on_notify({"READY": "1"})
        for _ in range(9):                           # the launcher's turns, 0.1 s apart: 0.9 s of silence
            real.now += 0.1
            assert p.check_watchdog() is None
        real.now += 3.0                              # the launcher's process stalled 3 s (the child waited on it)
        assert p.check_watchdog() is None            # 0.9 s + at most one step: not the child's silence
        assert watched.unwatched_s == pytest.approx(3.0 - STALL_STEP_S)
        p.on_notify({"WATCHDOG": "1"})               # the child answers once the launcher's process runs again
        fired, turns = None, 0
        while fired is None and turns < 100:        # now it hangs, while the launcher runs normally
            real.now += 0.1
            turns += 1
            fired = p.check_watchdog()
        assert turns == 21 and fired == "watchdog timeout (no WATCHDOG=1 for 2.1 s, limit 2 s): SIGABRT, SIGKILL in 1 s"
        assert child.wait(timeout=30) == -signal.SIGABRT
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    # a launcher starved to one turn a second still kills a hung child: after 2 s / STALL_STEP_S turns
    starved = SupervisedProcess("hung", SLEEPER, policy=RestartPolicy(), clock=real, watch_clock=watched,
                                watchdog=WatchdogSetting(timeout_s=2.0, abort_s=1.0))
    second = starved.spawn()
    try:
        starved.on_notify({"READY": "1"})
        fired, turns = None, 0
        while fired is None and turns < 100:
            real.now += 1.0
            turns += 1
            fired = starved.check_watchdog()
        assert turns == 9 and fired is not None and "no WATCHDOG=1 for 2.2 s" in fired   # 9 x 0.25 s > 2 s
    finally:
        second.kill()
        second.wait()


def test_the_watched_clock_is_real_time_while_the_launcher_runs_and_never_goes_back() -> None:
    real = FakeClock()
    watched = WatchedClock(real, max_step_s=0.5)
    start = watched()
    real.now += 0.4
    assert watched() == pytest.approx(start + 0.4)
    real.now += 10.0
    assert watched() == pytest.approx(start + 0.9) and watched.unwatched_s == pytest.approx(9.5)
    real.now -= 5.0                                  # a clock that went back counts nothing
    assert watched() == pytest.approx(start + 0.9)
    with pytest.raises(ValueError):
        WatchedClock(real, max_step_s=0.0)
