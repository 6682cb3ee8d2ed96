"""Register-level model of the Bosch BNO055 absolute-orientation IMU.

Page 0 and page 1 register files (PAGE_ID selects), identity registers, OPR_MODE
switching (CONFIG holds the outputs still; fusion modes run the fusion outputs; the
non-fusion modes fill only their sensors' registers), UNIT_SEL, CALIB_STAT that starts
partially calibrated and reaches 0xFF after ``calibrated_after_s`` of fusion (or
``calibrate()``), SYS_STATUS, and SYS_TRIGGER.RST_SYS, after which the chip NACKs for
``reset_time_s`` like the real part booting.

Mounting and sign conventions (docs/i2c-devices.md): sensor vectors (ACC, MAG, GYR, LIA,
GRV) are in chip axes x = body forward, y = body left, z = up, as for the MPU model.
Euler outputs are the vehicle's aerospace angles: heading = yaw clockwise from north in
0..360 deg, roll positive right side down, pitch positive nose up; the Android
orientation (UNIT_SEL.ORI) flips the sign of pitch, as the data sheet's Table 3-13 does.
In IMU mode (no magnetometer) heading is relative to the heading at mode entry.
The quaternion is the vehicle's body-to-NED attitude (w, x, y, z).
"""

from __future__ import annotations

import math
import random
import time
from typing import Any, Sequence

from u2sa_hw.mocks.i2c_chip import RegisterChip, RestingVehicle, Vehicle
from u2sa_hw.mocks.mpu9250_chip import ned_to_body
from u2sa_hw.ports.i2c.wire import OP_READ, STATUS_NACK
from u2sa_hw.protocols import bno055 as bno

_ACC_MODES = {bno.MODE_ACCONLY, bno.MODE_ACCMAG, bno.MODE_ACCGYRO, bno.MODE_AMG, *bno.FUSION_MODES}
_MAG_MODES = {bno.MODE_MAGONLY, bno.MODE_ACCMAG, bno.MODE_MAGGYRO, bno.MODE_AMG, bno.MODE_COMPASS, bno.MODE_M4G,
              bno.MODE_NDOF_FMC_OFF, bno.MODE_NDOF}
_GYR_MODES = {bno.MODE_GYROONLY, bno.MODE_ACCGYRO, bno.MODE_MAGGYRO, bno.MODE_AMG, bno.MODE_IMU,
              bno.MODE_NDOF_FMC_OFF, bno.MODE_NDOF}
# Registers that only take writes in CONFIG mode (the real chip ignores them otherwise).
_CONFIG_ONLY = frozenset({bno.UNIT_SEL, bno.PWR_MODE, bno.TEMP_SOURCE, bno.AXIS_MAP_CONFIG, bno.AXIS_MAP_SIGN,
                          *bno.CALIBRATION_PROFILE})
_PAGE1_RESET = {0x08: 0x0D, 0x09: 0x6D, 0x0A: 0x38, 0x0B: 0x00}  # ACC_Config, MAG_Config, GYR_Config_0/1
_UNIQUE_ID = range(0x50, 0x60)  # page 1


