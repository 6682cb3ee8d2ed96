"""The HSM's judgement with a fake clock: every time below is a plain number of seconds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from u2sa_hw import lcmtypes as t
from u2sa_hw.service.health import set_details
from u2sa_hw.service.health import truthy
from u2sa_hw.services.hsm.monitor import HealthMonitor
from u2sa_hw.services.hsm.rules import MonitorPolicy, WatchRule, rules_from_profile
from u2sa_hw.services.hsm.verdicts import Failed, FailsafeChange, Recovered, Restart
from u2sa_hw.profile.vehicle import ProfileError
from u2sa_hw.profile.loader import load_profile


def health(name: str, pid: int, status: str = "ok", **details: str) -> t.Health:
    msg = t.Health()
    msg.name, msg.pid, msg.status = name, pid, status
    set_details(msg, details)
    return msg


def of(kind: type, actions: list[Any]) -> list[Any]:
    return [a for a in actions if isinstance(a, kind)]


def state(mon: HealthMonitor, name: str, now: float) -> str:
    return next(v.state for v in mon.views(now) if v.name == name)


# These tests are about the rules and judge at sparse times: no confirmation wait, no stall
# detection (both have their own tests below).
POLICY = MonitorPolicy(max_restarts=2, restart_backoff_s=1.0, max_backoff_s=8.0, recovery_s=10.0, confirm_s=0.0,
                       stall_s=1e9)


def test_missed_heartbeat_requests_a_restart_after_the_timeout_only() -> None:
    mon = HealthMonitor([WatchRule("gps", heartbeat_timeout_s=3.0, startup_grace_s=5.0)], policy=POLICY, now=0.0)
    assert of(Restart, mon.evaluate(4.9)) == [] and state(mon, "gps", 4.9) == "starting"
    mon.on_health(health("gps", 100), 0.5)
    assert mon.evaluate(1.0) == []                          # nothing to do, no failsafe to lower
    assert of(Restart, mon.evaluate(3.4)) == [] and state(mon, "gps", 3.4) == "ok"
    restarts = of(Restart, mon.evaluate(3.6))
    assert len(restarts) == 1 and restarts[0].service == "gps" and restarts[0].attempt == 1
    assert "no heartbeat for 3.1 s (timeout 3 s)" in restarts[0].reason
    assert mon.evaluate(4.0) == [] and state(mon, "gps", 4.0) == "restarting"
    mon.on_health(health("gps", 200), 5.0)                 # the new process
    assert of(Recovered, mon.evaluate(5.1)) == [Recovered("gps")]
    row = next(v for v in mon.views(5.1) if v.name == "gps")
    assert row.state == "ok" and row.restarts == 1 and row.heartbeat_age_s == pytest.approx(0.1)


def test_repeated_failures_mark_failed_and_raise_the_failsafe_once() -> None:
    rules = [WatchRule("gps", startup_grace_s=2.0), WatchRule("camera", required=False, startup_grace_s=2.0)]
    mon = HealthMonitor(rules, policy=POLICY, now=0.0)
    a1 = mon.evaluate(2.1)
    assert [(r.service, r.attempt) for r in of(Restart, a1)] == [("gps", 1), ("camera", 1)]
    assert "no heartbeat in 2.1 s" in of(Restart, a1)[0].reason
    assert of(Restart, mon.evaluate(4.0)) == []             # within the grace after the restart
    assert [r.attempt for r in of(Restart, mon.evaluate(4.2))] == [2, 2]
    assert of(Restart, mon.evaluate(6.1)) == []
    final = mon.evaluate(6.3)
    failed = {f.service: f for f in of(Failed, final)}
    assert failed["gps"].required and not failed["camera"].required
    assert "after 2 restarts" in failed["gps"].reason
    changes = of(FailsafeChange, final)
    assert len(changes) == 1 and changes[0].active and changes[0].service == "gps"
    assert "required service gps failed: no heartbeat" in changes[0].reason
    assert mon.failsafe_active and mon.summary(6.3).startswith("FAILSAFE: required service gps failed")
    assert state(mon, "gps", 6.3) == "failed" and state(mon, "camera", 6.3) == "failed"
    assert mon.evaluate(60.0) == []                         # failed is final: no more restarts, no repeats
    assert mon.operator_clear() == "gps is still failed" and mon.failsafe_active


def test_restart_backoff_doubles() -> None:
    policy = MonitorPolicy(max_restarts=5, restart_backoff_s=4.0, max_backoff_s=100.0, confirm_s=0.0, stall_s=1e9)
    mon = HealthMonitor([WatchRule("imu", startup_grace_s=1.0)], policy=policy, now=0.0)
    times = []
    now = 0.0
    while len(times) < 4:
        now += 0.25                                   # exact in binary: no rounding at the edges
        if of(Restart, mon.evaluate(now)):
            times.append(now)
    assert [b - a for a, b in zip(times, times[1:])] == [4.0, 8.0, 16.0]


def test_stale_data_and_required_detail_are_restarted() -> None:
    rules = [WatchRule("gps", data_channel="STATE_INFO", stale_after_s=2.0, require_details=("fix",),
                       require_grace_s=5.0, heartbeat_timeout_s=3.0)]
    mon = HealthMonitor(rules, policy=POLICY, now=0.0)
    assert mon.data_channels() == {"STATE_INFO": {"gps"}}
    for i in range(4):
        mon.on_health(health("gps", 1, fix="1"), float(i))
        mon.on_data("gps", "STATE_INFO", float(i))
        mon.on_data("gps", "OBJECTS", float(i))             # another channel proves nothing
        assert of(Restart, mon.evaluate(float(i) + 0.5)) == []
    mon.on_health(health("gps", 1, fix="1"), 4.0)
    mon.on_health(health("gps", 1, fix="1"), 5.0)
    restart = of(Restart, mon.evaluate(5.1))
    assert len(restart) == 1 and "no data on STATE_INFO for 2.1 s (limit 2 s)" in restart[0].reason
    assert next(v.data_age_s for v in mon.views(5.1)) == pytest.approx(2.1)

    mon2 = HealthMonitor(rules, policy=POLICY, now=0.0)
    for i in range(8):
        mon2.on_health(health("gps", 1, fix="false"), float(i))
        mon2.on_data("gps", "STATE_INFO", float(i))
        found = of(Restart, mon2.evaluate(float(i) + 0.1))
        if found:
            break
    assert i == 5 and "fix=false" in found[0].reason and "required: fix" in found[0].reason


def test_recovery_forgives_restarts_and_degraded_only_restarts_when_configured() -> None:
    rules = [WatchRule("est", heartbeat_timeout_s=1.0, startup_grace_s=1.0, degraded_restart_s=4.0)]
    mon = HealthMonitor(rules, policy=POLICY, now=0.0)
    mon.on_health(health("est", 1), 0.0)
    assert of(Restart, mon.evaluate(1.5))[0].attempt == 1
    for i in range(2, 14):                                   # healthy for longer than recovery_s
        mon.on_health(health("est", 2), float(i))
        mon.evaluate(float(i))
    assert of(Restart, mon.evaluate(15.1))[0].attempt == 1   # the count started over
    mon.on_health(health("est", 3, status="degraded"), 16.0)
    for i in range(17, 21):
        mon.on_health(health("est", 3, status="degraded"), float(i))
        assert of(Restart, mon.evaluate(float(i))) == [] and state(mon, "est", float(i)) == "degraded"
    mon.on_health(health("est", 3, status="degraded"), 20.5)
    assert "degraded for 4.5 s" in of(Restart, mon.evaluate(20.5))[0].reason


def test_clean_stop_is_not_restarted_but_a_required_one_raises_the_failsafe() -> None:
    latched = HealthMonitor([WatchRule("ctl", heartbeat_timeout_s=1.0)], policy=POLICY, now=0.0)
    loose = HealthMonitor([WatchRule("ctl", heartbeat_timeout_s=1.0)],
                          policy=MonitorPolicy(failsafe_latch=False, confirm_s=0.0, stall_s=1e9), now=0.0)
    for mon in (latched, loose):
        mon.on_health(health("ctl", 1), 0.0)
        mon.evaluate(0.1)
        mon.on_health(health("ctl", 1, status="stopping"), 0.5)
        actions = mon.evaluate(2.0)
        assert of(Restart, actions) == [] and state(mon, "ctl", 2.0) == "stopped"
        assert of(FailsafeChange, actions)[0].active
        mon.on_health(health("ctl", 2), 3.0)                 # started again by someone
    assert loose.evaluate(3.1) == [Recovered("ctl"), FailsafeChange(False, "every required service is ok again", "")]
    assert latched.evaluate(3.1) == [Recovered("ctl")] and latched.failsafe_active
    assert latched.operator_clear() == "" and not latched.failsafe_active   # an operator's clear, all ok
    assert latched.evaluate(3.2) == []                       # it stays down


def test_unexpected_services_are_shown_never_restarted() -> None:
    mon = HealthMonitor([], policy=POLICY, now=0.0, default_timeout_s=3.0)
    mon.on_health(health("visitor", 9), 1.0)
    assert mon.evaluate(2.0) == []
    assert mon.evaluate(10.0) == [] and state(mon, "visitor", 10.0) == "missing"
    assert [v.watched for v in mon.views(10.0)] == [False]
    mon.evaluate(70.0)
    assert mon.views(70.0) == []


def test_truthy_details() -> None:
    assert all(truthy(v) for v in ("1", "true", "3D", "yes", " 2 "))
    assert not any(truthy(v) for v in (None, "", "0", "false", "No", "none", "off"))


def test_rules_from_profile(tmp_path: Path) -> None:
    (tmp_path / "vehicle.toml").write_text(
        '[services.gps]\nkind = "gps_nmea"\nsettings = { health_interval_s = 0.5 }\n'
        '[services.gps.supervision]\ndata_channel = "STATE_INFO"\nstale_after_s = 2\nrequire_details = ["fix"]\n'
        '[services.cam]\nkind = "world_modeler"\nrequired = false\n'
        '[services.old]\nkind = "camera"\nenabled = false\n'
        '[services.hsm]\nkind = "hsm"\n')
    rules = {r.name: r for r in rules_from_profile(load_profile(tmp_path / "vehicle.toml"), own_name="hsm")}
    assert set(rules) == {"gps", "cam"}
    assert rules["gps"].heartbeat_timeout_s == 1.5 and rules["gps"].stale_after_s == 2.0
    assert rules["gps"].require_details == ("fix",) and rules["gps"].required
    assert rules["cam"].heartbeat_timeout_s == 3.0 and not rules["cam"].required
    for body, message in (('stale_after_s = 2.0', "stale_after_s needs data_channel"),
                          ('stale_afer_s = 2.0', "unknown key 'stale_afer_s'"),
                          ('restart = "yes"', "'restart' must be bool, got str"),
                          ('require_details = "fix"', "must be a list of strings")):
        (tmp_path / "vehicle.toml").write_text(f'[services.gps]\nkind = "gps_nmea"\n[services.gps.supervision]\n{body}\n')
        with pytest.raises(ProfileError, match=message):
            rules_from_profile(load_profile(tmp_path / "vehicle.toml"), own_name="hsm")
