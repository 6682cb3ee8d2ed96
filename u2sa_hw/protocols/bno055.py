"""Bosch BNO055 (page 0) register table, modes, unit scales and conversions.

Shared by the IMU driver and the mock chip (mock_devices/bno055_chip.py). Facts come from
/work/shared/spec/devices/IMU_REGISTER_MAPS.md (BST-BNO055-DS000-14 rev 1.4 and Bosch's
reference driver division factors). Vector data registers are 16-bit signed,
little-endian (LSB first), x then y then z.
"""

from __future__ import annotations

import struct

I2C_ADDRESS = 0x28  # COM3 low
I2C_ADDRESS_ALT = 0x29  # COM3 high

# Page 0 registers
CHIP_ID = 0x00
ACC_ID = 0x01
MAG_ID = 0x02
GYR_ID = 0x03
SW_REV_ID_LSB = 0x04
SW_REV_ID_MSB = 0x05
BL_REV_ID = 0x06
PAGE_ID = 0x07
ACC_DATA_X_LSB = 0x08
MAG_DATA_X_LSB = 0x0E
GYR_DATA_X_LSB = 0x14
EUL_HEADING_LSB = 0x1A
EUL_ROLL_LSB = 0x1C
EUL_PITCH_LSB = 0x1E
QUA_DATA_W_LSB = 0x20
LIA_DATA_X_LSB = 0x28
GRV_DATA_X_LSB = 0x2E
TEMP = 0x34
CALIB_STAT = 0x35
ST_RESULT = 0x36
INT_STA = 0x37
SYS_CLK_STATUS = 0x38
SYS_STATUS = 0x39
SYS_ERR = 0x3A
UNIT_SEL = 0x3B
OPR_MODE = 0x3D
PWR_MODE = 0x3E
SYS_TRIGGER = 0x3F
TEMP_SOURCE = 0x40
AXIS_MAP_CONFIG = 0x41
AXIS_MAP_SIGN = 0x42
ACC_OFFSET_X_LSB = 0x55
MAG_RADIUS_MSB = 0x6A
CALIBRATION_PROFILE = range(ACC_OFFSET_X_LSB, MAG_RADIUS_MSB + 1)  # 22 bytes

DATA_REGISTERS = range(ACC_DATA_X_LSB, TEMP + 1)  # 0x08..0x34, sensor and fusion outputs

# Identity values
CHIP_ID_VALUE = 0xA0
ACC_ID_VALUE = 0xFB
MAG_ID_VALUE = 0x32
GYR_ID_VALUE = 0x0F

# OPR_MODE values
MODE_CONFIG = 0x00
MODE_ACCONLY = 0x01
MODE_MAGONLY = 0x02
MODE_GYROONLY = 0x03
MODE_ACCMAG = 0x04
MODE_ACCGYRO = 0x05
MODE_MAGGYRO = 0x06
MODE_AMG = 0x07
MODE_IMU = 0x08
MODE_COMPASS = 0x09
MODE_M4G = 0x0A
MODE_NDOF_FMC_OFF = 0x0B
MODE_NDOF = 0x0C
FUSION_MODES = frozenset({MODE_IMU, MODE_COMPASS, MODE_M4G, MODE_NDOF_FMC_OFF, MODE_NDOF})
MODE_NAMES = {
    MODE_CONFIG: "CONFIG", MODE_ACCONLY: "ACCONLY", MODE_MAGONLY: "MAGONLY", MODE_GYROONLY: "GYROONLY",
    MODE_ACCMAG: "ACCMAG", MODE_ACCGYRO: "ACCGYRO", MODE_MAGGYRO: "MAGGYRO", MODE_AMG: "AMG",
    MODE_IMU: "IMU", MODE_COMPASS: "COMPASS", MODE_M4G: "M4G", MODE_NDOF_FMC_OFF: "NDOF_FMC_OFF",
    MODE_NDOF: "NDOF",
}

