"""u2sa_hw.hil.player.Player._bursts (--fast): each serial burst leaves whole, in the order of first records,
nothing lost, and no other device's record recorded inside a burst goes out in the middle of it."""

from __future__ import annotations

import random
import threading
from typing import Any

from u2sa_hw.hil.player import Player


class Merging:
    """A serial-like device: records closer than its gap join (payload tuples concatenate, up to 6)."""

    def __init__(self, gap_s: float) -> None:
        self.burst_gap_s = gap_s

    @staticmethod
    def merge(first: tuple, second: tuple) -> tuple | None:
        return first + second if len(first) + len(second) <= 6 else None


class Plain:
    burst_gap_s = 0.0


def bursts(events: list[tuple[int, str, Any]], devices: dict[str, Any]) -> list[tuple[int, str, Any]]:
    player = Player("unused.mcap", devices=devices, transport=None, republish=set(), replayed_services=set(),
                    start_ns=0, end_ns=10**18, rate=None, abort=threading.Event(), abort_reason=lambda: "")
    player.events = lambda: iter(events)   # type: ignore[method-assign]
    return list(player._bursts())


def test_bursts_leave_whole_in_order_and_nothing_is_lost() -> None:
    for seed in range(400):
        rnd = random.Random(seed)
        devices = {"gps": Merging(rnd.choice([0.0, 1e-5, 5e-5])), "compass": Merging(2e-5), "rc": Plain(), "imu": Plain()}
        t, events = 0, []
        for i in range(rnd.randint(1, 80)):
            t += rnd.choice([0, 1000, 5000, 20000, 60000])
            events.append((t, rnd.choice(list(devices)), (i,)))
        out = bursts(events, devices)
        # nothing lost or duplicated, each device's records in their order
        for name in devices:
            assert [i for _t, d, p in out if d == name for i in p] == [p[0] for _t, d, p in events if d == name]
        # items leave in the order of their first record's time
        assert [o[0] for o in out] == sorted(o[0] for o in out)
        # a burst's records were recorded closer than its device's gap, and it ended on a silence or its size
        times = {p[0]: t for t, _d, p in events}
        for first, name, payload in out:
            gap = int(devices[name].burst_gap_s * 1e9)
            stamps = [times[i] for i in payload]
            assert stamps[0] == first and all(b - a < gap for a, b in zip(stamps, stamps[1:]))


def test_a_record_of_another_device_inside_a_burst_waits_for_the_burst() -> None:
    devices = {"gps": Merging(0.001), "rc": Plain()}
    events = [(0, "gps", (0,)), (100, "rc", (1,)), (200, "gps", (2,)), (5_000_000, "rc", (3,))]
    assert bursts(events, devices) == [(0, "gps", (0, 2)), (100, "rc", (1,)), (5_000_000, "rc", (3,))]
