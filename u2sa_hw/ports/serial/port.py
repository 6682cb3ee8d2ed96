"""Serial ports: a device path (``/dev/u2sa/gps``, a symlink to a pty) or a pyserial URL.

``open_serial`` opens paths with ``serial.Serial`` (exclusively locked, so two services
cannot read the same GPS) and URLs (``loop://``, ``socket://host:port``, ``spy://...``,
``rfc2217://...``) with ``serial.serial_for_url``. pyserial's exceptions are mapped to the
port error hierarchy: failing to open is ``PortUnavailable`` (with the group to join, the
udev rule to check or the process holding the port), and any failure of an open port
(pty master closed, USB adapter unplugged, socket dropped) is ``PortClosed``.

Every chunk read from the device is tapped as a ``RawSerial`` RX record, every write as TX. A
``readline`` that times out empty (the silence a driver ends a burst on) is tapped as an RX record
without data, once per silence: a log then says where the live driver saw a silence, which the
read times alone cannot (a driver busy between two reads left the bytes waiting in the device:
a gap in the read times, no silence). A replay hands the driver those silences and no others
(:mod:`u2sa_hw.ports.serial.clock`); readers of the data bytes see nothing of them.
"""

from __future__ import annotations

import logging
import threading

import serial

from u2sa_hw.messages import RawSerial
from u2sa_hw.ports.errors import PortClosed, PortTimeout
from u2sa_hw.ports.tap import RX, TX, Tap, call_tap, tapping

log = logging.getLogger(__name__)

MAX_LINE = 4096  # readline() gives up waiting for b"\n" after this many bytes (garbage)


def is_serial_url(address: str) -> bool:
    """True if *address* is a pyserial URL (``scheme://...``) rather than a device path."""
    return "://" in address


