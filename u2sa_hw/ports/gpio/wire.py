"""The mock GPIO chip's wire protocol and the events a GPIO port hands out, shared by driver and mock.

Frames ``kind:u8 length:u32be payload``; kind ``J`` is a JSON request or reply, kind ``E`` a
binary edge event (``MOCK_EDGE_RECORD``), kind ``T`` a clock tick (``MOCK_TICK_RECORD``: the
chip's time, sent only by a chip that keeps a clock of its own; kind ``S`` the same as a
*step*: the recorded driver's loop looked at its clock then), kind ``O`` the origin of such a
clock (``MOCK_ORIGIN_RECORD``) and kind ``B`` a recorded bus message (``MOCK_BUS_HEADER`` +
channel + bytes; a replay chip, to a driver that asked for it). The client end is
:class:`~u2sa_hw.ports.gpio.mock_client.MockGpioPort`; the chip end the mock device serves is
``u2sa_hw.mocks.gpio_chip``; docs/gpio-and-rc.md documents the requests.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any, Mapping, NamedTuple, Union

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
MOCK_MAX_FRAME = 1 << 20
EDGE_RISING, EDGE_FALLING = 1, 2  # gpiod EdgeEvent.Type values

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

