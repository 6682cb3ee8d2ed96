"""Messages an actuator took late (u2sa_hw/safety/late_take.py): the pure rule with a clock of the test's,
then an actuator over a real LCM transport taking a backlog of commands sent 0.3 s earlier."""

from __future__ import annotations

import time
from pathlib import Path

from conftest import wait_until
from test_abstract import RecordingActuator, _command, _run

from u2sa_hw import channels as ch
from u2sa_hw.bus.client import BusClient
from u2sa_hw.safety.late_take import LateTakeWatch

MS = 1000   # us


class Wall:
    """A wall clock the test moves (us)."""

    def __init__(self, us: int) -> None:
        self.us = us

    def __call__(self) -> int:
        return self.us


def test_a_message_taken_over_the_limit_after_the_quickest_is_late_whatever_the_clocks_offset() -> None:
    offset = 3_600_000_000   # the sender's clock an hour behind (a replay's stamps, another machine)
    wall = Wall(1_000_000_000 + offset)
    watch = LateTakeWatch(wall_us=wall)
    for k in range(10):   # taken 2-4 ms after they were sent
        wall.us += 20 * MS
        assert not watch.took(wall.us - offset - (2 + k % 3) * MS)
    wall.us += 20 * MS
    assert not watch.took(wall.us - offset - 90 * MS), "88 ms over the quickest: within the limit"
    wall.us += 20 * MS
    assert watch.took(wall.us - offset - 150 * MS), "148 ms over the quickest: held up"
    assert watch.details() == {"taken_late": 1, "taken_late_max_s": "0.15"}
    assert not watch.took(0), "an unstamped message says nothing"


def test_the_first_message_and_a_stepped_clock_set_the_quickest_anew() -> None:
    wall = Wall(5_000_000_000)
    watch = LateTakeWatch(wall_us=wall, baseline_s=10.0)
    assert not watch.took(wall.us - 500 * MS), "the first message: nothing to compare it with"
    wall.us += 10 * MS
    assert watch.took(wall.us - 700 * MS)
    # the wall clock steps back 30 s (NTP): every delay now looks 30 s short; two spans later it is the baseline
    wall.us -= 30_000_000
    for _ in range(3):
        wall.us += 11_000_000
        watch.took(wall.us - 30_000_000 - 2 * MS)   # sent before the step, taken after: one odd delay
        assert not watch.took(wall.us - 2 * MS)
    late = watch.late
    wall.us += 20 * MS
    assert not watch.took(wall.us - 3 * MS) and watch.late == late, "settled: a timely message is not late"
    assert watch.took(wall.us - 200 * MS)


def test_an_actuator_counts_the_commands_it_took_late_and_applies_them(tmp_path: Path, lcm_url: str,
                                                                      bus: BusClient) -> None:
    """Commands that waited 0.3 s before this actuator took them (their header stamps 0.3 s old, as a backlog
    held in its socket has) are counted over real LCM, and still applied in order: it only observes."""
    act = RecordingActuator("left", config_path=tmp_path / "left.toml",
                            settings={"command_timeout_s": 0.5, "rc_gating": False})
    thread = _run(act)
    try:
        for k in range(5):   # on time: the quickest delay
            bus.publish(ch.ACTUATOR_CMD, _command("left", k))
        wait_until(lambda: ("left", 4.0) in act.outputs, message="the timely commands")
        before = act.health_details()["taken_late"]
        for k in range(10, 14):   # the backlog: sent 0.3 s before now (the client would stamp them now)
            cmd = _command("left", k)
            cmd.base.header.timestamp_us = time.time_ns() // 1000 - 300_000
            cmd.base.header.source = "control"
            bus.transport.publish(ch.ACTUATOR_CMD, cmd)
        wait_until(lambda: ("left", 13.0) in act.outputs, message="the backlog taken")
        details = act.health_details()
        assert details["taken_late"] - before >= 4 and float(details["taken_late_max_s"]) >= 0.29, details
        assert [p for _, p in act.outputs if p >= 10] == [10.0, 11.0, 12.0, 13.0], "observed only: all applied"
    finally:
        act.stop()
        thread.join(5)
        act.kill()
        act.transport.stop()
