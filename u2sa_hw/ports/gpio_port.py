"""GPIO port: input lines with timestamped edge events and output lines, real or mock.

``open_gpio(device=..., chip="/dev/gpiochip0", ...)`` requests the lines from the kernel
through libgpiod v2 (``gpiod`` is imported only then, never at import time);
``chip="mock:/path/to.sock"`` requests them from ``u2sa_hw.mocks.gpio_chip.MockGpioChip``
over a Unix socket. Both hand out the same ``GpioPort``: ``get``, ``set``,
``read_edges`` and ``close``. Edge events carry the timestamp the kernel (or the mock
chip) took when the edge happened, never a time taken when the event was read, because
an RC pulse width is the difference of two such timestamps.

Mock chip wire protocol: frames ``kind:u8 length:u32be payload``; kind ``J`` is a JSON
request or reply, kind ``E`` a binary edge event (``MOCK_EDGE_RECORD``), kind ``T`` a clock
tick (``MOCK_TICK_RECORD``: the chip's time, sent only by a chip that keeps a clock of its
own; kind ``S`` the same as a *step*: the recorded driver's loop looked at its clock then), kind
``O`` the origin of such a clock (``MOCK_ORIGIN_RECORD``) and kind ``B`` a recorded
bus message (``MOCK_BUS_HEADER`` + channel + bytes; a replay chip, to a driver that asked for it).
The codec is here because driver and mock share it; docs/gpio-and-rc.md documents the requests.

The device clock. :meth:`GpioPort.now_ns` is the time the driver judges timeouts, debounce
and ageing against, on the clock of the edge stamps. A kernel chip stamps edges with
CLOCK_MONOTONIC, so its ``now_ns`` is CLOCK_MONOTONIC now, and so is a mock chip's unless it
says in its request reply that it keeps its own clock (``"clock": "device"``: a replay chip,
hil/replay_gpio.py). Then ``now_ns`` is the latest edge or tick time the driver has taken,
so recorded edges played at any speed are judged as they happened; and it is never held by a
chip that goes quiet: once nothing came from the chip for ``DEVICE_CLOCK_GRACE_S`` of wall
time, the clock runs on with the wall clock from there (a signal timeout then expires).
:meth:`GpioPort.clock_origin_ns` is where the recorded clock's zero lies on the device clock
(0 on a real chip: the device clock *is* CLOCK_MONOTONIC; a replay chip's offset), so a driver's
timed messages fall on the same grid of the recorded clock live and replayed.

Recorded bus inputs. A replay chip can also hand its driver the recorded bus messages the
driver asks for (:meth:`GpioPort.take_recorded_bus`: the RC mux's Health, FAILSAFE and
STATE_ESTIMATE), as :class:`BusInput` events in order with the edges, each stamped on the
device clock where the recording says it arrived. A real chip, and a mock chip without a clock
of its own, never do: their drivers hear the bus.
"""

from __future__ import annotations

import errno
import json
import socket
import struct
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator, Mapping, NamedTuple, Sequence, Union

from u2sa_hw import messages as m
from u2sa_hw.ports.errors import PortClosed, PortIOError, PortTimeout, PortUnavailable
from u2sa_hw.ports.tap import Tap, call_tap, tapping

MOCK_PREFIX = "mock:"
EDGES = ("both", "rising", "falling", "none")
BIASES = ("as-is", "pull-up", "pull-down", "disabled")
# frame kinds: JSON request/reply, edge event, clock tick, clock origin, recorded bus message
MOCK_JSON, MOCK_EDGE, MOCK_TICK, MOCK_ORIGIN, MOCK_BUS = b"J", b"E", b"T", b"O", b"B"
MOCK_STEP = b"S"      # a tick at which the recorded driver's loop looked at its clock (a replay chip's)
MOCK_KINDS = (MOCK_JSON, MOCK_EDGE, MOCK_TICK, MOCK_ORIGIN, MOCK_BUS, MOCK_STEP)
MOCK_FRAME_HEADER = struct.Struct(">cI")
MOCK_EDGE_RECORD = struct.Struct(">BIQQQ")
MOCK_TICK_RECORD = struct.Struct(">Q")
MOCK_ORIGIN_RECORD = struct.Struct(">q")      # the recorded clock's zero on the device clock (ns)
MOCK_BUS_HEADER = struct.Struct(">QH")        # device time (ns), channel name length; then the name, the bytes
DEVICE_CLOCK_GRACE_S = 2.0  # a device clock silent this long (wall) runs on with the wall clock
MOCK_MAX_FRAME = 1 << 20
EDGE_RISING, EDGE_FALLING = 1, 2  # gpiod EdgeEvent.Type values
EVENT_BUFFER = 1024  # edges kept unread per port; the oldest is dropped first, as the kernel does


