"""ODrive enumerations and error bits for CANSimple (firmware 0.5.x and 0.6.x).

Axis states, control and input modes, procedure results and reboot actions as in
ODriveArduino's ODriveEnums.h (0.6.x); the 0.6.x ODriveError bits; and the 0.5.x axis, motor
and controller error bits from the value tables of ODrive's 0.5.6 DBC. Summarised in
/work/shared/spec/devices/ODRIVE_CANSIMPLE.md. Imported through ``odrive_cansimple``.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag

class AxisState(IntEnum):
    """Axis_State / Axis_Requested_State (both firmware lines; 14 is 0.6 only)."""

    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    LOCKIN_SPIN = 9
    ENCODER_DIR_FIND = 10
    HOMING = 11
    ENCODER_HALL_POLARITY_CALIBRATION = 12
    ENCODER_HALL_PHASE_CALIBRATION = 13
    ANTICOGGING_CALIBRATION = 14


class ControlMode(IntEnum):
    """Set_Controller_Mode Control_Mode."""

    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(IntEnum):
    """Set_Controller_Mode Input_Mode."""

    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    MIX_CHANNELS = 4
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6
    MIRROR = 7
    TUNING = 8


class ProcedureResult(IntEnum):
    """Heartbeat byte 5 in firmware 0.6.x: the outcome of the last requested state."""

    SUCCESS = 0
    BUSY = 1
    CANCELLED = 2
    DISARMED = 3
    NO_RESPONSE = 4
    POLE_PAIR_CPR_MISMATCH = 5
    PHASE_RESISTANCE_OUT_OF_RANGE = 6
    PHASE_INDUCTANCE_OUT_OF_RANGE = 7
    UNBALANCED_PHASES = 8
    INVALID_MOTOR_TYPE = 9
    ILLEGAL_HALL_STATE = 10
    TIMEOUT = 11
    HOMING_WITHOUT_ENDSTOP = 12
    INVALID_STATE = 13
    NOT_CALIBRATED = 14
    NOT_CONVERGING = 15


class RebootAction(IntEnum):
    """Reboot byte 0 in firmware 0.6.x (0.5.x reboots on an empty frame)."""

    REBOOT = 0
    SAVE_CONFIGURATION = 1
    ERASE_CONFIGURATION = 2
    ENTER_DFU = 3


class OdriveError(IntFlag):
    """Firmware 0.6.x Axis_Error / Active_Errors / Disarm_Reason bits (ODriveError)."""

    NONE = 0
    INITIALIZING = 0x1
    SYSTEM_LEVEL = 0x2
    TIMING_ERROR = 0x4
    MISSING_ESTIMATE = 0x8
    BAD_CONFIG = 0x10
    DRV_FAULT = 0x20
    MISSING_INPUT = 0x40
    DC_BUS_OVER_VOLTAGE = 0x100
    DC_BUS_UNDER_VOLTAGE = 0x200
    DC_BUS_OVER_CURRENT = 0x400
    DC_BUS_OVER_REGEN_CURRENT = 0x800
    CURRENT_LIMIT_VIOLATION = 0x1000
    MOTOR_OVER_TEMP = 0x2000
    INVERTER_OVER_TEMP = 0x4000
    VELOCITY_LIMIT_VIOLATION = 0x8000
    POSITION_LIMIT_VIOLATION = 0x10000
    WATCHDOG_TIMER_EXPIRED = 0x1000000
    ESTOP_REQUESTED = 0x2000000
    SPINOUT_DETECTED = 0x4000000
    BRAKE_RESISTOR_DISARMED = 0x8000000
    THERMISTOR_DISCONNECTED = 0x10000000
    CALIBRATION_ERROR = 0x40000000


class AxisError05(IntFlag):
    """Firmware 0.5.x Axis_Error bits (DBC value table of message 1)."""

    NONE = 0
    INVALID_STATE = 0x1
    MOTOR_FAILED = 0x40
    SENSORLESS_ESTIMATOR_FAILED = 0x80
    ENCODER_FAILED = 0x100
    CONTROLLER_FAILED = 0x200
    WATCHDOG_TIMER_EXPIRED = 0x800
    MIN_ENDSTOP_PRESSED = 0x1000
    MAX_ENDSTOP_PRESSED = 0x2000
    ESTOP_REQUESTED = 0x4000
    HOMING_WITHOUT_ENDSTOP = 0x20000
    OVER_TEMP = 0x40000
    UNKNOWN_POSITION = 0x80000


class MotorError05(IntFlag):
    """Firmware 0.5.x Get_Motor_Error bits (DBC value table of message 3; 64-bit field)."""

    NONE = 0
    PHASE_RESISTANCE_OUT_OF_RANGE = 0x1
    PHASE_INDUCTANCE_OUT_OF_RANGE = 0x2
    DRV_FAULT = 0x8
    CONTROL_DEADLINE_MISSED = 0x10
    MODULATION_MAGNITUDE = 0x80
    CURRENT_SENSE_SATURATION = 0x400
    CURRENT_LIMIT_VIOLATION = 0x1000
    MODULATION_IS_NAN = 0x10000
    MOTOR_THERMISTOR_OVER_TEMP = 0x20000
    FET_THERMISTOR_OVER_TEMP = 0x40000
    TIMER_UPDATE_MISSED = 0x80000
    CURRENT_MEASUREMENT_UNAVAILABLE = 0x100000
    CONTROLLER_FAILED = 0x200000
    I_BUS_OUT_OF_RANGE = 0x400000
    BRAKE_RESISTOR_DISARMED = 0x800000
    SYSTEM_LEVEL = 0x1000000
    BAD_TIMING = 0x2000000
    UNKNOWN_PHASE_ESTIMATE = 0x4000000
    UNKNOWN_PHASE_VEL = 0x8000000
    UNKNOWN_TORQUE = 0x10000000
    UNKNOWN_CURRENT_COMMAND = 0x20000000
    UNKNOWN_CURRENT_MEASUREMENT = 0x40000000
    UNKNOWN_VBUS_VOLTAGE = 0x80000000
    UNKNOWN_VOLTAGE_COMMAND = 0x100000000
    UNKNOWN_GAINS = 0x200000000
    CONTROLLER_INITIALIZING = 0x400000000
    UNBALANCED_PHASES = 0x800000000


class ControllerError05(IntFlag):
    """Firmware 0.5.x Get_Controller_Error bits (DBC value table of message 29)."""

    NONE = 0
    OVERSPEED = 0x1
    INVALID_INPUT_MODE = 0x2
    UNSTABLE_GAIN = 0x4
    INVALID_MIRROR_AXIS = 0x8
    INVALID_LOAD_ENCODER = 0x10
    INVALID_ESTIMATE = 0x20
    INVALID_CIRCULAR_RANGE = 0x40
    SPINOUT_DETECTED = 0x80
