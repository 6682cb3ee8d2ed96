"""What the I2C IMU drivers share: the sample loop, retries, reconnection, mounting, rest calibration.

:class:`I2cImuDriver` is a Proprioceptive Sensor that reaches one chip through a
:class:`~u2sa_hw.ports.device_link.DeviceLink` (the ``device`` setting, default the service
name; its address ``i2c://BUS/CHIP`` from the profile's ``[devices.NAME]``). A subclass writes ``init_chip`` (identify
and configure the chip on every open) and ``read_sample`` (one burst read turned into a
State Information); this class paces the loop at ``rate_hz``, retries failed transactions,
counts every fault and reopens the chip after a loss:

- a failed transaction (NACK, EIO: ``PortIOError``) is retried ``retries`` times at once
  (``init_chip`` and ``read_sample`` get a :class:`RetryingI2c`); when every try fails
  the sample is skipped (``missed_samples``). After
  ``reinit_after_errors`` skipped samples in a row the chip is treated as lost (it may have
  lost power and forgotten its configuration): the port is closed and reopened with
  backoff, and ``init_chip`` runs again;
- a lost bus (``PortClosed``, ``PortTimeout``) is reopened with backoff at once;
- none of these stop the service; health shows the port state, the last error and the
  counters. A chip that answers with the wrong identity on the first open is a
  configuration error (:class:`ChipIdentityError`): the service exits with the message.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Mapping, Sequence, TypeVar

from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import ConfigError, field
from u2sa_hw.abstract import ProprioceptiveSensor
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence setters
from u2sa_hw.ports.errors import PortClosed, PortError, PortIOError, PortTimeout, PortUnavailable
from u2sa_hw.ports.declared import DeviceDeclarations
from u2sa_hw.ports.device_link import DeviceLink, device_setting
from u2sa_hw.ports.i2c.port import I2cPort

T = TypeVar("T")
Vector = tuple[float, float, float]
AXES = ("x", "y", "z")
PORT_FIELDS = ("device",)   # where the chip is: a change reopens it there


class ChipIdentityError(RuntimeError):
    """The chip at the configured address is not the one the driver drives."""


@dataclass(frozen=True)
class Mounting:
    """Body FRD axes as signed chip axes: ``"x,-y,-z"`` means forward = chip x, right =
    -chip y, down = -chip z (a chip lying flat, x forward, y left, z up)."""

    spec: str
    index: tuple[int, int, int]
    sign: tuple[float, float, float]

    @classmethod
    def parse(cls, spec: str) -> "Mounting":
        """Parse ``"x,-y,-z"``-style text; ConfigError unless it is a signed permutation of x, y, z."""
        parts = [p.strip().lower() for p in spec.split(",")]
        index, sign = [], []
        for part in parts:
            axis = part.lstrip("+-")
            if axis not in AXES or len(part) - len(axis) > 1:
                index = []
                break
            index.append(AXES.index(axis))
            sign.append(-1.0 if part.startswith("-") else 1.0)
        if len(parts) != 3 or sorted(index) != [0, 1, 2]:
            raise ConfigError(f"mounting {spec!r}: give forward, right and down as signed chip axes, each axis "
                              'once, e.g. "x,-y,-z" for a chip flat with x forward, y left, z up')
        return cls(spec, tuple(index), tuple(sign))  # type: ignore[arg-type]

    def to_body(self, chip: Sequence[float]) -> Vector:
        """A chip-axes vector in body FRD axes."""
        i, s = self.index, self.sign
        return s[0] * chip[i[0]], s[1] * chip[i[1]], s[2] * chip[i[2]]


@dataclass(frozen=True)
class RestResult:
    """One rest window: mean gyro (rad/s) and specific force (m/s^2), both FRD, and its verdict."""

    gyro_mean: Vector
    gyro_std_dps: float
    accel_mean: Vector
    accepted: bool
    reason: str


class RestCalibration:
    """Collects ``samples`` gyro/accelerometer readings and judges whether they were taken at rest.

    At rest means: every gyro axis's standard deviation below ``max_std_dps``, every axis's
    mean below ``max_rate_dps`` (a bias larger than the chip's zero-rate tolerance is a
    rotation), and the specific force within 10 % of g. A steady rotation slower than
    ``max_rate_dps`` cannot be told from bias: the vehicle must be still while it runs.

    Time is the samples' own: each comes with its stamp. A window is judged on its samples'
    values, so a stall of the process between two samples (no samples for a while) neither
    fails nor passes it. The bounded fallback is judged on sample time too: after
    ``give_up_s`` of samples without a window at rest, :attr:`overdue` says so (the driver
    shows it to the pilot) and the search goes on; a gap between two stamps longer than
    ``max_gap_s`` (a stall, a reopened chip, a clock that jumped) is not sample time. Moving
    data is never accepted, however long it lasts: the gyro stays uncalibrated.
    """

    GRAVITY = 9.80665

    def __init__(self, *, samples: int, max_std_dps: float, max_rate_dps: float, give_up_s: float = 30.0,
                 max_gap_s: float = 0.5) -> None:
        self.samples = samples
        self.max_std_dps = max_std_dps
        self.max_rate_dps = max_rate_dps
        self.give_up_s = give_up_s
        self.max_gap_s = max_gap_s
        self.searched_s = 0.0        # sample time spent looking for rest so far
        self.last_reason = ""        # why the last window was not at rest
        self._last_stamp: float | None = None
        self._gyro: list[Vector] = []
        self._accel: list[Vector] = []

    @property
    def overdue(self) -> bool:
        """``give_up_s`` of samples went by without a window at rest (the fallback: say so, keep looking)."""
        return self.searched_s >= self.give_up_s

    def add(self, gyro: Vector, accel: Vector, *, stamp: float) -> RestResult | None:
        """Add one sample taken at *stamp* (s, the sample's own clock); returns the verdict when the window is
        full (and starts a new one)."""
        last, self._last_stamp = self._last_stamp, stamp
        if last is not None and math.isfinite(stamp) and 0.0 < stamp - last <= self.max_gap_s:
            self.searched_s += stamp - last
        self._gyro.append(gyro)
        self._accel.append(accel)
        if len(self._gyro) < self.samples:
            return None
        gyro_s, accel_s = self._gyro, self._accel
        self._gyro, self._accel = [], []
        if not all(math.isfinite(x) for v in (*gyro_s, *accel_s) for x in v):
            self.last_reason = "unusable: a reading is not a number"
            return RestResult((0.0, 0.0, 0.0), math.inf, (0.0, 0.0, 0.0), False, self.last_reason)
        g_mean = tuple(statistics.fmean(v[i] for v in gyro_s) for i in range(3))
        a_mean = tuple(statistics.fmean(v[i] for v in accel_s) for i in range(3))
        std = max(math.degrees(statistics.pstdev(v[i] for v in gyro_s)) for i in range(3))
        worst_rate = max(abs(math.degrees(w)) for w in g_mean)
        force = math.sqrt(sum(a * a for a in a_mean))
        if std > self.max_std_dps:
            reason = f"moving: gyro std {std:.2f} deg/s > {self.max_std_dps:g}"
        elif worst_rate > self.max_rate_dps:
            reason = f"turning: mean rate {worst_rate:.2f} deg/s > {self.max_rate_dps:g}"
        elif abs(force - self.GRAVITY) > 0.1 * self.GRAVITY:
            reason = f"accelerating: specific force {force:.2f} m/s^2 is not g"
        else:
            reason = ""
        self.last_reason = reason
        return RestResult(g_mean, std, a_mean, not reason, reason)  # type: ignore[arg-type]


class RetryingI2c:
    """An I2C port whose every transaction is retried by *retry* (one NACK/EIO never fails a set-up)."""

    def __init__(self, port: I2cPort, retry: Callable[[Callable[[], Any]], Any]) -> None:
        self.port = port
        self._retry = retry

    def read_byte(self, register: int) -> int:
        """Read one register."""
        return self._retry(lambda: self.port.read_byte(register))

    def write_byte(self, register: int, value: int) -> None:
        """Write one register."""
        self._retry(lambda: self.port.write_byte(register, value))

    def read_block(self, register: int, length: int) -> bytes:
        """Read *length* bytes from *register* in one transaction."""
        return self._retry(lambda: self.port.read_block(register, length))

    def write_block(self, register: int, data: bytes) -> None:
        """Write *data* from *register* in one transaction."""
        self._retry(lambda: self.port.write_block(register, data))


class I2cImuDriver(DeviceDeclarations, ProprioceptiveSensor):
    """Base of the I2C IMU drivers (see the module docstring).

    Subclasses write ``init_chip`` and ``read_sample``; ``check_config``, ``chip_health`` and ``healthy``
    are optional.
    """

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("mpu9250", "mpu6500", "mpu6050")   # u2sa_hw/ports/declared.py
    CONFIG = (
        field("device", "", "the chip: its [devices.NAME] table (address i2c://BUS/CHIP) and RAW.<device> "
                            "(empty: the service name)"),
        field("rate_hz", 100.0, "samples published per second", gt=0, le=1000),
        field("retries", 2, "immediate retries of a failed I2C transaction", ge=0, le=100),
        field("reinit_after_errors", 10, "failed samples in a row before the chip is reopened and set up again", ge=1, le=10000),
        field("rate_sigma", 0.005, "rad/s, sigma of phi_dot/theta_dot/psi_dot", gt=0, le=10.0),
        field("accel_sigma", 0.3, "m/s^2, sigma of x_ddot/y_ddot/z_ddot", gt=0, le=100.0),
        field("record_raw", False, "publish every I2C transaction on RAW.<device>"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.samples = 0
        self.i2c_errors = 0
        self.retried_samples = 0
        self.missed_samples = 0
        self.reinits = 0
        self._failures_in_row = 0
        self._identified = False
        self._rate_window: tuple[float, int] = (time.monotonic(), 0)
        self.measured_rate_hz = 0.0
        self.port: DeviceLink[I2cPort] = DeviceLink(
            self, device=lambda: device_setting(self.config, self.name), raw_type=t.RawI2c,
            on_open=self._on_open)
        self._calibrated_said = False   # the ``calibrated`` detail as last published on a change
        self._reopen = False            # a device or address setting changed over the bus
        self._paced = False             # the bus paces the data reads (a replay's, paced=true): no timer

    # -- for subclasses -------------------------------------------------------------------
    def check_config(self) -> None:
        """Check the chip-specific config; raise ConfigError naming the field and the fix."""

    def init_chip(self, port: RetryingI2c, *, first: bool) -> None:
        """Identify and configure the chip (raise ChipIdentityError when *first*, else PortUnavailable)."""
        raise NotImplementedError

    def read_sample(self, port: RetryingI2c) -> t.StateInformation | None:
        """One sample as a State Information (body rates/accelerations in FRD), or None to skip."""
        raise NotImplementedError

    def chip_health(self) -> dict[str, Any]:
        """Chip-specific health details."""
        return {}

    def healthy(self) -> bool:
        """False while the chip's data is usable but not trustworthy yet (e.g. uncalibrated)."""
        return True

    # -- the device ------------------------------------------------------------------------
    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        """The one chip this service reads (``device``, else the service's name)."""
        return (device_setting(config, service),)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """Nothing: a chip mock needs only its address (its variant is the mock kind or its options)."""
        return {}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """The chip family and the variant the ``chip`` setting names (the MPU's; a BNO055 overrides it)."""
        return {"chip": "mpu", "variant": str(config.get("chip", "auto"))}

    def _check_device(self) -> None:
        problem = self.port.check()
        if problem:
            raise ConfigError(f"{self.name}: {problem}")

    # -- setup and loop -------------------------------------------------------------------
    def setup(self) -> None:
        """Check the config (a bad one stops the service with the reason) and prepare the port."""
        self._check_device()
        self.check_config()
        self.port.start()
        self._note_address()
        self.status = "degraded"  # until the chip is open and sampling

    def _note_address(self) -> None:
        address = self.port.address
        assert address is not None
        self.i2c_address = address.chip_address
        self._paced = address.mock and address.i2c_paced
        bus = address.i2c_bus
        self.where = f"0x{self.i2c_address:02x} on {bus if isinstance(bus, str) else f'/dev/i2c-{bus}'}"

    def on_config_change(self, name: str, value: Any) -> None:
        """A change of the device reopens the chip at its address at the next sample
        (DeviceLink.refresh: the old port is closed first); ``record_raw`` starts the tap at once."""
        if name in PORT_FIELDS:
            self._reopen = True
        if name == "record_raw" and value:
            self.port.record_changed()

    def _on_open(self, port: I2cPort) -> None:
        self.init_chip(RetryingI2c(port, self.with_retries), first=not self._identified)
        if self._identified:
            self.reinits += 1
        self._identified = True
        self._failures_in_row = 0

    def with_retries(self, fn: Callable[[], T]) -> T:
        """Run *fn*, retrying it ``retries`` times after PortIOError (each failure counted)."""
        tries_left = int(self.config["retries"]) + 1
        while True:
            try:
                return fn()
            except PortIOError:
                self.i2c_errors += 1
                tries_left -= 1
                if tries_left <= 0:
                    raise

    def run(self) -> None:
        """Sample at ``rate_hz`` on a fixed schedule until stopped; back to back on a paced bus (a replay's:
        it holds each data read until the recording's sample exists, docs/replay.md)."""
        next_at = time.monotonic()
        while self.wait(max(0.0, next_at - time.monotonic())):
            period = 0.0 if self._paced else 1.0 / float(self.config["rate_hz"])
            now = time.monotonic()
            next_at += period
            if next_at < now - period:  # fell behind (a stall, a slow reopen): start the schedule afresh
                next_at = now + period
            self.sample_once()

    def sample_once(self) -> None:
        """Read, convert and publish one sample; every port fault is counted and survived."""
        if self._reopen:
            self._reopen = False
            if self.port.refresh():
                self._note_address()
        try:
            port = self.port.get()
        except PortUnavailable:
            self.status = "degraded"
            return
        except ChipIdentityError as exc:
            self.error(str(exc))
            raise
        tries_before = self.i2c_errors
        try:
            msg = self.read_sample(RetryingI2c(port, self.with_retries))
        except PortIOError as exc:
            self.missed_samples += 1
            self._failures_in_row += 1
            if self._failures_in_row >= int(self.config["reinit_after_errors"]):
                self.port.lost(exc, port=port)
            self.status = "degraded"
            return
        except (PortClosed, PortTimeout) as exc:
            self.port.lost(exc, port=port)
            self.status = "degraded"
            return
        self._failures_in_row = 0
        if self.i2c_errors != tries_before:
            self.retried_samples += 1
        if msg is None:
            return
        msg.reference_frame = "FRD"
        self.publish_state(msg)
        self.samples += 1
        calibrated = self.healthy()
        self.status = "ok" if calibrated else "degraded"
        if calibrated != self._calibrated_said:
            # The pre-arm IMU check reads ``calibrated`` from health: say a change now, not at the next interval.
            self._calibrated_said = calibrated
            self.publish_health()

    def new_state(self) -> t.StateInformation:
        """An empty State Information stamped with the time of the sample."""
        msg = t.StateInformation()
        msg.header.timestamp_us = time.time_ns() // 1000
        return msg

    def health_details(self) -> dict[str, Any]:
        """Port state, fault counters, measured rate and the chip's own details."""
        start, count = self._rate_window
        now = time.monotonic()
        if now - start >= 0.5:
            self.measured_rate_hz = (self.samples - count) / (now - start)
            self._rate_window = (now, self.samples)
        link = self.port
        last = link.last_error
        return {
            **link.health(),
            "where": getattr(self, "where", ""),
            "port_error": str(last) if isinstance(last, PortError) else "",
            "reinits": self.reinits,
            "samples": self.samples, "rate_hz": f"{self.measured_rate_hz:.1f}", "i2c_errors": self.i2c_errors,
            "retried_samples": self.retried_samples, "missed_samples": self.missed_samples,
            "calibrated": self.healthy(),
            **self.chip_health(),
        }

    def kill(self) -> None:
        """Close the port, then stop."""
        self.port.close()
        super().kill()


def set_vector(msg: t.StateInformation, names: Sequence[str], values: Sequence[float], sigma: float) -> None:
    """Set three fields and their sigmas (``<name>_sigma``)."""
    msg.set(**{n: v for n, v in zip(names, values)}, **{f"{n}_sigma": sigma for n in names})


RATE_FIELDS = ("phi_dot", "theta_dot", "psi_dot")
ACCEL_FIELDS = ("x_ddot", "y_ddot", "z_ddot")
