"""The IMU's at-rest gyro calibration judges rest on the samples and its time on their own stamps
(issue 27, part 3): a stall of the process between samples cannot fail it, moving data never
calibrates however long it lasts, and the bounded fallback (no rest in ``rest_timeout_s`` of samples)
is one line the pilot reads in the pre-arm refusal. Pure logic with stamps passed in, then the
MPU-9250 driver object fed bursts by hand."""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Iterator

import pytest

from u2sa_hw.drivers.imu.common import RestCalibration
from u2sa_hw.drivers.imu.mpu9250 import Mpu9250ImuDriver
from u2sa_hw.profile.vehicle import VehicleProfile
from u2sa_hw.safety.prearm import PrearmChecks
from u2sa_hw.profile.loader import load_profile

from test_prearm import OK, health, write_profile

G = RestCalibration.GRAVITY
BIAS = (0.01, -0.005, 0.002)   # rad/s


def still(rng: random.Random) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    gyro = tuple(b + rng.gauss(0.0, math.radians(0.05)) for b in BIAS)
    return gyro, (rng.gauss(0.0, 0.02), rng.gauss(0.0, 0.02), -G + rng.gauss(0.0, 0.02))  # type: ignore[return-value]


def moving(rng: random.Random) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    gyro = tuple(rng.gauss(0.0, math.radians(5.0)) for _ in range(3))
    return gyro, (rng.gauss(0.0, 1.0), rng.gauss(0.0, 1.0), -G)  # type: ignore[return-value]


def stamps(start: float, count: int, *, hz: float = 100.0) -> Iterator[float]:
    return (start + i / hz for i in range(count))


def calibration(**kwargs: float) -> RestCalibration:
    return RestCalibration(samples=int(kwargs.pop("samples", 200)), max_std_dps=0.5, max_rate_dps=10.0, **kwargs)


def test_a_stall_between_samples_does_not_break_the_rest_window() -> None:
    rng = random.Random(1)
    cal = calibration()
    results = [cal.add(*still(rng), stamp=t) for t in stamps(100.0, 120)]
    # the process stalls 7 s (no samples); the vehicle is still before and after
    results += [cal.add(*still(rng), stamp=t) for t in stamps(108.2, 80)]
    verdicts = [r for r in results if r is not None]
    assert len(verdicts) == 1 and verdicts[0].accepted, verdicts
    assert verdicts[0].gyro_mean == pytest.approx(BIAS, abs=2e-4)
    assert cal.searched_s == pytest.approx(1.19 + 0.79, abs=1e-6), "the stall is not sample time"


def test_moving_data_never_calibrates_and_the_fallback_runs_on_sample_time() -> None:
    rng = random.Random(2)
    cal = calibration(give_up_s=30.0)
    verdicts = [cal.add(*moving(rng), stamp=t) for t in stamps(0.0, 2000)]   # 20 s of samples
    assert not cal.overdue
    # a 120 s stall of the process: no samples, and no sample time either
    verdicts += [cal.add(*moving(rng), stamp=t) for t in stamps(140.0, 500)]  # 25 s of samples in all
    # sample time only: 1999 + 499 intervals of 10 ms, the 120 s gap not among them
    assert not cal.overdue and cal.searched_s == pytest.approx(24.98, abs=1e-6)
    verdicts += [cal.add(*moving(rng), stamp=t) for t in stamps(145.0, 60_000)]   # ten more minutes of moving
    assert cal.overdue
    judged = [v for v in verdicts if v is not None]
    assert judged and not any(v.accepted for v in judged) and cal.last_reason.startswith("moving: gyro std")
    # once still: it calibrates (the fallback keeps looking); a window part moving, part still, does not
    rng2 = random.Random(3)
    after = [r for r in (cal.add(*still(rng2), stamp=t) for t in stamps(800.0, 400)) if r is not None]
    assert [r.accepted for r in after] == [False, True]


def test_bad_stamps_and_readings_never_crash_and_never_calibrate() -> None:
    cal = calibration(samples=3)
    for stamp in (5.0, 4.0, math.nan):   # a clock that went back, then no number
        result = cal.add((math.nan, 0.0, 0.0), (0.0, 0.0, -G), stamp=stamp)
    assert result is not None and not result.accepted and result.reason.startswith("unusable")
    assert cal.searched_s == 0.0


class Burst:
    """Feeds the driver's calibration one sample at a time, as read_sample does, with the stamps given."""

    def __init__(self, tmp_path: Path, **settings: float) -> None:
        profile = VehicleProfile(path=None, devices={"imu": {"address": "mock+i2c:///tmp/none.sock/0x68"}})
        self.driver = Mpu9250ImuDriver("imu", profile=profile, settings={"calibrate_samples": 100, "rate_hz": 50.0,
                                                                         **settings})
        self.driver.setup()   # the rest window from the settings; the chip is opened by the loop, never here

    def feed(self, sample_fn, rng: random.Random, times: Iterator[float]) -> None:
        for t in times:
            gyro, force = sample_fn(rng)
            self.driver._calibrate(gyro, force, stamp=t)


def test_the_driver_says_the_fallback_in_one_line_and_pre_arm_shows_it(tmp_path: Path, lcm_url: str) -> None:
    rig = Burst(tmp_path, rest_timeout_s=10.0)
    rng = random.Random(4)
    rig.feed(moving, rng, stamps(0.0, 400, hz=50.0))   # 8 s of samples
    assert rig.driver.calibration_state.startswith("waiting for rest (moving")
    rig.feed(moving, rng, stamps(60.0, 200, hz=50.0))  # after a stall: 12 s of samples in all
    state = rig.driver.calibration_state
    assert state.startswith("no rest found in 10 s of samples (moving: gyro std ")
    assert state.endswith("; it calibrates on the first 2.0 s at rest, never on moving data")
    assert not rig.driver.calibrated

    checks = PrearmChecks.from_profile(load_profile(write_profile(tmp_path, services={
        "imu": {"kind": "imu_mpu9250"}, "rc": {"kind": "rc_mux"}})))
    checks.on_health(health("imu", "degraded", calibrated="False", calibration=state), 0.0)
    reasons = [f.reason for f in checks.evaluate(0.1, **OK)]
    assert reasons == [f"imu: not calibrated ({state}; keep the vehicle still, then it passes)"]
    assert "\n" not in reasons[0]

    rig.feed(still, random.Random(5), stamps(80.0, 100, hz=50.0))
    assert rig.driver.calibrated and rig.driver.calibration_state == "calibrated"
    rig.driver.kill()
