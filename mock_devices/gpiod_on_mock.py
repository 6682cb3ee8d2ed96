"""libgpiod's kernel calls answered by mock GPIO chips, so the gpiod backend runs without a kernel chip.

This machine has no ``/dev/gpiochip*`` and no gpio-sim (configfs is not mounted), so the
port's gpiod backend (``u2sa_hw.ports.gpio.gpiod_backend.GpiodGpioPort``) cannot reach a kernel
chip. ``GpiodOnMockChips`` stands in for the two libgpiod v2 calls that open the kernel's
character device -- ``gpiod.request_lines(path, config=..., consumer=...)`` and
``gpiod.Chip(path)`` -- and answers them from a :class:`~u2sa_hw.mocks.gpio_chip.MockGpioChip`
over its socket, so the chip's own semantics (EBUSY naming the consumer, per-request
edges with timestamps, release on close) are the ones the mock backend is tested against.
Everything else is libgpiod's own: ``gpiod.LineSettings``, the ``gpiod.line`` enums,
``gpiod.EdgeEvent.Type`` and ``gpiod.RequestReleasedError``.

What the fake request does, as the kernel would: ``get_value`` / ``set_value`` with
``gpiod.line.Value``; ``wait_edge_events(timeout)`` and ``read_edge_events()`` with events
carrying ``event_type``, ``timestamp_ns``, ``line_offset``, ``global_seqno``,
``line_seqno``; ``release()``, after which every call raises RequestReleasedError. A path
nobody attached fails with ENOENT, lines in use with EBUSY, bad settings with EINVAL, and
a chip that went away fails every call with ENODEV. Install it with
``monkeypatch.setattr(gpiod, "request_lines", fake.request_lines)`` and
``monkeypatch.setattr(gpiod, "Chip", fake.Chip)``.
"""

from __future__ import annotations

import errno
import json
import os
import socket
import threading
from collections import deque
from dataclasses import dataclass
from datetime import timedelta
from types import SimpleNamespace
from typing import Any, Iterable

import gpiod
from gpiod.line import Bias, Direction, Edge, Value

from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.ports.gpio.wire import (EDGE_RISING, MOCK_EDGE, MOCK_EDGE_RECORD, MockFrameReader, MockProtocolError,
                                     encode_mock_json)

_BIAS = {Bias.AS_IS: "as-is", Bias.PULL_UP: "pull-up", Bias.PULL_DOWN: "pull-down", Bias.DISABLED: "disabled"}
_EDGE = {Edge.NONE: "none", Edge.RISING: "rising", Edge.FALLING: "falling", Edge.BOTH: "both"}
REPLY_TIMEOUT = 5.0


def _os_error(code: int, detail: str = "") -> OSError:
    return OSError(code, os.strerror(code) + (f" ({detail})" if detail else ""))


@dataclass(frozen=True)
class MockEdgeEvent:
    """What ``gpiod.EdgeEvent`` carries."""

    event_type: gpiod.EdgeEvent.Type
    timestamp_ns: int
    line_offset: int
    global_seqno: int
    line_seqno: int


