"""A mock GPIO character device behind a Unix socket, with timestamped edge events.

``MockGpioChip`` models what a driver sees of ``/dev/gpiochipN`` through libgpiod v2:
a client connection is one line request (like the kernel's request fd); lines are
requested as inputs (edge detection rising/falling/both/none, bias) or outputs (initial
value); a line already requested is refused with EBUSY naming its consumer; values are
read and written; edges on an input are delivered only to the client that requested it,
as gpiod ``EdgeEvent``s (type, timestamp_ns, line_offset, global_seqno, line_seqno)
with per-request sequence numbers. Closing the connection releases the lines.

The chip side is for simulations and tests: ``drive_input`` sets an input level (the
edge timestamp is the one given, else CLOCK_MONOTONIC now), ``read_output``,
``history`` (timestamped level changes), ``on_output`` callbacks, and faults:
``disconnect`` and ``stop_edges``. A chip made with ``device_clock=True`` (a replay chip)
keeps a clock of its own: its request reply says ``"clock": "device"``, ``tick`` sends its
time to the clients during silences, and the driver's port judges time by the edges and ticks
it takes (``GpioPort.now_ns``); ``set_origin`` tells the clients where the recorded clock's zero
lies on it, ``bus`` hands a recorded bus message to the clients that asked for its channel (op
``bus``), in order with the edges; ``backlog`` counts frames not yet sent, so a player can
wait instead of overflowing a client that reads slowly. The wire protocol lives in
``u2sa_hw.ports.gpio.wire`` (driver and mock share it) and is documented in
``docs/gpio-and-rc.md``; serving it on the socket (``start``, ``stop``, a reader and a writer thread
per client) is mock_devices/gpio_chip_server.py.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

from u2sa_hw.ports.gpio.wire import (BIASES, EDGE_FALLING, EDGE_RISING, EDGES, MOCK_EDGE, MOCK_EDGE_RECORD, MOCK_ORIGIN,
                                     MOCK_ORIGIN_RECORD, MOCK_STEP, MOCK_TICK, MOCK_TICK_RECORD, MockProtocolError,
                                     encode_bus_input, encode_mock_frame, encode_mock_json)
from u2sa_hw.ports.gpio.port import MOCK_PREFIX
from u2sa_hw.mocks.gpio_chip_server import ChipClient, GpioChipServer

log = logging.getLogger("u2sa_hw.mocks.gpio_chip")

OutputCallback = Callable[[int, int, int], None]


@dataclass(frozen=True)
class GpioChipRecord:
    """A level change: ``kind`` "output" (a client set it) or "input" (the chip side drove it)."""

    timestamp_ns: int
    line: int
    value: int
    kind: str


class ChipRefusal(Exception):
    """A request refused with a kernel-like errno name."""

    def __init__(self, errno_name: str, message: str, **extra: Any) -> None:
        super().__init__(message)
        self.reply = {"ok": False, "error": errno_name, "message": message, **extra}


class MockGpioChip(GpioChipServer):
    """A GPIO chip with *num_lines* lines served at *socket_path* (address ``mock:<path>``).

    *release_level* is the level an output falls to when its client releases it or goes
    away (the board's pull resistor); None keeps the last value as many SoCs do.
    """

    def __init__(self, *, socket_path: str, num_lines: int = 32, label: str = "mock-gpiochip",
                 release_level: int | None = 0, history_size: int = 100_000, device_clock: bool = False) -> None:
        self.device_clock = device_clock
        self.origin_ns: int | None = None   # a device clock's origin, once set_origin gave it
        self.socket_path = str(socket_path)
        self.num_lines = num_lines
        self.label = label
        self.release_level = release_level
        self.history: deque[GpioChipRecord] = deque(maxlen=history_size)
        self.dropped_edges = 0
        self.protocol_errors = 0
        self._lock = threading.RLock()
        self._levels = [0] * num_lines
        self._driven: dict[int, int] = {}  # input levels set by drive_input
        self._owners: dict[int, ChipClient] = {}
        self._clients: list[ChipClient] = []
        self._callbacks: list[OutputCallback] = []
        self._edges_stopped = False
        self._stop = threading.Event()
        self._server = self._acceptor = None   # listening: GpioChipServer.start

    @property
    def address(self) -> str:
        """What a driver config names: ``mock:<socket path>``."""
        return MOCK_PREFIX + self.socket_path

    # ---- chip side -------------------------------------------------------------------
    def drive_input(self, line: int, value: int, timestamp_ns: int | None = None) -> bool:
        """Set input *line* to *value*; a change is an edge stamped *timestamp_ns* (default now).

        Returns True when the level changed. Driving a line a client holds as an output
        raises ValueError (two drivers on one wire).
        """
        self._check_line(line)
        value = 1 if value else 0
        stamp = time.monotonic_ns() if timestamp_ns is None else int(timestamp_ns)
        with self._lock:
            owner = self._owners.get(line)
            if owner is not None and owner.lines[line]["direction"] == "output":
                raise ValueError(f"{self.label}: line {line} is an output of '{owner.consumer}'; "
                                 "the chip side can only drive inputs")
            previous = self._input_level(line)
            self._driven[line] = self._levels[line] = value
            if previous == value:
                return False
            self.history.append(GpioChipRecord(stamp, line, value, "input"))
            if owner is not None:
                self._deliver_edge(owner, line, value, stamp)
            return True

    def tick(self, timestamp_ns: int, *, step: bool = False) -> None:
        """A device-clock chip's time during a silence: sent to every client holding input lines. *step*: the
        recorded driver's loop looked at its clock then (its port's ``ClockTick.step``)."""
        frame = encode_mock_frame(MOCK_STEP if step else MOCK_TICK, MOCK_TICK_RECORD.pack(int(timestamp_ns)))
        with self._lock:
            for client in self._clients:
                if any(s["direction"] == "input" for s in client.lines.values()):
                    try:
                        client.outbox.put_nowait(frame)
                    except queue.Full:
                        self.dropped_edges += 1

    def set_origin(self, origin_ns: int) -> None:
        """Where the recorded clock's zero lies on this chip's clock: sent to the clients (before any frame
        stamped after it) and in later request replies."""
        frame = encode_mock_frame(MOCK_ORIGIN, MOCK_ORIGIN_RECORD.pack(int(origin_ns)))
        with self._lock:
            self.origin_ns = int(origin_ns)
            for client in self._clients:
                if client.lines:
                    self._send(client, frame)

    def bus(self, timestamp_ns: int, channel: str, data: bytes) -> int:
        """A recorded bus message, to every client that asked for *channel*; how many it went to."""
        frame = encode_bus_input(timestamp_ns, channel, data)
        sent = 0
        with self._lock:
            for client in self._clients:
                if channel in client.bus_channels:
                    self._send(client, frame)
                    sent += 1
        return sent

    def _send(self, client: ChipClient, frame: bytes) -> None:
        try:
            client.outbox.put_nowait(frame)
        except queue.Full:
            self.dropped_edges += 1

    def backlog(self) -> int:
        """Frames (edges, ticks, replies) queued for the clients and not yet sent."""
        with self._lock:
            return sum(client.outbox.qsize() for client in self._clients)

    def read_output(self, line: int) -> int:
        """The level of *line* as the chip drives it (the last value a client set)."""
        self._check_line(line)
        with self._lock:
            return self._levels[line]

    def on_output(self, callback: OutputCallback) -> None:
        """Call ``callback(line, value, timestamp_ns)`` on every output level change."""
        with self._lock:
            self._callbacks.append(callback)

    def consumers(self) -> dict[int, str]:
        """Lines in use and the consumer name of each (what ``gpioinfo`` shows)."""
        with self._lock:
            return {line: client.consumer for line, client in sorted(self._owners.items())}

    def disconnect(self, consumer: str | None = None) -> int:
        """Fault: drop the client(s) of *consumer* (all when None); returns how many."""
        with self._lock:
            victims = [c for c in self._clients if consumer is None or c.consumer == consumer]
        for client in victims:
            self._drop(client)
        return len(victims)

    def stop_edges(self, on: bool) -> None:
        """Fault: while on, levels still change but no edge events reach clients."""
        self._edges_stopped = on

    # ---- internals ---------------------------------------------------------------------
    def _check_line(self, line: int) -> None:
        if not 0 <= line < self.num_lines:
            raise ValueError(f"{self.label}: line {line} out of range 0..{self.num_lines - 1}")

    def _input_level(self, line: int) -> int:
        if line in self._driven:
            return self._driven[line]
        owner = self._owners.get(line)
        return 1 if owner is not None and owner.lines[line].get("bias") == "pull-up" else 0

    def _deliver_edge(self, client: ChipClient, line: int, value: int, stamp: int) -> None:
        edge = client.lines[line]["edge"]
        if edge == "none" or (edge == "rising" and not value) or (edge == "falling" and value):
            return
        if self._edges_stopped:
            self.dropped_edges += 1
            return
        client.global_seqno += 1
        client.line_seqno[line] = client.line_seqno.get(line, 0) + 1
        record = MOCK_EDGE_RECORD.pack(EDGE_RISING if value else EDGE_FALLING, line, stamp,
                                       client.global_seqno, client.line_seqno[line])
        try:
            client.outbox.put_nowait(encode_mock_frame(MOCK_EDGE, record))
        except queue.Full:
            self.dropped_edges += 1  # the client stopped reading; the kernel drops too

    def _set_output(self, line: int, value: int, fired: list[tuple[int, int, int]]) -> None:
        if self._levels[line] != value:
            stamp = time.monotonic_ns()
            self._levels[line] = value
            self.history.append(GpioChipRecord(stamp, line, value, "output"))
            fired.append((line, value, stamp))

    def _fire(self, fired: list[tuple[int, int, int]]) -> None:
        # outside the lock: a callback may drive inputs (the mux read-back line)
        for line, value, stamp in fired:
            for callback in list(self._callbacks):
                try:
                    callback(line, value, stamp)
                except Exception:  # noqa: BLE001 - a broken simulation hook must not kill the chip
                    log.exception("%s: on_output callback failed", self.label)

    def _answer(self, client: ChipClient, request: Any) -> None:
        if not isinstance(request, dict):
            raise MockProtocolError("request is not a JSON object")
        handler = {"request": self._op_request, "get": self._op_get, "set": self._op_set,
                   "release": self._op_release, "info": self._op_info, "bus": self._op_bus}.get(request.get("op"))
        fired: list[tuple[int, int, int]] = []
        try:
            if handler is None:
                raise ChipRefusal("EINVAL", f"unknown op {request.get('op')!r}")
            with self._lock:
                reply = {"ok": True, **handler(client, request, fired)}
        except ChipRefusal as exc:
            reply = exc.reply
        reply["id"] = request.get("id")
        self._fire(fired)
        try:
            client.outbox.put_nowait(encode_mock_json(reply))
        except queue.Full:
            self._drop(client)

    def _offset(self, key: Any) -> int:
        try:
            line = int(key)
        except (TypeError, ValueError):
            raise ChipRefusal("EINVAL", f"bad line offset {key!r}") from None
        if not 0 <= line < self.num_lines:
            raise ChipRefusal("EINVAL", f"line {line} out of range 0..{self.num_lines - 1}")
        return line

    def _op_request(self, client: ChipClient, req: dict, fired: list) -> dict:
        lines: dict[int, dict[str, Any]] = {}
        for key, settings in dict(req.get("lines") or {}).items():
            line = self._offset(key)
            direction, edge = settings.get("direction"), settings.get("edge", "none")
            bias, value = settings.get("bias", "as-is"), settings.get("value", 0)
            if direction not in ("input", "output") or edge not in EDGES or bias not in BIASES or value not in (0, 1):
                raise ChipRefusal("EINVAL", f"bad settings for line {line}: {settings}")
            lines[line] = {"direction": direction, "edge": edge if direction == "input" else "none",
                           "bias": bias, "value": value}
        if not lines:
            raise ChipRefusal("EINVAL", "a request needs at least one line")
        busy = {str(n): self._owners[n].consumer for n in lines if n in self._owners}
        if busy:
            raise ChipRefusal("EBUSY", "lines in use: " + ", ".join(f"{n} by '{c}'" for n, c in busy.items()),
                              consumers=busy)
        client.consumer = str(req.get("consumer") or client.consumer)
        reply: dict[str, Any] = {"clock": "device"} if self.device_clock else {}
        if self.device_clock and self.origin_ns is not None:
            reply["origin_ns"] = self.origin_ns
        for line, settings in lines.items():
            client.lines[line] = settings
            self._owners[line] = client
            if settings["direction"] == "output":
                self._driven.pop(line, None)
                self._set_output(line, settings["value"], fired)
            else:
                self._levels[line] = self._input_level(line)
        return reply

    def _op_bus(self, client: ChipClient, req: dict, fired: list) -> dict:
        if not self.device_clock:
            raise ChipRefusal("EINVAL", "this chip has no recorded bus (only a replay chip with a device clock)")
        channels = req.get("channels") or []
        if not isinstance(channels, list) or not all(isinstance(c, str) for c in channels):
            raise ChipRefusal("EINVAL", f"bad channels {channels!r}")
        client.bus_channels = frozenset(channels)
        return {"channels": sorted(client.bus_channels)}

    def _op_get(self, client: ChipClient, req: dict, fired: list) -> dict:
        values = []
        for key in req.get("lines") or []:
            line = self._offset(key)
            if line not in client.lines:
                raise ChipRefusal("EINVAL", f"line {line} is not part of this request")
            values.append(self._levels[line])
        return {"values": values}

    def _op_set(self, client: ChipClient, req: dict, fired: list) -> dict:
        updates = {self._offset(k): v for k, v in dict(req.get("values") or {}).items()}
        for line, value in updates.items():
            if line not in client.lines:
                raise ChipRefusal("EINVAL", f"line {line} is not part of this request")
            if client.lines[line]["direction"] != "output":
                raise ChipRefusal("EPERM", f"line {line} is an input")
            if value not in (0, 1):
                raise ChipRefusal("EINVAL", f"bad value {value!r} for line {line}")
        for line, value in updates.items():
            self._set_output(line, value, fired)
        return {}

    def _op_release(self, client: ChipClient, req: dict, fired: list) -> dict:
        self._release_lines(client, fired)
        return {}

    def _op_info(self, client: ChipClient, req: dict, fired: list) -> dict:
        used = {str(n): {"consumer": c.consumer, **c.lines[n]} for n, c in self._owners.items()}
        return {"label": self.label, "num_lines": self.num_lines, "lines": used}

    def _release_lines(self, client: ChipClient, fired: list) -> None:
        for line, settings in client.lines.items():
            self._owners.pop(line, None)
            if settings["direction"] == "output" and self.release_level is not None:
                self._set_output(line, self.release_level, fired)
        client.lines.clear()
        client.line_seqno.clear()
