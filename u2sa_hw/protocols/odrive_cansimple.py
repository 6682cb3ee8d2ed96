"""ODrive CANSimple: framing and payload codecs (command ids and enumerations re-exported).

Shared by the ODrive motor driver and the mock node (mock_devices/odrive_node.py). Facts
come from /work/shared/spec/devices/ODRIVE_CANSIMPLE.md: ODrive's can-protocol docs, CSV
and DBC for firmware 0.5.x (ODrive v3.x) and ODriveArduino's generated messages for 0.6.x
(ODrive Pro / S1 / Micro). Frames use 11-bit ids ``node_id << 5 | cmd``; payload fields
are little-endian and floats IEEE-754 float32. ``Get_*`` values are requested with an RTR
frame on the same id and answered on it; heartbeat and encoder estimates are also cyclic.

The two firmware lines share most ids but differ in the heartbeat's bytes 5-7, in what
ids 0x03-0x06, 0x15, 0x19, 0x1C and 0x1D mean, in the error bits, and in whether Reboot
and Clear_Errors carry a byte. Functions whose layout differs take ``firmware="0.5"|"0.6"``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import can

# the command ids and the enumerations live in their own table modules, re-exported here for one import
from u2sa_hw.protocols.odrive_commands import (COMMAND_NAMES_05, COMMAND_NAMES_06,  # noqa: F401
                                               COMMAND_NAMES_COMMON, Cmd)
from u2sa_hw.protocols.odrive_enums import (AxisError05, AxisState, ControllerError05,  # noqa: F401
                                            ControlMode, InputMode, MotorError05, OdriveError,
                                            ProcedureResult, RebootAction)

CMD_ID_BITS = 5
MAX_NODE_ID = 0x3F
UNADDRESSED_NODE_ID = 0x3F  # 0.6.x address discovery
FIRMWARES = ("0.5", "0.6")
FRAME_DLC = 8  # every data-carrying frame per the DBC (the firmware accepts shorter Set_Axis_State)
# pos_estimate is a float32 in turns: beyond 2**24 turns it cannot count single turns any more,
# so a larger value is no position an axis reports (it is a corrupted or mis-addressed frame)
MAX_POSITION_TURNS = float(2 ** 24)


class CanSimpleError(ValueError):
    """A CANSimple payload or id that cannot be decoded/encoded (says which message and why)."""


def check_firmware(firmware: str) -> str:
    """*firmware* if it is "0.5" or "0.6"; CanSimpleError otherwise."""
    if firmware not in FIRMWARES:
        raise CanSimpleError(f"ODrive firmware must be one of {', '.join(FIRMWARES)}, got {firmware!r}")
    return firmware


def command_name(cmd: int, *, firmware: str = "0.6") -> str:
    """The protocol document's name of *cmd* in that firmware line (``"cmd_0x1e"`` if unused)."""
    table = COMMAND_NAMES_05 if check_firmware(firmware) == "0.5" else COMMAND_NAMES_06
    return table.get(cmd) or COMMAND_NAMES_COMMON.get(cmd) or f"cmd_0x{cmd:02x}"


def arbitration_id(node_id: int, cmd: int) -> int:
    """The 11-bit id of *cmd* for *node_id*: ``node_id << 5 | cmd``."""
    if not 0 <= node_id <= MAX_NODE_ID:
        raise CanSimpleError(f"ODrive node_id must be 0..{MAX_NODE_ID}, got {node_id}")
    if not 0 <= cmd < 1 << CMD_ID_BITS:
        raise CanSimpleError(f"ODrive command id must be 0..0x1F, got {cmd:#x}")
    return node_id << CMD_ID_BITS | cmd


def split_arbitration_id(arb_id: int) -> tuple[int, int]:
    """(node_id, cmd) of an 11-bit CANSimple id."""
    if not 0 <= arb_id <= 0x7FF:
        raise CanSimpleError(f"CANSimple uses 11-bit ids, got {arb_id:#x}")
    return arb_id >> CMD_ID_BITS, arb_id & ((1 << CMD_ID_BITS) - 1)


