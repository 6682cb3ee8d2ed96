"""VESC enumerations for CAN (datatypes.h): packet ids, fault codes and the COMM packets used.

``PacketId`` is the whole CAN_PACKET_ID enum (bits 15..8 of a frame's 29-bit id),
``FaultCode`` is mc_fault_code, and ``CommPacket`` holds the COMM_PACKET_ID values this code
carries over CAN in multi-frame buffers. Summarised in /work/shared/spec/devices/VESC_CAN.md.
Imported through ``vesc_can``.
"""

from __future__ import annotations

from enum import IntEnum


class PacketId(IntEnum):
    """CAN_PACKET_ID (bits 15..8 of the extended id)."""

    SET_DUTY = 0
    SET_CURRENT = 1
    SET_CURRENT_BRAKE = 2
    SET_RPM = 3
    SET_POS = 4
    FILL_RX_BUFFER = 5
    FILL_RX_BUFFER_LONG = 6
    PROCESS_RX_BUFFER = 7
    PROCESS_SHORT_BUFFER = 8
    STATUS = 9
    SET_CURRENT_REL = 10
    SET_CURRENT_BRAKE_REL = 11
    SET_CURRENT_HANDBRAKE = 12
    SET_CURRENT_HANDBRAKE_REL = 13
    STATUS_2 = 14
    STATUS_3 = 15
    STATUS_4 = 16
    PING = 17
    PONG = 18
    DETECT_APPLY_ALL_FOC = 19
    DETECT_APPLY_ALL_FOC_RES = 20
    CONF_CURRENT_LIMITS = 21
    CONF_STORE_CURRENT_LIMITS = 22
    CONF_CURRENT_LIMITS_IN = 23
    CONF_STORE_CURRENT_LIMITS_IN = 24
    CONF_FOC_ERPMS = 25
    CONF_STORE_FOC_ERPMS = 26
    STATUS_5 = 27
    POLL_TS5700N8501_STATUS = 28
    CONF_BATTERY_CUT = 29
    CONF_STORE_BATTERY_CUT = 30
    SHUTDOWN = 31
    IO_BOARD_ADC_1_TO_4 = 32
    IO_BOARD_ADC_5_TO_8 = 33
    IO_BOARD_ADC_9_TO_12 = 34
    IO_BOARD_DIGITAL_IN = 35
    IO_BOARD_SET_OUTPUT_DIGITAL = 36
    IO_BOARD_SET_OUTPUT_PWM = 37
    BMS_V_TOT = 38
    BMS_I = 39
    BMS_AH_WH = 40
    BMS_V_CELL = 41
    BMS_BAL = 42
    BMS_TEMPS = 43
    BMS_HUM = 44
    BMS_SOC_SOH_TEMP_STAT = 45
    PSW_STAT = 46
    PSW_SWITCH = 47
    BMS_HW_DATA_1 = 48
    BMS_HW_DATA_2 = 49
    BMS_HW_DATA_3 = 50
    BMS_HW_DATA_4 = 51
    BMS_HW_DATA_5 = 52
    BMS_AH_WH_CHG_TOTAL = 53
    BMS_AH_WH_DIS_TOTAL = 54
    UPDATE_PID_POS_OFFSET = 55
    POLL_ROTOR_POS = 56
    NOTIFY_BOOT = 57
    STATUS_6 = 58
    GNSS_TIME = 59
    GNSS_LAT = 60
    GNSS_LON = 61
    GNSS_ALT_SPEED_HDOP = 62
    UPDATE_BAUD = 63
    BMS_STATUS_1 = 64
    BMS_STATUS_2 = 65
    BMS_STATUS_3 = 66
    BMS_STATUS_4 = 67
    BMS_STATUS_5 = 68


class FaultCode(IntEnum):
    """mc_fault_code (datatypes.h); reported over COMM_GET_VALUES, not in the STATUS frames."""

    NONE = 0
    OVER_VOLTAGE = 1
    UNDER_VOLTAGE = 2
    DRV = 3
    ABS_OVER_CURRENT = 4
    OVER_TEMP_FET = 5
    OVER_TEMP_MOTOR = 6
    GATE_DRIVER_OVER_VOLTAGE = 7
    GATE_DRIVER_UNDER_VOLTAGE = 8
    MCU_UNDER_VOLTAGE = 9
    BOOTING_FROM_WATCHDOG_RESET = 10
    ENCODER_SPI = 11
    ENCODER_SINCOS_BELOW_MIN_AMPLITUDE = 12
    ENCODER_SINCOS_ABOVE_MAX_AMPLITUDE = 13
    FLASH_CORRUPTION = 14
    HIGH_OFFSET_CURRENT_SENSOR_1 = 15
    HIGH_OFFSET_CURRENT_SENSOR_2 = 16
    HIGH_OFFSET_CURRENT_SENSOR_3 = 17
    UNBALANCED_CURRENTS = 18
    BRK = 19
    RESOLVER_LOT = 20
    RESOLVER_DOS = 21
    RESOLVER_LOS = 22


class CommPacket(IntEnum):
    """COMM_PACKET_ID values used over CAN here (datatypes.h)."""

    SET_APPCONF = 16
    GET_APPCONF = 17
