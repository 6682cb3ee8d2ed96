"""Supervision that does no harm, as pure logic with a fake clock (issue 10, point 5).

Heartbeats are judged by when the service sent them (its stamps), a problem is acted on only
once it has lasted ``confirm_s`` with nothing from the service meanwhile, and a stall of the HSM
itself rebases every judgement. The times below are plain seconds on the HSM's clock; the
services' stamps are on a wall clock that is far away from it (and, in one test, jumps).
"""

from __future__ import annotations

from typing import Any

import pytest

from u2sa_hw import lcmtypes as t
from u2sa_hw.services.hsm.monitor import HealthMonitor
from u2sa_hw.services.hsm.rules import MonitorPolicy, WatchRule
from u2sa_hw.services.hsm.stamps import SenderClock
from u2sa_hw.services.hsm.verdicts import Cancelled, Failed, FailsafeChange, Restart, Stalled

WALL = 1_700_000_000.0          # the services' CLOCK_REALTIME at HSM time 0
POLICY = MonitorPolicy(max_restarts=3, restart_backoff_s=1.0, confirm_s=0.5, stall_s=1.0)
NAMES = [f"svc{i:02d}" for i in range(12)]


class Sender:
    """One service process: Health messages stamped with its wall clock and numbered."""

    def __init__(self, name: str, pid: int, *, offset: float = WALL) -> None:
        self.name, self.pid, self.offset, self.sequence = name, pid, offset, 0

    def beat(self, sent: float, status: str = "ok") -> t.Health:
        self.sequence += 1
        msg = t.Health()
        msg.name, msg.pid, msg.status = self.name, self.pid, status
        msg.header.timestamp_us = int(round((sent + self.offset) * 1e6))
        msg.header.sequence = self.sequence
        return msg


def of(kind: type, actions: list[Any]) -> list[Any]:
    return [a for a in actions if isinstance(a, kind)]


def run(mon: HealthMonitor, senders: list[Sender], start: float, end: float, *, beat_s: float = 0.2,
        check_s: float = 0.1) -> list[Any]:
    """Services beat every *beat_s*, each read at once; the HSM judges every *check_s*; all actions."""
    actions: list[Any] = []
    steps = int(round((end - start) / check_s))
    per_beat = int(round(beat_s / check_s))
    for step in range(1, steps + 1):
        now = start + step * check_s
        if step % per_beat == 0:
            for s in senders:
                mon.on_health(s.beat(now), now)
        actions += mon.evaluate(now)
    return actions


def twelve(policy: MonitorPolicy = POLICY) -> tuple[HealthMonitor, list[Sender]]:
    rules = [WatchRule(n, heartbeat_timeout_s=1.0, startup_grace_s=5.0) for n in NAMES]
    return HealthMonitor(rules, policy=policy, now=0.0), [Sender(n, 100 + i) for i, n in enumerate(NAMES)]


def stop_and_wake(mon: HealthMonitor, senders: list[Sender], *, stopped_at: float, woke_at: float,
                  alive_until: dict[str, float] | None = None) -> list[Any]:
    """The HSM is stopped; its socket keeps the beats sent meanwhile; it wakes and judges before reading them."""
    alive_until = alive_until or {}
    backlog = []
    sent = stopped_at
    while sent + 0.2 < woke_at:
        sent += 0.2
        backlog += [s.beat(sent) for s in senders if sent <= alive_until.get(s.name, woke_at)]
    actions = mon.evaluate(woke_at)                  # the loop runs first: nothing read yet
    for msg in backlog:                              # then the handler thread drains the socket
        mon.on_health(msg, woke_at + 0.01)
    return actions


def test_an_hsm_stopped_for_6_s_restarts_nothing_when_it_wakes() -> None:
    mon, senders = twelve()
    assert of(Restart, run(mon, senders, 0.0, 10.0)) == []
    first = stop_and_wake(mon, senders, stopped_at=10.0, woke_at=16.0)
    assert first == [Stalled(6.0)]
    later = run(mon, senders, 16.0, 30.0)
    assert of(Restart, later) == [] and of(Failed, later) == [] and of(FailsafeChange, later) == []
    assert {v.state for v in mon.views(30.0)} == {"ok"} and sum(v.restarts for v in mon.views(30.0)) == 0