class EdgeEvent(NamedTuple):
    """One edge on an input line; ``timestamp_ns`` is CLOCK_MONOTONIC from the kernel/mock. (A named tuple:
    one is made per edge, and a frozen dataclass costs several times as much to make.)"""

    line: int
    rising: bool
    timestamp_ns: int


class ClockTick(NamedTuple):
    """The chip's clock reached ``timestamp_ns`` (a chip with a clock of its own, in recorded silences).
    ``step``: the recorded driver's loop looked at its clock then, with edges still on their way to it
    (a replay chip's, where the log shows the driver publishing while no edge reached it)."""

    timestamp_ns: int
    step: bool = False


@dataclass(frozen=True)
class BusInput:
    """A recorded bus message a replay chip hands its driver in order with the edges: the LCM payload
    (no signing trailer) of a message on ``channel``, arrived at ``timestamp_ns`` on the device clock."""

    timestamp_ns: int
    channel: str
    data: bytes


GpioEvent = Union[EdgeEvent, ClockTick, BusInput]


def encode_bus_input(timestamp_ns: int, channel: str, data: bytes) -> bytes:
    """A ``B`` frame: a recorded bus message for a driver that asked for its channel."""
    name = channel.encode()
    return encode_mock_frame(MOCK_BUS, MOCK_BUS_HEADER.pack(int(timestamp_ns), len(name)) + name + bytes(data))


def decode_bus_input(payload: bytes) -> BusInput:
    """The :class:`BusInput` in a ``B`` frame's payload."""
    timestamp_ns, length = MOCK_BUS_HEADER.unpack_from(payload)
    start = MOCK_BUS_HEADER.size
    if len(payload) < start + length:
        raise MockProtocolError(f"bus frame shorter than its channel name ({len(payload)} bytes)")
    return BusInput(timestamp_ns, payload[start:start + length].decode(), payload[start + length:])


class MockProtocolError(ValueError):
    """The mock chip wire protocol was violated (bad kind, oversized frame, bad JSON)."""


def encode_mock_frame(kind: bytes, payload: bytes) -> bytes:
    """One protocol frame: kind byte, big-endian payload length, payload."""
    return MOCK_FRAME_HEADER.pack(kind, len(payload)) + payload


def encode_mock_json(obj: Mapping[str, Any]) -> bytes:
    """A ``J`` frame holding *obj*."""
    return encode_mock_frame(MOCK_JSON, json.dumps(obj, separators=(",", ":")).encode())


