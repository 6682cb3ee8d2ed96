"""IMU driver for the InvenSense MPU-6050 / MPU-6500 / MPU-9250 family over I2C.

On every open of the chip (start, and after a lost bus or a chip that stopped answering):
WHO_AM_I is checked against ``chip`` (``auto`` takes any member of the family), the chip
is reset and woken on the gyro PLL, and SMPLRT_DIV, CONFIG (DLPF), GYRO_CONFIG and
ACCEL_CONFIG are written in one transaction and read back. Each sample is one 14-byte
burst from ACCEL_XOUT_H (accel, temperature and gyro of one instant), scaled by the
configured full scales and turned from chip axes into body FRD by ``mounting``.

What is published (reference_frame "FRD"):

- phi_dot, theta_dot, psi_dot: the body rates p, q, r (rad/s) minus the gyro bias. The
  bias is the mean of ``calibrate_samples`` readings taken at rest after start; a window
  that was not at rest (see :class:`~u2sa_hw.drivers.imu.common.RestCalibration`) is discarded and
  the next one tried, so a driver restarted while the vehicle moves calibrates at its next
  stop. Until then the rates carry no bias correction and ``uncalibrated_rate_sigma``. Rest
  is judged on the samples, and its time on their stamps, so a stall of the process between
  samples cannot fail it; after ``rest_timeout_s`` of samples with no window at rest, health
  says so in one line (``calibration``: "no rest found in 30 s of samples (...)"), the
  pre-arm IMU check shows it, and the search goes on: moving data never calibrates.
- x_ddot, y_ddot, z_ddot: body acceleration (m/s^2), i.e. the measured specific force with
  gravity removed. The chip cannot tell gravity from acceleration, so ``gravity`` says
  what is removed: ``rest`` (default) the specific force measured in the rest window
  (gravity at the start attitude plus the accelerometer's bias), ``level`` g along body
  down, ``none`` publishes no accelerations. Both assume the attitude stays near the
  one assumed (true of ground vehicles and boats, within g*sin(tilt)); say so with
  ``accel_sigma``. Use the BNO055, whose fusion removes gravity at any attitude, when it
  matters.
- psi (MPU-9250 only, once the magnetometer is calibrated): the tilt-compensated true
  heading from the AK8963 (drivers/imu/ak8963.py; its axes differ from the accel/gyro's:
  x<->y swapped, z inverted) and the accelerometer's roll and pitch, plus
  ``declination_deg``, with ``heading_sigma_deg``. An uncalibrated magnetometer gives no
  heading: hard iron alone can turn it by tens of degrees.

Calibration (docs/calibration.md, ``u2sa calibrate compass|imu``): ``mag_offset`` (µT) /
``mag_matrix`` and ``accel_offset`` (m/s^2) / ``accel_matrix`` correct the body-FRD vectors
as ``matrix @ (raw - offset)``; zero/identity means uncalibrated (health ``mag_calibrated``,
``accel_calibrated``). Setting ``calibration_stream_s`` over the bus publishes the raw
(uncorrected) body-FRD vectors on ``CAL.<service>`` for that many seconds (State
Information: x, y, z = magnetic field in µT when a new one was read; x_ddot, y_ddot,
z_ddot = specific force in m/s^2), so a dead ``u2sa calibrate`` leaves no stream running;
0 stops it, and it never starts from the file at start.
"""

from __future__ import annotations

import math
import time
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import MAX_TIMEOUT_S, ConfigError, field
from u2sa_hw.ports.errors import PortIOError, PortUnavailable
from u2sa_hw.calibration.correction import IDENTITY9, MAX_MAG_OFFSET, MAX_MATRIX_ENTRY, ZERO3, Correction, tilt_compensated_heading
from u2sa_hw.geo import wrap_angle
from u2sa_hw.protocols import mpu9250 as mpu

from u2sa_hw.drivers.imu.ak8963 import Ak8963, to_chip_axes
from u2sa_hw.drivers.imu.common import ChipIdentityError, I2cImuDriver, Mounting, RestCalibration, RetryingI2c, Vector

