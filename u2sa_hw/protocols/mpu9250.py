"""InvenSense MPU-6050 / MPU-6500 / MPU-9250 register table, scales and conversions.

Shared by the IMU driver and the mock chip (mock_devices/mpu9250_chip.py). Facts come
from /work/shared/spec/devices/IMU_REGISTER_MAPS.md (RM-MPU-6000A rev 4.2, RM-MPU-9250A
rev 1.4, Linux inv_mpu6050). All multi-byte sample registers are 16-bit two's complement,
big-endian (high byte first); a 14-byte burst read from ACCEL_XOUT_H returns accel x/y/z,
temperature and gyro x/y/z from one sampling instant.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

I2C_ADDRESS = 0x68  # AD0 low
I2C_ADDRESS_ALT = 0x69  # AD0 high

# Registers (hex = decimal in the datasheet)
SELF_TEST_X_GYRO = 0x00
XG_OFFSET_H = 0x13  # gyro offset registers 0x13..0x18 (MPU-6500/9250)
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
ACCEL_CONFIG2 = 0x1D  # MPU-6500/9250 only
LP_ACCEL_ODR = 0x1E
FIFO_EN = 0x23
INT_PIN_CFG = 0x37
INT_ENABLE = 0x38
INT_STATUS = 0x3A
ACCEL_XOUT_H = 0x3B
ACCEL_XOUT_L = 0x3C
ACCEL_YOUT_H = 0x3D
ACCEL_YOUT_L = 0x3E
ACCEL_ZOUT_H = 0x3F
ACCEL_ZOUT_L = 0x40
TEMP_OUT_H = 0x41
TEMP_OUT_L = 0x42
GYRO_XOUT_H = 0x43
GYRO_XOUT_L = 0x44
GYRO_YOUT_H = 0x45
GYRO_YOUT_L = 0x46
GYRO_ZOUT_H = 0x47
GYRO_ZOUT_L = 0x48
SIGNAL_PATH_RESET = 0x68
USER_CTRL = 0x6A
PWR_MGMT_1 = 0x6B
PWR_MGMT_2 = 0x6C
WHO_AM_I = 0x75
XA_OFFSET_H = 0x77  # accel offsets 0x77..0x7E (MPU-6500/9250)

BURST_START = ACCEL_XOUT_H
BURST_LENGTH = 14  # 0x3B..0x48
SAMPLE_REGISTERS = range(ACCEL_XOUT_H, GYRO_ZOUT_L + 1)

# PWR_MGMT_1 bits
PWR1_DEVICE_RESET = 0x80
PWR1_SLEEP = 0x40
PWR1_CYCLE = 0x20
PWR1_CLKSEL_MASK = 0x07

# INT_PIN_CFG bit that exposes the AK8963 magnetometer on the main bus (MPU-9250)
INT_PIN_CFG_BYPASS_EN = 0x02

# GYRO_CONFIG / ACCEL_CONFIG full-scale select: bits [4:3]
FS_SEL_SHIFT = 3
FS_SEL_MASK = 0x18
# CONFIG: DLPF_CFG bits [2:0]
DLPF_CFG_MASK = 0x07

ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)  # AFS_SEL 0..3: +-2, 4, 8, 16 g
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)  # FS_SEL 0..3: +-250, 500, 1000, 2000 dps
ACCEL_RANGE_G = (2, 4, 8, 16)
GYRO_RANGE_DPS = (250, 500, 1000, 2000)

STANDARD_GRAVITY = 9.80665  # m/s^2 per g


@dataclass(frozen=True)
class MpuVariant:
    """One member of the family: what WHO_AM_I reads, the power-up PWR_MGMT_1 value and
    the temperature formula T[degC] = TEMP_OUT / temp_lsb_per_c + temp_offset_c."""

    name: str
    who_am_i: int
    pwr_mgmt_1_reset: int
    temp_lsb_per_c: float
    temp_offset_c: float
    has_magnetometer: bool


VARIANTS: dict[str, MpuVariant] = {
    # MPU-6050 powers up asleep (PWR_MGMT_1 = 0x40) [RM6050].
    "mpu6050": MpuVariant("mpu6050", 0x68, 0x40, 340.0, 36.53, False),
    # MPU-6500 and MPU-9250 power up awake with CLKSEL=1 (0x01) [RM9250].
    "mpu6500": MpuVariant("mpu6500", 0x70, 0x01, 333.87, 21.0, False),
    "mpu9250": MpuVariant("mpu9250", 0x71, 0x01, 333.87, 21.0, True),
}
WHO_AM_I_TO_VARIANT = {v.who_am_i: name for name, v in VARIANTS.items()}


def fs_sel(config_value: int) -> int:
    """The full-scale index (0..3) held in a GYRO_CONFIG or ACCEL_CONFIG value."""
    return (config_value & FS_SEL_MASK) >> FS_SEL_SHIFT


def fs_config(index: int) -> int:
    """The GYRO_CONFIG / ACCEL_CONFIG value that selects full-scale *index* (0..3)."""
    if not 0 <= index <= 3:
        raise ValueError(f"full-scale index must be 0..3, got {index}")
    return index << FS_SEL_SHIFT


def accel_fs_index(range_g: int) -> int:
    """The AFS_SEL index for a range of +-*range_g* g (2, 4, 8 or 16)."""
    try:
        return ACCEL_RANGE_G.index(range_g)
    except ValueError:
        raise ValueError(f"accelerometer range must be one of {ACCEL_RANGE_G} g, got {range_g}") from None


def gyro_fs_index(range_dps: int) -> int:
    """The FS_SEL index for a range of +-*range_dps* deg/s (250, 500, 1000 or 2000)."""
    try:
        return GYRO_RANGE_DPS.index(range_dps)
    except ValueError:
        raise ValueError(f"gyro range must be one of {GYRO_RANGE_DPS} dps, got {range_dps}") from None


@dataclass(frozen=True)
class RawSample:
    """The seven signed counts of one 14-byte burst: accel x/y/z, temperature, gyro x/y/z."""

    ax: int
    ay: int
    az: int
    temp: int
    gx: int
    gy: int
    gz: int


_BURST = struct.Struct(">7h")


def decode_burst(data: bytes) -> RawSample:
    """Decode the 14 bytes read from ACCEL_XOUT_H (big-endian signed 16-bit)."""
    if len(data) != BURST_LENGTH:
        raise ValueError(f"MPU burst must be {BURST_LENGTH} bytes, got {len(data)}")
    return RawSample(*_BURST.unpack(data))


def encode_burst(sample: RawSample) -> bytes:
    """Encode a sample as the chip lays it out in 0x3B..0x48."""
    return _BURST.pack(sample.ax, sample.ay, sample.az, sample.temp, sample.gx, sample.gy, sample.gz)


def clamp_int16(value: float) -> int:
    """Round and saturate to a signed 16-bit count, as the chip's ADC does at full scale."""
    return max(-32768, min(32767, int(round(value))))


