"""Capture from the bus into an MCAP writer without ever blocking the bus.

The LCM handler thread only appends ``(channel, bytes, time, signer, trailer)`` to a bounded queue
(the verified payload and the sender id that signed it, ``Transport.last_sender``; on the
pilot's channels the whole verified packet, its 88-byte pilot trailer kept, so that a replay
can check the pilot's signature with the public key the log names); a
writer thread, which looks at the queue every 10 ms when it is empty instead of being woken
per message, drains it into :class:`McapLogWriter`, closing a chunk every
``flush_interval_s`` and checking the free disk space. A full queue drops the message and
counts it; a disk below the floor (or a failing write) stops the recording cleanly: the
writer thread finishes the file (summary, indexes) and says why in ``stats.stopped_reason``.
A write that fails (a full disk with ``min_free_mb = 0``) ends the file at its last complete
chunk, still indexed (:class:`~u2sa_hw.recording.mcap_log.McapFile`); the messages of the
chunk in progress are counted as dropped, not written.
:meth:`BusCapture.stop` never blocks on the queue, whatever state the writer thread is in.
"""

from __future__ import annotations

import logging
import queue
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from u2sa_hw.bus.auth import PILOT_TAG, PILOT_TRAILER_LEN, REJECTIONS
from u2sa_hw.bus.roles import PILOT_CHANNELS
from u2sa_hw.recording.mcap_log import BUS_METADATA, McapLogWriter
from u2sa_hw.bus.transport import Transport

log = logging.getLogger("u2sa_hw.recorder")

# stop() waits this long for the writer to write what is queued: less than the recorder unit's
# TimeoutStopSec (15 s), so a stalled disk is reported before systemd's SIGKILL.
JOIN_TIMEOUT_S = 10.0
DRAIN_POLL_S = 0.01   # the writer looks at the queue this often when it found it empty (a queue of 10 ms at most)


@dataclass
class CaptureStats:
    """Counters for health and the command line."""

    received: int = 0
    written: int = 0
    dropped: int = 0          # queue full, still queued when the recording stopped on an error, or cut off by it
    filtered: int = 0
    stopped_reason: str = ""
    per_channel: dict[str, int] = field(default_factory=dict)