def make_frame(node_id: int, cmd: int, data: bytes = b"") -> can.Message:
    """A standard-id data frame carrying *data* for *cmd* of *node_id*."""
    import can   # loads python-can with the first frame (see u2sa_hw/ports/can/port.py)
    return can.Message(arbitration_id=arbitration_id(node_id, cmd), data=data, is_extended_id=False)


def make_request(node_id: int, cmd: int, *, dlc: int = 0) -> can.Message:
    """An RTR frame asking *node_id* for a ``Get_*`` value (candump ``009#R``)."""
    import can
    return can.Message(arbitration_id=arbitration_id(node_id, cmd), is_remote_frame=True, dlc=dlc,
                       is_extended_id=False)


PROBE_SEEN = "ODrive heartbeats"   # what the frames probe_node recognises are called (u2sa check --probe)


def probe_node(frame: can.Message) -> int | None:
    """The node id of *frame* when it is a heartbeat (standard id, cmd 0x01, 8 bytes: every live axis sends
    one cyclically, whatever its state), else None; ``u2sa check --probe`` lists the nodes it heard. The
    length keeps a CANopen heartbeat (0x701, one byte) from passing for node 56's."""
    if frame.is_extended_id or frame.is_remote_frame or not 0 <= frame.arbitration_id <= 0x7FF:
        return None
    if len(frame.data) != FRAME_DLC:
        return None
    node, cmd = split_arbitration_id(frame.arbitration_id)
    return node if cmd == Cmd.HEARTBEAT else None


def probe_frame(node_id: int) -> can.Message:
    """A frame :func:`probe_node` recognises as *node_id*'s: an idle axis's heartbeat (tests and tools)."""
    return make_frame(node_id, Cmd.HEARTBEAT, encode_heartbeat(Heartbeat(axis_error=0, axis_state=AxisState.IDLE)))


def _need(data: bytes, length: int, what: str) -> bytes:
    if len(data) < length:
        raise CanSimpleError(f"ODrive {what}: needs {length} data bytes, got {len(data)} ({bytes(data).hex()})")
    return bytes(data)


def _pad(payload: bytes) -> bytes:
    return payload.ljust(FRAME_DLC, b"\0")


def encode_floats(*values: float) -> bytes:
    """One or two float32 fields (LE) padded to 8 bytes: Set_Input_Vel, Set_Limits, Get_Iq, ..."""
    return _pad(struct.pack(f"<{len(values)}f", *values))


def decode_floats(data: bytes, count: int, *, what: str = "float payload") -> tuple[float, ...]:
    """*count* float32 fields (LE) from the start of *data*."""
    return struct.unpack_from(f"<{count}f", _need(data, 4 * count, what))


def encode_u32(value: int) -> bytes:
    """One unsigned 32-bit field (LE) padded to 8 bytes: Set_Axis_State, error replies, node id."""
    if not 0 <= value <= 0xFFFFFFFF:
        raise CanSimpleError(f"ODrive u32 field out of range: {value}")
    return _pad(struct.pack("<I", value))


def decode_u32(data: bytes, *, what: str = "u32 payload") -> int:
    """The unsigned 32-bit field (LE) at byte 0."""
    return struct.unpack_from("<I", _need(data, 4, what))[0]


def encode_i32(value: int) -> bytes:
    """One signed 32-bit field (LE) padded to 8 bytes: 0.5 Set_Linear_Count."""
    if not -0x80000000 <= value <= 0x7FFFFFFF:
        raise CanSimpleError(f"ODrive i32 field out of range: {value}")
    return _pad(struct.pack("<i", value))


def decode_i32(data: bytes, *, what: str = "i32 payload") -> int:
    """The signed 32-bit field (LE) at byte 0."""
    return struct.unpack_from("<i", _need(data, 4, what))[0]


@dataclass(frozen=True)
class Heartbeat:
    """Heartbeat (0x01). ``procedure_result`` is 0.6 only; the three error flags are 0.5 only."""

    axis_error: int
    axis_state: int
    procedure_result: int = 0
    trajectory_done: bool = False
    motor_error_flag: bool = False
    encoder_error_flag: bool = False
    controller_error_flag: bool = False


