"""Test helper: a driver's-eye view of a serial mock (pyserial on its address, lines split at LF)."""

from __future__ import annotations

import time
from typing import Callable

import pytest
import serial
from pynmeagps import NMEAMessage, NMEAReader
from pynmeagps.exceptions import NMEAParseError


class SerialLineReader:
    """Opens *address* with pyserial as a driver would and hands out complete lines."""

    def __init__(self, address: str, *, baudrate: int = 9600) -> None:
        self.port = serial.Serial(address, baudrate, timeout=0.05)
        self._buf = bytearray()

    def close(self) -> None:
        self.port.close()

    def __enter__(self) -> "SerialLineReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def next_line(self, *, timeout: float = 5.0) -> bytes:
        """The next complete line (with its CR LF); fails the test after *timeout*."""
        deadline = time.monotonic() + timeout
        while b"\n" not in self._buf:
            if time.monotonic() > deadline:
                pytest.fail(f"no complete line from {self.port.port} within {timeout:g} s (have {bytes(self._buf)!r})")
            self._buf.extend(self.port.read(512))
        line, _, rest = bytes(self._buf).partition(b"\n")
        self._buf[:] = rest
        return line + b"\n"

    def next_matching(self, predicate: Callable[[bytes], bool], *, timeout: float = 5.0) -> bytes:
        """The next line for which *predicate* is true, skipping others."""
        deadline = time.monotonic() + timeout
        while True:
            line = self.next_line(timeout=max(0.0, deadline - time.monotonic()))
            if predicate(line):
                return line

    def next_sentence(self, msg_id: str, *, timeout: float = 5.0) -> NMEAMessage:
        """The next NMEA sentence of type *msg_id* (e.g. "GGA"), checksum verified by pynmeagps."""
        line = self.next_matching(lambda l: l[3:7] == f"{msg_id},".encode() and l.startswith(b"$"), timeout=timeout)
        return parse_nmea(line)

    def skip_past(self, data: bytes, *, timeout: float = 5.0) -> bytes:
        """Read until *data* has arrived, drop everything up to its end and return what was dropped."""
        deadline = time.monotonic() + timeout
        while data not in self._buf:
            if time.monotonic() > deadline:
                pytest.fail(f"{data[:16]!r}... did not arrive from {self.port.port} within {timeout:g} s")
            self._buf.extend(self.port.read(512))
        end = self._buf.index(data) + len(data)
        dropped = bytes(self._buf[:end])
        del self._buf[:end]
        return dropped

    def drain(self) -> None:
        """Drop everything received so far (kernel buffer and partial line)."""
        self.port.reset_input_buffer()
        self._buf.clear()

    def pending(self) -> int:
        """Bytes waiting unread (kernel buffer plus partial line)."""
        return self.port.in_waiting + len(self._buf)


def parse_nmea(line: bytes) -> NMEAMessage:
    """*line* parsed by pynmeagps with checksum validation (NMEAParseError when invalid)."""
    msg = NMEAReader.parse(line)
    if msg is None:
        raise NMEAParseError(f"pynmeagps does not know {line!r}")
    return msg
