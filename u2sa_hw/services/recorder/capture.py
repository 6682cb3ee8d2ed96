"""Capture from the bus into an MCAP writer without ever blocking the bus.

The LCM handler thread only appends ``(channel, bytes, time)`` to a bounded queue; a
writer thread drains it into :class:`McapLogWriter`, closing a chunk every
``flush_interval_s`` and checking the free disk space. A full queue drops the message and
counts it; a disk below the floor stops the recording cleanly with the reason.
"""

from __future__ import annotations

import logging
import queue
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from u2sa_hw.recording.mcap_log import McapLogWriter
from u2sa_hw.transport import Transport

log = logging.getLogger("u2sa_hw.recorder")


@dataclass
class CaptureStats:
    """Counters for health and the command line."""

    received: int = 0
    written: int = 0
    dropped: int = 0
    filtered: int = 0
    stopped_reason: str = ""
    per_channel: dict[str, int] = field(default_factory=dict)


class BusCapture:
    """Subscribes to every channel and feeds a writer thread through a bounded queue."""

    def __init__(self, transport: Transport, writer: McapLogWriter, *, include: str = ".*", exclude: str = "",
                 queue_size: int = 20000, flush_interval_s: float = 1.0, min_free_mb: float = 200.0) -> None:
        try:
            self._include = re.compile(include or ".*")
            self._exclude = re.compile(exclude) if exclude else None
        except re.error as exc:
            raise ValueError(f"bad channel pattern: {exc}") from None
        self.transport = transport
        self.writer = writer
        self.flush_interval = min(1.0, max(0.05, flush_interval_s))
        self.min_free = min_free_mb * 1e6
        self.stats = CaptureStats()
        self._queue: queue.Queue[tuple[str, bytes, int] | None] = queue.Queue(maxsize=queue_size)
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
        try:
            self._queue.put_nowait((channel, data, time.time_ns()))
        except queue.Full:
            self.stats.dropped += 1

    def start(self) -> None:
        """Subscribe and start the writer thread."""
        self.active = True
        self._thread = threading.Thread(target=self._drain, name="recorder-writer", daemon=True)
        self._thread.start()
        self._sub = self.transport.subscribe(".*", None, self._on_message, raw=True)

    def _space_ok(self) -> bool:
        try:
            free = shutil.disk_usage(self.writer.directory).free
        except OSError:
            return True
        if free < self.min_free:
            self.stats.stopped_reason = (f"free space on {self.writer.directory} is {free / 1e6:.0f} MB, below the "
                                         f"{self.min_free / 1e6:.0f} MB floor: recording stopped")
            log.error(self.stats.stopped_reason)
            return False
        return True

    def _drain(self) -> None:
        next_flush = time.monotonic() + self.flush_interval
        while True:
            timeout = max(0.0, next_flush - time.monotonic())
            try:
                item = self._queue.get(timeout=timeout)
            except queue.Empty:
                item = ()
            if item is None:
                break
            if item:
                channel, data, t_ns = item
                try:
                    self.writer.write(channel, data, t_ns)
                except OSError as exc:
                    self.stats.stopped_reason = f"cannot write {self.writer.directory}: {exc}; recording stopped"
                    log.error(self.stats.stopped_reason)
                    self.active = False
                    break
                self.stats.written += 1
                self.stats.per_channel[channel] = self.stats.per_channel.get(channel, 0) + 1
            if time.monotonic() >= next_flush:
                next_flush = time.monotonic() + self.flush_interval
                try:
                    self.writer.flush()
                except OSError as exc:
                    self.stats.stopped_reason = f"cannot flush {self.writer.directory}: {exc}; recording stopped"
                    log.error(self.stats.stopped_reason)
                    self.active = False
                    break
                if not self._space_ok():
                    self.active = False
                    break

    def stop(self) -> None:
        """Stop capturing, write what is queued, finish the file."""
        self.active = False
        if self._sub is not None:
            self.transport.unsubscribe(self._sub)
            self._sub = None
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=30)
            self._thread = None
        try:
            self.writer.close()
        except OSError as exc:
            log.error("closing %s failed: %s", self.writer.directory, exc)

    @property
    def queue_depth(self) -> int:
        """Messages waiting for the writer."""
        return self._queue.qsize()
