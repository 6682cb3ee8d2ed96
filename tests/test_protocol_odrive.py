"""ODrive CANSimple codecs against the worked frames of spec/devices/ODRIVE_CANSIMPLE.md and the DBC layouts."""

from __future__ import annotations

import struct

import pytest

from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols.odrive_cansimple import AxisState, Cmd, ControlMode, InputMode


def candump(msg) -> str:
    """A frame in candump notation, as the spec writes its worked frames."""
    if msg.is_remote_frame:
        return f"{msg.arbitration_id:03X}#R"
    return f"{msg.arbitration_id:03X}#{bytes(msg.data).hex().upper()}"


# ---- worked frames from the spec --------------------------------------------------------
def test_set_input_vel_node1() -> None:
    msg = cs.make_frame(1, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(2.5, 0.0))
    assert candump(msg) == "02D#0000204000000000"
    assert not msg.is_extended_id


def test_heartbeat_node3_closed_loop_06() -> None:
    hb = cs.Heartbeat(axis_error=0, axis_state=AxisState.CLOSED_LOOP_CONTROL, procedure_result=0, trajectory_done=True)
    assert candump(cs.make_frame(3, Cmd.HEARTBEAT, cs.encode_heartbeat(hb, firmware="0.6"))) == "061#0000000008000100"
    assert cs.decode_heartbeat(bytes.fromhex("0000000008000100"), firmware="0.6") == hb


def test_encoder_estimates_node0() -> None:
    assert candump(cs.make_frame(0, Cmd.GET_ENCODER_ESTIMATES, cs.encode_encoder_estimates(1.5, -0.25))) == \
        "009#0000C03F000080BE"
    assert cs.decode_encoder_estimates(bytes.fromhex("0000C03F000080BE")) == (1.5, -0.25)


def test_set_input_pos_node2() -> None:
    msg = cs.make_frame(2, Cmd.SET_INPUT_POS, cs.encode_set_input_pos(10.0, 1.5, -0.2))
    assert candump(msg) == "04C#00002041DC0538FF"
    pos, vel_ff, torque_ff = cs.decode_set_input_pos(msg.data)
    assert (pos, vel_ff, torque_ff) == (10.0, pytest.approx(1.5), pytest.approx(-0.2))


def test_set_axis_state_closed_loop_node0() -> None:
    assert candump(cs.make_frame(0, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))) == \
        "007#0800000000000000"
    assert cs.decode_set_axis_state(bytes.fromhex("08000000")) == AxisState.CLOSED_LOOP_CONTROL  # 4 bytes suffice


def test_bus_voltage_current_node0() -> None:
    msg = cs.make_frame(0, Cmd.GET_BUS_VOLTAGE_CURRENT, cs.encode_bus_voltage_current(24.1, 0.35))
    assert candump(msg) == "017#CDCCC0413333B33E"
    voltage, current = cs.decode_bus_voltage_current(msg.data)
    assert voltage == pytest.approx(24.1, abs=1e-5) and current == pytest.approx(0.35, abs=1e-6)


def test_rtr_request_encoder_estimates_node0() -> None:
    msg = cs.make_request(0, Cmd.GET_ENCODER_ESTIMATES)
    assert candump(msg) == "009#R" and msg.dlc == 0


def test_docs_example_node1_set_input_pos_is_0x2c() -> None:
    assert cs.arbitration_id(0x01, Cmd.SET_INPUT_POS) == 0x2C
    assert cs.split_arbitration_id(0x2C) == (1, Cmd.SET_INPUT_POS)


# ---- ids and names ----------------------------------------------------------------------
@pytest.mark.parametrize("node_id,cmd", [(-1, 1), (0x40, 1), (1, 0x20), (1, -1)])
def test_arbitration_id_rejects_out_of_range(node_id: int, cmd: int) -> None:
    with pytest.raises(cs.CanSimpleError, match="node_id|command id"):
        cs.arbitration_id(node_id, cmd)


def test_split_rejects_extended_ids() -> None:
    with pytest.raises(cs.CanSimpleError, match="11-bit"):
        cs.split_arbitration_id(0x800)


def test_every_id_round_trips() -> None:
    for node_id in range(cs.MAX_NODE_ID + 1):
        for cmd in range(32):
            assert cs.split_arbitration_id(cs.arbitration_id(node_id, cmd)) == (node_id, cmd)


