"""u2sa_hw.hil.player.Player: a republished message waits until the replayed state on ORDERED_CHANNELS (RC_MODE's
mode and autonomy_enabled) is the recorded one as of it, so a --fast replay cannot hand an actuator the
first command of an autonomy stint before the replayed RC mux has granted autonomy (the Ackermann corpus
log lost its first throttle and steering writes so). A state, not a count: a replay whose mux flapped more
often where the recording machine held it up still waits for the right state. A state the replay never
reaches is given up after ORDER_WAIT_S, counted, and not waited for again."""

from __future__ import annotations

import threading
from typing import Any

import pytest

import u2sa_hw.hil.player as player_module
from u2sa_hw.hil.player import Player

MANUAL, AUTONOMOUS = (0, False), (1, True)


class RecordingBus:
    """A transport stand-in: what was published, with the replayed state at that moment."""

    def __init__(self, state: dict[str, tuple]) -> None:
        self.state = state
        self.sent: list[tuple[str, Any]] = []

    def publish_bytes(self, channel: str, _data: bytes) -> None:
        self.sent.append((channel, self.state.get("RC_MODE")))


def play(events: list[tuple[int, str, Any]], state: dict[str, tuple], *,
         watched: bool = True) -> tuple[Player, RecordingBus]:
    bus = RecordingBus(state)
    p = Player("unused.mcap", devices={}, transport=bus, republish={"ACTUATOR_CMD"}, replayed_services={"rc"},
               start_ns=0, end_ns=10**18, rate=None, abort=threading.Event(), abort_reason=lambda: "",
               replayed_state=state.get if watched else None)
    p.events = lambda: iter(events)   # type: ignore[method-assign]
    return p, bus


EVENTS = [(0, "order:RC_MODE", MANUAL), (10, "order:RC_MODE", AUTONOMOUS), (20, "bus:ACTUATOR_CMD", b"a"),
          (30, "bus:ACTUATOR_CMD", b"b")]


def test_a_command_waits_for_the_replayed_rc_mode_state_recorded_before_it() -> None:
    state: dict[str, tuple] = {"RC_MODE": MANUAL}
    p, bus = play(EVENTS, state)

    def mux_grants_later() -> None:
        # the replayed mux flaps once more, then grants autonomy, only once the player waits
        while p.stats.order_waits == 0:
            threading.Event().wait(0.001)
        state["RC_MODE"] = (2, False)
        state["RC_MODE"] = AUTONOMOUS

    helper = threading.Thread(target=mux_grants_later)
    helper.start()
    stats = p.run()
    helper.join(timeout=10)
    assert bus.sent == [("ACTUATOR_CMD", AUTONOMOUS), ("ACTUATOR_CMD", AUTONOMOUS)]
    assert (stats.order_waits, stats.order_timeouts) == (1, 0)
    assert stats.republished_on == {"ACTUATOR_CMD": 2}


def test_a_state_the_replay_never_reaches_is_waited_for_once(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(player_module, "ORDER_WAIT_S", 0.05)
    p, bus = play(EVENTS, {"RC_MODE": MANUAL})
    stats = p.run()
    assert [c for c, _s in bus.sent] == ["ACTUATOR_CMD", "ACTUATOR_CMD"]
    assert (stats.order_waits, stats.order_timeouts) == (1, 1)   # the second command does not wait again


def test_without_a_watch_nothing_waits() -> None:
    p, bus = play(EVENTS, {}, watched=False)
    stats = p.run()
    assert len(bus.sent) == 2 and stats.order_waits == 0