class MockFrameReader:
    """Splits a byte stream into ``(kind, payload)`` frames; raises MockProtocolError on garbage."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[tuple[bytes, bytes]]:
        """Add received bytes; return the frames completed by them."""
        buffer = self._buffer
        buffer += data
        frames = []
        start, size, header = 0, len(buffer), MOCK_FRAME_HEADER.size
        while size - start >= header:
            kind, length = MOCK_FRAME_HEADER.unpack_from(buffer, start)
            if kind not in MOCK_KINDS or length > MOCK_MAX_FRAME:
                raise MockProtocolError(f"bad frame header kind={kind!r} length={length}")
            end = start + header + length
            if size < end:
                break
            frames.append((kind, bytes(buffer[start + header:end])))
            start = end
        del buffer[:start]   # once per read, not once per frame
        return frames


class GpioPort:
    """Requested GPIO lines of one chip; subclasses talk to gpiod or to the mock chip."""

    def __init__(self, *, device: str, address: str, inputs: Sequence[int], outputs: Mapping[int, int],
                 tap: Tap | None) -> None:
        self.device, self.address = device, address
        self.inputs, self.outputs = tuple(inputs), dict(outputs)  # outputs: line -> last value set
        self._tap, self._closed = tap, False
        # edges are tapped (RawGpioEdge) but from a replay chip (a device clock): they are the log's own
        # input played back, and re-tapping them only doubled the replay's bus traffic (writes still are)
        self._tap_edges = True

    is_open = property(lambda self: not self._closed, doc="False after close().")

    def get(self, line: int) -> int:
        """The current level (0/1) of a requested input or output line."""
        self._check(line, self.inputs + tuple(self.outputs), "a requested line")
        return self._get(line)

    def set(self, line: int, value: int) -> None:
        """Drive a requested output line to *value* (0/1) and tap the write."""
        self._check(line, tuple(self.outputs), "an output line")
        if value not in (0, 1):
            raise ValueError(f"{self.device}: GPIO value must be 0 or 1, not {value!r}")
        self._set(line, int(value))
        self.outputs[line] = int(value)
        self._tap_write(line, int(value))

    def read_edges(self, timeout: float) -> list[EdgeEvent]:
        """Edges that happened since the last call; waits up to *timeout* s for the first one."""
        return [e for e in self.read_events(timeout) if isinstance(e, EdgeEvent)]

    def now_ns(self) -> int | None:
        """The device clock (see the module docstring): CLOCK_MONOTONIC unless the chip keeps its own;
        None while a chip with its own clock has sent nothing yet."""
        return time.monotonic_ns()

    def clock_origin_ns(self) -> int:
        """Where the recorded clock's zero lies on the device clock: 0 but on a replay chip."""
        return 0

    def take_recorded_bus(self, channels: Sequence[str]) -> tuple[str, ...]:
        """Ask the chip for the recorded messages of *channels* as :class:`BusInput` events; the channels it
        will send (none but on a replay chip: the driver then hears the bus)."""
        return ()

    def read_events(self, timeout: float) -> list[GpioEvent]:
        """Edges (and a device-clock chip's ticks and recorded bus inputs) in the order the chip sent them;
        waits up to *timeout* s."""
        self._check_open()
        events = self._read_edges(timeout)
        if self._tap_edges and tapping(self._tap):
            for event in events:
                if not isinstance(event, EdgeEvent):
                    continue
                record = m.RawGpioEdge()
                record.device, record.line = self.device, event.line
                record.edge, record.kernel_timestamp_ns = int(event.rising), event.timestamp_ns
                call_tap(self._tap, record)
        return events

    def close(self) -> None:
        """Release the lines; further calls raise PortClosed."""
        if not self._closed:
            self._closed = True
            self._release()

    def _tap_write(self, line: int, value: int) -> None:
        if tapping(self._tap):
            record = m.RawGpioWrite()
            record.device, record.line, record.value = self.device, line, value
            call_tap(self._tap, record)

    def _check_open(self) -> None:
        if self._closed:
            raise PortClosed(self.device, "GPIO port is closed", address=self.address, fix="open the port again")

    def _check(self, line: int, allowed: Sequence[int], what: str) -> None:
        self._check_open()
        if line not in allowed:
            raise ValueError(f"{self.device}: line {line} is not {what} of this port "
                             f"(inputs {list(self.inputs)}, outputs {sorted(self.outputs)})")

    # backend hooks
    def _get(self, line: int) -> int: raise NotImplementedError  # noqa: E704
    def _set(self, line: int, value: int) -> None: raise NotImplementedError  # noqa: E704
    def _read_edges(self, timeout: float) -> list[GpioEvent]: raise NotImplementedError  # noqa: E704
    def _release(self) -> None: raise NotImplementedError  # noqa: E704


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