# AK8963 magnetometer inside the MPU-9250 (reach it with INT_PIN_CFG bypass) [RM9250 s.5, AK8963 datasheet s.8]
AK8963_ADDRESS = 0x0C
AK8963_WIA = 0x00
AK8963_WIA_VALUE = 0x48
AK8963_ST1 = 0x02
AK8963_HXL = 0x03
AK8963_ST2 = 0x09
AK8963_CNTL1 = 0x0A
AK8963_CNTL2 = 0x0B
AK8963_ASAX = 0x10
AK8963_UT_PER_LSB_16BIT = 0.15
AK8963_UT_PER_LSB_14BIT = 0.6
AK8963_ST1_DRDY = 0x01          # a new measurement is in HXL..HZH
AK8963_ST2_HOFL = 0x08          # magnetic sensor overflow: |field| beyond the range, the sample is invalid
AK8963_ST2_BITM = 0x10          # output is 16-bit
AK8963_CNTL1_BIT_16 = 0x10
AK8963_MODE_POWER_DOWN = 0x00
AK8963_MODE_CONTINUOUS_1 = 0x02  # 8 Hz
AK8963_MODE_CONTINUOUS_2 = 0x06  # 100 Hz
AK8963_MODE_FUSE_ROM = 0x0F
AK8963_CNTL2_SRST = 0x01
AK8963_MODE_WAIT_S = 0.0001     # >= 100 us after a mode change
AK8963_SAMPLE_START = AK8963_ST1
AK8963_SAMPLE_LENGTH = AK8963_ST2 - AK8963_ST1 + 1   # ST1, HXL..HZH, ST2 in one read (ST2 ends the read cycle)


def ak8963_adjustment(asa: int) -> float:
    """Sensitivity factor from one fuse-ROM ASA byte: ``H_adj = H * ((ASA - 128) * 0.5 / 128 + 1)``."""
    return (asa - 128) * 0.5 / 128 + 1


@dataclass(frozen=True)
class MagSample:
    """One AK8963 read of ST1..ST2: counts per AK8963 axis, whether it is new, whether it overflowed."""

    hx: int
    hy: int
    hz: int
    ready: bool
    overflow: bool
    sixteen_bit: bool


_MAG = struct.Struct("<B3hB")


def decode_mag(data: bytes) -> MagSample:
    """Decode the 8 bytes read from ST1 (little-endian signed 16-bit counts between ST1 and ST2)."""
    if len(data) != AK8963_SAMPLE_LENGTH:
        raise ValueError(f"AK8963 sample must be {AK8963_SAMPLE_LENGTH} bytes, got {len(data)}")
    st1, hx, hy, hz, st2 = _MAG.unpack(data)
    return MagSample(hx, hy, hz, bool(st1 & AK8963_ST1_DRDY), bool(st2 & AK8963_ST2_HOFL),
                     bool(st2 & AK8963_ST2_BITM))
