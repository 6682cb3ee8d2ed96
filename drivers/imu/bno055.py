"""IMU driver for the Bosch BNO055 absolute-orientation sensor over I2C.

On every open (start, and after a lost bus or a chip that stopped answering or reset
itself): CHIP_ID must read 0xA0; optionally the chip is reset; then in CONFIG mode the
driver selects page 0, normal power, units (m/s^2, rad/s, radians, Celsius, Windows
orientation) and the axis remap (``axis_map_config``/``axis_map_sign``), switches to the
fusion ``mode`` (NDOF by default) and reads OPR_MODE and UNIT_SEL back.

Each sample is one 26-byte read from GYR_DATA_X_LSB (gyro, Euler angles, quaternion,
linear acceleration of one fusion step). Once a second the status block TEMP..SYS_ERR is
read for health (temperature, CALIB_STAT, SYS_STATUS, SYS_ERR); a chip found back in
CONFIG mode (it reset) or reporting a system error is set up again.

What is published (reference_frame "FRD"; vectors in chip axes, which the axis remap
makes x forward, y left, z up, see docs/i2c-devices.md):

- phi, theta: roll and pitch (rad) from the Euler registers;
- psi: heading (rad, clockwise from north, in [-pi, pi)) only in the magnetometer modes
  (NDOF, NDOF_FMC_OFF) and once the system calibration level reaches
  ``min_heading_calibration``; in IMU mode the heading is relative to the start and is
  not published;
- phi_dot, theta_dot, psi_dot: body rates p, q, r (rad/s);
- x_ddot, y_ddot, z_ddot: body acceleration with gravity removed by the chip's fusion
  (the LIA registers), m/s^2.
"""

from __future__ import annotations

import math
import time
from typing import Any, Mapping

from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import ConfigError, field
from u2sa_hw.geo import wrap_angle
from u2sa_hw.ports.errors import PortClosed, PortIOError, PortUnavailable
from u2sa_hw.protocols import bno055 as bno

from u2sa_hw.drivers.imu.common import (ACCEL_FIELDS, RATE_FIELDS, ChipIdentityError, I2cImuDriver, Mounting,
                                RetryingI2c, set_vector)

MODES = {"ndof": bno.MODE_NDOF, "ndof_fmc_off": bno.MODE_NDOF_FMC_OFF, "imu": bno.MODE_IMU}
HEADING_MODES = frozenset({bno.MODE_NDOF, bno.MODE_NDOF_FMC_OFF})
UNITS = bno.UNIT_GYR_RPS | bno.UNIT_EUL_RAD  # m/s^2, rad/s, rad, Celsius, Windows orientation
CHIP_AXES_TO_FRD = Mounting.parse("x,-y,-z")  # after the chip's own axis remap
SAMPLE_START = bno.GYR_DATA_X_LSB
SAMPLE_LENGTH = bno.LIA_DATA_X_LSB + 6 - SAMPLE_START  # GYR, EUL, QUA, LIA: 26 bytes
STATUS_START = bno.TEMP
STATUS_LENGTH = bno.SYS_ERR + 1 - STATUS_START  # TEMP, CALIB_STAT, ST_RESULT, INT_STA, SYS_CLK, SYS_STATUS, SYS_ERR
BOOT_WAIT_S = 1.0  # after RST_SYS the chip NACKs for about 650 ms
STATUS_NAMES = {0: "idle", 1: "system error", 2: "initialising peripherals", 3: "initialising", 4: "self test",
                5: "fusion running", 6: "running without fusion"}