def test_without_the_protections_the_same_wake_restarts_every_service() -> None:
    # The scenario above with the stall rule and the confirmation off: the harm issue 10 saw.
    mon, senders = twelve(MonitorPolicy(max_restarts=3, confirm_s=0.0, stall_s=1e9))
    run(mon, senders, 0.0, 10.0)
    assert sorted(r.service for r in of(Restart, stop_and_wake(mon, senders, stopped_at=10.0, woke_at=16.0))) == NAMES


def test_a_service_that_died_during_the_stall_is_restarted_and_only_it() -> None:
    mon, senders = twelve()
    run(mon, senders, 0.0, 10.0)
    actions = stop_and_wake(mon, senders, stopped_at=10.0, woke_at=16.0, alive_until={"svc03": 12.0})
    alive = [s for s in senders if s.name != "svc03"]
    actions += run(mon, alive, 16.0, 20.0)
    restarts = of(Restart, actions)
    assert [(r.service, r.attempt) for r in restarts] == [("svc03", 1)]
    assert "no heartbeat for 4." in restarts[0].reason   # its last beat was sent at 12.0, read at 16.01


def test_a_service_silent_since_before_the_stall_is_judged_one_timeout_after_the_wake() -> None:
    mon, senders = twelve()
    run(mon, senders, 0.0, 10.0)
    alive = [s for s in senders if s.name != "svc07"]
    stop_and_wake(mon, alive, stopped_at=10.0, woke_at=16.0)
    actions = run(mon, alive, 16.0, 16.9)
    assert of(Restart, actions) == [] and next(v.state for v in mon.views(16.9) if v.name == "svc07") == "ok"
    actions = run(mon, alive, 16.9, 19.0)
    assert [r.service for r in of(Restart, actions)] == ["svc07"]


def test_a_heartbeat_read_after_the_decision_cancels_the_restart() -> None:
    mon = HealthMonitor([WatchRule("gps", heartbeat_timeout_s=1.0)], policy=POLICY, now=0.0)
    gps = Sender("gps", 7)
    mon.on_health(gps.beat(0.0), 0.0)
    assert mon.evaluate(0.9) == []
    late = gps.beat(0.8)                             # sent in time, but the HSM's reading lags
    assert of(Restart, mon.evaluate(1.1)) == []      # missing: pending, not acted on
    assert next(v.state for v in mon.views(1.1)) == "missing"
    mon.on_health(late, 1.2)
    actions = mon.evaluate(1.3)
    assert of(Cancelled, actions) == [Cancelled("gps", "no heartbeat for 1.1 s (timeout 1 s)", "heartbeat received")]
    assert of(Restart, actions) == [] and next(v.state for v in mon.views(1.3)) == "ok"
    # and truly silent: acted on once the problem has lasted confirm_s
    assert of(Restart, mon.evaluate(1.9)) == []
    restart = of(Restart, mon.evaluate(2.4))
    assert [r.service for r in restart] == ["gps"]


def test_data_cancels_a_stale_data_restart_but_heartbeats_do_not() -> None:
    rule = WatchRule("est", heartbeat_timeout_s=1.0, data_channel="STATE_ESTIMATE", stale_after_s=1.0)
    mon = HealthMonitor([rule], policy=POLICY, now=0.0)
    est = Sender("est", 9)
    mon.on_health(est.beat(0.0), 0.0)
    mon.on_data("est", "STATE_ESTIMATE", 0.0)
    mon.evaluate(0.1)
    mon.on_health(est.beat(1.0), 1.0)
    assert of(Restart, mon.evaluate(1.1)) == []      # stale data: pending
    mon.on_data("est", "STATE_ESTIMATE", 1.25)       # data after the decision point
    assert of(Cancelled, mon.evaluate(1.25))[0].evidence == "data received"
    now, actions = 1.25, []
    while not of(Restart, actions) and now < 10.0:   # data stops for good; heartbeats go on
        now += 0.25                                  # exact in binary: no rounding at the edges
        mon.on_health(est.beat(now), now)
        actions = mon.evaluate(now)
    # stale from 2.5 (1.25 s without data), acted on confirm_s later
    assert now == 3.0 and "no data on STATE_ESTIMATE" in of(Restart, actions)[0].reason


