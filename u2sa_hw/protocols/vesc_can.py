"""VESC CAN (VESC mode): ids, command scales, STATUS 1-6 and COMM-over-CAN codecs.

Shared by the VESC motor driver and the mock node (mock_devices/vesc_node.py). Facts come
from /work/shared/spec/devices/VESC_CAN.md (vedderb/bldc ``documentation/comm_can.md``,
``datatypes.h`` and ``comm/comm_can.c``). Frames use 29-bit extended ids
``packet_id << 8 | controller_id`` (controller id 255 addresses every VESC); payload integers
are big-endian, signed and scaled.

The firmware truncates ``value * scale`` to an integer; these encoders round to the nearest
integer instead, so a decimal value such as duty 0.29 arrives as 29000 rather than 28999.
The two agree whenever the product is within float rounding of an integer (every worked frame
in the spec) and never differ by more than one count.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import can

# the enumerations live in their own table module and are re-exported here for one import
from u2sa_hw.protocols.vesc_enums import CommPacket, FaultCode, PacketId  # noqa: F401

BROADCAST_ID = 255
MAX_CONTROLLER_ID = 255
STATUS_DLC = 8
DUTY_RANGE = (-1.0, 1.0)  # STATUS duty cycle: a fraction; the int16 x 1000 field can carry +-32.767


class VescCanError(ValueError):
    """A VESC CAN payload or id that cannot be decoded/encoded (says which packet and why)."""


# Simple commands: one int32 big-endian = value * scale. Units: duty and *_REL fractions -1..1,
# currents A, ERPM, degrees.
COMMAND_SCALES: dict[PacketId, float] = {
    PacketId.SET_DUTY: 100_000.0,
    PacketId.SET_CURRENT: 1_000.0,
    PacketId.SET_CURRENT_BRAKE: 1_000.0,
    PacketId.SET_RPM: 1.0,
    PacketId.SET_POS: 1_000_000.0,
    PacketId.SET_CURRENT_REL: 100_000.0,
    PacketId.SET_CURRENT_BRAKE_REL: 100_000.0,
    PacketId.SET_CURRENT_HANDBRAKE: 1_000.0,
    PacketId.SET_CURRENT_HANDBRAKE_REL: 100_000.0,
}

STATUS_PACKETS = (PacketId.STATUS, PacketId.STATUS_2, PacketId.STATUS_3, PacketId.STATUS_4,
                  PacketId.STATUS_5, PacketId.STATUS_6)
STATUS_NUMBER = {packet: number for number, packet in enumerate(STATUS_PACKETS, start=1)}


def ext_id(packet_id: int, controller_id: int) -> int:
    """The 29-bit id of *packet_id* for *controller_id*: ``packet_id << 8 | controller_id``."""
    if not 0 <= controller_id <= MAX_CONTROLLER_ID:
        raise VescCanError(f"VESC controller_id must be 0..255 (255 = broadcast), got {controller_id}")
    if not 0 <= packet_id <= 0xFF:
        raise VescCanError(f"VESC packet id must be 0..255, got {packet_id}")
    return packet_id << 8 | controller_id


def split_ext_id(arb_id: int) -> tuple[int, int]:
    """(packet_id, controller_id) of a VESC extended id; the unused bits 28..16 must be 0."""
    if not 0 <= arb_id <= 0xFFFF:
        raise VescCanError(f"VESC ids use bits 15..0 only (bits 28..16 are 0), got {arb_id:#x}")
    return arb_id >> 8, arb_id & 0xFF


def make_frame(controller_id: int, packet_id: int, data: bytes) -> can.Message:
    """An extended-id data frame carrying *data* for *packet_id* of *controller_id*."""
    import can   # loads python-can with the first frame (see u2sa_hw/ports/can/port.py)
    return can.Message(arbitration_id=ext_id(packet_id, controller_id), data=data, is_extended_id=True)


PROBE_SEEN = "VESC status frames"   # what the frames probe_node recognises are called (u2sa check --probe)
_STATUS_IDS = frozenset(int(p) for p in STATUS_PACKETS)


def probe_node(frame: can.Message) -> int | None:
    """The controller id of *frame* when it is a STATUS frame (extended id, a STATUS packet: a VESC sends
    them cyclically in VESC CAN mode), else None; ``u2sa check --probe`` lists the nodes it heard."""
    if not frame.is_extended_id or frame.is_remote_frame or not 0 <= frame.arbitration_id <= 0xFFFF:
        return None
    packet, node = split_ext_id(frame.arbitration_id)
    return node if packet in _STATUS_IDS else None


def probe_frame(node_id: int) -> can.Message:
    """A frame :func:`probe_node` recognises as *node_id*'s: a stopped motor's STATUS (tests and tools)."""
    return make_frame(node_id, PacketId.STATUS, encode_status(Status1(erpm=0.0, current_a=0.0, duty=0.0)))


def _need(data: bytes, length: int, what: str) -> bytes:
    if len(data) < length:
        raise VescCanError(f"VESC {what}: needs {length} data bytes, got {len(data)} ({bytes(data).hex()})")
    return bytes(data)


def _scaled(value: float, scale: float, bits: int, what: str) -> int:
    scaled = round(value * scale)
    limit = 1 << (bits - 1)
    if not -limit <= scaled < limit:
        raise VescCanError(f"VESC {what} {value} does not fit int{bits} x {scale:g}")
    return scaled


def encode_command(packet_id: int, value: float) -> bytes:
    """The 4-byte payload of a simple command (SET_DUTY, SET_CURRENT, SET_RPM, SET_POS, ...)."""
    scale = _command_scale(packet_id)
    return struct.pack(">i", _scaled(value, scale, 32, PacketId(packet_id).name))


def decode_command(packet_id: int, data: bytes) -> float:
    """The value of a simple command payload (bytes 0-3; a trailing off-delay is not read)."""
    scale = _command_scale(packet_id)
    return struct.unpack_from(">i", _need(data, 4, PacketId(packet_id).name))[0] / scale


def _command_scale(packet_id: int) -> float:
    try:
        return COMMAND_SCALES[PacketId(packet_id)]
    except (ValueError, KeyError):
        raise VescCanError(f"VESC packet {packet_id} is not a simple command; "
                           f"use one of {', '.join(p.name for p in COMMAND_SCALES)}") from None


def encode_set_duty(duty: float) -> bytes:
    """SET_DUTY payload: duty cycle -1..1 x 100000."""
    return encode_command(PacketId.SET_DUTY, duty)


def encode_set_current(current_a: float) -> bytes:
    """SET_CURRENT payload: motor current [A] x 1000 (4-byte form)."""
    return encode_command(PacketId.SET_CURRENT, current_a)


def encode_set_current_brake(current_a: float) -> bytes:
    """SET_CURRENT_BRAKE payload: brake current [A] x 1000."""
    return encode_command(PacketId.SET_CURRENT_BRAKE, current_a)


def encode_set_rpm(erpm: float) -> bytes:
    """SET_RPM payload: electrical RPM x 1."""
    return encode_command(PacketId.SET_RPM, erpm)


def encode_set_pos(degrees: float) -> bytes:
    """SET_POS payload: position [deg] x 1000000."""
    return encode_command(PacketId.SET_POS, degrees)


@dataclass(frozen=True)
class Status1:
    """STATUS: ERPM, total motor current [A], duty cycle (-1..1)."""

    erpm: float
    current_a: float
    duty: float


@dataclass(frozen=True)
class Status2:
    """STATUS_2: amp-hours used and charged."""

    amp_hours: float
    amp_hours_charged: float


@dataclass(frozen=True)
class Status3:
    """STATUS_3: watt-hours used and charged."""

    watt_hours: float
    watt_hours_charged: float


@dataclass(frozen=True)
class Status4:
    """STATUS_4: FET and motor temperature [degC], input current [A], PID position [deg]."""

    temp_fet_c: float
    temp_motor_c: float
    current_in_a: float
    pid_pos_deg: float


@dataclass(frozen=True)
class Status5:
    """STATUS_5: tachometer (6 counts per electrical revolution) and input voltage [V]."""

    tachometer: int
    voltage_in_v: float


@dataclass(frozen=True)
class Status6:
    """STATUS_6: ADC1..3 [V] and the PPM input (-1..1)."""

    adc1_v: float
    adc2_v: float
    adc3_v: float
    ppm: float


# packet -> (dataclass, struct format, scales per field); all big-endian, 8 bytes
_STATUS_LAYOUTS: dict[PacketId, tuple[type, str, tuple[float, ...]]] = {
    PacketId.STATUS: (Status1, ">ihh", (1.0, 10.0, 1000.0)),
    PacketId.STATUS_2: (Status2, ">ii", (10000.0, 10000.0)),
    PacketId.STATUS_3: (Status3, ">ii", (10000.0, 10000.0)),
    PacketId.STATUS_4: (Status4, ">hhhh", (10.0, 10.0, 10.0, 50.0)),
    PacketId.STATUS_5: (Status5, ">ihxx", (1.0, 10.0)),
    PacketId.STATUS_6: (Status6, ">hhhh", (1000.0, 1000.0, 1000.0, 1000.0)),
}

StatusMessage = Status1 | Status2 | Status3 | Status4 | Status5 | Status6


def status_packet_id(status: StatusMessage) -> PacketId:
    """The packet id that carries *status*."""
    for packet, (cls, _, _) in _STATUS_LAYOUTS.items():
        if isinstance(status, cls):
            return packet
    raise VescCanError(f"not a VESC status message: {status!r}")


def encode_status(status: StatusMessage) -> bytes:
    """The 8-byte payload of any STATUS_n message."""
    packet = status_packet_id(status)
    cls, fmt, scales = _STATUS_LAYOUTS[packet]
    values = [getattr(status, name) for name in cls.__dataclass_fields__]
    sizes = {"i": 32, "h": 16}
    fields = [c for c in fmt[1:] if c in sizes]
    ints = [_scaled(v, s, sizes[c], f"{packet.name}.{n}")
            for v, s, c, n in zip(values, scales, fields, cls.__dataclass_fields__)]
    return struct.pack(fmt, *ints)


def decode_status(packet_id: int, data: bytes) -> StatusMessage:
    """The STATUS_n dataclass of a status payload (packet 9, 14, 15, 16, 27 or 58)."""
    try:
        cls, fmt, scales = _STATUS_LAYOUTS[PacketId(packet_id)]
    except (ValueError, KeyError):
        raise VescCanError(f"VESC packet {packet_id} is not a STATUS message") from None
    ints = struct.unpack_from(fmt, _need(data, STATUS_DLC, PacketId(packet_id).name))
    values = [i / s for i, s in zip(ints, scales)]
    if cls is Status5:
        values[0] = ints[0]  # the tachometer is a raw count
    return cls(*values)


# ---- COMM packets over CAN (multi-frame buffers) -------------------------------------------
# comm_can.c carries a COMM_* packet (the UART protocol's payload) to a VESC in FILL_RX_BUFFER
# frames (u8 offset + 7 bytes, offsets up to 255), then FILL_RX_BUFFER_LONG (u16 offset + 6
# bytes), then PROCESS_RX_BUFFER (sender id, send mode, u16 length, u16 CRC, all big-endian);
# up to 6 bytes fit one PROCESS_SHORT_BUFFER (sender id, send mode, payload). With send mode 0
# the VESC answers the same way, addressed to the sender id. The COMM ids are ``CommPacket``.
SEND_REPLY = 0  # process the packet and send the answer back to the sender over CAN
SHORT_MAX = 6
# app configuration as confgenerator_serialize_appconf() writes it: u32 APPCONF_SIGNATURE,
# u8 controller_id, u32 timeout_msec, float32_auto timeout_brake_current, ...
APPCONF_ID_OFFSET = 4
APPCONF_TIMEOUT_OFFSET = 5


def crc16(data: bytes) -> int:
    """CRC-16/XMODEM (poly 0x1021, init 0) as the VESC's crc16() computes it."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def buffer_frames(target_id: int, sender_id: int, payload: bytes, *, send: int = SEND_REPLY) -> list[can.Message]:
    """The frames that carry COMM packet *payload* from *sender_id* to *target_id*."""
    if not payload or len(payload) > 0xFFFF:
        raise VescCanError(f"VESC COMM packet must be 1..65535 bytes, got {len(payload)}")
    if len(payload) <= SHORT_MAX:
        return [make_frame(target_id, PacketId.PROCESS_SHORT_BUFFER, bytes([sender_id, send]) + payload)]
    frames, offset = [], 0
    while offset < len(payload) and offset <= 0xFF:
        frames.append(make_frame(target_id, PacketId.FILL_RX_BUFFER, bytes([offset]) + payload[offset:offset + 7]))
        offset += 7
    while offset < len(payload):
        frames.append(make_frame(target_id, PacketId.FILL_RX_BUFFER_LONG,
                                 struct.pack(">H", offset) + payload[offset:offset + 6]))
        offset += 6
    tail = struct.pack(">BBHH", sender_id, send, len(payload), crc16(payload))
    return frames + [make_frame(target_id, PacketId.PROCESS_RX_BUFFER, tail)]


