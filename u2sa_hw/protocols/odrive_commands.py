"""ODrive CANSimple command ids and their names in each firmware line (0.5.x and 0.6.x).

The command table of /work/shared/spec/devices/ODRIVE_CANSIMPLE.md: a command id is the low 5
bits of a frame's 11-bit id (``node_id << 5 | cmd``). The two firmware lines share most ids,
but some mean something else (or nothing) in the other line: ``Cmd`` names both meanings, and
the name tables say which applies where. Imported through ``odrive_cansimple``, whose
``command_name`` reads these tables.
"""

from __future__ import annotations

from enum import IntEnum


class Cmd(IntEnum):
    """Command ids (low 5 bits of the arbitration id); 0.5.x names are aliases of the same ids."""

    GET_VERSION = 0x00  # 0.6 (0.5: CANOpen NMT, reserved)
    HEARTBEAT = 0x01
    ESTOP = 0x02
    GET_ERROR = 0x03
    RX_SDO = 0x04
    TX_SDO = 0x05
    ADDRESS = 0x06
    SET_AXIS_STATE = 0x07
    SET_AXIS_STARTUP_CONFIG = 0x08  # 0.5, never implemented by the firmware
    GET_ENCODER_ESTIMATES = 0x09
    GET_ENCODER_COUNT = 0x0A  # 0.5
    SET_CONTROLLER_MODE = 0x0B
    SET_INPUT_POS = 0x0C
    SET_INPUT_VEL = 0x0D
    SET_INPUT_TORQUE = 0x0E
    SET_LIMITS = 0x0F
    START_ANTICOGGING = 0x10  # 0.5
    SET_TRAJ_VEL_LIMIT = 0x11
    SET_TRAJ_ACCEL_LIMITS = 0x12
    SET_TRAJ_INERTIA = 0x13
    GET_IQ = 0x14
    GET_TEMPERATURE = 0x15
    REBOOT = 0x16
    GET_BUS_VOLTAGE_CURRENT = 0x17
    CLEAR_ERRORS = 0x18
    SET_ABSOLUTE_POSITION = 0x19
    SET_POS_GAIN = 0x1A
    SET_VEL_GAINS = 0x1B
    GET_TORQUES = 0x1C
    GET_POWERS = 0x1D
    ENTER_DFU_MODE = 0x1F  # 0.6
    # firmware 0.5.x meanings of shared ids
    GET_MOTOR_ERROR = 0x03
    GET_ENCODER_ERROR = 0x04
    GET_SENSORLESS_ERROR = 0x05
    SET_AXIS_NODE_ID = 0x06
    GET_SENSORLESS_ESTIMATES = 0x15
    SET_LINEAR_COUNT = 0x19
    GET_ADC_VOLTAGE = 0x1C
    GET_CONTROLLER_ERROR = 0x1D


# the protocol document's names: ids whose meaning depends on the firmware line, then the shared ones
COMMAND_NAMES_05 = {0x00: "CANOpen_NMT", 0x03: "Get_Motor_Error", 0x04: "Get_Encoder_Error",
                    0x05: "Get_Sensorless_Error", 0x06: "Set_Axis_Node_ID", 0x08: "Set_Axis_Startup_Config",
                    0x0A: "Get_Encoder_Count", 0x10: "Start_Anticogging", 0x15: "Get_Sensorless_Estimates",
                    0x19: "Set_Linear_Count", 0x1C: "Get_ADC_Voltage", 0x1D: "Get_Controller_Error"}
COMMAND_NAMES_06 = {0x00: "Get_Version", 0x03: "Get_Error", 0x04: "RxSdo", 0x05: "TxSdo", 0x06: "Address",
                    0x15: "Get_Temperature", 0x19: "Set_Absolute_Position", 0x1C: "Get_Torques",
                    0x1D: "Get_Powers", 0x1F: "Enter_DFU_Mode"}
COMMAND_NAMES_COMMON = {0x01: "Heartbeat", 0x02: "Estop", 0x07: "Set_Axis_State", 0x09: "Get_Encoder_Estimates",
                        0x0B: "Set_Controller_Mode", 0x0C: "Set_Input_Pos", 0x0D: "Set_Input_Vel",
                        0x0E: "Set_Input_Torque", 0x0F: "Set_Limits", 0x11: "Set_Traj_Vel_Limit",
                        0x12: "Set_Traj_Accel_Limits", 0x13: "Set_Traj_Inertia", 0x14: "Get_Iq", 0x16: "Reboot",
                        0x17: "Get_Bus_Voltage_Current", 0x18: "Clear_Errors", 0x1A: "Set_Pos_Gain",
                        0x1B: "Set_Vel_Gains"}