def test_sender_clock_keeps_the_spacing_of_a_backlog_and_survives_clock_steps() -> None:
    clock = SenderClock()
    us = lambda wall: int(wall * 1e6)  # noqa: E731
    assert clock.sent_at(stamp_us=us(WALL), sequence=1, received=10.0) == 10.0
    # a backlog read at 20.0: each keeps the spacing it was sent with (plus CATCH_UP of the 10 s
    # the HSM did not read: 0.5 s, the side of caution)
    assert [clock.sent_at(stamp_us=us(WALL + k), sequence=1 + k, received=20.0) for k in (1, 2, 3)] \
        == [11.5, 12.5, 13.5]
    assert clock.sent_at(stamp_us=us(WALL + 3), sequence=3, received=20.1) is None    # a duplicate
    # the sender's clock steps forward a day: never younger than its reception
    assert clock.sent_at(stamp_us=us(WALL + 86400), sequence=5, received=20.5) == 20.5
    # ... and back by a year: re-anchored on the reception
    assert clock.sent_at(stamp_us=us(WALL - 3e7), sequence=6, received=21.0) == 21.0
    assert clock.sent_at(stamp_us=us(WALL - 3e7 + 1), sequence=7, received=22.0) == 22.0
    # no stamp at all: the reception time
    assert clock.sent_at(stamp_us=0, sequence=0, received=23.0) == 23.0
    # a small step back (0.5 s) leaves the estimate behind; it catches up with the receptions
    clock = SenderClock()
    clock.sent_at(stamp_us=us(WALL), sequence=1, received=0.0)
    behind = [clock.sent_at(stamp_us=us(WALL + k - 0.5), sequence=1 + k, received=float(k)) for k in range(1, 30)]
    assert behind[0] == 0.55 and behind[-1] == 29.0


def test_the_view_shows_a_late_read_heartbeat_at_its_age_since_sent() -> None:
    mon = HealthMonitor([WatchRule("imu", heartbeat_timeout_s=5.0)], policy=POLICY, now=0.0)
    imu = Sender("imu", 3)
    mon.on_health(imu.beat(0.0), 0.0)
    for sent in (1.0, 2.0, 3.0):
        mon.on_health(imu.beat(sent), 4.5)
    # sent at 3.0 (plus CATCH_UP of the 4.5 s between readings), not 0 s ago as its reading says
    assert next(v.heartbeat_age_s for v in mon.views(4.5)) == pytest.approx(1.5 - 0.05 * 4.5)


def test_a_failed_service_stays_failed_through_a_stall_of_the_hsm() -> None:
    """The stall rebases the judgements so a pause of the HSM harms nothing, but it is no evidence of
    recovery: a required GPS given up on for sending no data (while it heartbeats) stays failed, with
    the failsafe up, when the HSM stalls and wakes; it recovers only when its data comes back."""
    policy = MonitorPolicy(max_restarts=1, restart_backoff_s=1.0, confirm_s=0.5, stall_s=1.0, failsafe_latch=False)
    rule = WatchRule("gps", heartbeat_timeout_s=1.0, startup_grace_s=1.0, data_channel="STATE_INFO",
                     stale_after_s=1.0)
    mon = HealthMonitor([rule], policy=policy, now=0.0)
    gps = Sender("gps", 7)
    actions = run(mon, [gps], 0.0, 8.0)
    assert [f.service for f in of(Failed, actions)] == ["gps"] and mon.failsafe_active
    actions = stop_and_wake(mon, [gps], stopped_at=8.0, woke_at=11.0)
    actions += run(mon, [gps], 11.0, 14.0)
    assert of(FailsafeChange, actions) == [] and mon.failsafe_active
    assert all(a.__class__.__name__ != "Recovered" for a in actions), actions
    assert next(v.state for v in mon.views(14.0)) == "failed"
    mon.on_data("gps", "STATE_INFO", 14.05)            # its data is back: that is recovery
    actions = run(mon, [gps], 14.0, 14.5)
    assert [a.__class__.__name__ for a in actions] == ["Recovered", "FailsafeChange"] and not mon.failsafe_active
