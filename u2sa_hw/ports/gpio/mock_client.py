"""The client of a mock GPIO chip: one Unix-socket connection is one line request, like a kernel request fd.

It speaks :mod:`u2sa_hw.ports.gpio.wire` to ``u2sa_hw.mocks.gpio_chip.MockGpioChip`` (or a
replay chip, hil/replay_gpio.py, which keeps a clock of its own: see the device clock in
:mod:`u2sa_hw.ports.gpio.port`).
"""

from __future__ import annotations

import json
import socket
import struct
import threading
import time
from collections import deque
from typing import Any, Mapping, Sequence

from u2sa_hw.ports.errors import PortClosed, PortIOError, PortTimeout, PortUnavailable
from u2sa_hw.ports.gpio.port import MOCK_PREFIX, GpioPort
from u2sa_hw.ports.gpio.wire import (EDGE_RISING, MOCK_BUS, MOCK_EDGE, MOCK_EDGE_RECORD, MOCK_ORIGIN,
                                     MOCK_ORIGIN_RECORD, MOCK_STEP, MOCK_TICK, MOCK_TICK_RECORD, ClockTick, EdgeEvent,
                                     GpioEvent, MockFrameReader, MockProtocolError, decode_bus_input, encode_mock_json)
from u2sa_hw.ports.tap import Tap

DEVICE_CLOCK_GRACE_S = 2.0  # a device clock silent this long (wall) runs on with the wall clock
EVENT_BUFFER = 1024  # edges kept unread per port; the oldest is dropped first, as the kernel does