class BusCapture:
    """Subscribes to every channel and feeds a writer thread through a bounded queue.

    *disk_usage* is ``shutil.disk_usage`` (anything returning an object with ``free`` in
    bytes for a path); the free space of the log directory is checked when the writer
    starts and after every flush.
    """

    def __init__(self, transport: Transport, writer: McapLogWriter, *, include: str = ".*", exclude: str = "",
                 queue_size: int = 20000, flush_interval_s: float = 1.0, min_free_mb: float = 200.0,
                 disk_usage: Callable[[Path], Any] = shutil.disk_usage) -> None:
        try:
            self._include = re.compile(include or ".*")
            self._exclude = re.compile(exclude) if exclude else None
        except re.error as exc:
            raise ValueError(f"bad channel pattern: {exc}") from None
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, got {queue_size}")
        self.transport = transport
        self.writer = writer
        # The log holds verified payloads (the transport strips the trailers); it says which bus
        # they came from and, in each file, how many packets verification dropped meanwhile.
        writer.run.bus_security = "signed" if transport.auth is not None else "open"
        writer.run.bus_key_id = transport.key_id()
        # The pilot's messages keep their trailer (Ed25519: checking it needs only the public key, which
        # the log names), so a replay can tell that the RC mux signed every recorded RC_MODE and MANUAL_CMD.
        verifier = transport.auth.keyring.pilot_verifier() if transport.auth is not None else None
        self._keep_pilot = verifier is not None
        if verifier is not None:
            writer.run.pilot_key = verifier.public.hex()
            writer.run.pilot_key_id = verifier.id.hex()
        writer.closing_metadata = self.bus_metadata
        self.flush_interval = min(1.0, max(0.05, flush_interval_s))
        self.min_free = min_free_mb * 1e6
        self.disk_usage = disk_usage
        self.stats = CaptureStats()
        self._queue: queue.Queue[tuple[str, bytes, int, str, int] | None] = queue.Queue(maxsize=queue_size)
        self._finish = threading.Event()   # stop() asked: write what is queued, then finish the file
        self._lost_seen = 0                # writer.lost already moved from written to dropped
        self._cuts_seen = 0                # writer.cut_short lines already reported
        self._thread: threading.Thread | None = None
        self._sub: Any = None
        self.active = False

    def wanted(self, channel: str) -> bool:
        """True when *channel* passes the include/exclude patterns."""
        return bool(self._include.fullmatch(channel)) and not (self._exclude and self._exclude.fullmatch(channel))

    def _on_message(self, channel: str, data: bytes) -> None:
        if not self.active:
            return
        self.stats.received += 1
        if not self.wanted(channel):
            self.stats.filtered += 1
            return
        trailer = 0
        if self._keep_pilot and channel in PILOT_CHANNELS:
            packet = self.transport.packet   # verified: the transport checked the pilot's signature
            if len(packet) == len(data) + PILOT_TRAILER_LEN and packet.endswith(PILOT_TAG):
                data, trailer = packet, PILOT_TRAILER_LEN
        try:
            self._queue.put_nowait((channel, data, time.time_ns(), self.transport.last_sender, trailer))
        except queue.Full:
            self.stats.dropped += 1

    def bus_metadata(self) -> dict[str, dict[str, str]]:
        """The ``u2sa_bus`` record: the bus's security and the packets dropped as unsigned, forged, replayed, foreign."""
        rejected = self.transport.rejected()
        totals = {why: sum(c[why] for c in rejected.values()) for why in REJECTIONS}
        by_channel = "; ".join(f"{ch}: " + ", ".join(f"{why} {n}" for why, n in c.items() if n)
                               for ch, c in rejected.items())
        return {BUS_METADATA: {"security": self.writer.run.bus_security, "key_id": self.writer.run.bus_key_id,
                               **{why: str(n) for why, n in totals.items()}, "by_channel": by_channel}}

    def start(self) -> None:
        """Subscribe and start the writer thread."""
        self.active = True
        self._thread = threading.Thread(target=self._drain, name="recorder-writer", daemon=True)
        self._thread.start()
        self._sub = self.transport.subscribe(".*", None, self._on_message, raw=True)

    def _space_ok(self) -> bool:
        where = self.writer.directory.absolute()
        while not where.exists() and where != where.parent:
            where = where.parent   # the directory is made at the first write: its file system is the parent's
        try:
            free = self.disk_usage(where).free
        except OSError:
            return True   # cannot be asked: keep recording
        if free < self.min_free:
            self.stats.stopped_reason = (f"free space on {self.writer.directory} is {free / 1e6:.0f} MB, below the "
                                         f"{self.min_free / 1e6:.0f} MB floor (min_free_mb): recording stopped; "
                                         "free some space and restart the recorder")
            return False
        return True

    def _halt(self, reason: str) -> None:
        """Stop recording on an error: refuse new messages, count the queued ones as dropped, finish the file."""
        self.active = False
        if reason:
            self.stats.stopped_reason = reason
        log.error(self.stats.stopped_reason)
        self._count_unwritten()
        self._close_writer()

    def _count_unwritten(self) -> None:
        """Empty the queue, counting its messages as dropped."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                self.stats.dropped += 1

    def _close_writer(self) -> None:
        """Finish the current file; what a write error cut off moves from written to dropped, and is said."""
        try:
            self.writer.close()
        except OSError as exc:
            self._say(f"cannot finish the file in {self.writer.directory} ({exc}): repair it with u2sa log recover")
        lost, self._lost_seen = self.writer.lost - self._lost_seen, self.writer.lost
        self.stats.written -= lost
        self.stats.dropped += lost
        for line in self.writer.cut_short[self._cuts_seen:]:
            self._say(line)
        self._cuts_seen = len(self.writer.cut_short)

    def _say(self, what: str) -> None:
        """Log *what* and add it to the stopped reason (a file finished early stops the recording too)."""
        log.error(what)
        self.stats.stopped_reason = f"{self.stats.stopped_reason}; {what}" if self.stats.stopped_reason else what

    def _drain(self) -> None:
        if not self._space_ok():
            self._halt("")
            return
        next_flush = time.monotonic() + self.flush_interval
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                if self._finish.is_set():
                    break   # stop() asked (its end marker may not have fit in the queue), and everything is written
                # Woken every DRAIN_POLL_S, not by each message: at thousands of messages a second a wake-up per
                # message cost the bus's handler thread (and the process's GIL) more than writing them.
                self._finish.wait(max(0.0, min(DRAIN_POLL_S, next_flush - time.monotonic())))
                item = ()
            if item is None:
                break
            if item:
                channel, data, t_ns, signer, trailer = item
                try:
                    self.writer.write(channel, data, t_ns, signer, trailer)
                except OSError as exc:
                    self.stats.dropped += 1   # this message: in no file
                    self._halt(f"cannot write {self.writer.directory}: {exc}; recording stopped")
                    return
                self.stats.written += 1
                self.stats.per_channel[channel] = self.stats.per_channel.get(channel, 0) + 1
            if time.monotonic() >= next_flush:
                next_flush = time.monotonic() + self.flush_interval
                try:
                    self.writer.flush()
                except OSError as exc:
                    self._halt(f"cannot flush {self.writer.directory}: {exc}; recording stopped")
                    return
                if not self._space_ok():
                    self._halt("")
                    return
        self._close_writer()

    def stop(self) -> None:
        """Stop capturing, write what is queued and finish the file; never blocks on a full queue."""
        self.active = False
        if self._sub is not None:
            self.transport.unsubscribe(self._sub)
            self._sub = None
        thread, self._thread = self._thread, None
        if thread is not None and thread.is_alive():
            self._finish.set()
            try:
                self._queue.put_nowait(None)
            except queue.Full:
                pass   # the writer sees _finish once it has emptied the queue
            thread.join(timeout=JOIN_TIMEOUT_S)
            if thread.is_alive():
                log.error("the recorder's writer did not finish %s within %g s (disk stalled?); the file is left "
                          "unfinished: repair it with u2sa log recover", self.writer.directory, JOIN_TIMEOUT_S)
                return
        self._count_unwritten()   # put by a handler that ran as the writer stopped on an error
        self._close_writer()   # nothing open when the writer thread finished it already

    @property
    def queue_depth(self) -> int:
        """Messages waiting for the writer."""
        return self._queue.qsize()