class SerialPort:
    """An open serial port; reads and writes bytes, taps them, and maps errors.

    ``read`` and ``readline`` return ``b""`` when nothing arrives within the timeout.
    ``readline`` returns only complete lines: a partial line stays buffered for the next
    call (and for ``read``), so a driver never sees half an NMEA sentence as a line. An empty
    ``readline`` is tapped as an RX record without data, once per silence (module docstring).
    ``device_clock`` is False: an empty ``readline`` is a silence of the device
    (:meth:`went_quiet`), and a line's time is the reader's clock (a replay's
    :class:`~u2sa_hw.ports.serial.clock.StampedSerialPort` says otherwise).
    """

    device_clock = False

    def __init__(self, handle: serial.SerialBase, *, device: str, address: str, tap: Tap | None = None,
                 pyserial_url: bool | None = None) -> None:
        self.device = device
        self.address = address
        # a pyserial URL (socket://, rfc2217://) rather than a device path: as the address said, else from the text
        self.pyserial_url = is_serial_url(address) if pyserial_url is None else pyserial_url
        self._serial = handle
        self._tap = tap
        self._buffer = bytearray()
        self._read_lock = threading.Lock()
        self._closed = False
        self._silence_tapped = False   # the current silence has its record (no data read since)

    @property
    def framing(self) -> str:
        """The framing applied to the device: data bits, parity, stop bits (``8N1``, ``7E2``)."""
        handle = self._serial
        return f"{handle.bytesize}{handle.parity}{float(handle.stopbits):g}"

    @property
    def is_open(self) -> bool:
        """True until the port is closed or the device is lost."""
        return not self._closed and bool(self._serial.is_open)

    def _lost(self, exc: BaseException, action: str) -> PortClosed:
        """Close the dead handle and build the PortClosed to raise."""
        self._closed = True
        try:
            self._serial.close()
        except Exception:  # noqa: BLE001 - the device is already gone; closing is best effort
            pass
        if self.pyserial_url:
            fix = f"restore the connection to {self.address}; ReconnectingPort reopens it"
        else:
            fix = "plug the device back in (for a pty: restart the mock device); ReconnectingPort reopens it"
        return PortClosed(self.device, f"{action} failed, device lost ({exc})", address=self.address, fix=fix)

    def _check_open(self) -> None:
        if self._closed:
            raise PortClosed(self.device, "port is closed", address=self.address,
                             fix="open the port again (ReconnectingPort does this)")

    def _read_raw(self, size: int) -> bytes:
        """Read up to *size* bytes from the device, waiting up to the timeout."""
        self._check_open()
        try:
            return self._serial.read(size)
        except (serial.SerialException, OSError, TypeError, ValueError) as exc:
            # TypeError/ValueError: pyserial's select() on a handle closed underneath it.
            raise self._lost(exc, "read") from exc

    def _tapped(self, data: bytes) -> bytes:
        if data:
            self._silence_tapped = False
            if tapping(self._tap):
                call_tap(self._tap, _record(self.device, RX, data))
        return data

    def _tap_silence(self) -> None:
        """A ``readline`` timed out empty: tap an RX record without data, the first time since data came (one
        record per silence, not per empty read of a quiet line)."""
        if self._silence_tapped:
            return
        self._silence_tapped = True
        if tapping(self._tap):
            call_tap(self._tap, _record(self.device, RX, b""))

    def _read_waiting(self) -> bytes:
        """Wait up to the timeout for one byte, then take whatever else is waiting (not tapped)."""
        data = self._read_raw(1)
        if data:
            try:
                waiting = self._serial.in_waiting
            except (serial.SerialException, OSError) as exc:
                raise self._lost(exc, "read") from exc
            if waiting:
                data += self._read_raw(waiting)
        return data

    def _read_available(self) -> bytes:
        """What :meth:`_read_waiting` gives, tapped."""
        return self._tapped(self._read_waiting())

    def line_time_ns(self) -> int | None:
        """The device's time of the last line: None, a real port has no device clock."""
        return None

    def went_quiet(self) -> bool:
        """True: an empty ``readline`` of a real port is the device falling silent for the timeout."""
        return True

    def read(self, size: int = 1) -> bytes:
        """Up to *size* bytes, buffered ones first; like pyserial it waits up to the timeout
        for the rest (``b""`` if nothing came)."""
        with self._read_lock:
            data = bytes(self._buffer[:size])
            del self._buffer[:size]
            if len(data) < size:
                data += self._tapped(self._read_raw(size - len(data)))
            return data

    def readline(self) -> bytes:
        """One line ending in ``b"\\n"``, or ``b""`` if none completes before the device falls
        silent for a timeout. A run of MAX_LINE bytes without a newline is returned as is."""
        with self._read_lock:
            while b"\n" not in self._buffer and len(self._buffer) < MAX_LINE:
                chunk = self._read_available()
                if not chunk:
                    self._tap_silence()
                    return b""
                self._buffer += chunk
            end = self._buffer.find(b"\n")
            end = end + 1 if end >= 0 else MAX_LINE
            line = bytes(self._buffer[:end])
            del self._buffer[:end]
            return line

    def write(self, data: bytes) -> int:
        """Write *data*; returns the number of bytes written (tapped as TX)."""
        self._check_open()
        data = bytes(data)
        try:
            written = self._serial.write(data)
        except serial.SerialTimeoutException as exc:
            raise PortTimeout(self.device, f"write timed out ({exc})", address=self.address,
                              fix="the device does not accept data: check flow control and the cable") from exc
        except (serial.SerialException, OSError, TypeError, ValueError) as exc:
            raise self._lost(exc, "write") from exc
        written = len(data) if written is None else written
        if written and tapping(self._tap):
            call_tap(self._tap, _record(self.device, TX, data[:written]))
        return written

    def close(self) -> None:
        """Close the port (idempotent)."""
        self._closed = True
        try:
            self._serial.close()
        except (serial.SerialException, OSError) as exc:
            log.debug("%s: closing %s: %s", self.device, self.address, exc)

    def __enter__(self) -> SerialPort:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "open" if self.is_open else "closed"
        return f"<SerialPort {self.device} {self.address} {state}>"


def _record(device: str, direction: int, data: bytes) -> RawSerial:
    record = RawSerial()
    record.device = device
    record.direction = direction
    record.length = len(data)
    record.data = data
    return record
