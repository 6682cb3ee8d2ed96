"""The calibration's parts on their own: the correction and its checks, the tilt-compensated heading,
the AK8963 reads (ASA, DRDY, HOFL) against the mock chip, and the CLI's progress line."""

from __future__ import annotations

import io
import math
import random
from pathlib import Path

import pytest

from u2sa_hw.drivers.imu.ak8963 import Ak8963, to_chip_axes
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Ak8963Chip, Mpu9250Chip, OrientedVehicle, ned_to_body
from u2sa_hw.calibration.correction import IDENTITY9, ZERO3, Correction, tilt_compensated_heading
from u2sa_hw.cli.calibrate_cmd import AccelCollector, MagCollector, Progress
from u2sa_hw.ports.address import DeviceAddress, parse_address
from u2sa_hw.ports.i2c.port import open_i2c
from u2sa_hw.protocols import mpu9250 as mpu

EARTH_UT = (20.0, 0.0, 45.0)


def test_correction_defaults_are_uncalibrated_and_bad_matrices_are_refused() -> None:
    assert not Correction.from_config(ZERO3, IDENTITY9, what="mag").calibrated
    c = Correction.from_config([1.0, 2.0, 3.0], [2.0, 0, 0, 0, 1.0, 0, 0, 0, 0.5], what="mag")
    assert c.calibrated and c.apply((2.0, 4.0, 7.0)) == (2.0, 2.0, 2.0)
    for offset, matrix, why in (([0.0, 0.0], IDENTITY9, "3 numbers"), (ZERO3, [1.0] * 8, "got 3 and 8"),
                                ([math.nan, 0, 0], IDENTITY9, "finite"),
                                (ZERO3, [1.0, 0, 0, 0, 1.0, 0, 0, 0, 0.0], "determinant"),       # singular
                                (ZERO3, [1.0, 0, 0, 0, 1.0, 0, 0, 0, -1.0], "determinant")):     # a mirror
        with pytest.raises(ValueError, match=why):
            Correction.from_config(offset, matrix, what="mag_offset/mag_matrix")


def test_tilt_compensated_heading_is_the_yaw_at_any_roll_and_pitch() -> None:
    rng = random.Random(1)
    for _ in range(200):
        roll, pitch, yaw = rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), rng.uniform(-math.pi, math.pi)
        force = ned_to_body((0.0, 0.0, -9.80665), roll, pitch, yaw)
        mag = ned_to_body(EARTH_UT, roll, pitch, yaw)
        assert math.remainder(tilt_compensated_heading(force, mag) - yaw, math.tau) == pytest.approx(0.0, abs=1e-9)
    assert tilt_compensated_heading((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)) is None
    assert tilt_compensated_heading((0.0, 0.0, -9.8), (math.inf, 0.0, 0.0)) is None


def _mag_rig(tmp_path: Path, **chip: object) -> tuple[MockI2cBus, Ak8963Chip, Ak8963]:
    bus = MockI2cBus(socket_path=str(tmp_path / "bus.sock"))
    imu = bus.add(Mpu9250Chip(vehicle=OrientedVehicle(yaw=0.7, roll=0.2)))
    ak = bus.add(Ak8963Chip(parent=imu, noise_ut=0.0, **chip))  # type: ignore[arg-type]
    return bus, ak, Ak8963(retries=lambda: 1)


def _mpu_address(bus: MockI2cBus) -> DeviceAddress:
    """The MPU device's address on *bus*; the magnetometer opens beside it."""
    return parse_address(f"mock+i2c://{bus.socket_path}/0x68", device="imu")


class _Direct:
    """The MPU's port as the driver's RetryingI2c looks to the magnetometer (write_byte only)."""

    def __init__(self, port: object) -> None:
        self.port = port

    def write_byte(self, register: int, value: int) -> None:
        self.port.write_byte(register, value)  # type: ignore[attr-defined]


def test_ak8963_set_up_applies_asa_and_gives_the_field_in_chip_axes(tmp_path: Path) -> None:
    bus, ak, mag = _mag_rig(tmp_path, asa=(176, 100, 140))
    with bus:
        mpu_port = open_i2c(device="imu", bus=bus.address, address=0x68)
        assert mag.setup(_Direct(mpu_port), device="imu", mpu_address=_mpu_address(bus)), mag.state
        assert mag.asa == (176, 100, 140) and mag.state == "continuous 100 Hz, 16-bit"
        field = mag.read()
        assert field is not None
        body = ned_to_body(EARTH_UT, 0.2, 0.0, 0.7)
        expected_chip = (body[0], -body[1], -body[2])
        assert to_chip_axes(field) == pytest.approx(expected_chip, abs=0.15)   # one 16-bit count after ASA
        assert ak.mode == mpu.AK8963_MODE_CONTINUOUS_2 and ak.peek(mpu.AK8963_CNTL1) & mpu.AK8963_CNTL1_BIT_16
        mpu_port.close()
        mag.close()


