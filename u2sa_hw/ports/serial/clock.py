"""A device clock for replayed serial devices, carried in-band through the pty.

A pty carries bytes, not times, so a replayed driver would measure silences on its own wall
clock, which a busy machine or ``u2sa replay --fast`` changes. The replay's serial device
(``u2sa_hw/ports/serial/replay.py``) therefore writes each recorded chunk as a *frame*: its recorded
read time, then its bytes::

    ESC 'T' <16 lower-case hex digits: the stamp in ns>  <data, each ESC doubled>

``ESC`` is 0x1B. ``ESC ESC`` is one data byte 0x1B; ``ESC 'T'`` with 16 hex digits starts a
new frame; a frame with no data is a clock tick (the recorded line was silent until then).
Anything else (an ``ESC`` followed by another byte, a stamp that is not hex, data before the
first stamp) is garbage: dropped and counted, never handed to the driver.

A log whose live port recorded its silences (an empty ``RawSerial`` RX record each time a
``readline`` of the live driver timed out empty, :meth:`SerialPort.readline`) is written with
two more kinds, so the replayed driver sees exactly the silences the live one saw::

    ESC 'R' <16 hex digits> <data>   a frame as 'T', of a stream whose silences are recorded: a
                                     gap before it, however long, is no silence (the live driver
                                     was busy while the bytes waited in the device)
    ESC 'Q' <16 hex digits>          a recorded silence: the live driver's read timed out here

Only ``'T'`` frames keep the older rule (a gap of ``timeout`` or more between two frames' stamps
is a silence), for logs recorded before the silences were.

:class:`StampedSerialPort` decodes the frames inside ``readline()``/``read()`` and replays
what the recorded driver's reads saw: a line's time (:meth:`~StampedSerialPort.line_time_ns`)
is the stamp of the frame that held its last byte, and an empty ``readline()`` stands for a
recorded silence (``'Q'``), or in a stream without them a gap of ``timeout`` or more on the
device clock (:meth:`~StampedSerialPort.went_quiet`), however long the replay took to deliver
it. Only an address that says ``clock=stamped`` opens this port, and only a ``mock+serial``
address may say it: a real device can never set the time its driver sees.
"""

from __future__ import annotations

import time
from collections import deque

import serial

from u2sa_hw.ports.serial.port import MAX_LINE, SerialPort
from u2sa_hw.ports.tap import Tap

ESC = 0x1B
STAMP = ord("T")
RECORDED = ord("R")          # a frame of a stream with recorded silences: no gap is a silence
SILENCE = ord("Q")           # a recorded silence (no data)
_STARTS = frozenset((STAMP, RECORDED, SILENCE))
STAMP_DIGITS = 16
HEADER_LEN = 2 + STAMP_DIGITS
DEVICE_CLOCK_GRACE_S = 2.0   # the pty silent this long (wall): a readline timeout is a silence again
# ... in a stream whose silences are recorded ('R', 'Q'), where a wall-clock gap is never one: only a replay
# that stopped feeding (the player's own stall limit is 20 s). A --fast replay on a loaded machine may hold
# the rest of a burst back for seconds while other drivers take their input (the live driver read an epoch
# in two parts, held up in between): 2 s there split one epoch into two fixes, in 1 replay of 5.
RECORDED_SILENCES_GRACE_S = 30.0
_HEX = frozenset(b"0123456789abcdefABCDEF")

Frame = tuple[int, "bytes | None"]   # (stamp ns, data bytes; empty for a clock tick, None for a recorded silence)


def _header(kind: int, stamp_ns: int) -> bytes:
    if not 0 <= stamp_ns < 1 << 64:
        raise ValueError(f"stamp {stamp_ns} ns does not fit in 16 hex digits")
    return bytes((ESC, kind)) + b"%016x" % stamp_ns


