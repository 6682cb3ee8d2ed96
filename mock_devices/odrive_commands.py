"""What the mock ODrive node does with each CANSimple command: :class:`OdriveCommands`.

A mixin of :class:`~u2sa_hw.mocks.odrive_node.OdriveCanNode`, which owns the axis's state and hands
every frame on its id to the tables built here (after feeding the watchdog). The getters answer an RTR
(or empty) frame with the value of the firmware in force (0.6 or 0.5); the setters carry out
Set_Axis_State, the controller mode and inputs, the limits and gains, RxSdo (through
mock_devices/odrive_config.py), Clear_Errors, Reboot (save, erase, DFU) and the encoder position.
They use the node's state and its ``_boot``, ``_drive``, ``_estimates``, ``_error_bit``,
``_raise_error``, ``_send`` and ``stop_answering``.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from u2sa_hw.mocks.odrive_config import VERSION_06, endpoint_access
from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols.odrive_cansimple import AxisState, Cmd, InputMode, ProcedureResult

CALIBRATION_STATES = frozenset({AxisState.STARTUP_SEQUENCE, AxisState.FULL_CALIBRATION_SEQUENCE,
                                AxisState.MOTOR_CALIBRATION, AxisState.ENCODER_INDEX_SEARCH,
                                AxisState.ENCODER_OFFSET_CALIBRATION, AxisState.LOCKIN_SPIN,
                                AxisState.ENCODER_DIR_FIND, AxisState.HOMING,
                                AxisState.ENCODER_HALL_POLARITY_CALIBRATION,
                                AxisState.ENCODER_HALL_PHASE_CALIBRATION, AxisState.ANTICOGGING_CALIBRATION})


class OdriveCommands:
    """The CANSimple command set of the mock ODrive node (see the module docstring)."""

    def _getter_table(self) -> dict[int, Callable[[], bytes]]:
        table: dict[int, Callable[[], bytes]] = {
            Cmd.GET_ENCODER_ESTIMATES: lambda: cs.encode_encoder_estimates(*self._estimates()),
            Cmd.GET_IQ: lambda: cs.encode_floats(0.0, 0.0),  # no current model
            Cmd.GET_BUS_VOLTAGE_CURRENT: lambda: cs.encode_bus_voltage_current(self.bus_voltage_v,
                                                                                 self.bus_current_a),
        }
        if self.firmware == "0.6":
            table.update({
                Cmd.GET_VERSION: lambda: cs.encode_version(VERSION_06),
                Cmd.GET_ERROR: lambda: cs.encode_get_error(self.axis_error, self.disarm_reason),
                Cmd.GET_TEMPERATURE: lambda: cs.encode_floats(self.fet_temp_c, self.motor_temp_c),
                Cmd.GET_TORQUES: lambda: cs.encode_floats(0.0, 0.0),
                Cmd.GET_POWERS: lambda: cs.encode_floats(0.0, 0.0),
            })
        else:
            table.update({
                Cmd.GET_MOTOR_ERROR: lambda: cs.encode_motor_error(self.motor_error),
                Cmd.GET_ENCODER_ERROR: lambda: cs.encode_u32(self.encoder_error),
                Cmd.GET_SENSORLESS_ERROR: lambda: cs.encode_u32(0),
                Cmd.GET_CONTROLLER_ERROR: lambda: cs.encode_u32(self.controller_error),
                Cmd.GET_SENSORLESS_ESTIMATES: lambda: cs.encode_encoder_estimates(*self._estimates()),
                Cmd.GET_ENCODER_COUNT: self._encoder_count,
            })
        return table

    def _encoder_count(self) -> bytes:
        shadow = round(self._estimates()[0] * self.encoder_cpr)
        return cs.encode_encoder_count(shadow, shadow % self.encoder_cpr)

    def _setter_table(self) -> dict[int, Callable[[bytes, float], None]]:
        cfg = self._config_floats
        table: dict[int, Callable[[bytes, float], None]] = {
            Cmd.ESTOP: lambda data, now: self._raise_error(self._error_bit("ESTOP_REQUESTED")),
            Cmd.SET_AXIS_STATE: lambda data, now: self._request_state(cs.decode_set_axis_state(data)),
            Cmd.SET_CONTROLLER_MODE: self._set_controller_mode,
            Cmd.SET_INPUT_POS: self._set_input_pos,
            Cmd.SET_INPUT_VEL: self._set_input_vel,
            Cmd.SET_INPUT_TORQUE: lambda data, now: setattr(self, "input_torque", cs.decode_floats(data, 1)[0]),
            Cmd.SET_LIMITS: cfg("vel_limit", "current_limit"),
            Cmd.SET_TRAJ_VEL_LIMIT: cfg("traj_vel_limit"),
            Cmd.SET_TRAJ_ACCEL_LIMITS: cfg("traj_accel_limit", "traj_decel_limit"),
            Cmd.SET_TRAJ_INERTIA: cfg("traj_inertia"),
            Cmd.SET_POS_GAIN: cfg("pos_gain"),
            Cmd.SET_VEL_GAINS: cfg("vel_gain", "vel_integrator_gain"),
            Cmd.REBOOT: self._reboot,
            Cmd.CLEAR_ERRORS: self._clear_errors,
        }
        if self.firmware == "0.6":
            table[Cmd.RX_SDO] = self._rx_sdo
            table[Cmd.SET_ABSOLUTE_POSITION] = lambda data, now: self._set_position(cs.decode_floats(data, 1)[0])
            table[Cmd.ENTER_DFU_MODE] = lambda data, now: self.stop_answering(True)
        else:
            table[Cmd.SET_LINEAR_COUNT] = lambda data, now: self._set_position(
                cs.decode_i32(data, what="Set_Linear_Count") / self.encoder_cpr)
            table[Cmd.SET_AXIS_NODE_ID] = self._set_node_id
        return table

    def _request_state(self, state: int) -> None:
        if state == AxisState.CLOSED_LOOP_CONTROL:
            if self.axis_error:
                self.procedure_result = ProcedureResult.DISARMED
                return
            if self.axis_state != AxisState.CLOSED_LOOP_CONTROL:
                self.vel_setpoint = 0.0
                self.input_pos = self._estimates()[0]  # the firmware holds position on arming
            self.axis_state = AxisState.CLOSED_LOOP_CONTROL
            self.procedure_result = ProcedureResult.SUCCESS
        elif state == AxisState.IDLE or state in CALIBRATION_STATES:
            # the mock is calibrated: a calibration request completes at once and leaves the axis IDLE
            self.axis_state = AxisState.IDLE
            self.procedure_result = ProcedureResult.SUCCESS
            self._drive(0.0)
        elif state != AxisState.UNDEFINED:
            if self.firmware == "0.5":
                self._raise_error(int(cs.AxisError05.INVALID_STATE))
            self.procedure_result = ProcedureResult.INVALID_STATE

    def _rx_sdo(self, data: bytes, now: float) -> None:
        opcode, endpoint, raw = cs.decode_rx_sdo(data)
        self.sdo_log.append((now, opcode, endpoint, raw))
        reply = endpoint_access(self.config, opcode, endpoint, raw, frozen=self.config_frozen, node_name=self.name)
        if reply is not None:
            self._send(cs.make_frame(self.node_id, Cmd.TX_SDO, reply))

    def _set_controller_mode(self, data: bytes, now: float) -> None:
        self.config.control_mode, self.config.input_mode = cs.decode_set_controller_mode(data)

    def _set_input_vel(self, data: bytes, now: float) -> None:
        self.input_vel, self.input_torque = cs.decode_set_input_vel(data)

    def _set_input_pos(self, data: bytes, now: float) -> None:
        self.input_pos, self.vel_ff, self.input_torque = cs.decode_set_input_pos(data)
        if self.config.input_mode == InputMode.TRAP_TRAJ:  # the only mode that plans a trajectory
            self._traj_done = False

    def _config_floats(self, *fields: str) -> Callable[[bytes, float], None]:
        """A setter storing a payload's float32 fields, in order, in the named config fields."""
        def setter(data: bytes, now: float) -> None:
            for field, value in zip(fields, cs.decode_floats(data, len(fields))):
                setattr(self.config, field, value)
        return setter

    def _set_position(self, pos_rev: float) -> None:
        self._pos_offset += pos_rev - self._estimates()[0]

    def _set_node_id(self, data: bytes, now: float) -> None:
        node_id = cs.decode_u32(data, what="Set_Axis_Node_ID")
        cs.arbitration_id(node_id, 0)
        self.config.node_id = node_id

    def _clear_errors(self, data: bytes, now: float) -> None:
        self.axis_error = self.motor_error = self.encoder_error = self.controller_error = 0
        self.identify = bool(data[:1] == b"\x01")

    def _reboot(self, data: bytes, now: float) -> None:
        action = cs.decode_reboot(data) if self.firmware == "0.6" else cs.RebootAction.REBOOT
        if action == cs.RebootAction.SAVE_CONFIGURATION:
            self._saved = dataclasses.replace(self.config)
            return
        if action == cs.RebootAction.ERASE_CONFIGURATION:
            self._saved = dataclasses.replace(self._factory)
        elif action == cs.RebootAction.ENTER_DFU:
            self.stop_answering(True)
            return
        self._boot()
