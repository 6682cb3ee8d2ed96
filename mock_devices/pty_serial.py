"""A serial device on a pseudo-terminal, reachable by a driver at a symlink like a USB adapter.

``PtySerialDevice`` holds a pty at a symlink (say ``/tmp/sim/gps``, pointing at the slave
``/dev/pts/N``; the pty itself is :class:`u2sa_hw.ports.serial.pty_link.PtyLink`, which the
replay's serial device uses too): a driver opens the symlink with pyserial exactly as it
would open ``/dev/u2sa/gps``. The mock writes to the master side; a reader
thread keeps what the driver writes, with timestamps.

Faults, as the driver sees them through pyserial:

- ``inject_garbage(n)``: n random bytes appear in the stream.
- ``silence(True)``: the device stops writing (writes are discarded) until ``silence(False)``.
- ``disconnect()``: the master is closed and the symlink removed, as when a USB adapter is
  unplugged. pyserial's ``read()`` on the still-open port raises ``SerialException``
  ("device reports readiness to read but returned no data"), ``write()`` raises
  ``SerialException`` ("write failed: [Errno 5] Input/output error"), and reopening fails
  with "No such file or directory" until ``reconnect()``.
- ``reconnect()``: a new pty, the symlink re-pointed at it atomically (rename over it).

``line_settings()`` reads back the line settings the driver applied through its end, as the
kernel keeps them: the baud rate and the stop bits. (Linux ptys force 8 data bits and no
parity whatever the driver asks, so those two cannot be observed on a pty.)

A pty has no baud rate: the driver may set any rate and bytes move at memory speed. The
mock holds its own slave descriptor so the master never sees EIO while no driver has the
port open; bytes written then wait in the kernel buffer and pyserial flushes them when it
opens the port. The master is non-blocking: when the driver does not read and the kernel
buffer is full, further bytes are dropped and counted (``dropped_bytes``), as a UART would.

``PeriodicSerialDevice`` is the base of the mock sensors that send an epoch of lines at a
rate (GPS, compasses): it owns a ``PtySerialDevice`` as ``link`` and adds the history of
sent lines and ``bad_checksums(on)`` to the link's faults.
"""

from __future__ import annotations

import logging
import os
import random
import termios
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from u2sa_hw.mocks.vehicle_sim import SimVehicle, VehicleTruth
from u2sa_hw.ports.serial.pty_link import PtyLink

log = logging.getLogger(__name__)

TX = "tx"  # device -> driver
RX = "rx"  # driver -> device


@dataclass(frozen=True)
class SerialRecord:
    """One chunk of bytes that crossed the link; ``t`` is time.monotonic(), ``note`` e.g. "garbage"."""

    t: float
    direction: str
    data: bytes
    note: str = ""


@dataclass(frozen=True)
class LineSettings:
    """The line settings the kernel holds for the pty: ``baudrate`` (bit/s) and ``stopbits`` (1 or 2)."""

    baudrate: int
    stopbits: int


_SPEEDS = {getattr(termios, f"B{rate}"): rate for rate in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200,
                                                             230400, 460800, 921600) if hasattr(termios, f"B{rate}")}


