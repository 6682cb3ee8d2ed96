"""A port builds a raw record only while its tap records (u2sa_hw.ports.tap.RecordingTap): with
``record_raw`` off a driver pays nothing per frame for the recording it does not do."""

from __future__ import annotations

from typing import Any

import can
import pytest

from u2sa_hw.ports.can import port as can_port
from u2sa_hw.ports.can.port import open_can
from u2sa_hw.ports.tap import RX, TX, RecordingTap, tapping


def test_tapping_asks_a_tap_that_can_say_and_trusts_a_plain_callable() -> None:
    on = [False]
    tap = RecordingTap(lambda _r: None, active=lambda: on[0])
    assert not tapping(tap) and not tapping(None)
    on[0] = True
    assert tapping(tap) and tapping(lambda _r: None)


def test_a_can_port_builds_records_only_while_its_tap_records(monkeypatch: pytest.MonkeyPatch) -> None:
    built: list[int] = []
    real = can_port._record

    def counting(device: str, direction: int, msg: can.Message) -> Any:
        built.append(direction)
        return real(device, direction, msg)

    monkeypatch.setattr(can_port, "_record", counting)
    on = [False]
    published: list[Any] = []
    tap = RecordingTap(published.append, active=lambda: on[0])
    driver = open_can(device="motor", interface="virtual", channel="u2sa-tap-test", tap=tap)
    peer = open_can(device="peer", interface="virtual", channel="u2sa-tap-test")
    try:
        for recording in (False, True):
            on[0] = recording
            driver.send(can.Message(arbitration_id=0x10, data=b"\x01", is_extended_id=False))
            peer.send(can.Message(arbitration_id=0x20, data=b"\x02", is_extended_id=False))
            got = driver.recv(5.0)
            assert got is not None and got.arbitration_id == 0x20
        assert built == [TX, RX]   # only the second round, while recording
        assert [(r.direction, r.arbitration_id) for r in published] == [(TX, 0x10), (RX, 0x20)]
    finally:
        driver.close()
        peer.close()
