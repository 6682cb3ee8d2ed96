"""hil.player.Player: a republished message waits for the replayed services' messages on ORDERED_CHANNELS
(RC_MODE) that the recording had before it, so a --fast replay cannot hand an actuator the first command
of an autonomy stint before the replayed RC mux has granted autonomy (the Ackermann corpus log lost its
first two throttle writes so); a replay that publishes fewer goes on after ORDER_WAIT_S, counted."""

from __future__ import annotations

import threading
from typing import Any

import pytest

import hil.player as player_module
from hil.player import Player


class RecordingBus:
    """A transport stand-in: what was published, with the replayed RC_MODE count at that moment."""

    def __init__(self, seen: dict[str, int]) -> None:
        self.seen = seen
        self.sent: list[tuple[str, int]] = []

    def publish_bytes(self, channel: str, _data: bytes) -> None:
        self.sent.append((channel, self.seen.get("RC_MODE", 0)))


def play(events: list[tuple[int, str, Any]], seen: dict[str, int], *, watched: bool = True) -> tuple[Player, RecordingBus]:
    bus = RecordingBus(seen)
    p = Player("unused.mcap", devices={}, transport=bus, republish={"ACTUATOR_CMD"}, replayed_services={"rc"},
               start_ns=0, end_ns=10**18, rate=None, abort=threading.Event(), abort_reason=lambda: "",
               replayed_seen=(lambda c: seen.get(c, 0)) if watched else None)
    p.events = lambda: iter(events)   # type: ignore[method-assign]
    return p, bus


EVENTS = [(0, "order:RC_MODE", None), (10, "order:RC_MODE", None), (20, "bus:ACTUATOR_CMD", b"a"),
          (30, "bus:ACTUATOR_CMD", b"b")]


def test_a_command_waits_for_the_replayed_rc_mode_recorded_before_it() -> None:
    seen: dict[str, int] = {"RC_MODE": 1}
    p, bus = play(EVENTS, seen)

    def mux_publishes_later() -> None:
        # the replayed mux's second RC_MODE reaches the bus only once the player is waiting for it
        while p.stats.order_waits == 0:
            threading.Event().wait(0.001)
        seen["RC_MODE"] = 2

    helper = threading.Thread(target=mux_publishes_later)
    helper.start()
    stats = p.run()
    helper.join(timeout=10)
    assert bus.sent == [("ACTUATOR_CMD", 2), ("ACTUATOR_CMD", 2)]
    assert (stats.order_waits, stats.order_timeouts) == (1, 0)
    assert stats.republished_on == {"ACTUATOR_CMD": 2}


def test_a_replay_that_publishes_fewer_goes_on_after_the_wait_once(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(player_module, "ORDER_WAIT_S", 0.05)
    p, bus = play(EVENTS, {"RC_MODE": 1})
    stats = p.run()
    assert [c for c, _n in bus.sent] == ["ACTUATOR_CMD", "ACTUATOR_CMD"]
    assert (stats.order_waits, stats.order_timeouts) == (1, 1)   # the second command does not wait again


def test_without_a_watch_nothing_waits() -> None:
    p, bus = play(EVENTS, {}, watched=False)
    stats = p.run()
    assert len(bus.sent) == 2 and stats.order_waits == 0
