"""The serial kind's replay device: a pty at a symlink that plays a log's ``RawSerial`` records to a driver.

:class:`ReplaySerialDevice` stands on the kind's pty (:class:`u2sa_hw.ports.serial.pty_link.PtyLink`, as
the mock serial devices do); recorded RX bytes are written into it, with backpressure instead of
drops; what the driver writes is kept and checked against the recorded TX bytes. Stamped (the
replay's mode), each recorded chunk goes as a frame with its recorded read time, and each recorded
silence goes as a silence frame, so the driver times lines and silences by the recording
(:mod:`u2sa_hw.ports.serial.clock`), not by when the replay delivers them. A silence is what the live
port recorded (an RX record without data: a ``readline`` that timed out empty); a log from before
those records gets a clock tick wherever two recorded reads are ``burst_gap_s`` or more apart, which a
live driver busy between two reads of one burst also leaves (issue 24).

It needs nothing from ``hil``, so it lives in its kind's package; the replay (``hil/``) makes it
through the kind's ``replay`` part (``u2sa_hw.hil.replay_devices.make_serial_device``, which reads
the driver's declared ``burst_gap_s``) and plays into it. :class:`ReplayStalled` and
:func:`fd_open_by` serve every replay device.
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.ports.serial.clock import encode_frame, encode_silence
from u2sa_hw.ports.serial.pty_link import PtyLink
from u2sa_hw.ports.tap import RX, TX


class ReplayStalled(RuntimeError):
    """A driver stopped taking its recorded input; the message names the device."""


def fd_open_by(pid: int | None, target: str) -> bool:
    """True when process *pid* has a descriptor open on the path *target* (Linux /proc)."""
    if not pid:
        return False
    fd_dir = Path(f"/proc/{pid}/fd")
    try:
        entries = list(fd_dir.iterdir())
    except OSError:
        return False
    for entry in entries:
        try:
            if os.readlink(entry) == target:
                return True
        except OSError:
            continue
    return False


def record_stamp_ns(record: Any, *, previous: int = 0) -> int:
    """The device-clock time (ns) of a recorded RX chunk: its header stamp, which the driver's tap set
    when the chunk was read (wall clock, like the driver's own line times); *previous* without one."""
    stamp_us = int(getattr(getattr(record, "header", None), "timestamp_us", 0) or 0)
    return stamp_us * 1000 if stamp_us > 0 else previous


@dataclass
class StampedChunks:
    """RX chunks with their device-clock stamps, written as one (``--fast`` merges a burst); a chunk
    without bytes is a clock tick (the recorded line was silent until then), one with None a recorded
    silence."""

    chunks: list[tuple[int, bytes | None]] = field(default_factory=list)
    direction: int = RX

    @property
    def length(self) -> int:
        """Data bytes held."""
        return sum(len(data) for _, data in self.chunks if data)


class ReplaySerialDevice:
    """A pty at *link_path*; recorded RX bytes go to the driver, its writes are compared with TX.

    *stamped*: every chunk is written as a stamped frame and the driver's address says
    ``clock=stamped`` (module docstring); ``preload`` then finds whether the log records its
    silences (``silences_recorded``) or, for an older log, where the gaps put them.
    """

    kind = "serial"

    def __init__(self, *, name: str, link_path: Path | str, burst_gap_s: float = 0.05,
                 write_timeout_s: float = 10.0, stamped: bool = False) -> None:
        self.name = name
        self.stamped = stamped
        self._ticks: list[tuple[int, int]] = []   # (log time, stamp) of a tick after each gap (older logs)
        self._last_stamp = 0
        self.silences_recorded = False   # the log has the live port's silence records: only they are silences
        self.burst_gap_s = burst_gap_s  # records closer than this are one burst (the driver's epoch_gap_s)
        self.link_path = Path(link_path)
        self.write_timeout_s = write_timeout_s
        self._written = bytearray()        # what the driver wrote
        self._pty = PtyLink(link_path=self.link_path, name=f"replay-{name}", on_data=self._written.extend)
        self._expected_tx = bytearray()    # what the recorded driver wrote
        self.fed_bytes = 0
        self.fed_chunks = 0

    @property
    def address(self) -> str:
        """The path the driver opens."""
        return str(self.link_path)

    def mock_address(self, real: DeviceAddress | None) -> str:
        """``mock+serial://<the pty symlink>`` with the recorded address's framing (and ``clock=stamped``)."""
        params = ({k: v for k, v in real.params.items() if k not in ("usb", "serial", "clock")}
                  if real is not None else {})
        if self.stamped:
            params["clock"] = "stamped"
        return make_address("serial", self.address, params=params, mock=True, device=self.name).url

    def config_changes(self) -> dict[str, Any]:
        """Nothing besides the address."""
        return {}

    def preload(self, log_path: Path, *, start_ns: int, end_ns: int) -> None:
        """Stamped: find whether the log has the live port's silence records (an RX record without data, up to
        the window's end); then those are fed as silences and nothing else is one. A log without them: note a
        clock tick ``burst_gap_s`` after each recorded RX chunk that the next one follows later than that on
        the device clock (and after the last one, when the window goes on that long), so the driver ends a
        burst on the gap, at once and at any replay speed."""
        if not self.stamped:
            return
        # The log reader is the recording layer's, above the ports (docs/architecture.md): imported when a
        # replay runs, never by a driver that opens a serial port.
        from u2sa_hw.recording.log_reader import LogFile

        gap = max(1, int(self.burst_gap_s * 1e9))
        ticks: list[tuple[int, int]] = []
        prev: tuple[int, int] | None = None   # (log time, stamp) of the previous RX chunk
        marked = False
        for m in LogFile(log_path).messages(rf"RAW\.{re.escape(self.name)}"):
            if m.log_time_ns > end_ns:
                break
            try:
                rec, _ = REGISTRY.decode(m.data)
            except MalformedMessage:
                continue
            if getattr(rec, "direction", None) != RX:
                continue
            if not bytes(getattr(rec, "data", b"")):
                marked = True
                continue
            if m.log_time_ns < start_ns:
                continue
            stamp = record_stamp_ns(rec, previous=prev[1] if prev else m.log_time_ns)
            if prev is not None and stamp - prev[1] >= gap:
                ticks.append((max(prev[0], min(prev[0] + gap - 1, m.log_time_ns - 1)), prev[1] + gap))
            prev = (m.log_time_ns, stamp)
        if prev is not None and end_ns - prev[0] >= gap:
            ticks.append((prev[0] + gap - 1, prev[1] + gap))
        self.silences_recorded = marked
        self._ticks = [] if marked else ticks

    def clock_ticks(self) -> Iterator[tuple[int, StampedChunks]]:
        """``(log time, tick)`` of each recorded silence (see :meth:`preload`), in log order; the player
        merges them into the stream. A tick is placed within the burst gap of the chunk before it, so
        ``--fast`` writes it with that burst."""
        for log_ns, stamp in self._ticks:
            yield log_ns, StampedChunks([(stamp, b"")])

    @property
    def slave_name(self) -> str:
        """The pty's slave (``/dev/pts/N``) the symlink points at ("" before ``start()``)."""
        return self._pty.slave_name

    def start(self) -> None:
        """Create the pty (raw mode, non-blocking master), the symlink and the reader of driver writes."""
        self._pty.open()

    def stop(self) -> None:
        """Stop the reader, remove the symlink, close the pty."""
        self._pty.close()

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The driver has finished opening the pty: pyserial flushes the input while it opens, so
        bytes fed earlier would be lost. A serial sensor says ``port = open`` in its health once
        the open returned; for a driver without that detail, holding the slave open must do."""
        if "port" in health:
            return health["port"] == "open" and fd_open_by(pid, self.slave_name)
        return fd_open_by(pid, self.slave_name)

    def _encoded(self, record: Any) -> tuple[bytes, int]:
        """What goes into the pty for an RX *record* (stamped: its frames) and how many data bytes it holds."""
        if not self.stamped:
            return bytes(record.data), len(record.data)
        marked = self.silences_recorded
        chunks = self._chunks(record) if isinstance(record, StampedChunks) or record.data or marked else []
        return (b"".join(encode_silence(stamp) if data is None else encode_frame(stamp, data, silences_recorded=marked)
                         for stamp, data in chunks),
                sum(len(d) for _, d in chunks if d))

    def feed(self, record: Any) -> None:
        """Write an RX record's bytes (stamped: its frames) into the pty, waiting while the driver's
        buffer is full; note TX."""
        if record.direction == TX:
            self._expected_tx += bytes(record.data)
            return
        if record.direction != RX:
            return
        data, size = self._encoded(record)
        if not data:
            return
        view = memoryview(data)
        deadline = time.monotonic() + self.write_timeout_s
        while view:
            n = self._pty.write(view)
            if n:
                view = view[n:]
                continue
            if time.monotonic() > deadline:
                raise ReplayStalled(f"{self.name}: the driver has not read its serial input for "
                                    f"{self.write_timeout_s:g} s ({self.address}); is the service still running?")
            self._pty.wait_writable(0.05)
        self.fed_bytes += size
        self.fed_chunks += 1 if size else 0

    def merge(self, first: Any, second: Any, *, limit: int = 4096) -> Any | None:
        """One RX record holding both chunks (``--fast`` feeds runs at once), or None when they cannot merge.
        Stamped, the chunks keep their own stamps (:class:`StampedChunks`)."""
        if first.direction != RX or second.direction != RX or first.length + second.length > limit:
            return None
        if self.stamped or isinstance(first, StampedChunks) or isinstance(second, StampedChunks):
            return StampedChunks(self._chunks(first) + self._chunks(second))
        merged = type(first)()
        merged.device, merged.direction = first.device, RX
        merged.data = bytes(first.data) + bytes(second.data)
        merged.length = len(merged.data)
        return merged

    def _chunks(self, record: Any) -> list[tuple[int, bytes | None]]:
        """A record's (stamp, data) chunks; a recorded silence (no data, in a log that records them) has None."""
        if isinstance(record, StampedChunks):
            return list(record.chunks)
        stamp = record_stamp_ns(record, previous=self._last_stamp)
        self._last_stamp = stamp
        data = bytes(record.data)
        return [(stamp, data if data or not self.silences_recorded else None)]

    def pending(self) -> int:
        """Bytes in the pty the driver has not read yet."""
        return self._pty.pending()

    def report(self) -> dict[str, Any]:
        """Bytes and chunks fed; the driver's writes against the recorded ones."""
        written, expected = bytes(self._written), bytes(self._expected_tx)
        out: dict[str, Any] = {"kind": self.kind, "fed_bytes": self.fed_bytes, "fed_chunks": self.fed_chunks,
                               "tx_bytes": len(written), "tx_recorded_bytes": len(expected)}
        if written != expected:
            common = next((i for i, (a, b) in enumerate(zip(written, expected)) if a != b), min(len(written),
                                                                                          len(expected)))
            out["divergences"] = 1
            out["divergence"] = (f"the driver wrote {len(written)} bytes, the recording has {len(expected)}; "
                                 f"they differ from byte {common}")
        else:
            out["divergences"] = 0
        return out