# Members outside the register table's three that share their register layout [LNX].
COMPATIBLE_WHO_AM_I = {0x73: ("MPU-9255", "mpu9250"), 0x74: ("MPU-6515", "mpu6500")}
CHIP_NAMES = {"mpu6050": "MPU-6050", "mpu6500": "MPU-6500", "mpu9250": "MPU-9250"}
GRAVITY_MODES = ("rest", "level", "none")
RESET_WAIT_S = 0.1  # PWR_MGMT_1.DEVICE_RESET takes up to 100 ms [RM6050]
WAKE_WAIT_S = 0.01
CAL_PREFIX = "CAL."
MAG_MAX_AGE_S = 0.1   # a heading needs a field read this recently (counted in samples at rate_hz: see read_sample)


def identify(who_am_i: int) -> tuple[str, str] | None:
    """(variant, part name) for a WHO_AM_I value of the family, or None."""
    variant = mpu.WHO_AM_I_TO_VARIANT.get(who_am_i)
    if variant is not None:
        return variant, CHIP_NAMES[variant]
    if who_am_i in COMPATIBLE_WHO_AM_I:
        part, variant = COMPATIBLE_WHO_AM_I[who_am_i]
        return variant, part
    return None


def sample_rate_divider(rate_hz: float, dlpf_cfg: int) -> int:
    """SMPLRT_DIV for *rate_hz*: the gyro runs at 1 kHz with the DLPF on (1..6), else 8 kHz."""
    internal = 1000.0 if 1 <= dlpf_cfg <= 6 else 8000.0
    return max(0, min(255, round(internal / rate_hz) - 1))


