"""``u2sa calibrate compass|imu`` end to end: the real MPU-9250 driver process against the mock
MPU-9250 + AK8963 with known iron and accelerometer errors, turned through orientations by
the test (OrientedVehicle), the real CLI over the real bus; the saved calibration is checked
against the mock's truth and the published heading afterwards."""

from __future__ import annotations

import math
import random
import signal
import shutil
import subprocess
import tempfile
import threading
import tomllib
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
from conftest import U2SA, ServiceProcesses, wait_until
from serial_driver_harness import DriverProbe, start_driver, write_profile

from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Ak8963Chip, Mpu9250Chip, OrientedVehicle

G = 9.80665
# the mock's truth, in the chips' own axes
HARD_IRON_UT = (30.0, -20.0, 10.0)                       # AK8963 axes
SOFT_IRON = ((1.10, 0.05, 0.0), (0.05, 0.90, 0.03), (0.0, 0.03, 1.0))   # symmetric: what a fit can undo
ACCEL_OFFSET_G = (0.03, -0.02, 0.05)                     # MPU chip axes
ACCEL_MATRIX = ((1.02, 0.01, 0.0), (0.01, 0.98, 0.0), (0.0, 0.0, 1.01))
# AK8963 axes -> MPU chip axes (x<->y, -z), chip -> body FRD with mounting "x,-y,-z"
MAG_TO_CHIP = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], dtype=float)
CHIP_TO_BODY = np.diag([1.0, -1.0, -1.0])
POSE_ATTITUDES = {"-z": (0.0, 0.0), "+z": (math.pi, 0.0), "+x": (0.0, math.pi / 2), "-x": (0.0, -math.pi / 2),
                  "-y": (math.pi / 2, 0.0), "+y": (-math.pi / 2, 0.0)}   # (roll, pitch)


@pytest.fixture
def rig(tmp_path: Path, services: ServiceProcesses, bus) -> Iterator[tuple[OrientedVehicle, DriverProbe, Path]]:
    """The mock MPU-9250 with its AK8963 on a mock bus, the driver running, its health calibrated."""
    sockets = Path(tempfile.mkdtemp(prefix="cal", dir="/tmp"))
    vehicle = OrientedVehicle()
    i2c = MockI2cBus(socket_path=str(sockets / "bus.sock"))
    mpu = i2c.add(Mpu9250Chip(vehicle=vehicle, seed=5, accel_offset_g=ACCEL_OFFSET_G, accel_matrix=ACCEL_MATRIX))
    i2c.add(Ak8963Chip(parent=mpu, seed=5, hard_iron_ut=HARD_IRON_UT, soft_iron=SOFT_IRON))
    with i2c:
        probe = DriverProbe(bus, "imu")
        profile = write_profile(tmp_path, name="imu", kind="imu_mpu9250", settings={"calibrate_samples": 20},
                                devices={"imu": f"mock+i2c://{i2c.socket_path}/0x68"})
        start_driver(services, profile, "imu")
        probe.wait_health(lambda d, s: s == "ok" and d.get("magnetometer", "").startswith("continuous"),
                          message="the IMU running with its magnetometer", timeout=20)
        yield vehicle, probe, profile
    shutil.rmtree(sockets, ignore_errors=True)