class BufferAssembler:
    """Collects FILL_RX_BUFFER(_LONG) frames and returns the packet a PROCESS frame completes."""

    def __init__(self, size: int = 4096) -> None:
        self._buffer = bytearray(size)
        self.crc_errors = 0

    def feed(self, packet: int, data: bytes) -> tuple[int, int, bytes] | None:
        """(sender_id, send mode, payload) once complete; VescCanError for a bad frame or CRC."""
        data = bytes(data)
        if packet == PacketId.FILL_RX_BUFFER:
            self._put(_need(data, 1, "FILL_RX_BUFFER")[0], data[1:])
        elif packet == PacketId.FILL_RX_BUFFER_LONG:
            self._put(struct.unpack_from(">H", _need(data, 2, "FILL_RX_BUFFER_LONG"))[0], data[2:])
        elif packet == PacketId.PROCESS_SHORT_BUFFER:
            raw = _need(data, 3, "PROCESS_SHORT_BUFFER")
            return raw[0], raw[1], raw[2:]
        elif packet == PacketId.PROCESS_RX_BUFFER:
            sender, send, length, crc = struct.unpack_from(">BBHH", _need(data, 6, "PROCESS_RX_BUFFER"))
            if length > len(self._buffer):
                raise VescCanError(f"VESC PROCESS_RX_BUFFER: length {length} exceeds the "
                                   f"{len(self._buffer)}-byte buffer")
            payload = bytes(self._buffer[:length])
            if crc16(payload) != crc:
                self.crc_errors += 1
                raise VescCanError(f"VESC PROCESS_RX_BUFFER from id {sender}: CRC {crc:#06x} does not match the "
                                   f"{length} bytes received ({crc16(payload):#06x}); a frame was lost")
            return sender, send, payload
        return None

    def _put(self, offset: int, chunk: bytes) -> None:
        if offset + len(chunk) > len(self._buffer):
            raise VescCanError(f"VESC FILL_RX_BUFFER: offset {offset} beyond the {len(self._buffer)}-byte buffer")
        self._buffer[offset:offset + len(chunk)] = chunk


