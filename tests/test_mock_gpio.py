"""The mock GPIO chip (its wire protocol, chip-side API and faults), the mock RC receiver
(pulse widths measured from edge timestamps) and the RC multiplexer model."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

import pytest

from conftest import REPO, wait_until
from u2sa_hw.mocks.gpio_chip import GpioChipRecord, MockGpioChip
from u2sa_hw.mocks.rc_receiver import MuxMock, RcFrame, RcReceiverMock
from u2sa_hw.ports.errors import PortClosed
from u2sa_hw.ports.gpio.wire import MOCK_EDGE_RECORD, MockFrameReader, encode_mock_json
from u2sa_hw.ports.gpio.port import GpioPort, open_gpio

RC_LINES = {"throttle": 5, "steering": 6, "mode": 13}


@pytest.fixture
def chip(tmp_path: Path) -> Iterator[MockGpioChip]:
    with MockGpioChip(socket_path=str(tmp_path / "gpio.sock"), num_lines=32) as c:
        yield c


@pytest.fixture
def rc(chip: MockGpioChip) -> Iterator[RcReceiverMock]:
    receiver = RcReceiverMock(chip, lines=RC_LINES, frame_hz=50).start()
    yield receiver
    receiver.stop()


class RawClient:
    """Speaks the chip's wire protocol directly, to see what gpiod's EdgeEvent would carry."""

    def __init__(self, path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.sock.settimeout(5.0)
        self.reader = MockFrameReader()
        self.pending: list[tuple[bytes, bytes]] = []

    def frame(self) -> tuple[bytes, bytes]:
        while not self.pending:
            self.pending.extend(self.reader.feed(self.sock.recv(4096)))
        return self.pending.pop(0)

    def call(self, **request: object) -> dict:
        self.sock.sendall(encode_mock_json({"id": 1, **request}))
        kind, payload = self.frame()
        assert kind == b"J"
        return json.loads(payload)

    def edge(self) -> tuple[int, int, int, int, int]:
        kind, payload = self.frame()
        assert kind == b"E"
        return MOCK_EDGE_RECORD.unpack(payload)


def pulse_widths_us(port: GpioPort, *, frames: int) -> dict[int, list[float]]:
    """Pulse widths per line (falling minus rising edge timestamp) over *frames* pulses each."""
    rising: dict[int, int] = {}
    widths: dict[int, list[float]] = {}

    def collect() -> bool:
        for event in port.read_edges(0.05):
            if event.rising:
                rising[event.line] = event.timestamp_ns
            elif event.line in rising:
                widths.setdefault(event.line, []).append((event.timestamp_ns - rising.pop(event.line)) / 1000)
        return len(widths) == len(RC_LINES) and all(len(w) >= frames for w in widths.values())

    wait_until(collect, timeout=10.0, message=f"{frames} pulses on every channel")
    return widths


def test_edges_have_gpiod_style_sequence_numbers_per_request(chip: MockGpioChip) -> None:
    client = RawClient(chip.socket_path)
    reply = client.call(op="request", consumer="raw", lines={"2": {"direction": "input", "edge": "both"},
                                                             "3": {"direction": "input", "edge": "falling"}})
    assert reply["ok"], reply
    chip.drive_input(2, 1, 100)
    chip.drive_input(3, 1, 150)  # rising on a falling-only line: no event, no sequence number
    chip.drive_input(3, 0, 200)
    chip.drive_input(2, 0, 300)
    # (event type 1 rising / 2 falling, line, timestamp, global seqno, line seqno)
    assert [client.edge() for _ in range(3)] == [(1, 2, 100, 1, 1), (2, 3, 200, 2, 1), (2, 2, 300, 3, 2)]
    assert client.call(op="info")["lines"]["2"]["consumer"] == "raw"


def test_the_chip_refuses_what_the_kernel_refuses(chip: MockGpioChip) -> None:
    client = RawClient(chip.socket_path)
    assert client.call(op="request", lines={"40": {"direction": "input"}})["error"] == "EINVAL"
    assert client.call(op="request", lines={"1": {"direction": "input"}, "2": {"direction": "output"}})["ok"]
    assert client.call(op="set", values={"1": 1})["error"] == "EPERM"
    assert client.call(op="get", lines=[9])["error"] == "EINVAL"
    assert client.call(op="request", lines={"2": {"direction": "input"}})["error"] == "EBUSY"
    assert client.call(op="frobnicate")["error"] == "EINVAL"


def test_garbage_from_a_client_drops_that_client_only(chip: MockGpioChip) -> None:
    port = open_gpio(device="good", chip=chip.address, inputs=[4])
    bad = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    bad.connect(chip.socket_path)
    bad.settimeout(5.0)
    bad.sendall(b"\xff\x00\x00\x00\x05hello")
    wait_until(lambda: chip.protocol_errors == 1, message="the protocol error to be counted")
    assert bad.recv(10) == b""
    chip.drive_input(4, 1, 42)
    assert port.read_edges(5.0)[0].timestamp_ns == 42
    port.close()


def test_output_history_and_callbacks_record_changes(chip: MockGpioChip) -> None:
    seen = []
    chip.on_output(lambda line, value, stamp: seen.append((line, value)))
    port = open_gpio(device="enable", chip=chip.address, outputs={21: 0})
    port.set(21, 1)
    port.set(21, 1)  # no change, no record
    port.set(21, 0)
    assert seen == [(21, 1), (21, 0)]
    outputs = [r for r in chip.history if r.kind == "output"]
    assert [(r.line, r.value) for r in outputs] == [(21, 1), (21, 0)]
    assert outputs[0].timestamp_ns <= outputs[1].timestamp_ns
    with pytest.raises(ValueError, match="output"):
        chip.drive_input(21, 1)
    port.close()


def test_pull_up_input_reads_high_until_driven(chip: MockGpioChip) -> None:
    port = open_gpio(device="button", chip=chip.address, inputs=[8], bias="pull-up")
    assert port.get(8) == 1
    chip.drive_input(8, 0, 7)
    assert port.get(8) == 0
    assert GpioChipRecord(7, 8, 0, "input") in chip.history
    port.close()


def test_stop_edges_fault_keeps_levels_but_delivers_no_edges(chip: MockGpioChip) -> None:
    port = open_gpio(device="rc", chip=chip.address, inputs=[5])
    chip.stop_edges(True)
    chip.drive_input(5, 1, 10)
    assert port.get(5) == 1
    assert port.read_edges(0.2) == [] and chip.dropped_edges == 1
    chip.stop_edges(False)
    chip.drive_input(5, 0, 20)
    assert [e.timestamp_ns for e in port.read_edges(5.0)] == [20]
    port.close()


def test_disconnect_fault_closes_the_port_and_releases_outputs(chip: MockGpioChip) -> None:
    port = open_gpio(device="enable", chip=chip.address, outputs={21: 1})
    other = open_gpio(device="other", chip=chip.address, inputs=[3])
    assert chip.disconnect("u2sa:enable") == 1
    with pytest.raises(PortClosed):
        wait_until(lambda: port.read_edges(0.05) and False, message="PortClosed")
    assert chip.read_output(21) == 0  # the board's pull-down takes the released line low
    assert chip.consumers() == {3: "u2sa:other"}
    other.close()


def test_rc_pulse_widths_from_edge_timestamps_match_the_set_values(chip: MockGpioChip,
                                                                   rc: RcReceiverMock) -> None:
    port = open_gpio(device="rc_input", chip=chip.address, inputs=list(RC_LINES.values()))
    rc.set_pulse("throttle", 1234.5)
    rc.set_pulse("steering", 1900)
    rc.set_mode_switch(True)
    pulse_widths_us(port, frames=2)  # let frames set before the changes pass
    widths = pulse_widths_us(port, frames=5)
    for name, expected in {"throttle": 1234.5, "steering": 1900.0, "mode": 2000.0}.items():
        assert all(abs(w - expected) < 1.0 for w in widths[RC_LINES[name]][-5:]), (name, widths[RC_LINES[name]])
    port.close()


def test_rc_signal_loss_stops_all_edges(chip: MockGpioChip, rc: RcReceiverMock) -> None:
    port = open_gpio(device="rc_input", chip=chip.address, inputs=list(RC_LINES.values()))
    pulse_widths_us(port, frames=1)
    rc.signal_loss(True)
    lost = lambda: sum(1 for f in list(rc.history) if f.pulses_us is None)  # noqa: E731
    wait_until(lambda: lost() >= 2, message="frames without signal")
    port.read_edges(0.0)  # drain what was sent before the loss
    seen_lost = lost()
    wait_until(lambda: lost() >= seen_lost + 3, message="three more frames without signal")
    assert port.read_edges(0.0) == []
    assert port.get(5) == 0
    rc.signal_loss(False)
    assert pulse_widths_us(port, frames=1)
    port.close()


def test_a_receiver_thread_held_up_notes_the_stall_and_how_long_no_frame_came(chip: MockGpioChip,
                                                                              rc: RcReceiverMock) -> None:
    held, release = threading.Event(), threading.Event()

    def hold(frame: RcFrame) -> None:   # runs in the receiver's thread: hold it as an overloaded machine does
        if not held.is_set():
            held.set()
            release.wait(5.0)

    wait_until(lambda: rc.frames_sent >= 1, message="a first frame")
    noted = len(rc.stalls)   # an overloaded machine may have stalled it already
    rc.add_frame_listener(hold)
    wait_until(held.is_set, message="the receiver thread held")
    began = time.monotonic_ns()
    release.wait(0.15)   # held at least 150 ms after handing over a frame: no frame for 130 ms beyond the period
    release.set()
    wait_until(lambda: len(rc.stalls) > noted, message="the stall noted")
    ended, beyond_ns = rc.stalls[noted]
    assert beyond_ns >= 150_000_000 - rc.frame_period_ns and ended >= began + 150_000_000


def test_rc_glitches_are_isolated_single_frames(chip: MockGpioChip, rc: RcReceiverMock) -> None:
    port = open_gpio(device="rc_input", chip=chip.address, inputs=[RC_LINES["throttle"]])
    rc.glitch(2, channel="throttle", pulse_us=500)
    series: list[float] = []
    rising: dict[int, int] = {}

    def collect() -> bool:
        for e in port.read_edges(0.05):
            if e.rising:
                rising[e.line] = e.timestamp_ns
            elif e.line in rising:
                series.append((e.timestamp_ns - rising.pop(e.line)) / 1000)
        return series.count(500.0) == 2 and series[-1] == 1500.0 and len(series) >= 5

    wait_until(collect, message="two glitches followed by a good frame")
    glitches = [i for i, w in enumerate(series) if w == 500.0]
    assert glitches[1] - glitches[0] == 2  # a good frame between them
    assert set(series) == {500.0, 1500.0}
    port.close()


def test_rc_rejects_pulses_that_do_not_fit_a_frame(chip: MockGpioChip) -> None:
    rc = RcReceiverMock(chip, lines={f"ch{i}": i for i in range(8)}, frame_hz=50)
    with pytest.raises(ValueError, match="slot"):
        rc.set_pulse("ch0", 2500)
    with pytest.raises(ValueError, match="unknown RC channel"):
        rc.set_pulse("aux", 1500)


def test_mux_selects_autonomous_only_when_software_and_pilot_agree(chip: MockGpioChip,
                                                                   rc: RcReceiverMock) -> None:
    mux = MuxMock(chip, rc, enable_line=21, select_line=20).start()
    port = open_gpio(device="rc_mux", chip=chip.address, inputs=[20], outputs={21: 0})
    assert mux.selected == "rc" and port.get(20) == 0
    port.set(21, 1)
    assert mux.selected == "rc"  # software alone cannot take over
    rc.set_mode_switch(True)
    wait_until(lambda: mux.selected == "autonomous", message="the autonomous side")
    assert port.get(20) == 1 and port.read_edges(5.0)[-1].rising
    port.set(21, 0)
    assert mux.selected == "rc"  # software gives up at once
    port.set(21, 1)
    assert mux.selected == "autonomous"
    rc.set_mode_switch(False)
    wait_until(lambda: mux.selected == "rc", message="the pilot taking back control")
    rc.set_mode_switch(True)
    wait_until(lambda: mux.selected == "autonomous", message="the autonomous side again")
    rc.signal_loss(True)
    wait_until(lambda: mux.selected == "rc", message="the RC side on signal loss")
    rc.signal_loss(False)
    wait_until(lambda: mux.selected == "autonomous", message="the autonomous side after the signal returns")
    port.close()  # the service dies: its enable line is released and falls low
    wait_until(lambda: mux.selected == "rc", message="the RC side after the service is gone")
    assert [side for _, side in mux.history][-2:] == ["autonomous", "rc"]


def test_a_stuck_mux_ignores_its_inputs_until_freed(chip: MockGpioChip, rc: RcReceiverMock) -> None:
    mux = MuxMock(chip, rc, enable_line=21, select_line=20).start()
    port = open_gpio(device="rc_mux", chip=chip.address, inputs=[20], outputs={21: 0})
    try:
        mux.stick("autonomous")
        assert mux.stuck == "autonomous" and mux.selected == "autonomous" and port.get(20) == 1
        rc.set_mode_switch(True)
        port.set(21, 1)
        mux.stick("rc")                      # both inputs say autonomous; jammed on the pilot side
        assert mux.selected == "rc" and port.get(20) == 0
        mux.stick(None)                      # free again: its inputs (both autonomous) decide
        assert mux.stuck is None
        wait_until(lambda: mux.selected == "autonomous", message="the mux following its inputs again")
        assert port.get(20) == 1
        port.set(21, 0)
        assert mux.selected == "rc" and port.get(20) == 0
        with pytest.raises(ValueError, match="side must be"):
            mux.stick("pilot")
    finally:
        port.close()


def test_rc_receiver_in_another_process_measured_over_the_socket(tmp_path: Path) -> None:
    sock = tmp_path / "rc.sock"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.mocks.rc_receiver", "--socket", str(sock),
                             "--pulse", "throttle=1750,steering=1100"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().startswith("ready mock:")
        port = open_gpio(device="rc_input", chip=f"mock:{sock}", inputs=list(RC_LINES.values()))
        widths = pulse_widths_us(port, frames=3)
        assert all(abs(w - 1750) < 1.0 for w in widths[5]), widths[5]
        assert all(abs(w - 1100) < 1.0 for w in widths[6]), widths[6]
        assert all(abs(w - 1000) < 1.0 for w in widths[13]), widths[13]
        port.close()
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0


# ------------------------------------------------------------ a replay chip (a device clock) -------
def test_a_device_clock_chip_hands_its_driver_the_origin_steps_and_the_recorded_bus_in_order(tmp_path: Path) -> None:
    from u2sa_hw.ports.gpio.wire import BusInput, ClockTick, EdgeEvent

    with MockGpioChip(socket_path=str(tmp_path / "replay.sock"), device_clock=True, release_level=None) as chip:
        chip.set_origin(123_000)                       # before the driver: in its request reply
        port = open_gpio(device="rc", chip=chip.address, inputs=[5])
        try:
            assert port.device_clock and port.clock_origin_ns() == 123_000
            assert port.take_recorded_bus(["U2SA_HEALTH", "FAILSAFE"]) == ("FAILSAFE", "U2SA_HEALTH")
            chip.drive_input(5, 1, 1_000)
            assert chip.bus(1_000, "FAILSAFE", b"\x01\x02") == 1
            assert chip.bus(1_000, "STATE_ESTIMATE", b"x") == 0     # not asked for: not sent
            chip.tick(5_000)
            chip.tick(9_000, step=True)
            chip.drive_input(5, 0, 2_000)                 # a late edge: stamped before the step
            chip.set_origin(456_000)                      # set again: sent to the client in order too
            events: list = []
            wait_until(lambda: events.extend(port.read_events(0.05)) or len(events) >= 5, message="five events")
            assert events == [EdgeEvent(5, True, 1_000), BusInput(1_000, "FAILSAFE", b"\x01\x02"), ClockTick(5_000),
                              ClockTick(9_000, step=True), EdgeEvent(5, False, 2_000)]
            assert port.now_ns() == 9_000                 # the latest time taken, not the wall clock
            wait_until(lambda: port.clock_origin_ns() == 456_000, message="the new origin")
        finally:
            port.close()


def test_a_chip_without_a_device_clock_has_no_recorded_bus_and_a_real_clock(chip: MockGpioChip) -> None:
    port = open_gpio(device="rc", chip=chip.address, inputs=[5])
    try:
        assert not port.device_clock and port.clock_origin_ns() == 0
        assert port.take_recorded_bus(["FAILSAFE"]) == ()          # the driver hears the bus
        raw = RawClient(chip.socket_path)
        reply = raw.call(op="bus", channels=["FAILSAFE"])
        assert not reply["ok"] and reply["error"] == "EINVAL" and "replay chip" in reply["message"]
    finally:
        port.close()