def test_command_names_follow_the_firmware_line() -> None:
    assert cs.command_name(0x03, firmware="0.5") == "Get_Motor_Error"
    assert cs.command_name(0x03, firmware="0.6") == "Get_Error"
    assert cs.command_name(0x19, firmware="0.5") == "Set_Linear_Count"
    assert cs.command_name(0x19, firmware="0.6") == "Set_Absolute_Position"
    assert cs.command_name(0x0D) == "Set_Input_Vel"
    assert cs.command_name(0x1E) == "cmd_0x1e"
    assert Cmd.GET_MOTOR_ERROR == Cmd.GET_ERROR == 0x03
    with pytest.raises(cs.CanSimpleError, match="firmware"):
        cs.command_name(1, firmware="0.4")


def test_enumeration_values_from_the_spec() -> None:
    assert ControlMode.VELOCITY_CONTROL == 2 and InputMode.VEL_RAMP == 2 and InputMode.TRAP_TRAJ == 5
    assert AxisState.IDLE == 1 and AxisState.ANTICOGGING_CALIBRATION == 14
    assert cs.OdriveError.WATCHDOG_TIMER_EXPIRED == 0x1000000
    assert cs.OdriveError.ESTOP_REQUESTED == 0x2000000
    assert cs.AxisError05.WATCHDOG_TIMER_EXPIRED == 0x800 and cs.AxisError05.ESTOP_REQUESTED == 0x4000
    assert cs.MotorError05.UNBALANCED_PHASES == 1 << 35
    assert cs.ProcedureResult.DISARMED == 3 and cs.RebootAction.ENTER_DFU == 3


# ---- firmware 0.5 heartbeat: DBC bits 40 (motor), 48 (encoder), 56 (controller), 63 (traj done) ----
@pytest.mark.parametrize("field,bit", [("motor_error_flag", 40), ("encoder_error_flag", 48),
                                       ("controller_error_flag", 56), ("trajectory_done", 63)])
def test_heartbeat_05_flag_bits(field: str, bit: int) -> None:
    hb = cs.Heartbeat(axis_error=0x800, axis_state=AxisState.IDLE, **{field: True})
    raw = cs.encode_heartbeat(hb, firmware="0.5")
    value = int.from_bytes(raw, "little")
    assert value == 0x800 | 1 << 32 | 1 << bit
    assert cs.decode_heartbeat(raw, firmware="0.5") == hb


def test_heartbeat_06_keeps_procedure_result() -> None:
    hb = cs.Heartbeat(axis_error=int(cs.OdriveError.ESTOP_REQUESTED), axis_state=AxisState.IDLE,
                      procedure_result=cs.ProcedureResult.DISARMED)
    raw = cs.encode_heartbeat(hb)
    assert raw == struct.pack("<IBBBB", 0x2000000, 1, 3, 0, 0)
    assert cs.decode_heartbeat(raw) == hb


# ---- round trips ------------------------------------------------------------------------
def test_round_trips() -> None:
    assert cs.decode_set_controller_mode(cs.encode_set_controller_mode(ControlMode.VELOCITY_CONTROL,
                                                                       InputMode.VEL_RAMP)) == (2, 2)
    assert cs.decode_set_input_vel(cs.encode_set_input_vel(-1.25, 0.5)) == (-1.25, 0.5)
    assert cs.decode_set_limits(cs.encode_set_limits(4.0, 12.5)) == (4.0, 12.5)
    assert cs.decode_get_error(cs.encode_get_error(0x1000040, 0x40)) == (0x1000040, 0x40)
    assert cs.decode_motor_error(cs.encode_motor_error(1 << 35 | 8)) == 1 << 35 | 8
    assert cs.decode_motor_error(struct.pack("<I", 0x1000)) == 0x1000  # a DBC-sized 32-bit reply
    assert cs.decode_encoder_count(cs.encode_encoder_count(-9000, 7384)) == (-9000, 7384)
    assert cs.decode_i32(cs.encode_i32(-123456)) == -123456
    assert cs.decode_floats(cs.encode_floats(3.0), 1) == (3.0,)
    version = cs.Version(2, 3, 6, 56, 0, 6, 10, 0)
    assert cs.decode_version(cs.encode_version(version)) == version