class _Connection:
    """One socket to a mock chip: JSON calls and the edge events of this request."""

    def __init__(self, socket_path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.sock.connect(socket_path)
        except OSError:
            self.sock.close()
            raise _os_error(errno.ENODEV, f"the mock chip at {socket_path} is not there") from None
        self.cond = threading.Condition()
        self.replies: dict[int, dict[str, Any]] = {}
        self.edges: deque[MockEdgeEvent] = deque(maxlen=1024)
        self.lost = False
        self._next_id = 0
        threading.Thread(target=self._read, daemon=True, name="gpiod-on-mock").start()

    def _read(self) -> None:
        frames = MockFrameReader()
        try:
            while data := self.sock.recv(65536):
                for kind, payload in frames.feed(data):
                    self._dispatch(kind, payload)
        except (OSError, MockProtocolError, ValueError):
            pass
        with self.cond:
            self.lost = True
            self.cond.notify_all()

    def _dispatch(self, kind: bytes, payload: bytes) -> None:
        with self.cond:
            if kind == MOCK_EDGE:
                etype, line, stamp, global_seq, line_seq = MOCK_EDGE_RECORD.unpack(payload)
                rising = gpiod.EdgeEvent.Type.RISING_EDGE if etype == EDGE_RISING else gpiod.EdgeEvent.Type.FALLING_EDGE
                self.edges.append(MockEdgeEvent(rising, stamp, line, global_seq, line_seq))
            else:
                reply = json.loads(payload)
                self.replies[int(reply.get("id", -1))] = reply
            self.cond.notify_all()

    def call(self, **request: Any) -> dict[str, Any]:
        with self.cond:
            self._next_id += 1
            request["id"] = call_id = self._next_id
        try:
            self.sock.sendall(encode_mock_json(request))
        except OSError:
            raise _os_error(errno.ENODEV, "the chip went away") from None
        with self.cond:
            self.cond.wait_for(lambda: call_id in self.replies or self.lost, REPLY_TIMEOUT)
            reply = self.replies.pop(call_id, None)
        if reply is None:
            raise _os_error(errno.ENODEV if self.lost else errno.ETIMEDOUT, "the chip went away")
        return reply

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class MockLineRequest:
    """What the port uses of ``gpiod.LineRequest``, on a mock chip."""

    def __init__(self, connection: _Connection) -> None:
        self._conn = connection
        self._released = False

    def _check(self) -> _Connection:
        if self._released:
            raise gpiod.RequestReleasedError()
        return self._conn

    @staticmethod
    def _answer(reply: dict[str, Any]) -> dict[str, Any]:
        if not reply.get("ok"):
            code = {"EPERM": errno.EPERM, "EBUSY": errno.EBUSY}.get(reply.get("error"), errno.EINVAL)
            raise _os_error(code, str(reply.get("message", "")))
        return reply

    def get_value(self, offset: int) -> Value:
        """The line's level."""
        reply = self._answer(self._check().call(op="get", lines=[offset]))
        return Value.ACTIVE if reply["values"][0] else Value.INACTIVE

    def set_value(self, offset: int, value: Value) -> None:
        """Drive an output line."""
        self._answer(self._check().call(op="set", values={str(offset): 1 if value == Value.ACTIVE else 0}))

    def wait_edge_events(self, timeout: timedelta | float | None = None) -> bool:
        """True once an edge is waiting (False after *timeout*); ENODEV once the chip is gone."""
        conn = self._check()
        seconds = timeout.total_seconds() if isinstance(timeout, timedelta) else timeout
        with conn.cond:
            conn.cond.wait_for(lambda: conn.edges or conn.lost, seconds)
            if conn.edges:
                return True
            if conn.lost:
                raise _os_error(errno.ENODEV, "the chip went away")
        return False

    def read_edge_events(self, max_events: int | None = None) -> list[MockEdgeEvent]:
        """The waiting edges, oldest first (up to *max_events*)."""
        conn = self._check()
        with conn.cond:
            if not conn.edges and conn.lost:
                raise _os_error(errno.ENODEV, "the chip went away")
            count = len(conn.edges) if max_events is None else min(max_events, len(conn.edges))
            return [conn.edges.popleft() for _ in range(count)]

    def release(self) -> None:
        """Release the lines (the next call raises RequestReleasedError)."""
        if self._released:
            return
        self._released = True
        if not self._conn.lost:
            try:
                self._conn.call(op="release")
            except OSError:
                pass
        self._conn.close()


class GpiodOnMockChips:
    """Kernel chip paths (``/dev/gpiochip7``) answered by mock chips; see the module docstring."""

    def __init__(self) -> None:
        self._chips: dict[str, str] = {}
        fake = self

        class MockChip:
            """What the port uses of ``gpiod.Chip``: line info, as a context manager."""

            def __init__(self, path: str) -> None:
                self.path = path
                self._socket = fake._socket(path)

            def get_line_info(self, offset: int) -> SimpleNamespace:
                conn = _Connection(self._socket)
                try:
                    used = conn.call(op="info").get("lines", {})
                finally:
                    conn.close()
                line = used.get(str(offset))
                return SimpleNamespace(offset=offset, used=line is not None,
                                       consumer=line["consumer"] if line else "")

            def close(self) -> None:
                """Nothing held open."""

            def __enter__(self) -> "MockChip":
                return self

            def __exit__(self, *exc: object) -> None:
                self.close()

        self.Chip = MockChip

    def attach(self, path: str, chip: MockGpioChip) -> None:
        """Answer the kernel chip *path* from *chip* (which must be started)."""
        self._chips[path] = chip.socket_path

    def _socket(self, path: str) -> str:
        socket_path = self._chips.get(path)
        if socket_path is None or not os.path.exists(socket_path):
            raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), path)
        return socket_path

    def request_lines(self, path: str, config: dict[Any, Any], consumer: str | None = None,
                      event_buffer_size: int | None = None,
                      output_values: dict[Any, Value] | None = None) -> MockLineRequest:
        """``gpiod.request_lines``: the lines of *config* ({offset or offsets: LineSettings}) as one request."""
        socket_path = self._socket(path)
        lines: dict[str, dict[str, Any]] = {}
        for key, settings in config.items():
            offsets: Iterable[Any] = key if isinstance(key, (tuple, list, frozenset, set)) else (key,)
            settings = settings or gpiod.LineSettings()
            for offset in offsets:
                if not isinstance(offset, int):
                    raise ValueError(f"line names are not supported by the mock chip, got {offset!r}")
                if settings.direction == Direction.OUTPUT:
                    value = (output_values or {}).get(offset, settings.output_value)
                    lines[str(offset)] = {"direction": "output", "value": 1 if value == Value.ACTIVE else 0,
                                          "bias": _BIAS[settings.bias]}
                else:
                    lines[str(offset)] = {"direction": "input", "edge": _EDGE[settings.edge_detection],
                                          "bias": _BIAS[settings.bias]}
        conn = _Connection(socket_path)
        reply = conn.call(op="request", consumer=consumer or "", lines=lines)
        if not reply.get("ok"):
            conn.close()
            code = errno.EBUSY if reply.get("error") == "EBUSY" else errno.EINVAL
            raise _os_error(code, str(reply.get("message", "")))
        return MockLineRequest(conn)