def encode_frame(stamp_ns: int, data: bytes = b"", *, silences_recorded: bool = False) -> bytes:
    """One frame: *data* (any bytes) stamped *stamp_ns*; no data is a clock tick. *silences_recorded*: the
    stream carries its silences (:func:`encode_silence`), so no gap before this frame is one (``'R'``)."""
    kind = RECORDED if silences_recorded else STAMP
    return _header(kind, stamp_ns) + bytes(data).replace(b"\x1b", b"\x1b\x1b")


def encode_silence(stamp_ns: int) -> bytes:
    """A recorded silence at *stamp_ns*: the live driver's read timed out empty there (``'Q'``)."""
    return _header(SILENCE, stamp_ns)


class FrameDecoder:
    """Decodes a stamped byte stream fed in pieces of any size (a frame may be split anywhere)."""

    def __init__(self) -> None:
        self._pending = bytearray()        # an incomplete escape or stamp, kept for the next feed
        self.stamp_ns: int | None = None   # the stamp of the frame being read
        self.garbage = 0                   # bytes dropped: bad escapes, bad stamps, data before any stamp
        self.silences_recorded = False     # an 'R' frame or a 'Q' silence came: only 'Q' is a silence

    def feed(self, raw: bytes) -> list[Frame]:
        """The frames (or continuations of the current frame) that *raw* completes, in order."""
        buf = self._pending + raw
        self._pending = bytearray()
        frames: list[Frame] = []
        data = bytearray()
        i, n = 0, len(buf)

        def close() -> None:
            if self.stamp_ns is not None and data:
                frames.append((self.stamp_ns, bytes(data)))
            elif data:
                self.garbage += len(data)
            data.clear()

        while i < n:
            byte = buf[i]
            if byte != ESC:
                data.append(byte)
                i += 1
                continue
            if i + 1 >= n:
                break
            kind = buf[i + 1]
            if kind == ESC:
                data.append(ESC)
                i += 2
            elif kind in _STARTS:
                if i + HEADER_LEN > n:
                    break
                digits = bytes(buf[i + 2:i + HEADER_LEN])
                i += HEADER_LEN
                if not all(c in _HEX for c in digits):
                    self.garbage += HEADER_LEN
                    continue
                close()
                self.stamp_ns = int(digits, 16)
                if kind != STAMP:
                    self.silences_recorded = True
                # a silence, or the frame's start: a tick until data follows
                frames.append((self.stamp_ns, None if kind == SILENCE else b""))
            else:
                self.garbage += 2
                i += 2
        close()
        self._pending = bytearray(buf[i:])
        return _joined(frames)


def _joined(frames: list[Frame]) -> list[Frame]:
    """A frame's start merged with the data that followed it in the same feed."""
    out: list[Frame] = []
    for stamp, data in frames:
        if data and out and out[-1][0] == stamp and out[-1][1] == b"":
            out[-1] = (stamp, data)
        else:
            out.append((stamp, data))
    return out


