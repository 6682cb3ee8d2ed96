"""The silences a live serial driver saw, recorded and replayed (issue 24, the split epoch in mid-log).

The live port ends a burst only when a ``readline`` waits ``epoch_gap_s`` and gets nothing; a driver busy
between two reads (publishing health) leaves the bytes waiting in the device, which the read times alone
cannot tell from a silence. So the live port taps each silence as an RX record without data, once per
silence, and a replay of a log that has them hands the driver those silences and no others; a log from
before them keeps the gap rule. Deterministic: every record is fed before the port is read, and only the
device clock says what a silence is (the wall-clock grace is set out of reach).
"""

from __future__ import annotations

import datetime as dt
import os
import threading
import tty
from pathlib import Path

import pytest
from gps_stream_builder import START, Solution, gga, rmc, vtg

from u2sa_hw.drivers.gps_nmea.epochs import GpsEpochCollector
from u2sa_hw.drivers.nmea_fields import Epoch, parse_sentence
from u2sa_hw.hil.player import Player
from u2sa_hw.ports.serial.replay import ReplaySerialDevice
from u2sa_hw.messages import RawSerial
from u2sa_hw.ports.serial import clock as serial_clock
from u2sa_hw.ports.opener import open_port
from u2sa_hw.ports.serial.clock import FrameDecoder, encode_frame, encode_silence
from u2sa_hw.ports.tap import RX
from u2sa_hw.recording.mcap_log import McapFile, RunInfo

MS = 1_000_000   # ns
T0 = 1_700_000_000 * 1000 * MS
SOL = Solution(when=START, lat=29.19, lon=-81.05, speed=2.0, course=90.0, heading=91.0)
NEXT = Solution(when=START + dt.timedelta(seconds=1), lat=29.19002, lon=-81.05, speed=2.0, course=90.0,
                heading=91.0)
SILENCE = b""   # a record without data: the live port's read timed out empty


def raw(at_ns: int, data: bytes) -> RawSerial:
    rec = RawSerial()
    rec.header.timestamp_us = at_ns // 1000
    rec.device, rec.direction, rec.data, rec.length = "gps", RX, data, len(data)
    return rec


def write_log(path: Path, records: list[tuple[int, bytes]]) -> Path:
    """A log of ``RAW.gps`` records ``(ms after T0, data)``, each logged when it was read."""
    f = McapFile(path, compression="none", chunk_size=1024, run=RunInfo(vehicle="t"))
    for at_ms, data in records:
        f.write("RAW.gps", raw(T0 + at_ms * MS, data).encode(), T0 + at_ms * MS + 1000)
    f.close()
    return path


def replayed_epochs(tmp_path: Path, log: Path, *, fast: bool) -> list[Epoch]:
    """The epochs the GPS driver's loop (drivers/serial_sensor.py: a line to the collector, a silence to
    ``flush``) forms from *log* replayed through the stamped replay device, fed as ``u2sa replay`` feeds it
    (``--fast``: in bursts) before a line is read."""
    device = ReplaySerialDevice(name="gps", link_path=tmp_path / "dev" / "gps", burst_gap_s=0.05, stamped=True)
    device.preload(log, start_ns=0, end_ns=2 ** 63 - 1)
    player = Player(log, devices={"gps": device}, transport=None, republish=set(), replayed_services=set(),
                    start_ns=0, end_ns=2 ** 63 - 1, rate=None if fast else 1.0, abort=threading.Event(),
                    abort_reason=lambda: "")
    device.start()
    port = open_port(device.mock_address(None), device="gps", timeout=0.05)
    col = GpsEpochCollector(end_on_complete=False)   # epochs end on a silence or the next time only
    epochs: list[Epoch] = []
    try:
        for _t, _target, payload in (player._bursts() if fast else player.events()):
            device.feed(payload)
        while True:
            line = port.readline()
            if line:
                sentence = parse_sentence(line)
                assert sentence is not None, line
                epochs += col.add(sentence, received=port.line_time_ns() / 1e9)
            elif port.went_quiet():
                done = col.flush()
                if done is not None:
                    epochs.append(done)
            elif device.pending() == 0 and not port._frames and not port._buffer:
                break   # everything fed was read
    finally:
        port.close()
        device.stop()
    return epochs


