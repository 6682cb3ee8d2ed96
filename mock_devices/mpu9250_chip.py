"""Register-level model of the InvenSense MPU-6050 / MPU-6500 / MPU-9250 and the AK8963.

The model samples the simulated vehicle's truth on every read that touches the sample
registers 0x3B..0x48, so one 14-byte burst gives accel, temperature and gyro from one
instant (as the chip's shadow registers do) while separate byte reads may not.

Mounting (documented in docs/i2c-devices.md): the chip lies flat with chip x = body
forward, chip y = body left, chip z = up. With the vehicle's FRD specific force
(accel_x, accel_y, accel_z) and body rates (p, q, r):
    chip accel = (accel_x, -accel_y, -accel_z) / g   -> +1 g on z at rest
    chip gyro  = (p, -q, -r) in deg/s + a constant per-axis bias (chip axes) + noise
The accelerometer's errors are modelled in chip axes and g, ``measured = accel_matrix @ true
+ accel_offset_g`` (scales on the diagonal, misalignment off it; defaults identity and zero),
so a calibration can be checked against a known truth. Noise is Gaussian, seeded.
While PWR_MGMT_1.SLEEP is set the sample registers are not
updated: they hold their last value, which is 0 after power-up or DEVICE_RESET.
"""

from __future__ import annotations

import math
import random
import threading
import time
from types import SimpleNamespace
from typing import Sequence

from u2sa_hw.mocks.i2c_chip import RegisterChip, RestingVehicle, Vehicle
from u2sa_hw.ports.i2c.wire import OP_READ, STATUS_NACK
from u2sa_hw.protocols import mpu9250 as mpu

IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
_SAMPLE_SPAN = range(mpu.INT_STATUS, mpu.GYRO_ZOUT_L + 1)  # reads here see a fresh sample


class Mpu9250Chip(RegisterChip):
    """An MPU-6050/6500/9250 accel/gyro die at 0x68 (or 0x69), sampling *vehicle*."""

    read_only = frozenset({mpu.WHO_AM_I, mpu.INT_STATUS, *mpu.SAMPLE_REGISTERS})

    def __init__(self, *, address: int = mpu.I2C_ADDRESS, variant: str = "mpu9250", vehicle: Vehicle | None = None,
                 seed: int = 0, gyro_bias_dps: tuple[float, float, float] = (0.8, -0.5, 0.3),
                 gyro_noise_dps: float = 0.05, accel_noise_g: float = 0.002, temperature_c: float = 25.0,
                 accel_offset_g: Sequence[float] = (0.0, 0.0, 0.0),
                 accel_matrix: Sequence[Sequence[float]] = IDENTITY) -> None:
        if variant not in mpu.VARIANTS:
            raise ValueError(f"unknown MPU variant {variant!r}: use one of {sorted(mpu.VARIANTS)}")
        self.variant = mpu.VARIANTS[variant]
        self.reset_values = {mpu.WHO_AM_I: self.variant.who_am_i, mpu.PWR_MGMT_1: self.variant.pwr_mgmt_1_reset}
        self.vehicle: Vehicle = vehicle if vehicle is not None else RestingVehicle()
        self.gyro_bias_dps = tuple(gyro_bias_dps)
        self.gyro_noise_dps = gyro_noise_dps
        self.accel_noise_g = accel_noise_g
        self.accel_offset_g = _vector("accel_offset_g", accel_offset_g)
        self.accel_matrix = _matrix("accel_matrix", accel_matrix)
        self.temperature_c = temperature_c
        self._rng = random.Random(seed)
        self.samples = 0  # how many times the sample registers were refreshed
        super().__init__(address=address)

    @property
    def asleep(self) -> bool:
        """True while PWR_MGMT_1.SLEEP is set (sample registers frozen)."""
        return bool(self.peek(mpu.PWR_MGMT_1) & mpu.PWR1_SLEEP)

    @property
    def accel_lsb_per_g(self) -> float:
        """Counts per g at the current ACCEL_CONFIG full scale."""
        return mpu.ACCEL_LSB_PER_G[mpu.fs_sel(self.peek(mpu.ACCEL_CONFIG))]

    @property
    def gyro_lsb_per_dps(self) -> float:
        """Counts per deg/s at the current GYRO_CONFIG full scale."""
        return mpu.GYRO_LSB_PER_DPS[mpu.fs_sel(self.peek(mpu.GYRO_CONFIG))]

    @property
    def dlpf_cfg(self) -> int:
        """CONFIG.DLPF_CFG as written (stored; the model does not filter)."""
        return self.peek(mpu.CONFIG) & mpu.DLPF_CFG_MASK

    @property
    def bypass_enabled(self) -> bool:
        """True when INT_PIN_CFG.BYPASS_EN exposes the AK8963 on the main bus."""
        return bool(self.peek(mpu.INT_PIN_CFG) & mpu.INT_PIN_CFG_BYPASS_EN)

    def write_register(self, register: int, value: int) -> None:
        """PWR_MGMT_1.DEVICE_RESET resets every register and clears itself."""
        if register == mpu.PWR_MGMT_1 and value & mpu.PWR1_DEVICE_RESET:
            self.reset()
            return
        super().write_register(register, value)

    def begin_transaction(self, op: int, register: int, length: int) -> None:
        """Latch one fresh sample before a read that reaches the sample registers."""
        if op != OP_READ or self.asleep:
            return
        last = register + length - 1
        if last < _SAMPLE_SPAN.start or register > _SAMPLE_SPAN.stop - 1:
            return
        self.latch_sample()

    def latch_sample(self) -> None:
        """Sample the vehicle now and fill 0x3A..0x48 (INT_STATUS.DATA_RDY_INT set)."""
        with self._lock:
            truth = self.vehicle.snapshot()
            g = mpu.STANDARD_GRAVITY
            true_g = (truth.accel_x / g, -truth.accel_y / g, -truth.accel_z / g)
            accel_g = tuple(o + sum(k * a for k, a in zip(row, true_g))
                            for row, o in zip(self.accel_matrix, self.accel_offset_g))
            rates = (truth.roll_rate, -truth.pitch_rate, -truth.yaw_rate)
            gyro_dps = tuple(math.degrees(w) + b for w, b in zip(rates, self.gyro_bias_dps))
            a_scale, g_scale = self.accel_lsb_per_g, self.gyro_lsb_per_dps
            counts = [mpu.clamp_int16((a + self._rng.gauss(0.0, self.accel_noise_g)) * a_scale) for a in accel_g]
            temp = (self.temperature_c + self._rng.gauss(0.0, 0.05) - self.variant.temp_offset_c)
            counts.append(mpu.clamp_int16(temp * self.variant.temp_lsb_per_c))
            counts += [mpu.clamp_int16((w + self._rng.gauss(0.0, self.gyro_noise_dps)) * g_scale) for w in gyro_dps]
            self._regs[mpu.BURST_START:mpu.BURST_START + mpu.BURST_LENGTH] = mpu.encode_burst(mpu.RawSample(*counts))
            self._regs[mpu.INT_STATUS] = 0x01
            self.samples += 1