class StampedSerialPort(SerialPort):
    """A mock serial port whose bytes arrive in stamped frames: the driver reads the recorded
    times (:meth:`line_time_ns`) and silences (:meth:`went_quiet`) instead of its wall clock."""

    device_clock = True

    def __init__(self, handle: serial.SerialBase, *, device: str, address: str, tap: Tap | None = None,
                 timeout: float = 0.1) -> None:
        super().__init__(handle, device=device, address=address, tap=tap)
        self.timeout_ns = int(timeout * 1e9)   # a silence this long on the device clock ended a read
        self._decoder = FrameDecoder()
        self._frames: deque[Frame] = deque()   # decoded, not yet in the line buffer
        self._runs: deque[list[int]] = deque()  # [byte count, stamp] of the line buffer's bytes
        self._clock_ns: int | None = None       # the stamp of the last frame moved into the line buffer
        self._line_ns: int | None = None
        self._clock_quiet = False
        self._heard_at: float | None = None     # monotonic time bytes last came from the pty

    @property
    def garbage_bytes(self) -> int:
        """Bytes of the stamped stream that were no frame (dropped)."""
        return self._decoder.garbage

    def line_time_ns(self) -> int | None:
        """The device-clock stamp (ns) of the frame that held the last byte of the last line returned."""
        return self._line_ns

    def went_quiet(self) -> bool:
        """True when the last empty ``readline()`` stands for a silence of the device: a recorded one, one of
        ``timeout`` on the device clock, or the pty silent for DEVICE_CLOCK_GRACE_S of wall time
        (RECORDED_SILENCES_GRACE_S in a stream with recorded silences: a stopped replay never holds a
        burst back for ever); False for a wall-clock timeout while the device clock is fresh (the replay
        is only slower than the recording)."""
        heard = self._heard_at
        grace = RECORDED_SILENCES_GRACE_S if self._decoder.silences_recorded else DEVICE_CLOCK_GRACE_S
        return self._clock_quiet or heard is None or time.monotonic() - heard >= grace

    def _fill(self) -> bool:
        """Wait up to the timeout for bytes from the pty and decode them; False when none came. The data is
        tapped as it arrives; the silences are not (they would be tapped out of order with it)."""
        raw = self._read_waiting()
        if not raw:
            return False
        self._heard_at = time.monotonic()
        frames = self._decoder.feed(raw)
        self._frames.extend(frames)
        self._tapped(b"".join(data for _, data in frames if data))
        return True

    def _take_frame(self) -> None:
        stamp, data = self._frames.popleft()   # a recorded silence (no data) only moves the clock here (read())
        self._clock_ns = stamp
        if data:
            self._buffer += data
            self._runs.append([len(data), stamp])

    def _take_bytes(self, count: int) -> tuple[bytes, int | None]:
        """The first *count* buffered bytes and the stamp of the frame that held the last of them."""
        out = bytes(self._buffer[:count])
        del self._buffer[:count]
        stamp = None
        while count > 0 and self._runs:
            run = self._runs[0]
            stamp = run[1]
            used = min(count, run[0])
            run[0] -= used
            count -= used
            if not run[0]:
                self._runs.popleft()
        return out, stamp

    def read(self, size: int = 1) -> bytes:
        """Up to *size* data bytes (no framing), buffered ones first; waits up to the timeout when none are."""
        with self._read_lock:
            self._clock_quiet = False
            while len(self._buffer) < size:
                if self._frames:
                    self._take_frame()
                elif self._buffer or not self._fill():
                    break
            data, _ = self._take_bytes(min(size, len(self._buffer)))
            return data

    def readline(self) -> bytes:
        """One line (as :meth:`SerialPort.readline`), or ``b""`` on a silence (:meth:`went_quiet` True): a
        recorded one (``'Q'``: the live driver's read timed out there), or in a stream without recorded
        silences a gap of ``timeout`` or more on the device clock before the next frame; or ``b""`` when
        nothing came from the pty within the timeout of wall time."""
        with self._read_lock:
            self._clock_quiet = False
            while b"\n" not in self._buffer and len(self._buffer) < MAX_LINE:
                if not self._frames:
                    if not self._fill():
                        return b""
                    continue
                stamp, data = self._frames[0]
                if data is None:   # a recorded silence: the live driver's read found nothing here
                    self._frames.popleft()
                    self._clock_ns = stamp
                    self._clock_quiet = True
                    return b""
                if (not self._decoder.silences_recorded and self._clock_ns is not None
                        and stamp - self._clock_ns >= self.timeout_ns):
                    self._clock_ns = stamp   # said once: the frame is taken on the next call
                    self._clock_quiet = True
                    return b""
                self._take_frame()
            end = self._buffer.find(b"\n")
            line, self._line_ns = self._take_bytes(end + 1 if end >= 0 else MAX_LINE)
            return line

    def __repr__(self) -> str:
        state = "open" if self.is_open else "closed"
        return f"<StampedSerialPort {self.device} {self.address} {state}>"