def test_frames_are_dlc_8_unless_the_dbc_says_empty() -> None:
    for payload in (cs.encode_set_axis_state(8), cs.encode_set_input_vel(1.0), cs.encode_floats(1.0),
                    cs.encode_u32(3), cs.encode_set_input_pos(1.0)):
        assert len(payload) == 8
    assert cs.encode_clear_errors(firmware="0.5") == b"" and cs.encode_reboot(firmware="0.5") == b""
    assert cs.encode_clear_errors(identify=True) == b"\x01"
    assert cs.encode_reboot(cs.RebootAction.SAVE_CONFIGURATION) == b"\x01"
    assert cs.decode_reboot(b"") == cs.RebootAction.REBOOT and cs.decode_reboot(b"\x02") == 2


# ---- bad input ----------------------------------------------------------------------------
@pytest.mark.parametrize("decode", [cs.decode_heartbeat, cs.decode_set_input_vel, cs.decode_set_input_pos,
                                    cs.decode_encoder_estimates, cs.decode_set_controller_mode,
                                    cs.decode_bus_voltage_current, cs.decode_get_error, cs.decode_version])
def test_truncated_payloads_raise_a_named_error(decode) -> None:
    with pytest.raises(cs.CanSimpleError, match=r"ODrive \w+: needs \d+ data bytes, got 3 \(010203\)"):
        decode(b"\x01\x02\x03")


def test_set_input_pos_feed_forward_must_fit_int16() -> None:
    with pytest.raises(cs.CanSimpleError, match="vel_ff 40.0 does not fit int16"):
        cs.encode_set_input_pos(0.0, 40.0)
    assert cs.decode_set_input_pos(cs.encode_set_input_pos(0.0, 32.767, -32.768))[1:] == \
        (pytest.approx(32.767), pytest.approx(-32.768))


def test_u32_out_of_range() -> None:
    with pytest.raises(cs.CanSimpleError, match="out of range"):
        cs.encode_u32(-1)


# ---- 0.6 endpoint access (RxSdo / TxSdo) ------------------------------------------------------
def test_sdo_frames_follow_the_rxsdo_txsdo_layout() -> None:
    # node 1 writes 0.3 (float32 0x3E99999A) to endpoint 0x0123: opcode 1, u16 id LE, reserved, value LE
    write = cs.make_frame(1, cs.Cmd.RX_SDO, cs.encode_sdo_write(0x0123, "float", 0.3))
    assert (write.arbitration_id, bytes(write.data).hex()) == (0x24, "012301009a99993e")
    assert bytes(cs.encode_sdo_write(0x0124, "bool", True)).hex() == "0124010001"
    assert bytes(cs.encode_sdo_read(0x0123)).hex() == "00230100"
    assert cs.decode_rx_sdo(write.data) == (1, 0x0123, bytes.fromhex("9a99993e"))
    reply = cs.encode_tx_sdo(0x0123, "float", 0.3)
    endpoint, raw = cs.decode_tx_sdo(reply)
    assert endpoint == 0x0123 and cs.sdo_value("float", raw) == pytest.approx(0.3)
    assert cs.sdo_value("bool", cs.decode_tx_sdo(cs.encode_tx_sdo(7, "bool", False))[1]) is False


def test_sdo_bad_input_raises_a_named_error() -> None:
    with pytest.raises(cs.CanSimpleError, match="RxSdo: opcode must be 0"):
        cs.decode_rx_sdo(bytes([7, 1, 0, 0]))
    with pytest.raises(cs.CanSimpleError, match="TxSdo: needs 4 data bytes"):
        cs.decode_tx_sdo(b"\x00\x01")
    with pytest.raises(cs.CanSimpleError, match="float endpoint value: needs 4"):
        cs.sdo_value("float", b"\x01")
    with pytest.raises(cs.CanSimpleError, match="endpoint type must be one of"):
        cs.encode_sdo_write(1, "double", 1.0)


def test_version_text_marks_unreleased_builds() -> None:
    release = cs.Version(2, 3, 6, 56, 0, 6, 10, 0)
    assert cs.version_text(release) == "0.6.10"
    assert cs.version_text(cs.Version(2, 3, 6, 56, 0, 6, 10, 1)) == "0.6.10-dev"