def encode_heartbeat(hb: Heartbeat, *, firmware: str = "0.6") -> bytes:
    """Heartbeat payload: 0.6 ``u32 error, u8 state, u8 result, u8 bit0 traj_done, 0``;
    0.5 ``u32 error, u8 state, bit40 motor, bit48 encoder, bit56 controller, bit63 traj_done``."""
    if check_firmware(firmware) == "0.6":
        tail = bytes([hb.procedure_result & 0xFF, int(hb.trajectory_done), 0])
    else:
        tail = bytes([int(hb.motor_error_flag), int(hb.encoder_error_flag),
                      int(hb.controller_error_flag) | (0x80 if hb.trajectory_done else 0)])
    return struct.pack("<IB", hb.axis_error & 0xFFFFFFFF, hb.axis_state & 0xFF) + tail


def decode_heartbeat(data: bytes, *, firmware: str = "0.6") -> Heartbeat:
    """Inverse of :func:`encode_heartbeat`."""
    raw = _need(data, 8, "Heartbeat")
    error, state = struct.unpack_from("<IB", raw)
    if check_firmware(firmware) == "0.6":
        return Heartbeat(error, state, procedure_result=raw[5], trajectory_done=bool(raw[6] & 1))
    return Heartbeat(error, state, trajectory_done=bool(raw[7] & 0x80), motor_error_flag=bool(raw[5] & 1),
                     encoder_error_flag=bool(raw[6] & 1), controller_error_flag=bool(raw[7] & 1))


def encode_set_axis_state(state: int) -> bytes:
    """Set_Axis_State (0x07): u32 requested state."""
    return encode_u32(int(state))


def decode_set_axis_state(data: bytes) -> int:
    """Requested state of a Set_Axis_State payload (the firmware needs only 4 bytes)."""
    return decode_u32(data, what="Set_Axis_State")


def encode_set_controller_mode(control_mode: int, input_mode: int) -> bytes:
    """Set_Controller_Mode (0x0B): u32 control mode, u32 input mode."""
    return struct.pack("<II", int(control_mode), int(input_mode))


def decode_set_controller_mode(data: bytes) -> tuple[int, int]:
    """(control_mode, input_mode) of a Set_Controller_Mode payload."""
    return struct.unpack_from("<II", _need(data, 8, "Set_Controller_Mode"))


def encode_set_input_vel(vel_rev_s: float, torque_ff_nm: float = 0.0) -> bytes:
    """Set_Input_Vel (0x0D): f32 velocity [rev/s], f32 torque feed-forward [Nm]."""
    return encode_floats(vel_rev_s, torque_ff_nm)


def decode_set_input_vel(data: bytes) -> tuple[float, float]:
    """(vel_rev_s, torque_ff_nm) of a Set_Input_Vel payload."""
    return decode_floats(data, 2, what="Set_Input_Vel")  # type: ignore[return-value]


def _i16_milli(value: float, what: str) -> int:
    scaled = round(value * 1000.0)
    if not -0x8000 <= scaled <= 0x7FFF:
        raise CanSimpleError(f"ODrive Set_Input_Pos {what} {value} does not fit int16 x 0.001 (+-32.767)")
    return scaled


def encode_set_input_pos(pos_rev: float, vel_ff_rev_s: float = 0.0, torque_ff_nm: float = 0.0) -> bytes:
    """Set_Input_Pos (0x0C): f32 position [rev], i16 vel_ff x0.001 [rev/s], i16 torque_ff x0.001 [Nm]."""
    return struct.pack("<fhh", pos_rev, _i16_milli(vel_ff_rev_s, "vel_ff"), _i16_milli(torque_ff_nm, "torque_ff"))


def decode_set_input_pos(data: bytes) -> tuple[float, float, float]:
    """(pos_rev, vel_ff_rev_s, torque_ff_nm) of a Set_Input_Pos payload."""
    pos, vel_ff, torque_ff = struct.unpack_from("<fhh", _need(data, 8, "Set_Input_Pos"))
    return pos, vel_ff * 0.001, torque_ff * 0.001