class Mpu9250ImuDriver(I2cImuDriver):
    """MPU-6050/6500/9250 accel/gyro over I2C: body rates and accelerations in FRD."""

    IDENTITY_REGISTER = mpu.WHO_AM_I

    CONFIG = (
        field("chip", "auto", "auto, mpu6050, mpu6500 or mpu9250 (checked against WHO_AM_I)"),
        field("gyro_range_dps", 500, "gyro full scale: 250, 500, 1000 or 2000 deg/s", choices=(250, 500, 1000, 2000)),
        field("accel_range_g", 4, "accelerometer full scale: 2, 4, 8 or 16 g", choices=(2, 4, 8, 16)),
        field("dlpf_cfg", 3, "CONFIG.DLPF_CFG 0..6 (3: about 42 Hz bandwidth, 1 kHz gyro rate)", ge=0, le=6),
        field("mounting", "x,-y,-z", "body forward,right,down as signed chip axes (chip flat, x fwd, y left, z up)"),
        field("calibrate_samples", 200, "gyro bias window at rest after start (0: no calibration)", ge=0, le=100000),
        field("rest_max_std_dps", 0.5, "a window whose gyro std exceeds this is not at rest", gt=0, le=2000),
        field("rest_max_rate_dps", 10.0, "a window whose mean rate exceeds this is turning, not bias", gt=0, le=2000),
        field("rest_timeout_s", 30.0, "seconds of samples without a window at rest before health says the "
              "vehicle will not keep still (the search goes on; moving data never calibrates)", gt=0, le=MAX_TIMEOUT_S),
        field("uncalibrated_rate_sigma", 0.1, "rad/s, rate sigma until the bias is calibrated", gt=0, le=10.0),
        field("gravity", "rest", "what x_ddot..z_ddot lose: rest, level or none (no accelerations)", choices=GRAVITY_MODES),
        field("mag_offset", list(ZERO3), "magnetometer hard iron (µT, body FRD); set by u2sa calibrate compass",
              item_type=float, ge=-MAX_MAG_OFFSET, le=MAX_MAG_OFFSET),
        field("mag_matrix", list(IDENTITY9), "magnetometer soft iron/scale, 9 numbers row-major; corrected = "
              "matrix @ (raw - offset); identity with a zero offset = uncalibrated (no heading)", item_type=float, ge=-MAX_MATRIX_ENTRY, le=MAX_MATRIX_ENTRY),
        field("accel_offset", list(ZERO3), "accelerometer offset (m/s^2, body FRD); set by u2sa calibrate imu",
              item_type=float, ge=-1000.0, le=1000.0),
        field("accel_matrix", list(IDENTITY9), "accelerometer scale/misalignment, 9 numbers row-major",
              item_type=float, ge=-MAX_MATRIX_ENTRY, le=MAX_MATRIX_ENTRY),
        field("declination_deg", 0.0, "magnetic declination, east positive: true = magnetic + declination",
              ge=-180, le=180),
        field("heading_sigma_deg", 3.0, "sigma of psi from the magnetometer (deg)", gt=0, le=180),
        field("calibration_stream_s", 0.0, "seconds to publish raw vectors on CAL.<service> for u2sa calibrate "
              "(0: off; only a change over the bus starts it)", ge=0, le=3600),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.variant: mpu.MpuVariant | None = None
        self.part = ""
        self.who_am_i: int | None = None
        self.temperature_c: float | None = None
        self.gyro_bias: Vector = (0.0, 0.0, 0.0)
        self.rest_force: Vector = (0.0, 0.0, -RestCalibration.GRAVITY)
        self.calibrated = False
        self.calibration_state = "not started"
        self.calibration: RestCalibration | None = None
        self.mag: Ak8963 | None = None
        self._samples_since_field: int | None = None   # samples since the magnetometer last had a new field
        self.mag_correction = Correction((0.0, 0.0, 0.0), tuple(IDENTITY9))
        self.accel_correction = Correction((0.0, 0.0, 0.0), tuple(IDENTITY9))
        self.stream_until = 0.0     # monotonic time the CAL stream ends
        self.heading_deg: float | None = None

    def check_config(self) -> None:
        """Ranges, DLPF, chip, mounting and gravity mode; ConfigError names the field."""
        c = self.config
        try:
            self.gyro_fs = mpu.gyro_fs_index(int(c["gyro_range_dps"]))
            self.accel_fs = mpu.accel_fs_index(int(c["accel_range_g"]))
            self.scale = (mpu.STANDARD_GRAVITY / mpu.ACCEL_LSB_PER_G[self.accel_fs],   # m/s^2, rad/s per count
                          math.radians(1.0 / mpu.GYRO_LSB_PER_DPS[self.gyro_fs]))
        except ValueError as exc:
            raise ConfigError(f"{self.name}: {exc}") from None
        if not 0 <= int(c["dlpf_cfg"]) <= 6:
            raise ConfigError(f"{self.name}: config 'dlpf_cfg' must be 0..6, got {c['dlpf_cfg']}")
        if c["chip"] != "auto" and c["chip"] not in mpu.VARIANTS:
            raise ConfigError(f"{self.name}: config 'chip' must be auto or one of {sorted(mpu.VARIANTS)}, "
                              f"got {c['chip']!r}")
        if c["gravity"] not in GRAVITY_MODES:
            raise ConfigError(f"{self.name}: config 'gravity' must be one of {GRAVITY_MODES}, got {c['gravity']!r}")
        self.mounting = Mounting.parse(c["mounting"])
        self._corrections()   # only checked here: this also runs with a value being tried

    def _corrections(self) -> tuple[Correction, Correction]:
        c = self.config
        try:
            return (Correction.from_config(c["mag_offset"], c["mag_matrix"], what="mag_offset/mag_matrix"),
                    Correction.from_config(c["accel_offset"], c["accel_matrix"], what="accel_offset/accel_matrix"))
        except ValueError as exc:
            raise ConfigError(f"{self.name}: {exc}") from None

    def setup(self) -> None:
        """Check the config, prepare the port and the gyro bias window."""
        super().setup()
        c = self.config
        self.mag_correction, self.accel_correction = self._corrections()
        if int(c["calibrate_samples"]) > 0:
            self.calibration = RestCalibration(samples=int(c["calibrate_samples"]),
                                               max_std_dps=float(c["rest_max_std_dps"]),
                                               max_rate_dps=float(c["rest_max_rate_dps"]),
                                               give_up_s=float(c["rest_timeout_s"]))
            self.calibration_state = "calibrating"
        else:
            self.calibrated, self.calibration_state = True, "off"
        self.register_publisher(self.cal_channel, t.StateInformation)

    @property
    def cal_channel(self) -> str:
        """``CAL.<service>``: raw vectors while ``calibration_stream_s`` runs."""
        return CAL_PREFIX + self.name

    def on_config_change(self, name: str, value: Any) -> None:
        """The calibration fields apply at once; the stream starts or stops."""
        super().on_config_change(name, value)
        if name == "calibration_stream_s":
            self.stream_until = time.monotonic() + float(value) if float(value) > 0 else 0.0
            self.logger.info("%s: calibration stream on %s %s", self.name, self.cal_channel,
                             f"for {float(value):g} s" if value else "off")
        elif name.startswith(("mag_", "accel_")):
            self.mag_correction, self.accel_correction = self._corrections()
            self.logger.info("%s: %s = %s applied", self.name, name, value)

    # -- chip set-up ----------------------------------------------------------------------
    def init_chip(self, port: RetryingI2c, *, first: bool) -> None:
        """Check WHO_AM_I, reset, wake, configure, read the configuration back."""
        who = port.read_byte(mpu.WHO_AM_I)
        self._check_identity(who, first=first)
        variant = self.variant
        assert variant is not None
        port.write_byte(mpu.PWR_MGMT_1, mpu.PWR1_DEVICE_RESET)
        time.sleep(RESET_WAIT_S)
        port.write_byte(mpu.PWR_MGMT_1, 0x01)  # awake, clock from the X gyro PLL
        time.sleep(WAKE_WAIT_S)
        dlpf = int(self.config["dlpf_cfg"])
        wanted = bytes((sample_rate_divider(float(self.config["rate_hz"]), dlpf), dlpf,
                        mpu.fs_config(self.gyro_fs), mpu.fs_config(self.accel_fs)))
        port.write_block(mpu.SMPLRT_DIV, wanted)  # 0x19..0x1C in one transaction
        if variant.name != "mpu6050":
            port.write_byte(mpu.ACCEL_CONFIG2, dlpf)  # the accelerometer's own DLPF (A_DLPFCFG)
        got = port.read_block(mpu.SMPLRT_DIV, len(wanted))
        if got != wanted or port.read_byte(mpu.PWR_MGMT_1) & mpu.PWR1_SLEEP:
            raise PortIOError(self.name, f"configuration did not take: wrote {wanted.hex()} to 0x19.., read "
                                         f"{got.hex()}", address=self.where,
                              fix="check the chip's power and wiring; the driver retries")
        if variant.has_magnetometer:
            # on every open, from the device's address now: the same bus as the MPU (a mock or replay
            # socket too), so a reopen on an address change takes the magnetometer along
            address = self.port.address
            assert address is not None
            if self.mag is None:
                self.mag = Ak8963(retries=lambda: int(self.config["retries"]), tap=self.port.tap)
            if not self.mag.setup(port, device=self.port.device, mpu_address=address):
                self.logger.warning("%s: magnetometer: %s; no heading", self.name, self.mag.state)
        elif self.mag is not None:
            self.mag.close(f"none: the chip is now an {self.part}")

    def _check_identity(self, who: int, *, first: bool) -> None:
        found = identify(who)
        wanted = self.config["chip"]
        if found is None:
            problem = (f"the chip at {self.where} answers WHO_AM_I 0x{who:02x}, not an MPU-6050/6500/9250 "
                       "(0x68/0x70/0x71)")
            fix = "check the address (an MPU answers at 0x68 or 0x69) and that the chip is an MPU"
        elif wanted != "auto" and found[0] != wanted:
            problem = (f"the chip at {self.where} answers WHO_AM_I 0x{who:02x} ({found[1]}), but chip = "
                       f"\"{wanted}\" expects 0x{mpu.VARIANTS[wanted].who_am_i:02x}")
            fix = f'set chip = "{found[0]}" (or "auto") in the config, or check the address'
        else:
            self.variant, self.part, self.who_am_i = mpu.VARIANTS[found[0]], found[1], who
            return
        if first:
            raise ChipIdentityError(f"{self.name}: {problem}; fix: {fix}")
        raise PortUnavailable(self.name, problem, address=self.where, fix=fix)

    # -- samples --------------------------------------------------------------------------
    def sample_once(self) -> None:
        """As the base does, after closing a magnetometer port left from an MPU port that is no longer
        open (lost, or replaced on an address change): the MPU's next open sets it up again."""
        if self.mag is not None and self.mag.port is not None and self.port.state != "open":
            self.mag.close("closed with the MPU's port; set up again when it reopens")
        super().sample_once()

    def read_sample(self, port: RetryingI2c) -> t.StateInformation | None:
        """One burst: scale, rotate into FRD, calibrate, build the message."""
        raw = mpu.decode_burst(port.read_block(mpu.BURST_START, mpu.BURST_LENGTH))
        msg = self.new_state()
        variant = self.variant
        assert variant is not None
        g_per_count, rad_per_count = self.scale
        raw_force = self.mounting.to_body((raw.ax * g_per_count, raw.ay * g_per_count, raw.az * g_per_count))
        force = self.accel_correction.apply(raw_force)
        gyro = self.mounting.to_body((raw.gx * rad_per_count, raw.gy * rad_per_count, raw.gz * rad_per_count))
        self.temperature_c = raw.temp / variant.temp_lsb_per_c + variant.temp_offset_c
        if not self.calibrated and self.calibration is not None:
            self._calibrate(gyro, raw_force, stamp=msg.header.timestamp_us / 1e6)
        bias = self.gyro_bias
        sigma = float(self.config["rate_sigma" if self.calibrated else "uncalibrated_rate_sigma"])
        values = {"phi_dot": gyro[0] - bias[0], "theta_dot": gyro[1] - bias[1], "psi_dot": gyro[2] - bias[2],
                  "phi_dot_sigma": sigma, "theta_dot_sigma": sigma, "psi_dot_sigma": sigma}
        mode = self.config["gravity"]
        if mode != "none":
            # the rest window holds raw readings, so a calibration saved later corrects it too
            ref = (self.accel_correction.apply(self.rest_force) if mode == "rest"
                   else (0.0, 0.0, -RestCalibration.GRAVITY))
            a_sigma = float(self.config["accel_sigma"])
            values.update(x_ddot=force[0] - ref[0], y_ddot=force[1] - ref[1], z_ddot=force[2] - ref[2],
                          x_ddot_sigma=a_sigma, y_ddot_sigma=a_sigma, z_ddot_sigma=a_sigma)
        msg.set(**values)   # both vectors and their sigmas in one set
        raw_mag = self._read_mag()
        if raw_mag is not None or self._field_recent():
            self._heading(msg, force, raw_mag)
        if self.stream_until and time.monotonic() < self.stream_until:
            self._stream(msg.header.timestamp_us, raw_force, raw_mag)
        elif self.stream_until:
            self.stream_until = 0.0
            self.logger.info("%s: calibration stream ended (its time ran out)", self.name)
        return msg

    def _read_mag(self) -> Vector | None:
        """The newest field in body FRD (µT, uncorrected), or None when none new."""
        if self.mag is None:
            return None
        got = self.mag.read()
        if got is None:
            if self._samples_since_field is not None:
                self._samples_since_field += 1
            return None
        self._samples_since_field = 0
        return self.mounting.to_body(to_chip_axes(got))

    def _field_recent(self) -> bool:
        """The last field is under MAG_MAX_AGE_S old, counted in samples at ``rate_hz`` rather than on the wall
        clock: a replay reads the recorded samples faster, or held up by the player, and must keep the same
        headings (docs/replay.md); live, the samples come on the rate_hz timer, so the two agree."""
        since = self._samples_since_field
        return self.mag is not None and since is not None and since / float(self.config["rate_hz"]) < MAG_MAX_AGE_S

    def _heading(self, msg: t.StateInformation, force: Vector, raw_mag: Vector | None) -> None:
        if not self.mag_correction.calibrated or self.mag is None or self.mag.last is None:
            self.heading_deg = None
            return
        body = raw_mag if raw_mag is not None else self.mounting.to_body(to_chip_axes(self.mag.last))
        heading = tilt_compensated_heading(force, self.mag_correction.apply(body))
        if heading is None:
            return
        psi = wrap_angle(heading + math.radians(float(self.config["declination_deg"])))
        self.heading_deg = math.degrees(psi) % 360.0
        msg.set(psi=psi, psi_sigma=math.radians(float(self.config["heading_sigma_deg"])))

    def _stream(self, timestamp_us: int, raw_force: Vector, raw_mag: Vector | None) -> None:
        cal = t.StateInformation()
        cal.header.timestamp_us = timestamp_us
        cal.sensor_name, cal.reference_frame = self.name, "FRD"
        cal.set(x_ddot=raw_force[0], y_ddot=raw_force[1], z_ddot=raw_force[2])
        if raw_mag is not None:
            cal.set(x=raw_mag[0], y=raw_mag[1], z=raw_mag[2])
        self.publish(self.cal_channel, cal)

    def _calibrate(self, gyro: Vector, force: Vector, *, stamp: float) -> None:
        cal = self.calibration
        assert cal is not None
        was_overdue = cal.overdue
        result = cal.add(gyro, force, stamp=stamp)
        if cal.overdue and not was_overdue:
            self.calibration_state = self._no_rest(cal)
            self.logger.warning("%s: %s", self.name, self.calibration_state)
        if result is None:
            return
        if not result.accepted:
            self.calibration_state = self._no_rest(cal) if cal.overdue else f"waiting for rest ({result.reason})"
            self.logger.warning("%s: gyro bias window rejected: %s; trying again", self.name, result.reason)
            return
        self.gyro_bias, self.rest_force = result.gyro_mean, result.accel_mean
        self.calibrated, self.calibration_state = True, "calibrated"
        self.logger.info("%s: gyro bias %s deg/s (FRD), std %.3f deg/s; rest specific force %s m/s^2", self.name,
                         _fmt(math.degrees(b) for b in self.gyro_bias), result.gyro_std_dps, _fmt(self.rest_force))

    def _no_rest(self, cal: RestCalibration) -> str:
        """The fallback's one line: no rest for rest_timeout_s of samples, what it waits for, that it goes on."""
        window_s = cal.samples / float(self.config["rate_hz"])
        why = f" ({cal.last_reason})" if cal.last_reason else ""
        return (f"no rest found in {cal.give_up_s:g} s of samples{why}; it calibrates on the first "
                f"{window_s:.1f} s at rest, never on moving data")

    def healthy(self) -> bool:
        """Degraded until the gyro bias is calibrated."""
        return self.calibrated

    def chip_health(self) -> dict[str, Any]:
        """Part, WHO_AM_I, temperature, ranges, calibration and the bias found."""
        return {
            "chip": self.part or "not identified",
            "who_am_i": f"0x{self.who_am_i:02x}" if self.who_am_i is not None else "",
            "temperature_c": f"{self.temperature_c:.1f}" if self.temperature_c is not None else "",
            "gyro_range_dps": self.config["gyro_range_dps"], "accel_range_g": self.config["accel_range_g"],
            "calibration": self.calibration_state,
            "gyro_bias_dps": _fmt(math.degrees(b) for b in self.gyro_bias),
            "gravity": self.config["gravity"],
            "mag_calibrated": _yes(self.mag_correction.calibrated),
            "accel_calibrated": _yes(self.accel_correction.calibrated),
            **self._mag_health(),
        }

    def _mag_health(self) -> dict[str, Any]:
        if self.mag is None:
            return {}
        return {"magnetometer": self.mag.state, "mag_address": str(self.mag.address or ""),
                "mag_samples": self.mag.samples, "mag_overflows": self.mag.overflows,
                "mag_errors": self.mag.errors, "mag_asa": ",".join(map(str, self.mag.asa or ())),
                "heading_deg": "" if self.heading_deg is None else f"{self.heading_deg:.1f}",
                "calibration_stream": "on" if self.stream_until else "off"}

    def kill(self) -> None:
        """Close the magnetometer's port too."""
        if self.mag is not None:
            self.mag.close()
        super().kill()


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


def _fmt(values: Any) -> str:
    return ",".join(f"{v:.4f}" for v in values)