class PtySerialDevice:
    """A pty whose slave is reachable at *link_path*; write() sends bytes to the driver."""

    def __init__(self, *, link_path: str | os.PathLike[str], name: str = "serial",
                 on_receive: Callable[[bytes], None] | None = None, history_size: int = 10_000,
                 seed: int = 0) -> None:
        self.link_path = Path(link_path)
        self.name = name
        self.on_receive = on_receive
        self._history: deque[SerialRecord] = deque(maxlen=history_size)
        self._rng = random.Random(seed)
        self._lock = threading.Lock()  # guards _pair against write/disconnect races
        self._pair: PtyLink | None = None
        self._silent = False
        self.dropped_bytes = 0

    # ---- lifecycle -------------------------------------------------------------------
    @property
    def address(self) -> str:
        """The path a driver config names (the symlink)."""
        return str(self.link_path)

    @property
    def port_name(self) -> str | None:
        """The current slave device (/dev/pts/N), None while disconnected."""
        pair = self._pair
        return pair.slave_name if pair else None

    @property
    def connected(self) -> bool:
        """True while the device is 'plugged in'."""
        return self._pair is not None

    def line_settings(self) -> LineSettings:
        """The baud rate and stop bits the driver set on its end (the master shares the slave's termios)."""
        pair = self._pair
        if pair is None:
            raise RuntimeError(f"{self.name}: not connected; start() or reconnect() first")
        attrs = pair.termios_attrs()
        return LineSettings(baudrate=_SPEEDS.get(attrs[4], 0), stopbits=2 if attrs[2] & termios.CSTOPB else 1)

    def start(self) -> None:
        """Create the pty and the symlink (a no-op when already connected)."""
        with self._lock:
            if self._pair is None:
                self._plug()

    def stop(self) -> None:
        """Close the pty and remove the symlink."""
        self.disconnect()

    def disconnect(self) -> None:
        """Unplug: close the master (the driver's reads and writes fail) and remove the symlink."""
        with self._lock:
            pair, self._pair = self._pair, None
        if pair is None:
            return
        pair.close()
        log.info("%s: disconnected %s (%s)", self.name, self.link_path, pair.slave_name)

    def reconnect(self) -> None:
        """Replug: a new pty, with the symlink re-pointed at it atomically."""
        self.disconnect()
        self.start()

    def _plug(self) -> None:
        pair = PtyLink(link_path=self.link_path, name=self.name, on_data=self._received)
        pair.open()
        self._pair = pair
        log.info("%s: %s -> %s", self.name, self.link_path, pair.slave_name)

    # ---- writing ---------------------------------------------------------------------
    def write(self, data: bytes, *, note: str = "") -> int:
        """Send *data* to the driver; returns the bytes accepted (0 when silent or unplugged)."""
        if self._silent:
            return 0
        return self._write(data, note)

    def _write(self, data: bytes, note: str) -> int:
        if not data:
            return 0
        with self._lock:
            pair = self._pair
            if pair is None:
                return 0
            try:
                n = pair.write(data)
            except OSError as exc:  # EIO: the pty went away under us
                log.warning("%s: write to %s failed: %s", self.name, pair.slave_name, exc)
                n = 0
        if n < len(data):
            self.dropped_bytes += len(data) - n
        if n:
            self._history.append(SerialRecord(time.monotonic(), TX, bytes(data[:n]), note))
        return n

    def inject_garbage(self, n: int) -> bytes:
        """Write *n* seeded random bytes into the stream (even while silenced); returns them."""
        garbage = bytes(self._rng.randrange(256) for _ in range(n))
        self._write(garbage, "garbage")
        return garbage

    def silence(self, on: bool) -> None:
        """Stop (True) or resume (False) sending; the link stays up."""
        self._silent = bool(on)

    @property
    def silenced(self) -> bool:
        """True while silence(True) is in effect."""
        return self._silent

    # ---- reading ---------------------------------------------------------------------
    def _received(self, data: bytes) -> None:
        self._history.append(SerialRecord(time.monotonic(), RX, data))
        if self.on_receive is not None:
            try:
                self.on_receive(data)
            except Exception:  # a device model's bug must not kill the link
                log.exception("%s: on_receive handler failed on %r", self.name, data[:64])

    @property
    def history(self) -> list[SerialRecord]:
        """Everything sent (tx) and received (rx), oldest first, up to history_size records."""
        return list(self._history)

    def received(self) -> bytes:
        """All bytes the driver has written so far, concatenated."""
        return b"".join(r.data for r in list(self._history) if r.direction == RX)


def corrupt_checksum(line: bytes) -> bytes:
    """*line* (``...*HH\\r\\n``) with its two checksum digits replaced by a wrong value."""
    star = line.rfind(b"*")
    try:
        good = int(line[star + 1:star + 3], 16)
    except ValueError:
        return line  # no checksum to corrupt
    return line[:star + 1] + f"{good ^ 0x5A:02X}".encode() + line[star + 3:]