class MockGpioPort(GpioPort):
    """Client of a MockGpioChip: one connection is one line request, like a kernel request fd."""

    REPLY_TIMEOUT = 5.0

    def __init__(self, *, device: str, socket_path: str, inputs: Sequence[int], outputs: Mapping[int, int],
                 edge: str, bias: str, tap: Tap | None) -> None:
        super().__init__(device=device, address=MOCK_PREFIX + socket_path, inputs=inputs, outputs=outputs, tap=tap)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._sock.connect(socket_path)
        except OSError as exc:
            self._sock.close()
            raise PortUnavailable(device, f"no mock GPIO chip is listening at {socket_path} ({exc.strerror})",
                                  address=self.address, fix="start the mock chip (u2sa_hw.mocks.gpio_chip."
                                                            "MockGpioChip) or correct the address") from exc
        self._cond, self._send_lock = threading.Condition(), threading.Lock()
        self._edges: deque[GpioEvent] = deque()
        self._replies: dict[int, dict[str, Any]] = {}
        self._next_id, self._lost = 0, ""  # _lost: why the connection is gone, once it is
        self.device_clock = False          # the chip keeps its own clock (a replay chip)
        self._origin_ns = 0                # the recorded clock's zero on that clock (sent by the chip)
        self._taken_ns: int | None = None  # the latest edge/tick time handed to the driver
        self._heard_at = time.monotonic()  # wall time the chip last sent an edge or tick
        self._reader = threading.Thread(target=self._read_loop, name=f"gpio-mock-{device}", daemon=True)
        self._reader.start()
        lines: dict[str, dict[str, Any]] = {str(n): {"direction": "input", "edge": edge, "bias": bias} for n in inputs}
        for n, value in outputs.items():
            lines[str(n)] = {"direction": "output", "value": value, "bias": bias}
        try:
            reply = self._call({"op": "request", "consumer": f"u2sa:{device}", "lines": lines})
        except (PortClosed, PortTimeout) as exc:
            reply = {"ok": False, "message": f"no answer ({exc})"}
        if not reply.get("ok"):
            self.close()
            if reply.get("error") == "EBUSY":
                users = ", ".join(f"line {n} by '{c}'" for n, c in sorted(reply.get("consumers", {}).items()))
                message, fix = f"GPIO lines in use: {users}", "stop the process holding the line or change the line"
            else:
                message, fix = f"mock chip refused the request: {reply.get('message')}", "check lines and settings"
            raise PortUnavailable(device, message, address=self.address, fix=fix + " in this service's config")
        self.device_clock = reply.get("clock") == "device"
        self._tap_edges = not self.device_clock
        if self.device_clock and isinstance(reply.get("origin_ns"), int):
            self._origin_ns = int(reply["origin_ns"])
        for n, value in outputs.items():
            self._tap_write(n, value)

    def now_ns(self) -> int | None:
        """CLOCK_MONOTONIC, or on a device-clock chip the latest time taken, run on by the wall clock
        once the chip has been silent for DEVICE_CLOCK_GRACE_S (a stopped clock never holds a timeout)."""
        if not self.device_clock:
            return time.monotonic_ns()
        with self._cond:
            if self._taken_ns is None:
                return None
            silent_s = time.monotonic() - self._heard_at
            return self._taken_ns + max(0, int((silent_s - DEVICE_CLOCK_GRACE_S) * 1e9))

    def clock_origin_ns(self) -> int:
        """0, or on a device-clock chip the origin it sent (before its first stamped frame)."""
        with self._cond:
            return self._origin_ns

    def take_recorded_bus(self, channels: Sequence[str]) -> tuple[str, ...]:
        """On a device-clock chip, ask for *channels* (op ``bus``); the channels it accepted."""
        if not self.device_clock or not channels:
            return ()
        reply = self._call({"op": "bus", "channels": list(channels)})
        return tuple(str(c) for c in reply.get("channels", ())) if reply.get("ok") else ()

    def _read_loop(self) -> None:
        frames = MockFrameReader()
        reason = "the mock chip closed the connection"
        try:
            while True:
                data = self._sock.recv(65536)
                if not data:
                    break
                events: list[GpioEvent] = []
                for kind, payload in frames.feed(data):
                    event = self._event(kind, payload)
                    if event is not None:
                        events.append(event)
                        continue
                    self._queue(events)   # what came before a reply or an origin goes first
                    events = []
                    self._dispatch(kind, payload)
                self._queue(events)
        except OSError as exc:
            reason = f"connection to the mock chip failed ({exc})"
        except (ValueError, TypeError, AttributeError, struct.error) as exc:
            reason = f"mock chip sent garbage ({exc})"
        with self._cond:
            self._lost = reason
            self._cond.notify_all()

    def _event(self, kind: bytes, payload: bytes) -> GpioEvent | None:
        """The event in an edge, tick or bus frame (None for a reply or an origin)."""
        if kind == MOCK_EDGE:
            event_type, line, timestamp_ns, _global, _line_seq = MOCK_EDGE_RECORD.unpack(payload)
            return EdgeEvent(line=line, rising=event_type == EDGE_RISING, timestamp_ns=timestamp_ns)
        if kind in (MOCK_TICK, MOCK_STEP):
            return ClockTick(MOCK_TICK_RECORD.unpack(payload)[0], step=kind == MOCK_STEP)
        if kind == MOCK_BUS:
            if not self.device_clock:
                raise MockProtocolError("a bus frame from a chip without a device clock")
            return decode_bus_input(payload)
        return None

    def _queue(self, events: list[GpioEvent]) -> None:
        """Hand the events of one read to the driver at once (one lock, one wake-up)."""
        if not events:
            return
        with self._cond:
            # a replay chip's edges are all kept (its player paces them by what the chip still has
            # to send); holding this reader back instead would also hold back the reply to a
            # write the driver waits for behind them
            self._edges.extend(events)
            if not self.device_clock:
                while len(self._edges) > EVENT_BUFFER:
                    self._edges.popleft()   # the oldest is dropped first, as the kernel does
            self._heard_at = time.monotonic()
            self._cond.notify_all()

    def _dispatch(self, kind: bytes, payload: bytes) -> None:
        """A reply or an origin frame (events go through :meth:`_event` and :meth:`_queue`)."""
        if kind == MOCK_ORIGIN:
            with self._cond:
                self._origin_ns = MOCK_ORIGIN_RECORD.unpack(payload)[0]
            return
        reply = json.loads(payload)
        with self._cond:
            self._replies[int(reply.get("id", -1))] = reply
            self._cond.notify_all()

    def _lost_error(self, reason: str) -> PortClosed:
        return PortClosed(self.device, reason, address=self.address, fix="restart the mock chip; the driver reconnects")

    def _call(self, request: dict[str, Any]) -> dict[str, Any]:
        """Send *request* and wait for its reply (``ok`` true or an ``error`` errno name)."""
        with self._cond:
            self._next_id += 1
            request["id"] = request_id = self._next_id
        try:
            with self._send_lock:
                self._sock.sendall(encode_mock_json(request))
        except OSError as exc:
            raise self._lost_error(f"mock chip connection lost ({exc})") from exc
        with self._cond:
            self._cond.wait_for(lambda: request_id in self._replies or self._lost, self.REPLY_TIMEOUT)
            reply = self._replies.pop(request_id, None)
            if reply is None and self._lost:
                raise self._lost_error(self._lost)
        if reply is None:
            raise PortTimeout(self.device, f"mock chip did not answer '{request['op']}' within {self.REPLY_TIMEOUT:g} s",
                              address=self.address, fix="check the mock chip process")
        return reply

    def _transaction(self, request: dict[str, Any]) -> dict[str, Any]:
        reply = self._call(request)
        if not reply.get("ok"):
            raise PortIOError(self.device, f"{request['op']} failed: {reply.get('error')}: {reply.get('message')}",
                              address=self.address)
        return reply

    def _get(self, line: int) -> int:
        return int(self._transaction({"op": "get", "lines": [line]})["values"][0])

    def _set(self, line: int, value: int) -> None:
        self._transaction({"op": "set", "values": {str(line): value}})

    def _read_edges(self, timeout: float) -> list[GpioEvent]:
        with self._cond:
            self._cond.wait_for(lambda: self._edges or self._lost or self._closed, timeout)
            events = list(self._edges)
            self._edges.clear()
            if not events and self._lost:
                raise self._lost_error(self._lost)
            if events and self.device_clock:
                self._taken_ns = max(self._taken_ns or 0, max(e.timestamp_ns for e in events))
        return events

    def _release(self) -> None:
        if not self._lost:  # release before hanging up so the lines are free when close() returns, as in the kernel
            try:
                self._call({"op": "release"})
            except (PortClosed, PortTimeout):
                pass
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        with self._cond:
            self._cond.notify_all()
        if threading.current_thread() is not self._reader:
            self._reader.join(timeout=2.0)