def encode_encoder_estimates(pos_rev: float, vel_rev_s: float) -> bytes:
    """Get_Encoder_Estimates reply (0x09): f32 position [rev], f32 velocity [rev/s]."""
    return encode_floats(pos_rev, vel_rev_s)


def decode_encoder_estimates(data: bytes) -> tuple[float, float]:
    """(pos_rev, vel_rev_s) of an encoder estimates frame."""
    return decode_floats(data, 2, what="Get_Encoder_Estimates")  # type: ignore[return-value]


def encode_set_limits(vel_limit_rev_s: float, current_limit_a: float) -> bytes:
    """Set_Limits (0x0F): f32 velocity limit [rev/s], f32 current limit [A]."""
    return encode_floats(vel_limit_rev_s, current_limit_a)


def decode_set_limits(data: bytes) -> tuple[float, float]:
    """(vel_limit_rev_s, current_limit_a) of a Set_Limits payload."""
    return decode_floats(data, 2, what="Set_Limits")  # type: ignore[return-value]


def encode_bus_voltage_current(voltage_v: float, current_a: float) -> bytes:
    """Get_Bus_Voltage_Current reply (0x17): f32 bus voltage [V], f32 bus current [A]."""
    return encode_floats(voltage_v, current_a)


def decode_bus_voltage_current(data: bytes) -> tuple[float, float]:
    """(voltage_v, current_a) of a Get_Bus_Voltage_Current reply."""
    return decode_floats(data, 2, what="Get_Bus_Voltage_Current")  # type: ignore[return-value]


def encode_get_error(active_errors: int, disarm_reason: int) -> bytes:
    """Get_Error reply (0x03, firmware 0.6): u32 active errors, u32 disarm reason."""
    return struct.pack("<II", active_errors & 0xFFFFFFFF, disarm_reason & 0xFFFFFFFF)


def decode_get_error(data: bytes) -> tuple[int, int]:
    """(active_errors, disarm_reason) of a 0.6 Get_Error reply."""
    return struct.unpack_from("<II", _need(data, 8, "Get_Error"))


def encode_motor_error(motor_error: int) -> bytes:
    """Get_Motor_Error reply (0x03, firmware 0.5): the CSV's u64 (the DBC declares only 32 bits)."""
    return struct.pack("<Q", motor_error & 0xFFFFFFFFFFFFFFFF)


def decode_motor_error(data: bytes) -> int:
    """Motor error of a 0.5 Get_Motor_Error reply (u64; a 4-byte reply is read as u32)."""
    raw = _need(data, 4, "Get_Motor_Error")
    return struct.unpack_from("<Q", raw)[0] if len(raw) >= 8 else struct.unpack_from("<I", raw)[0]


def encode_clear_errors(*, identify: bool = False, firmware: str = "0.6") -> bytes:
    """Clear_Errors (0x18): 0.6 carries u8 Identify (DLC 1), 0.5 is empty (DLC 0)."""
    return bytes([int(identify)]) if check_firmware(firmware) == "0.6" else b""


def encode_reboot(action: int = RebootAction.REBOOT, *, firmware: str = "0.6") -> bytes:
    """Reboot (0x16): 0.6 carries u8 action (DLC 1), 0.5 is empty (DLC 0) and always reboots."""
    return bytes([int(action)]) if check_firmware(firmware) == "0.6" else b""


def decode_reboot(data: bytes) -> int:
    """The Reboot action (an empty 0.5 frame means REBOOT)."""
    return data[0] if data else RebootAction.REBOOT


@dataclass(frozen=True)
class Version:
    """Get_Version reply (0x00, firmware 0.6)."""

    protocol: int
    hw_major: int
    hw_minor: int
    hw_variant: int
    fw_major: int
    fw_minor: int
    fw_revision: int
    fw_unreleased: int