def appconf_timeout_ms(appconf: bytes, *, controller_id: int) -> int:
    """timeout_msec of a serialized app configuration; VescCanError unless its controller_id
    byte is *controller_id* (the check that the layout is the one this code knows)."""
    raw = _need(appconf, APPCONF_TIMEOUT_OFFSET + 4, "app configuration")
    if raw[APPCONF_ID_OFFSET] != controller_id:
        raise VescCanError(f"VESC app configuration: controller_id byte is {raw[APPCONF_ID_OFFSET]}, expected "
                           f"{controller_id}; unknown layout (firmware too new or too old for this driver)")
    return struct.unpack_from(">I", raw, APPCONF_TIMEOUT_OFFSET)[0]


def appconf_with_timeout(appconf: bytes, timeout_ms: int, *, controller_id: int) -> bytes:
    """*appconf* with timeout_msec replaced (everything else unchanged)."""
    appconf_timeout_ms(appconf, controller_id=controller_id)
    if not 0 <= timeout_ms <= 0xFFFFFFFF:
        raise VescCanError(f"VESC timeout_msec must fit u32, got {timeout_ms}")
    end = APPCONF_TIMEOUT_OFFSET + 4
    return appconf[:APPCONF_TIMEOUT_OFFSET] + struct.pack(">I", timeout_ms) + appconf[end:]