@dataclass(frozen=True)
class SentLine:
    """One line a device sent: ``t`` time.monotonic(), ``text`` without CR LF, ``valid`` False
    when bad_checksums() corrupted it."""

    t: float
    text: str
    valid: bool


class PeriodicSerialDevice(ABC):
    """Base of mock serial sensors that write an epoch of lines at *rate_hz* from the vehicle truth.

    A subclass implements ``epoch_lines(truth)``; this class runs the pty link, the timing,
    the history of sent lines and the faults every such sensor has.
    """

    def __init__(self, vehicle: SimVehicle, *, link_path: str | os.PathLike[str], rate_hz: float, name: str,
                 seed: int = 0, history_size: int = 10_000) -> None:
        if not rate_hz > 0:
            raise ValueError(f"{name}: rate_hz must be > 0, got {rate_hz!r}")
        self.vehicle = vehicle
        self.rate_hz = float(rate_hz)
        self.name = name
        self.rng = random.Random(seed)  # the device's measurement noise
        self.link = PtySerialDevice(link_path=link_path, name=name, seed=seed, on_receive=self.on_command,
                                    history_size=history_size)
        self._bad_checksums = False
        self.epochs = 0  # emit_once() calls so far, whether or not anything went out
        self._sent: deque[SentLine] = deque(maxlen=history_size)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    @abstractmethod
    def epoch_lines(self, truth: VehicleTruth) -> list[bytes]:
        """The complete lines (checksummed, CR LF ended) this device sends for one epoch."""

    def on_command(self, data: bytes) -> None:
        """Bytes the driver wrote; ignored by default (they stay in ``link.history``)."""

    def emit_once(self) -> int:
        """Sample the vehicle and write one epoch of lines now; returns how many lines went out."""
        sent = 0
        for line in self.epoch_lines(self.vehicle.snapshot()):
            valid = not self._bad_checksums
            if not valid:
                line = corrupt_checksum(line)
            if self.link.write(line) == len(line):  # a partial write is counted in link.dropped_bytes
                self._sent.append(SentLine(time.monotonic(), line.decode("ascii").rstrip("\r\n"), valid))
                sent += 1
        self.epochs += 1
        return sent

    # ---- lifecycle -------------------------------------------------------------------
    @property
    def address(self) -> str:
        """The path a driver config names (the pty symlink)."""
        return self.link.address

    @property
    def history(self) -> list[SentLine]:
        """The lines sent so far, oldest first (silenced or unplugged epochs are not in it)."""
        return list(self._sent)

    def start(self) -> None:
        """Plug the link in and start sending at rate_hz."""
        self.link.start()
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, daemon=True, name=f"{type(self).__name__}-{self.name}")
            self._thread.start()

    def stop(self) -> None:
        """Stop sending and unplug the link."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.link.stop()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            try:
                self.emit_once()
            except Exception:  # one bad epoch must not end the device
                log.exception("%s: failed to build or send an epoch", self.name)
            next_t += period
            if time.monotonic() - next_t > 1.0:
                next_t = time.monotonic()

    # ---- faults ----------------------------------------------------------------------
    def bad_checksums(self, on: bool) -> None:
        """Send every line with a wrong checksum (True) or correct ones again (False)."""
        self._bad_checksums = bool(on)

    def inject_garbage(self, n: int) -> bytes:
        """Write *n* seeded random bytes between lines; returns them."""
        return self.link.inject_garbage(n)

    def silence(self, on: bool) -> None:
        """Stop (True) or resume (False) sending; the port stays open."""
        self.link.silence(on)

    def disconnect(self) -> None:
        """Unplug the device: the driver's port fails and the path disappears."""
        self.link.disconnect()

    def reconnect(self) -> None:
        """Plug the device back in at the same path (a new pty)."""
        self.link.reconnect()