# SYS_STATUS values
STATUS_IDLE = 0
STATUS_ERROR = 1
STATUS_INIT_PERIPHERALS = 2
STATUS_INIT = 3
STATUS_SELF_TEST = 4
STATUS_FUSION_RUNNING = 5
STATUS_RUNNING_NO_FUSION = 6

# UNIT_SEL bits
UNIT_ACC_MG = 0x01  # else m/s^2
UNIT_GYR_RPS = 0x02  # else dps
UNIT_EUL_RAD = 0x04  # else degrees
UNIT_TEMP_F = 0x10  # else Celsius
UNIT_ORI_ANDROID = 0x80  # else Windows

# SYS_TRIGGER bits
TRIGGER_SELF_TEST = 0x01
TRIGGER_RST_SYS = 0x20
TRIGGER_RST_INT = 0x40
TRIGGER_CLK_SEL = 0x80

# Scales: LSB per unit [BNO Tables 3-22..3-35]
ACCEL_LSB_PER_MS2 = 100.0
ACCEL_LSB_PER_MG = 1.0
MAG_LSB_PER_UT = 16.0
GYRO_LSB_PER_DPS = 16.0
GYRO_LSB_PER_RPS = 900.0
EULER_LSB_PER_DEG = 16.0
EULER_LSB_PER_RAD = 900.0
QUATERNION_LSB = 16384.0
TEMP_LSB_PER_C = 1.0
TEMP_LSB_PER_F = 2.0

# Timing [BSH]: seconds
CONFIG_TO_OPERATION_S = 0.007
OPERATION_TO_CONFIG_S = 0.019
RESET_TO_CONFIG_S = 0.65


def calib_stat(*, sys: int, gyr: int, acc: int, mag: int) -> int:
    """Pack the four 0..3 calibration levels into a CALIB_STAT byte."""
    for name, level in (("sys", sys), ("gyr", gyr), ("acc", acc), ("mag", mag)):
        if not 0 <= level <= 3:
            raise ValueError(f"calibration level {name} must be 0..3, got {level}")
    return (sys << 6) | (gyr << 4) | (acc << 2) | mag


def split_calib_stat(value: int) -> dict[str, int]:
    """Unpack CALIB_STAT into {"sys", "gyr", "acc", "mag"} levels 0..3 (3 = calibrated)."""
    return {"sys": (value >> 6) & 3, "gyr": (value >> 4) & 3, "acc": (value >> 2) & 3, "mag": value & 3}


_VEC3 = struct.Struct("<3h")
_VEC4 = struct.Struct("<4h")


def decode_vector(data: bytes) -> tuple[int, int, int]:
    """Decode six little-endian bytes into three signed counts (x, y, z or h, r, p)."""
    if len(data) != 6:
        raise ValueError(f"BNO055 vector must be 6 bytes, got {len(data)}")
    return _VEC3.unpack(data)


def encode_vector(x: int, y: int, z: int) -> bytes:
    """Encode three signed counts as the chip lays them out."""
    return _VEC3.pack(x, y, z)


def decode_quaternion(data: bytes) -> tuple[float, float, float, float]:
    """Decode eight bytes from QUA_DATA_W_LSB into a unit quaternion (w, x, y, z)."""
    if len(data) != 8:
        raise ValueError(f"BNO055 quaternion must be 8 bytes, got {len(data)}")
    return tuple(c / QUATERNION_LSB for c in _VEC4.unpack(data))  # type: ignore[return-value]


def encode_quaternion(w: float, x: float, y: float, z: float) -> bytes:
    """Encode a unit quaternion as four signed counts (1 = 2^14)."""
    return _VEC4.pack(*(clamp_int16(c * QUATERNION_LSB) for c in (w, x, y, z)))


def clamp_int16(value: float) -> int:
    """Round and saturate to a signed 16-bit count."""
    return max(-32768, min(32767, int(round(value))))