def encode_version(version: Version) -> bytes:
    """Get_Version reply payload: eight u8 fields."""
    return bytes([version.protocol, version.hw_major, version.hw_minor, version.hw_variant,
                  version.fw_major, version.fw_minor, version.fw_revision, version.fw_unreleased])


def decode_version(data: bytes) -> Version:
    """Inverse of :func:`encode_version`."""
    return Version(*_need(data, 8, "Get_Version")[:8])


def encode_encoder_count(shadow_count: int, count_in_cpr: int) -> bytes:
    """Get_Encoder_Count reply (0x0A, firmware 0.5): i32 shadow count, i32 count in CPR."""
    return struct.pack("<ii", shadow_count, count_in_cpr)


def decode_encoder_count(data: bytes) -> tuple[int, int]:
    """(shadow_count, count_in_cpr) of a 0.5 Get_Encoder_Count reply."""
    return struct.unpack_from("<ii", _need(data, 8, "Get_Encoder_Count"))


# ---- 0.6 endpoint access (RxSdo 0x04 / TxSdo 0x05) ------------------------------------------
# Endpoint ids come from the flat_endpoints.json of one firmware build and change between builds,
# so they are never hard-coded here: the caller names them (and the build they belong to).
SDO_READ = 0
SDO_WRITE = 1
SDO_TYPES = {"float": "<f", "bool": "<?", "uint8": "<B", "uint16": "<H", "uint32": "<I", "int32": "<i"}


def _sdo_format(kind: str) -> str:
    try:
        return SDO_TYPES[kind]
    except KeyError:
        raise CanSimpleError(f"ODrive endpoint type must be one of {', '.join(SDO_TYPES)}, got {kind!r}") from None


def encode_sdo_read(endpoint_id: int) -> bytes:
    """RxSdo read request: u8 opcode 0, u16 endpoint id, u8 reserved (DLC 4)."""
    return struct.pack("<BHB", SDO_READ, endpoint_id, 0)


def encode_sdo_write(endpoint_id: int, kind: str, value: float | int | bool) -> bytes:
    """RxSdo write: u8 opcode 1, u16 endpoint id, u8 reserved, the value in the endpoint's type (LE)."""
    return struct.pack("<BHB", SDO_WRITE, endpoint_id, 0) + struct.pack(_sdo_format(kind), value)


def decode_rx_sdo(data: bytes) -> tuple[int, int, bytes]:
    """(opcode, endpoint_id, value bytes) of an RxSdo frame."""
    raw = _need(data, 4, "RxSdo")
    opcode, endpoint, _ = struct.unpack_from("<BHB", raw)
    if opcode not in (SDO_READ, SDO_WRITE):
        raise CanSimpleError(f"ODrive RxSdo: opcode must be 0 (read) or 1 (write), got {opcode}")
    return opcode, endpoint, raw[4:]


def encode_tx_sdo(endpoint_id: int, kind: str, value: float | int | bool) -> bytes:
    """TxSdo reply: u8 reserved, u16 endpoint id, u8 reserved, the value in the endpoint's type (LE)."""
    return struct.pack("<BHB", 0, endpoint_id, 0) + struct.pack(_sdo_format(kind), value)


def decode_tx_sdo(data: bytes) -> tuple[int, bytes]:
    """(endpoint_id, value bytes) of a TxSdo reply."""
    raw = _need(data, 4, "TxSdo")
    return struct.unpack_from("<H", raw, 1)[0], raw[4:]


def sdo_value(kind: str, raw: bytes) -> float | int | bool:
    """The value of *raw* endpoint bytes read as *kind* (float, bool, uint8, ...)."""
    fmt = _sdo_format(kind)
    return struct.unpack_from(fmt, _need(raw, struct.calcsize(fmt), f"{kind} endpoint value"))[0]


def version_text(version: Version) -> str:
    """``"0.6.10"`` for a Get_Version reply (``"0.6.10-dev"`` for an unreleased build)."""
    text = f"{version.fw_major}.{version.fw_minor}.{version.fw_revision}"
    return text + "-dev" if version.fw_unreleased else text