class Ak8963Chip(RegisterChip):
    """The AK8963 magnetometer inside an MPU-9250, at 0x0C on the main bus while the MPU's
    INT_PIN_CFG.BYPASS_EN is set (it NACKs otherwise, as the real part is then hidden).

    Field model: a fixed Earth field in NED (µT) rotated into the body frame by the
    vehicle's attitude, then into chip axes (x forward, y left, z up) and finally into the
    AK8963's own axes (mag x = chip y, mag y = chip x, mag z = -chip z). Output is 16-bit
    (0.15 µT/LSB) or 14-bit (0.6 µT/LSB) little-endian, divided by the fuse-ROM sensitivity
    adjustment so a driver must apply ASA to get the field back.

    The vehicle's iron is modelled in the AK8963's axes: ``measured = soft_iron @ field +
    hard_iron_ut`` (defaults identity and zero). A symmetric soft-iron matrix is what an
    ellipsoid fit can undo fully (a rotation part cannot be told from the mounting). A count
    beyond the 16-bit range (+-32760, 4912 µT) sets ST2.HOFL, as the chip does.
    """

    read_only = frozenset({mpu.AK8963_WIA, 0x01, mpu.AK8963_ST1, *range(mpu.AK8963_HXL, mpu.AK8963_ST2 + 1),
                           mpu.AK8963_ASAX, mpu.AK8963_ASAX + 1, mpu.AK8963_ASAX + 2})

    MODE_POWER_DOWN = 0x0
    MODE_SINGLE = 0x1
    MODE_FUSE_ROM = 0xF

    def __init__(self, *, parent: Mpu9250Chip, address: int = mpu.AK8963_ADDRESS,
                 earth_field_ut: tuple[float, float, float] = (20.0, 0.0, 45.0),
                 asa: tuple[int, int, int] = (176, 177, 165), noise_ut: float = 0.3, seed: int = 0,
                 hard_iron_ut: Sequence[float] = (0.0, 0.0, 0.0),
                 soft_iron: Sequence[Sequence[float]] = IDENTITY) -> None:
        self.parent = parent
        self.hard_iron_ut = _vector("hard_iron_ut", hard_iron_ut)
        self.soft_iron = _matrix("soft_iron", soft_iron)
        self.earth_field_ut = tuple(earth_field_ut)
        self.asa = tuple(asa)
        self.noise_ut = noise_ut
        self.reset_values = {mpu.AK8963_WIA: mpu.AK8963_WIA_VALUE, 0x01: 0x9A}
        self._rng = random.Random(seed + 0x0C)
        super().__init__(address=address)

    @property
    def mode(self) -> int:
        """CNTL1.MODE (0 power-down, 1 single, 2/6 continuous, 0xF fuse ROM)."""
        return self.peek(mpu.AK8963_CNTL1) & 0x0F

    def _handle(self, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        if not (self.parent.variant.has_magnetometer and self.parent.bypass_enabled):
            return STATUS_NACK, b""
        return super()._handle(op, register, length, data)

    def read_register(self, register: int) -> int:
        """ASA reads only in fuse-ROM mode; ST2 read releases the data latch."""
        if register in (mpu.AK8963_ASAX, mpu.AK8963_ASAX + 1, mpu.AK8963_ASAX + 2):
            return self.asa[register - mpu.AK8963_ASAX] if self.mode == self.MODE_FUSE_ROM else 0
        value = self._regs[register]
        if register == mpu.AK8963_ST2:
            self._regs[mpu.AK8963_ST1] &= ~0x01
            if self.mode == self.MODE_SINGLE:
                self._regs[mpu.AK8963_CNTL1] &= 0xF0  # single measurement done: back to power-down
        return value

    def write_register(self, register: int, value: int) -> None:
        """CNTL2.SRST resets the chip."""
        if register == mpu.AK8963_CNTL2 and value & 0x01:
            self.reset()
            return
        super().write_register(register, value)

    def begin_transaction(self, op: int, register: int, length: int) -> None:
        """Reading ST1 in a measurement mode latches a new measurement (DRDY=1)."""
        if op == OP_READ and register <= mpu.AK8963_ST1 < register + length and self.mode not in (
                self.MODE_POWER_DOWN, self.MODE_FUSE_ROM):
            self._latch()

    def _latch(self) -> None:
        truth = self.parent.vehicle.snapshot()
        body = ned_to_body(self.earth_field_ut, truth.roll, truth.pitch, truth.yaw)
        chip = (body[0], -body[1], -body[2])
        ideal = (chip[1], chip[0], -chip[2])
        mag_axes = tuple(b + sum(k * f for k, f in zip(row, ideal))
                         for row, b in zip(self.soft_iron, self.hard_iron_ut))
        sixteen = bool(self.peek(mpu.AK8963_CNTL1) & 0x10)
        scale = mpu.AK8963_UT_PER_LSB_16BIT if sixteen else mpu.AK8963_UT_PER_LSB_14BIT
        out = bytearray()
        overflow = False
        limit = 32760 if sixteen else 8190
        for field, asa in zip(mag_axes, self.asa):
            value = (field + self._rng.gauss(0.0, self.noise_ut)) / mpu.ak8963_adjustment(asa) / scale
            overflow = overflow or abs(value) > limit
            count = mpu.clamp_int16(value)
            out += count.to_bytes(2, "little", signed=True)
        self._regs[mpu.AK8963_HXL:mpu.AK8963_HXL + 6] = out
        self._regs[mpu.AK8963_ST1] = mpu.AK8963_ST1_DRDY
        self._regs[mpu.AK8963_ST2] = ((mpu.AK8963_ST2_BITM if sixteen else 0x00)
                                      | (mpu.AK8963_ST2_HOFL if overflow else 0x00))


def ned_to_body(v: tuple[float, float, float], roll: float, pitch: float, yaw: float) -> tuple[float, float, float]:
    """Rotate an NED vector into the FRD body frame (yaw-pitch-roll, aerospace order)."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    n, e, d = v
    x = cp * cy * n + cp * sy * e - sp * d
    y = (sr * sp * cy - cr * sy) * n + (sr * sp * sy + cr * cy) * e + sr * cp * d
    z = (cr * sp * cy + sr * sy) * n + (cr * sp * sy - sr * cy) * e + cr * cp * d
    return x, y, z


def _vector(name: str, v: Sequence[float]) -> tuple[float, float, float]:
    out = tuple(float(x) for x in v)
    if len(out) != 3 or not all(math.isfinite(x) for x in out):
        raise ValueError(f"{name} must be three finite numbers, got {v!r}")
    return out  # type: ignore[return-value]


def _matrix(name: str, m: Sequence[Sequence[float]]) -> tuple[tuple[float, float, float], ...]:
    rows = tuple(_vector(name, row) for row in m)
    if len(rows) != 3:
        raise ValueError(f"{name} must be a 3x3 matrix (three rows of three), got {m!r}")
    return rows


class OrientedVehicle:
    """A test hook: a vehicle held still at an attitude the test sets (``orient``), e.g. to turn a
    board through the orientations of a calibration. Its specific force is gravity's reaction
    at that attitude (FRD: ``(0, 0, -g)`` level), its rates are zero."""

    def __init__(self, *, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> None:
        self._lock = threading.Lock()
        self._attitude = (roll, pitch, yaw)

    def orient(self, *, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> None:
        """Hold the vehicle at this attitude (radians, aerospace yaw-pitch-roll)."""
        with self._lock:
            self._attitude = (float(roll), float(pitch), float(yaw))

    def snapshot(self) -> SimpleNamespace:
        """A VehicleTruth-shaped record of the attitude held now."""
        with self._lock:
            roll, pitch, yaw = self._attitude
        fx, fy, fz = ned_to_body((0.0, 0.0, -mpu.STANDARD_GRAVITY), roll, pitch, yaw)
        return SimpleNamespace(t=time.monotonic(), roll=roll, pitch=pitch, yaw=yaw, roll_rate=0.0, pitch_rate=0.0,
                               yaw_rate=0.0, accel_x=fx, accel_y=fy, accel_z=fz)