class Bno055Chip(RegisterChip):
    """A BNO055 at 0x28 (or 0x29) sampling *vehicle*."""

    # Page 0 read-only registers; checked in write_register because page 1 reuses the numbers.
    page0_read_only = frozenset({*range(bno.CHIP_ID, bno.BL_REV_ID + 1), *bno.DATA_REGISTERS, bno.CALIB_STAT,
                                 bno.ST_RESULT, bno.INT_STA, bno.SYS_CLK_STATUS, bno.SYS_STATUS, bno.SYS_ERR})
    reset_values = {
        bno.CHIP_ID: bno.CHIP_ID_VALUE, bno.ACC_ID: bno.ACC_ID_VALUE, bno.MAG_ID: bno.MAG_ID_VALUE,
        bno.GYR_ID: bno.GYR_ID_VALUE, bno.SW_REV_ID_LSB: 0x11, bno.SW_REV_ID_MSB: 0x03, bno.BL_REV_ID: 0x15,
        bno.ST_RESULT: 0x0F, bno.SYS_STATUS: bno.STATUS_IDLE, bno.UNIT_SEL: 0x80, bno.OPR_MODE: bno.MODE_CONFIG,
        bno.AXIS_MAP_CONFIG: 0x24, bno.AXIS_MAP_SIGN: 0x00,
    }

    def __init__(self, *, address: int = bno.I2C_ADDRESS, vehicle: Vehicle | None = None, seed: int = 0,
                 initial_calibration: int = bno.calib_stat(sys=0, gyr=3, acc=1, mag=0),
                 calibrated_after_s: float = 5.0, reset_time_s: float = bno.RESET_TO_CONFIG_S,
                 earth_field_ut: tuple[float, float, float] = (20.0, 0.0, 45.0), accel_noise_ms2: float = 0.02,
                 gyro_noise_dps: float = 0.05, temperature_c: float = 25.0) -> None:
        self.vehicle: Vehicle = vehicle if vehicle is not None else RestingVehicle()
        self.initial_calibration = initial_calibration
        self.calibrated_after_s = calibrated_after_s
        self.reset_time_s = reset_time_s
        self.earth_field_ut = tuple(earth_field_ut)
        self.accel_noise_ms2 = accel_noise_ms2
        self.gyro_noise_dps = gyro_noise_dps
        self.temperature_c = temperature_c
        self._rng = random.Random(seed)
        self._page1 = bytearray(256)
        self._unique_id = bytes(random.Random(seed ^ 0x055).randrange(256) for _ in _UNIQUE_ID)
        self._booting_until = 0.0
        self._fusion_seconds = 0.0  # fusion time accumulated before the current fusion run
        self._fusion_since: float | None = None
        self._heading_zero = 0.0
        self._calibrated = False
        self.samples = 0
        super().__init__(address=address)

    def reset(self) -> None:
        """Power-on state: CONFIG mode, page 0, calibration back to its initial level."""
        with self._lock:
            super().reset()
            self._page1[:] = bytes(256)
            for reg, value in _PAGE1_RESET.items():
                self._page1[reg] = value
            self._page1[_UNIQUE_ID.start:_UNIQUE_ID.stop] = self._unique_id
            self._regs[bno.CALIB_STAT] = self.initial_calibration
            self._fusion_seconds, self._fusion_since, self._calibrated = 0.0, None, False

    @property
    def mode(self) -> int:
        """The current OPR_MODE (low nibble)."""
        return self.peek(bno.OPR_MODE) & 0x0F

    @property
    def page(self) -> int:
        """The selected register page (0 or 1)."""
        return self.peek(bno.PAGE_ID) & 0x01

    def calibrate(self) -> None:
        """Make CALIB_STAT read 0xFF (all of SYS, GYR, ACC, MAG fully calibrated) from now on."""
        with self._lock:
            self._calibrated = True
            self._regs[bno.CALIB_STAT] = 0xFF

    def set_calibration(self, *, sys: int, gyr: int, acc: int, mag: int) -> None:
        """Script CALIB_STAT levels (0..3 each); the timed calibration starts over."""
        with self._lock:
            self._regs[bno.CALIB_STAT] = bno.calib_stat(sys=sys, gyr=gyr, acc=acc, mag=mag)
            self._calibrated = self._regs[bno.CALIB_STAT] == 0xFF
            self._fusion_seconds = 0.0
            self._fusion_since = time.monotonic() if self._fusion_since is not None else None

    def _handle(self, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        if time.monotonic() < self._booting_until:
            return STATUS_NACK, b""
        return super()._handle(op, register, length, data)

    def read_register(self, register: int) -> int:
        """Page 1 reads come from the page 1 file (PAGE_ID is on both pages)."""
        if register == bno.CALIB_STAT and self.page == 0:
            self._update_calibration()
        if self.page == 1 and register != bno.PAGE_ID:
            return self._page1[register]
        return self._regs[register]

    def write_register(self, register: int, value: int) -> None:
        """OPR_MODE switches modes, SYS_TRIGGER resets, config registers need CONFIG mode."""
        if register == bno.PAGE_ID:
            self._regs[bno.PAGE_ID] = value & 0x01
        elif self.page == 1:
            if self.mode == bno.MODE_CONFIG and register not in _UNIQUE_ID:
                self._page1[register] = value
        elif register in self.page0_read_only:
            pass
        elif register in _CONFIG_ONLY:
            if self.mode == bno.MODE_CONFIG:
                self._regs[register] = value
        elif register == bno.OPR_MODE:
            self._set_mode(value & 0x0F)
        elif register == bno.SYS_TRIGGER:
            if value & bno.TRIGGER_RST_SYS:
                self.reset()
                self._booting_until = time.monotonic() + self.reset_time_s
            else:
                self._regs[bno.SYS_TRIGGER] = value & bno.TRIGGER_CLK_SEL  # other bits clear themselves
        else:
            super().write_register(register, value)

    def _set_mode(self, mode: int) -> None:
        if mode not in bno.MODE_NAMES:
            return  # reserved values are ignored by the chip
        now = time.monotonic()
        if self._fusion_since is not None:
            self._fusion_seconds += now - self._fusion_since
            self._fusion_since = None
        if mode in bno.FUSION_MODES:
            self._fusion_since = now
            self._heading_zero = self.vehicle.snapshot().yaw if mode == bno.MODE_IMU else 0.0
        self._regs[bno.OPR_MODE] = mode
        if mode == bno.MODE_CONFIG:
            self._regs[bno.SYS_STATUS] = bno.STATUS_IDLE
        else:
            fused = mode in bno.FUSION_MODES
            self._regs[bno.SYS_STATUS] = bno.STATUS_FUSION_RUNNING if fused else bno.STATUS_RUNNING_NO_FUSION

    def _update_calibration(self) -> None:
        if self._calibrated or self._fusion_since is None:
            return
        if self._fusion_seconds + time.monotonic() - self._fusion_since >= self.calibrated_after_s:
            self.calibrate()

    def begin_transaction(self, op: int, register: int, length: int) -> None:
        """Latch fresh outputs before a page-0 read that reaches the data registers."""
        if op != OP_READ or self.page != 0 or self.mode == bno.MODE_CONFIG:
            return
        if register + length - 1 < bno.DATA_REGISTERS.start or register > bno.DATA_REGISTERS.stop - 1:
            return
        self.latch_sample()

    def latch_sample(self) -> None:
        """Sample the vehicle and fill the data registers the current mode produces."""
        with self._lock:
            mode, units = self.mode, self._regs[bno.UNIT_SEL]
            truth = self.vehicle.snapshot()
            g = 9.80665
            acc = (truth.accel_x, -truth.accel_y, -truth.accel_z)
            cr, sr, cp, sp = math.cos(truth.roll), math.sin(truth.roll), math.cos(truth.pitch), math.sin(truth.pitch)
            grv = (g * sp, g * sr * cp, g * cr * cp)
            gyr = (math.degrees(truth.roll_rate), -math.degrees(truth.pitch_rate), -math.degrees(truth.yaw_rate))
            body_mag = ned_to_body(self.earth_field_ut, truth.roll, truth.pitch, truth.yaw)
            mag = (body_mag[0], -body_mag[1], -body_mag[2])
            acc_scale = bno.ACCEL_LSB_PER_MG / (g / 1000.0) if units & bno.UNIT_ACC_MG else bno.ACCEL_LSB_PER_MS2
            gyr_scale = bno.GYRO_LSB_PER_RPS * math.pi / 180 if units & bno.UNIT_GYR_RPS else bno.GYRO_LSB_PER_DPS
            noisy_acc = [a + self._rng.gauss(0.0, self.accel_noise_ms2) for a in acc]
            if mode in _ACC_MODES:
                self._put_vector(bno.ACC_DATA_X_LSB, noisy_acc, acc_scale)
            if mode in _MAG_MODES:
                self._put_vector(bno.MAG_DATA_X_LSB, mag, bno.MAG_LSB_PER_UT)
            if mode in _GYR_MODES:
                self._put_vector(bno.GYR_DATA_X_LSB, [w + self._rng.gauss(0.0, self.gyro_noise_dps) for w in gyr],
                                 gyr_scale)
            if mode in bno.FUSION_MODES:
                self._put_fusion(truth, units, [a - b for a, b in zip(noisy_acc, grv)], grv, acc_scale)
            temp = self.temperature_c * 1.8 + 32 if units & bno.UNIT_TEMP_F else self.temperature_c
            lsb = bno.TEMP_LSB_PER_F if units & bno.UNIT_TEMP_F else bno.TEMP_LSB_PER_C
            self._regs[bno.TEMP] = max(-128, min(127, round(temp * lsb))) & 0xFF
            self.samples += 1

    def _put_fusion(self, truth: Any, units: int, lia: list[float], grv: tuple[float, ...],
                    acc_scale: float) -> None:
        heading = (truth.yaw - self._heading_zero) % (2 * math.pi)
        pitch = -truth.pitch if units & bno.UNIT_ORI_ANDROID else truth.pitch
        euler = (heading, truth.roll, pitch)
        eul_scale = bno.EULER_LSB_PER_RAD if units & bno.UNIT_EUL_RAD else bno.EULER_LSB_PER_DEG * 180 / math.pi
        self._put_vector(bno.EUL_HEADING_LSB, euler, eul_scale)
        quat = _quaternion(truth.roll, truth.pitch, heading)
        self._regs[bno.QUA_DATA_W_LSB:bno.QUA_DATA_W_LSB + 8] = bno.encode_quaternion(*quat)
        self._put_vector(bno.LIA_DATA_X_LSB, lia, acc_scale)
        self._put_vector(bno.GRV_DATA_X_LSB, grv, acc_scale)

    def _put_vector(self, register: int, values: Sequence[float], scale: float) -> None:
        counts = [bno.clamp_int16(v * scale) for v in values]
        self._regs[register:register + 6] = bno.encode_vector(*counts)


def _quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """Body-to-NED attitude quaternion (w, x, y, z) for aerospace yaw-pitch-roll angles."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)