def calibrate(services: ServiceProcesses, profile: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([*U2SA, "calibrate", *args, "--vehicle", str(profile)], cwd=services.workdir,
                            env=services.env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def turn_while(proc: subprocess.Popen, step) -> tuple[str, str]:
    """Call *step()* every 20 ms until *proc* ends; its output."""
    done = threading.Event()

    def run() -> None:
        while not done.wait(0.02):
            step()

    mover = threading.Thread(target=run, daemon=True)
    mover.start()
    try:
        out, err = proc.communicate(timeout=120)
    finally:
        done.set()
        mover.join()
    return out, err


def saved(profile: Path) -> dict:
    """The imu's config file, with the calibration defaults for fields it does not hold."""
    path = profile.parent / "config" / "imu.toml"
    defaults = {"mag_offset": [0.0] * 3, "mag_matrix": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], "accel_offset": [0.0] * 3,
                "calibration_stream_s": 0.0}
    return {**defaults, **(tomllib.loads(path.read_text()) if path.exists() else {})}


def latest(probe: DriverProbe, name: str, n: int = 20) -> float:
    count = probe.state_count()
    states = probe.wait_states(n, since=count)[-n:]
    assert all(m.has(name) for m, _ in states), f"{name} missing"
    return math.atan2(sum(math.sin(getattr(m, name)) for m, _ in states),
                      sum(math.cos(getattr(m, name)) for m, _ in states))


def test_compass_calibration_fits_the_mock_iron_and_the_heading_is_right_afterwards(
        services: ServiceProcesses, rig) -> None:
    vehicle, probe, profile = rig
    vehicle.orient(yaw=1.0)
    msg = probe.wait_states(5, since=probe.state_count())[-1][0]
    assert not msg.has("psi")             # uncalibrated: no heading at all
    health = probe.wait_health(lambda d, s: "mag_calibrated" in d, message="health with the calibration state")
    assert health["mag_calibrated"] == "no" and health["accel_calibrated"] == "no"

    rng = random.Random(3)
    proc = calibrate(services, profile, "compass", "imu", "--timeout", "60")
    out, err = turn_while(proc, lambda: vehicle.orient(roll=rng.uniform(-math.pi, math.pi),
                                                       pitch=math.asin(rng.uniform(-1, 1)),
                                                       yaw=rng.uniform(-math.pi, math.pi)))
    assert proc.returncode == 0, err
    assert "coverage [##########################] 100%" in out and "saved" in out

    cfg = saved(profile)
    offset_truth = CHIP_TO_BODY @ MAG_TO_CHIP @ np.array(HARD_IRON_UT)     # (-20, -30, 10) in body FRD
    assert cfg["mag_offset"] == pytest.approx(list(offset_truth), abs=1.0)
    soft_body = CHIP_TO_BODY @ MAG_TO_CHIP @ np.array(SOFT_IRON) @ MAG_TO_CHIP.T @ CHIP_TO_BODY.T
    undone = np.array(cfg["mag_matrix"]).reshape(3, 3) @ soft_body          # c * identity when the fit is right
    assert undone / np.trace(undone) * 3 == pytest.approx(np.eye(3), abs=0.02)
    assert cfg["calibration_stream_s"] == 0.0     # turned off at the end
    listed = services.cli("param", "list", "imu", "--vehicle", str(profile))
    assert "mag_offset" in listed.stdout and f"{cfg['mag_offset'][0]!r}"[:6] in listed.stdout

    health = probe.wait_health(lambda d, s: d.get("mag_calibrated") == "yes", message="mag calibrated in health")
    assert health["calibration_stream"] == "off"
    vehicle.orient(yaw=1.0)
    wait_until(lambda: probe.states and abs(math.remainder(probe.states[-1][0].psi - 1.0, math.tau)) < 0.1,
               message="the heading to follow yaw 1.0")
    # the accelerometer is not calibrated yet: its 0.03 g offset tilts the levelling by ~1.7 deg, which the
    # field's steep dip (45 of 49 uT vertical) turns into ~4 deg of heading
    assert abs(math.remainder(latest(probe, "psi") - 1.0, math.tau)) < math.radians(6.0)
    body_k = CHIP_TO_BODY @ np.array(ACCEL_MATRIX) @ CHIP_TO_BODY.T
    for name, value in (("accel_matrix", list(np.linalg.inv(body_k).ravel())),
                        ("accel_offset", list(CHIP_TO_BODY @ np.array(ACCEL_OFFSET_G) * G))):
        assert services.cli("param", "set", "imu", name, repr([float(v) for v in value]),
                            "--vehicle", str(profile)).returncode == 0
    for roll, pitch, yaw in ((0.0, 0.0, 1.0), (0.0, 0.0, -2.5), (0.3, -0.2, 2.0), (-0.25, 0.35, -0.7)):
        vehicle.orient(roll=roll, pitch=pitch, yaw=yaw)
        wait_until(lambda: probe.states and abs(math.remainder(probe.states[-1][0].psi - yaw, math.tau)) < 0.05,
                   message=f"the heading to follow yaw {yaw}")
        assert abs(math.remainder(latest(probe, "psi") - yaw, math.tau)) < math.radians(1.0), (roll, pitch, yaw)


def test_a_level_turn_only_is_refused_and_nothing_is_saved(services: ServiceProcesses, rig) -> None:
    vehicle, probe, profile = rig
    yaw = [0.0]

    def turn() -> None:
        yaw[0] += 0.05
        vehicle.orient(yaw=yaw[0])

    proc = calibrate(services, profile, "compass", "imu", "--timeout", "6")
    out, err = turn_while(proc, turn)
    assert proc.returncode == 1, out
    assert "nothing saved" in err and ("coverage" in err or "ellipsoid" in err or "plane" in err), err
    cfg = saved(profile)
    assert cfg["mag_offset"] == [0.0, 0.0, 0.0] and cfg["mag_matrix"] == [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    assert cfg["calibration_stream_s"] == 0.0
    health = probe.wait_health(lambda d, s: d.get("calibration_stream") == "off", message="the stream off")
    assert health["mag_calibrated"] == "no"
    assert not probe.wait_states(5, since=probe.state_count())[-1][0].has("psi")


def test_accelerometer_six_poses_fit_the_mock_errors(services: ServiceProcesses, rig) -> None:
    vehicle, probe, profile = rig
    order = list(POSE_ATTITUDES.values())
    tick = [0]

    def pose() -> None:                  # each pose held 1.6 s (80 ticks of 20 ms), then the next
        roll, pitch = order[(tick[0] // 80) % len(order)]
        tick[0] += 1
        vehicle.orient(roll=roll, pitch=pitch, yaw=0.4)

    proc = calibrate(services, profile, "imu", "imu", "--timeout", "60")
    out, err = turn_while(proc, pose)
    assert proc.returncode == 0, err
    assert "[+x] [-x] [+y] [-y] [+z] [-z]" in out and "saved" in out
    cfg = saved(profile)
    assert cfg["accel_offset"] == pytest.approx(list(CHIP_TO_BODY @ np.array(ACCEL_OFFSET_G) * G), abs=0.01)
    k_body = CHIP_TO_BODY @ np.array(ACCEL_MATRIX) @ CHIP_TO_BODY.T
    assert np.array(cfg["accel_matrix"]).reshape(3, 3) @ k_body == pytest.approx(np.eye(3), abs=0.003)
    health = probe.wait_health(lambda d, s: d.get("accel_calibrated") == "yes", message="accel calibrated in health")
    assert health["mag_calibrated"] == "no"
    # applied live: level and still, the corrected specific force is g straight up (the rest window is raw,
    # so with gravity "rest" the accelerations stay near zero; see x_ddot)
    vehicle.orient(yaw=0.4)
    count = probe.state_count()
    states = probe.wait_states(30, since=count)[-30:]
    assert abs(np.mean([m.x_ddot for m, _ in states])) < 0.05


# ---------------------------------------------------------------- the serial compass (OS5000 raw field) -------
OS5000_HARD_IRON_MG = (120.0, -80.0, 40.0)                # body FRD: the compass's axes
OS5000_SOFT_IRON = ((1.08, -0.04, 0.0), (-0.04, 0.93, 0.02), (0.0, 0.02, 1.0))


def test_os5000_raw_field_calibration_and_the_heading_from_the_corrected_field(
        services: ServiceProcesses, bus, tmp_path: Path) -> None:
    from u2sa_hw.mocks.serial_compass import Os5000CompassDevice

    vehicle = OrientedVehicle()
    dev = Os5000CompassDevice(vehicle, link_path=tmp_path / "dev" / "compass", rate_hz=50.0, seed=2, raw_field=True,
                              heading_sigma_deg=0.0, attitude_sigma_deg=0.0,
                              hard_iron_mg=OS5000_HARD_IRON_MG, soft_iron=OS5000_SOFT_IRON)
    dev.start()
    try:
        profile = write_profile(tmp_path, name="compass", kind="compass_serial",
                                settings={"format": "os5000", "raw_field": True},
                                devices={"compass": f"serial://{dev.address}?baud=19200"})
        probe = DriverProbe(bus, "compass")
        start_driver(services, profile, "compass")
        probe.wait_health(lambda d, s: s == "ok" and d.get("mag_calibrated") == "no", message="the compass running")
        rng = random.Random(8)
        proc = calibrate(services, profile, "compass", "compass", "--timeout", "60")
        out, err = turn_while(proc, lambda: vehicle.orient(roll=rng.uniform(-math.pi, math.pi),
                                                           pitch=math.asin(rng.uniform(-1, 1)),
                                                           yaw=rng.uniform(-math.pi, math.pi)))
        assert proc.returncode == 0, err
        cfg = tomllib.loads((tmp_path / "config" / "compass.toml").read_text())
        assert cfg["mag_offset"] == pytest.approx(list(OS5000_HARD_IRON_MG), abs=4.0)
        undone = np.array(cfg["mag_matrix"]).reshape(3, 3) @ np.array(OS5000_SOFT_IRON)
        assert undone / np.trace(undone) * 3 == pytest.approx(np.eye(3), abs=0.02)
        probe.wait_health(lambda d, s: d.get("mag_calibrated") == "yes" and d.get("source") == "$C field",
                          message="the heading from the corrected field")
        for roll, pitch, yaw in ((0.0, 0.0, 1.0), (0.3, -0.2, -2.0)):
            vehicle.orient(roll=roll, pitch=pitch, yaw=yaw)
            wait_until(lambda: probe.states and abs(math.remainder(probe.states[-1][0].psi - yaw, math.tau)) < 0.03,
                       message=f"the heading to follow yaw {yaw}")
            assert abs(math.remainder(latest(probe, "psi", 10) - yaw, math.tau)) < math.radians(1.0)
    finally:
        dev.stop()


def test_a_compass_without_raw_field_values_is_not_offered_calibration(
        services: ServiceProcesses, bus, tmp_path: Path) -> None:
    from u2sa_hw.mocks.serial_compass import NmeaCompassDevice

    dev = NmeaCompassDevice(OrientedVehicle(), link_path=tmp_path / "dev" / "compass", rate_hz=20.0)
    dev.start()
    try:
        profile = write_profile(tmp_path, name="compass", kind="compass_serial", settings={},
                                devices={"compass": f"serial://{dev.address}?baud=4800"})
        probe = DriverProbe(bus, "compass")
        start_driver(services, profile, "compass")
        probe.wait_health(lambda d, s: s == "ok", message="the compass running")
        result = services.cli("calibrate", "compass", "compass", "--vehicle", str(profile))
        assert result.returncode == 1
        assert "reports no raw field values" in result.stderr and 'format = "os5000"' in result.stderr
        imu = services.cli("calibrate", "imu", "compass", "--vehicle", str(profile))
        assert imu.returncode == 1 and "has no accelerometer calibration" in imu.stderr
    finally:
        dev.stop()


def test_dry_run_shows_the_fit_and_saves_nothing_and_a_singular_matrix_is_refused(
        services: ServiceProcesses, rig) -> None:
    vehicle, probe, profile = rig
    rng = random.Random(4)
    proc = calibrate(services, profile, "compass", "imu", "--timeout", "60", "--dry-run")
    out, err = turn_while(proc, lambda: vehicle.orient(roll=rng.uniform(-math.pi, math.pi),
                                                       pitch=math.asin(rng.uniform(-1, 1)),
                                                       yaw=rng.uniform(-math.pi, math.pi)))
    assert proc.returncode == 0, err
    assert "offset (hard iron)" in out and "dry run: not saved" in out
    assert saved(profile)["mag_offset"] == [0.0, 0.0, 0.0]
    refused = services.cli("param", "set", "imu", "mag_matrix", "[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]",
                           "--vehicle", str(profile))
    assert refused.returncode == 1 and "determinant" in refused.stderr
    assert saved(profile)["mag_matrix"] == [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]


def test_ctrl_c_turns_the_stream_off_and_saves_nothing(services: ServiceProcesses, rig) -> None:
    _vehicle, probe, profile = rig
    proc = calibrate(services, profile, "compass", "imu", "--timeout", "60")
    probe.wait_health(lambda d, s: d.get("calibration_stream") == "on", message="the stream on")
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and "interrupted: nothing saved" in err
    probe.wait_health(lambda d, s: d.get("calibration_stream") == "off", message="the stream off again")
    assert saved(profile)["mag_offset"] == [0.0, 0.0, 0.0] and saved(profile)["calibration_stream_s"] == 0.0
