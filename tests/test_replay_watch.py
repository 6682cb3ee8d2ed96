"""The end of a replay (hil/replay_watch.py) on a clock of the test's own: no services, no bus, no sleeping.

A servo driver's only output is its write, tapped as a ``RawPwmWrite`` on ``RAW.<device>``; its health
may count the last recorded command before that write goes out. The replay's end must then wait for the
write: its quiet time starts at the count at the earliest, and a driver's raw output tap restarts it
(tests/test_replay_gpio.py's pwm replay once lost the servo's last write so).
"""

from __future__ import annotations

import threading
from typing import Callable

import pytest

from u2sa_hw import lcmtypes as t
from u2sa_hw.hil.replay_plan import ReplayError
from u2sa_hw.hil.replay_watch import GIVE_UP_S, ReplayWatch


class FakeTime:
    """A clock that moves only when the code under test sleeps, and what happens at which time."""

    def __init__(self) -> None:
        self.now = 0.0
        self.events: list[tuple[float, Callable[[], None]]] = []

    def clock(self) -> float:
        """The time now, s."""
        return self.now

    def at(self, when: float, what: Callable[[], None]) -> None:
        """Run *what* once the clock reaches *when*."""
        self.events.append((when, what))
        self.events.sort(key=lambda e: e[0])

    def sleep(self, dt: float) -> None:
        """Move the clock on by *dt* and run what is due."""
        self.now = round(self.now + dt, 9)
        while self.events and self.events[0][0] <= self.now + 1e-9:
            self.events.pop(0)[1]()


def encoded(msg: object, source: str) -> bytes:
    """*msg* from service *source*, as the replay bus carries it."""
    msg.header.source = source   # type: ignore[attr-defined]
    return msg.encode()   # type: ignore[attr-defined]


def servo_watch(clock: FakeTime) -> ReplayWatch:
    """A watch of one replayed servo service that takes ACTUATOR_CMD from the bus, none counted yet."""
    watch = ReplayWatch({"servos"}, clock=clock.clock)
    watch.listeners = {"ACTUATOR_CMD": {"servos"}}
    watch.heard = {"servos": {"ACTUATOR_CMD": 0}}
    return watch


def test_a_drivers_write_after_the_count_of_its_command_is_waited_for() -> None:
    """The count comes at 0.5 s, the writes the last command makes at 1.3 s and 2.2 s: the replay ends 1 s after
    the last write, not at 1.0 s (1 s after the start, all quiet, the command counted), which lost them."""
    clock = FakeTime()
    watch = servo_watch(clock)
    clock.at(0.5, lambda: watch.heard.update(servos={"ACTUATOR_CMD": 1}))
    clock.at(1.3, lambda: watch.on_message("RAW.rudder", encoded(t.RawPwmWrite(), "servos")))
    clock.at(2.2, lambda: watch.on_message("RAW.throttle", encoded(t.RawPwmWrite(), "servos")))
    watch.settle({"ACTUATOR_CMD": 1}, 1.0, abort=threading.Event(), reason=str, sleep=clock.sleep)
    assert not clock.events, "the replay ended before the driver's writes"
    assert 3.2 <= clock.now < 3.3
    assert watch.received == {}   # raw taps are outputs for the quiet time, not counted against health's


def test_the_quiet_time_starts_at_the_count_at_the_earliest() -> None:
    """Quiet since the start and the command counted at 2.0 s: the end is 1 s after the count."""
    clock = FakeTime()
    watch = servo_watch(clock)
    clock.at(2.0, lambda: watch.heard.update(servos={"ACTUATOR_CMD": 1}))
    watch.settle({"ACTUATOR_CMD": 1}, 1.0, abort=threading.Event(), reason=str, sleep=clock.sleep)
    assert 3.0 <= clock.now < 3.1


@pytest.mark.parametrize("channel, msg, source", [
    ("RAW.gps", t.RawSerial(), "servos"),          # a device's input record, tapped by the driver: not an output
    ("RAW.rudder", t.RawPwmWrite(), "live_servos"),  # a write of a service the replay does not run
    ("U2SA_HEALTH", t.Health(), "servos"),          # contract traffic
])
def test_what_is_not_a_replayed_output_does_not_restart_the_quiet_time(channel: str, msg: object,
                                                                       source: str) -> None:
    clock = FakeTime()
    watch = servo_watch(clock)
    watch.heard = {"servos": {"ACTUATOR_CMD": 1}}
    clock.at(0.5, lambda: watch.on_message(channel, encoded(msg, source)))
    watch.settle({"ACTUATOR_CMD": 1}, 1.0, abort=threading.Event(), reason=str, sleep=clock.sleep)
    assert 1.0 <= clock.now < 1.1


def test_outputs_on_a_services_own_channels_and_its_gpio_writes_restart_it() -> None:
    clock = FakeTime()
    watch = servo_watch(clock)
    watch.heard = {"servos": {"ACTUATOR_CMD": 1}}
    clock.at(0.5, lambda: watch.on_message("ACTUATOR_STATE", encoded(t.ActuatorCommand(), "servos")))
    clock.at(1.2, lambda: watch.on_message("RAW.lamp", encoded(t.RawGpioWrite(), "servos")))
    watch.settle({"ACTUATOR_CMD": 1}, 1.0, abort=threading.Event(), reason=str, sleep=clock.sleep)
    assert 2.2 <= clock.now < 2.3
    assert watch.received == {"servos": 1}


def test_the_wait_gives_up_and_an_abort_stops_it() -> None:
    clock = FakeTime()
    watch = servo_watch(clock)   # never counted
    watch.settle({"ACTUATOR_CMD": 1}, 1.0, abort=threading.Event(), reason=str, sleep=clock.sleep)
    assert GIVE_UP_S <= clock.now < GIVE_UP_S + 0.1
    abort = threading.Event()
    clock.at(clock.now + 0.5, abort.set)
    with pytest.raises(ReplayError, match="servos died"):
        watch.settle({"ACTUATOR_CMD": 1}, 1.0, abort=abort, reason=lambda: "servos died", sleep=clock.sleep)