@pytest.fixture(autouse=True)
def _device_clock_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(serial_clock, "DEVICE_CLOCK_GRACE_S", 3600.0)   # only the recording says silence


HELD_UP = [(0, gga(SOL)), (60, rmc(SOL) + vtg(SOL)), (160, SILENCE), (1000, gga(NEXT)), (1060, SILENCE)]


@pytest.mark.parametrize("fast", [True, False], ids=["fast", "timed"])
def test_one_epoch_read_in_two_reads_60ms_apart_without_a_silence_replays_as_one_epoch(
        tmp_path: Path, fast: bool) -> None:
    """The live driver was busy between its two reads of one epoch: no silence was recorded between them."""
    epochs = replayed_epochs(tmp_path, write_log(tmp_path / "held.mcap", HELD_UP), fast=fast)
    assert [e.kinds() for e in epochs] == [["GGA", "RMC", "VTG"], ["GGA"]]
    assert not any(e.supplement for e in epochs)


@pytest.mark.parametrize("fast", [True, False], ids=["fast", "timed"])
def test_a_recorded_silence_inside_an_epoch_replays_as_the_two_parts_the_live_driver_saw(
        tmp_path: Path, fast: bool) -> None:
    log = write_log(tmp_path / "silent.mcap", [(0, gga(SOL)), (55, SILENCE), (60, rmc(SOL) + vtg(SOL)),
                                               (160, SILENCE), (1000, gga(NEXT)), (1060, SILENCE)])
    epochs = replayed_epochs(tmp_path, log, fast=fast)
    assert [e.kinds() for e in epochs] == [["GGA"], ["RMC", "VTG"], ["GGA"]]
    assert [e.supplement for e in epochs] == [False, True, False]


def test_a_log_without_silence_records_keeps_the_gap_rule(tmp_path: Path) -> None:
    """Recorded before the silences were: a gap of epoch_gap_s between two reads is all the log says."""
    old = [(at, data) for at, data in HELD_UP if data]
    epochs = replayed_epochs(tmp_path, write_log(tmp_path / "old.mcap", old), fast=True)
    assert [e.kinds() for e in epochs] == [["GGA"], ["RMC", "VTG"], ["GGA"]]


def test_a_silence_frame_never_merges_with_a_frame_of_its_stamp_and_marks_the_stream() -> None:
    stream = encode_frame(5, b"a", silences_recorded=True) + encode_silence(7) + encode_frame(7, b"b")
    for piece in (1, 5, len(stream)):
        decoder = FrameDecoder()
        frames = [f for i in range(0, len(stream), piece) for f in decoder.feed(stream[i:i + piece])]
        assert [f for f in frames if f[1] != b""] == [(5, b"a"), (7, None), (7, b"b")], piece
        assert decoder.silences_recorded and decoder.garbage == 0
    plain = FrameDecoder()
    plain.feed(encode_frame(5, b"a") + encode_frame(7))
    assert not plain.silences_recorded


def test_the_live_port_taps_one_record_per_silence_not_per_empty_read(tmp_path: Path) -> None:
    master, slave = os.openpty()
    link = tmp_path / "gps"
    os.symlink(os.ttyname(slave), link)
    tty.setraw(slave)
    taps: list[RawSerial] = []
    port = open_port(f"mock+serial://{link}", device="gps", tap=taps.append, timeout=0.05)
    try:
        os.write(master, b"$A\n")
        assert port.readline() == b"$A\n"
        assert port.readline() == b"" and port.readline() == b"" and port.went_quiet()   # one silence, two reads
        os.write(master, b"$B")
        assert port.readline() == b""   # a partial line, then nothing: a silence (the line stays buffered)
        os.write(master, b"\n")
        assert port.readline() == b"$B\n"
        assert [bytes(r.data) for r in taps if r.direction == RX] == [b"$A\n", b"", b"$B", b"", b"\n"]
        assert all(r.length == len(r.data) for r in taps)
    finally:
        port.close()
        os.close(master)
        os.close(slave)