class Bno055ImuDriver(I2cImuDriver):
    """BNO055 over I2C: attitude, body rates and gravity-free acceleration in FRD."""

    MOCK_KINDS = ("bno055",)
    IDENTITY_REGISTER = bno.CHIP_ID
    CONFIG = (
        field("mode", "ndof", "fusion mode: ndof, ndof_fmc_off or imu (no magnetometer: no heading)", choices=MODES),
        field("axis_map_config", 0x24, "AXIS_MAP_CONFIG: remap so chip x = forward, y = left, z = up", ge=0, le=0xFF),
        field("axis_map_sign", 0x00, "AXIS_MAP_SIGN for the remap", ge=0, le=0xFF),
        field("reset_on_start", False, "reset the chip (SYS_TRIGGER.RST_SYS) on every open"),
        field("min_heading_calibration", 1, "publish psi once CALIB_STAT.SYS reaches this (0..3)", ge=0, le=3),
        field("attitude_sigma", 0.02, "rad, sigma of phi and theta", gt=0, le=math.pi),
        field("heading_sigma", 0.05, "rad, sigma of psi", gt=0, le=math.pi),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.calibration = {"sys": 0, "gyr": 0, "acc": 0, "mag": 0}
        self.sys_status: int | None = None
        self.sys_error = 0
        self.temperature_c: float | None = None
        self.software = ""
        self._since_status = 0

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """A BNO055 (one variant)."""
        return {"chip": "bno055", "variant": "auto"}

    def check_config(self) -> None:
        """Mode, axis map and calibration threshold; ConfigError names the field."""
        c = self.config
        if c["mode"] not in MODES:
            raise ConfigError(f"{self.name}: config 'mode' must be one of {sorted(MODES)}, got {c['mode']!r}")
        self.mode = MODES[c["mode"]]
        for name in ("axis_map_config", "axis_map_sign"):
            if not 0 <= int(c[name]) <= 0xFF:
                raise ConfigError(f"{self.name}: config '{name}' must be a register byte 0..0xFF, got {c[name]}")
        if not 0 <= int(c["min_heading_calibration"]) <= 3:
            raise ConfigError(f"{self.name}: config 'min_heading_calibration' must be 0..3")

    # -- chip set-up ----------------------------------------------------------------------
    def init_chip(self, port: RetryingI2c, *, first: bool) -> None:
        """Check CHIP_ID, optionally reset, configure in CONFIG mode, enter the fusion mode."""
        chip_id = port.read_byte(bno.CHIP_ID)
        if chip_id != bno.CHIP_ID_VALUE and port.read_byte(bno.PAGE_ID) == 1:
            port.write_byte(bno.PAGE_ID, 0)  # left on page 1 (by a driver that died there)
            chip_id = port.read_byte(bno.CHIP_ID)
        self._check_identity(chip_id, first=first)
        if self.config["reset_on_start"]:
            port.write_byte(bno.SYS_TRIGGER, bno.TRIGGER_RST_SYS)
            self._wait_for_boot(port)
        port.write_byte(bno.OPR_MODE, bno.MODE_CONFIG)
        time.sleep(bno.OPERATION_TO_CONFIG_S + 0.005)
        port.write_byte(bno.PWR_MODE, 0)
        port.write_byte(bno.UNIT_SEL, UNITS)
        port.write_block(bno.AXIS_MAP_CONFIG, bytes((int(self.config["axis_map_config"]),
                                                     int(self.config["axis_map_sign"]))))
        rev = port.read_block(bno.SW_REV_ID_LSB, 2)
        self.software = f"{rev[1]:x}.{rev[0]:02x}"
        port.write_byte(bno.OPR_MODE, self.mode)
        time.sleep(bno.CONFIG_TO_OPERATION_S + 0.005)
        mode, units = port.read_byte(bno.OPR_MODE) & 0x0F, port.read_byte(bno.UNIT_SEL)
        if mode != self.mode or units != UNITS:
            raise PortIOError(self.name, f"configuration did not take: OPR_MODE {mode:#04x} (wanted {self.mode:#04x}), "
                                         f"UNIT_SEL {units:#04x} (wanted {UNITS:#04x})", address=self.where,
                              fix="check the chip's power and wiring; the driver retries")
        self._since_status = 0
        self._read_status(port)

    def _check_identity(self, chip_id: int, *, first: bool) -> None:
        if chip_id == bno.CHIP_ID_VALUE:
            return
        problem = f"the chip at {self.where} answers CHIP_ID 0x{chip_id:02x}, not a BNO055 (0xA0)"
        fix = "check the address (a BNO055 answers at 0x28 or 0x29) and the driver kind (an MPU needs imu_mpu9250)"
        if first:
            raise ChipIdentityError(f"{self.name}: {problem}; fix: {fix}")
        raise PortUnavailable(self.name, problem, address=self.where, fix=fix)

    def _wait_for_boot(self, port: RetryingI2c) -> None:
        deadline = time.monotonic() + BOOT_WAIT_S
        while True:
            time.sleep(0.05)
            try:
                if port.port.read_byte(bno.CHIP_ID) == bno.CHIP_ID_VALUE:  # booting NACKs are expected: not counted
                    return
            except PortIOError:
                if time.monotonic() > deadline:
                    raise

    # -- samples --------------------------------------------------------------------------
    def read_sample(self, port: RetryingI2c) -> t.StateInformation | None:
        """One 26-byte read; once a second also the status block."""
        self._since_status += 1
        if self._since_status >= float(self.config["rate_hz"]):
            self._since_status = 0
            self._read_status(port)
            if self.sys_status in (bno.STATUS_IDLE, bno.STATUS_ERROR):
                # Reported as a lost port so the chip is reopened and set up again.
                raise PortClosed(self.name, f"chip left its fusion mode ({STATUS_NAMES[self.sys_status]}, "
                                            f"SYS_ERR {self.sys_error})", address=self.where,
                                 fix="the driver sets the chip up again; check its power if this repeats")
        data = port.read_block(SAMPLE_START, SAMPLE_LENGTH)
        gyr = bno.decode_vector(data[0:6])
        heading, roll, pitch = bno.decode_vector(data[6:12])
        lia = bno.decode_vector(data[20:26])
        msg = self.new_state()
        c = self.config
        attitude_sigma = float(c["attitude_sigma"])
        msg.set(phi=roll / bno.EULER_LSB_PER_RAD, theta=pitch / bno.EULER_LSB_PER_RAD,
                phi_sigma=attitude_sigma, theta_sigma=attitude_sigma)
        if self.mode in HEADING_MODES and self.calibration["sys"] >= int(c["min_heading_calibration"]):
            msg.set(psi=wrap_angle(heading / bno.EULER_LSB_PER_RAD), psi_sigma=float(c["heading_sigma"]))
        set_vector(msg, RATE_FIELDS, CHIP_AXES_TO_FRD.to_body([w / bno.GYRO_LSB_PER_RPS for w in gyr]),
                   float(c["rate_sigma"]))
        set_vector(msg, ACCEL_FIELDS, CHIP_AXES_TO_FRD.to_body([a / bno.ACCEL_LSB_PER_MS2 for a in lia]),
                   float(c["accel_sigma"]))
        return msg

    def _read_status(self, port: RetryingI2c) -> None:
        block = port.read_block(STATUS_START, STATUS_LENGTH)
        self.temperature_c = int.from_bytes(block[0:1], "little", signed=True) / bno.TEMP_LSB_PER_C
        self.calibration = bno.split_calib_stat(block[1])
        self.sys_status, self.sys_error = block[bno.SYS_STATUS - STATUS_START], block[bno.SYS_ERR - STATUS_START]

    def healthy(self) -> bool:
        """Degraded while heading is withheld for lack of calibration (in the heading modes)."""
        return self.mode not in HEADING_MODES or self.calibration["sys"] >= int(self.config["min_heading_calibration"])

    def chip_health(self) -> dict[str, Any]:
        """Calibration levels, fusion status, temperature and firmware."""
        cal = self.calibration
        return {
            "chip": f"BNO055 fw {self.software}" if self.software else "not identified",
            "mode": self.config["mode"],
            "calibration": f"sys {cal['sys']} gyr {cal['gyr']} acc {cal['acc']} mag {cal['mag']}",
            "calib_sys": cal["sys"], "calib_gyr": cal["gyr"], "calib_acc": cal["acc"], "calib_mag": cal["mag"],
            "sys_status": STATUS_NAMES.get(self.sys_status, str(self.sys_status)) if self.sys_status is not None
            else "", "sys_error": self.sys_error,
            "temperature_c": f"{self.temperature_c:.0f}" if self.temperature_c is not None else "",
            "heading": "published" if self.healthy() and self.mode in HEADING_MODES else "withheld",
        }