def test_ak8963_overflow_drops_the_sample_and_counts_it(tmp_path: Path) -> None:
    bus, _, mag = _mag_rig(tmp_path, hard_iron_ut=(6000.0, 0.0, 0.0))   # a magnet on the board
    with bus:
        mpu_port = open_i2c(device="imu", bus=bus.address, address=0x68)
        assert mag.setup(_Direct(mpu_port), device="imu", mpu_address=_mpu_address(bus))
        assert mag.read() is None and mag.read() is None
        assert mag.overflows == 2 and mag.samples == 0
        mpu_port.close()
        mag.close()


def test_ak8963_absent_is_reported_not_raised(tmp_path: Path) -> None:
    bus = MockI2cBus(socket_path=str(tmp_path / "bus.sock"))
    bus.add(Mpu9250Chip(variant="mpu9250"))
    mag = Ak8963(retries=lambda: 1)
    with bus:
        mpu_port = open_i2c(device="imu", bus=bus.address, address=0x68)
        assert not mag.setup(_Direct(mpu_port), device="imu", mpu_address=_mpu_address(bus))
        assert mag.state.startswith("not answering") and mag.read() is None
        mpu_port.close()


def test_progress_is_plain_lines_on_a_change_when_not_a_terminal() -> None:
    out = io.StringIO()
    progress = Progress(out)
    for text in ("a", "a", "b", "b", "c"):
        progress.show(text)
    progress.done()
    assert out.getvalue() == "a\nb\nc\n"


def test_the_collectors_show_coverage_and_poses() -> None:
    from u2sa_hw import lcmtypes as t

    mags, poses = MagCollector(), AccelCollector()
    assert mags.status().endswith("0%  samples 0") and "(0/6" in poses.status()
    rng = random.Random(2)
    for _ in range(400):
        msg = t.StateInformation()
        v = [rng.gauss(0, 1) for _ in range(3)]
        n = math.sqrt(sum(x * x for x in v))
        msg.set(x=50 * v[0] / n + 30, y=50 * v[1] / n - 10, z=50 * v[2] / n + 5)   # a sphere off the origin
        mags.add(msg)
    assert mags.coverage() == 1.0 and mags.finished()
    level = t.StateInformation()
    level.set(x_ddot=0.0, y_ddot=0.0, z_ddot=-9.80665)
    for _ in range(60):
        poses.add(level)
    assert "[-z]" in poses.status() and "(1/6" in poses.status() and not poses.finished()


def test_the_compass_fit_is_shown_in_the_unit_of_its_source() -> None:
    """An OS5000's raw field (its service has raw_field) is in mG, the MPU-9250's AK8963 in uT."""
    import argparse

    from u2sa_hw import lcmtypes as t
    from u2sa_hw.cli.calibrate_cmd import FITS, mag_unit

    os5000 = {"format": '"os5000"', "raw_field": "true", "mag_offset": "[0.0, 0.0, 0.0]"}
    mpu9250 = {"mag_offset": "[0.0, 0.0, 0.0]", "accel_offset": "[0.0, 0.0, 0.0]"}
    assert (mag_unit(os5000), mag_unit(mpu9250)) == ("mG", "uT")
    make_collector, fit = FITS["compass"]
    for config, radius, unit, earth in ((os5000, 480.0, "mG", "250..650"), (mpu9250, 48.0, "uT", "25..65")):
        mags = make_collector()
        rng = random.Random(3)
        for _ in range(400):
            v = [rng.gauss(0, 1) for _ in range(3)]
            n = math.sqrt(sum(x * x for x in v))
            msg = t.StateInformation()
            msg.set(x=radius * v[0] / n + radius / 2, y=radius * v[1] / n, z=radius * v[2] / n)
            mags.add(msg)
        _values, problems, lines = fit(mags, argparse.Namespace(min_coverage=0.9), config)
        assert problems == []
        assert lines[0].endswith(f" {unit}") and f"{radius:.1f} {unit} (Earth: {earth})" in lines[4], lines