class GpiodGpioPort(GpioPort):
    """Lines of a kernel GPIO character device, through libgpiod v2."""

    def __init__(self, *, device: str, chip_path: str, inputs: Sequence[int], outputs: Mapping[int, int],
                 edge: str, bias: str, tap: Tap | None) -> None:
        super().__init__(device=device, address=chip_path, inputs=inputs, outputs=outputs, tap=tap)
        try:
            import gpiod
            from gpiod.line import Bias, Direction, Edge, Value
        except ImportError as exc:
            raise PortUnavailable(device, f"cannot use {chip_path}: the gpiod (libgpiod v2) bindings are missing",
                                  address=chip_path, fix="pip install 'gpiod>=2.1' into the u2sa venv") from exc
        self._gpiod = gpiod
        bias_setting, edge_setting = Bias[bias.replace("-", "_").upper()], Edge[edge.upper()]
        config: dict[int, Any] = {n: gpiod.LineSettings(direction=Direction.INPUT, edge_detection=edge_setting,
                                                        bias=bias_setting) for n in inputs}
        for n, value in outputs.items():
            config[n] = gpiod.LineSettings(direction=Direction.OUTPUT, bias=bias_setting,
                                           output_value=Value.ACTIVE if value else Value.INACTIVE)
        self._lock = threading.Lock()
        try:
            self._request = gpiod.request_lines(chip_path, config=config, consumer=f"u2sa:{device}")
        except OSError as exc:
            raise self._open_error(exc, list(config)) from exc
        except ValueError as exc:
            raise PortUnavailable(device, f"cannot request lines {sorted(config)}: {exc}", address=chip_path,
                                  fix="use line offsets the chip has (gpioinfo lists them)") from exc
        for n, value in outputs.items():
            self._tap_write(n, value)

    def _open_error(self, exc: OSError, offsets: list[int]) -> PortUnavailable:
        path, code = self.address, exc.errno
        if code == errno.ENOENT:
            message, fix = f"GPIO chip {path} does not exist", ("list the chips with `gpiodetect` and put the right "
                                                                "/dev/gpiochipN in the service config, or use a mock "
                                                                "chip address mock:/path.sock")
        elif code in (errno.EACCES, errno.EPERM):
            message, fix = f"no permission to open {path}", (f"add the service user to group gpio (usermod -aG gpio "
                                                             f"<user>) and give {path} to group gpio with a udev rule "
                                                             "(u2sa install does both)")
        elif code == errno.EBUSY:
            message, fix = f"GPIO lines in use: {self._line_users(offsets)}", (
                "stop the process holding the line (gpioinfo shows the consumer) or change the line in this "
                "service's config")
        elif code in (errno.ENODEV, errno.ENOTTY):
            message, fix = f"{path} is not a GPIO character device", "point the config at a /dev/gpiochipN (gpiodetect)"
        else:
            message, fix = f"cannot request GPIO lines {offsets}: {exc.strerror}", "check the lines against `gpioinfo`"
        return PortUnavailable(self.device, message, address=path, fix=fix)

    def _line_users(self, offsets: list[int]) -> str:
        try:
            with self._gpiod.Chip(self.address) as chip:
                infos = [chip.get_line_info(n) for n in offsets]
        except (OSError, ValueError):
            return f"one of lines {offsets} (consumer unknown)"
        return ", ".join(f"line {i.offset} by '{i.consumer or 'unnamed'}'" for i in infos if i.used) or str(offsets)

    @contextmanager
    def _request_failures(self) -> Iterator[None]:
        try:
            yield
        except (OSError, self._gpiod.RequestReleasedError) as exc:
            raise PortClosed(self.device, f"GPIO request failed ({exc})", address=self.address,
                             fix="check the chip; the driver re-requests the lines") from exc

    def _get(self, line: int) -> int:
        with self._request_failures(), self._lock:
            return 1 if self._request.get_value(line) else 0

    def _set(self, line: int, value: int) -> None:
        level = self._gpiod.line.Value.ACTIVE if value else self._gpiod.line.Value.INACTIVE
        with self._request_failures(), self._lock:
            self._request.set_value(line, level)

    def _read_edges(self, timeout: float) -> list[EdgeEvent]:
        rising = self._gpiod.EdgeEvent.Type.RISING_EDGE
        with self._request_failures():
            # the wait is a poll() on the request fd; only the read needs the lock
            if not self._request.wait_edge_events(timeout):
                return []
            with self._lock:
                events = self._request.read_edge_events()
        return [EdgeEvent(line=e.line_offset, rising=e.event_type is rising, timestamp_ns=e.timestamp_ns)
                for e in events]

    def _release(self) -> None:
        with self._lock:
            self._request.release()


def open_gpio(*, device: str, chip: str, inputs: Sequence[int] = (), outputs: Mapping[int, int] | None = None,
              edge: str = "both", bias: str = "as-is", tap: Tap | None = None) -> GpioPort:
    """Request *inputs* (with *edge* detection) and *outputs* (line -> initial value) on *chip*.

    *chip* is a kernel GPIO chip (``/dev/gpiochip0``) or ``mock:/path/to.sock``.
    *bias* is one of ``as-is``, ``pull-up``, ``pull-down``, ``disabled`` for every line.
    Raises PortUnavailable (naming the chip and the fix) when the lines cannot be had.
    """
    inputs, outputs = list(inputs), dict(outputs or {})
    if edge not in EDGES or bias not in BIASES:
        raise ValueError(f"{device}: edge must be one of {EDGES} and bias one of {BIASES}, not {edge!r}, {bias!r}")
    lines = inputs + list(outputs)
    if not lines:
        raise ValueError(f"{device}: a GPIO port needs at least one input or output line")
    if any(not isinstance(n, int) or isinstance(n, bool) or n < 0 for n in lines) or len(set(lines)) != len(lines):
        raise ValueError(f"{device}: line offsets must be distinct non-negative integers, got inputs {inputs} "
                         f"and outputs {sorted(outputs)}")
    if any(v not in (0, 1) for v in outputs.values()):
        raise ValueError(f"{device}: initial output values must be 0 or 1, got {outputs}")
    if chip.startswith(MOCK_PREFIX):
        return MockGpioPort(device=device, socket_path=chip[len(MOCK_PREFIX):], inputs=inputs, outputs=outputs,
                            edge=edge, bias=bias, tap=tap)
    return GpiodGpioPort(device=device, chip_path=chip, inputs=inputs, outputs=outputs, edge=edge, bias=bias, tap=tap)
