"""The I2C IMU drivers as real ``u2sa service`` processes against the mock I2C bus.

The bus and its chip models run in the test process (or, for the kill test, in their own
process) and sample one SimVehicle; the driver publishes over real LCM multicast and the
probe compares what it says with the vehicle's truth.
"""

from __future__ import annotations

import math
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Iterator

import pytest
from conftest import REPO, ServiceProcesses, wait_until
from serial_driver_harness import SIM_ORIGIN, DriverProbe, start_driver, write_profile

from u2sa_hw.mocks.bno055_chip import Bno055Chip
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Mpu9250Chip
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.lcmtypes import RawI2c
from u2sa_hw.ports.i2c.wire import OP_WRITE
from u2sa_hw.ports.tap import raw_channel
from u2sa_hw.protocols import bno055 as bno
from u2sa_hw.protocols import mpu9250 as mpu

RATE_FIELDS = ("phi_dot", "theta_dot", "psi_dot")
ACCEL_FIELDS = ("x_ddot", "y_ddot", "z_ddot")


@pytest.fixture
def socket_dir() -> Iterator[Path]:
    """A short directory for Unix sockets (tmp_path can exceed the 108-byte limit)."""
    path = Path(tempfile.mkdtemp(prefix="imu", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def sim() -> Iterator[SimVehicle]:
    """A differential rover at rest, stepping in real time."""
    vehicle = SimVehicle(**SIM_ORIGIN, model="differential", start_yaw=2.5)
    vehicle.start(rate_hz=200)
    yield vehicle
    vehicle.stop()


def on(i2c: MockI2cBus, device: str, chip: int = mpu.I2C_ADDRESS) -> dict[str, str]:
    """The profile's device table: *device* is the chip at *chip* on the mock bus *i2c*."""
    return {device: f"mock+i2c://{i2c.socket_path}/0x{chip:02x}"}


def mean_of(states: list, name: str) -> float:
    return statistics.fmean(m.get(name) for m, _ in states)


def test_mpu9250_calibrates_at_rest_then_rates_and_accelerations_follow_the_vehicle(
        tmp_path: Path, services: ServiceProcesses, bus, sim: SimVehicle, socket_dir: Path) -> None:
    sim.set_wheel_speed("left", 0.5)
    sim.set_wheel_speed("right", -0.5)  # turning in place at 2 rad/s: not at rest
    i2c = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    chip = i2c.add(Mpu9250Chip(vehicle=sim, seed=11, gyro_bias_dps=(0.8, -0.5, 0.3)))
    with i2c:
        probe = DriverProbe(bus, "imu")
        profile = write_profile(tmp_path, name="imu", kind="imu_mpu9250",
                                settings={"calibrate_samples": 40, "gyro_range_dps": 500}, devices=on(i2c, "imu"))
        start_driver(services, profile, "imu")
        waiting = probe.wait_health(lambda d, s: d.get("calibration", "").startswith("waiting for rest"),
                                    message="the calibration to refuse a turning vehicle")
        assert waiting["status"] == "degraded" and "turning" in waiting["calibration"]
        assert waiting["calibrated"] == "False"
        uncalibrated = probe.wait_states(1)[-1][0]
        assert uncalibrated.psi_dot_sigma == pytest.approx(0.1)

        sim.set_wheel_speed("left", 0.0)
        sim.set_wheel_speed("right", 0.0)
        health = probe.wait_health(lambda d, s: d.get("calibration") == "calibrated", message="gyro calibration")
        assert health["calibrated"] == "True"
        # the mock's chip-axes bias (0.8, -0.5, 0.3) deg/s is (0.8, 0.5, -0.3) in FRD
        bias = [float(v) for v in health["gyro_bias_dps"].split(",")]
        assert bias == pytest.approx([0.8, 0.5, -0.3], abs=0.05)
        assert chip.peek(mpu.GYRO_CONFIG) == mpu.fs_config(1) and chip.peek(mpu.CONFIG) == 3
        assert float(health["temperature_c"]) == pytest.approx(25.0, abs=0.5)
        at_rest = probe.wait_states(50, since=probe.state_count())[-50:]
        for name in RATE_FIELDS:  # without calibration each would be off by 0.3..0.8 deg/s (5..14 mrad/s)
            assert abs(mean_of(at_rest, name)) < 0.002, name
        for name in ACCEL_FIELDS:
            assert abs(mean_of(at_rest, name)) < 0.05, name
        msg = at_rest[-1][0]
        assert msg.reference_frame == "FRD" and msg.sensor_name == "imu"
        assert msg.psi_dot_sigma == pytest.approx(0.005) and msg.x_ddot_sigma == pytest.approx(0.3)
        assert not msg.has("psi") and not msg.has("x")

        sim.set_wheel_speed("left", 1.0)
        sim.set_wheel_speed("right", 0.5)  # forward 0.75 m/s turning right at 1 rad/s: 0.75 m/s^2 to the right
        wait_until(lambda: probe.states[-1][0].psi_dot > 0.9, message="the turn to show")
        truth = sim.snapshot()
        turning = probe.wait_states(50, since=probe.state_count())[-50:]
        assert mean_of(turning, "psi_dot") == pytest.approx(truth.yaw_rate, abs=0.005)
        assert mean_of(turning, "y_ddot") == pytest.approx(truth.accel_y, abs=0.05)
        assert abs(mean_of(turning, "phi_dot")) < 0.003 and abs(mean_of(turning, "x_ddot")) < 0.05


def test_mpu9250_says_it_is_calibrated_in_health_at_once(tmp_path: Path, services: ServiceProcesses, bus,
                                                         sim: SimVehicle, socket_dir: Path) -> None:
    """With a 60 s health interval only the start and the calibration hook publish health (pre-arm reads it)."""
    i2c = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    i2c.add(Mpu9250Chip(vehicle=sim, seed=4))
    with i2c:
        probe = DriverProbe(bus, "imu")
        profile = write_profile(tmp_path, name="imu", kind="imu_mpu9250",
                                settings={"calibrate_samples": 40, "health_interval_s": 60.0}, devices=on(i2c, "imu"))
        start_driver(services, profile, "imu")

        def said() -> list[str]:
            return [{kv.key: kv.value for kv in h.details}.get("calibrated", "") for h in list(probe.health)]

        wait_until(lambda: "True" in said(), timeout=20, message="calibrated = True published on the change")
        assert said()[0] == "False"                  # the health at start: not calibrated yet


@pytest.mark.parametrize(("variant", "part", "gyro_dps", "accel_g", "dlpf", "rate_hz"), [
    ("mpu6050", "MPU-6050", 250, 2, 1, 100.0),
    ("mpu6500", "MPU-6500", 1000, 8, 5, 50.0),
    ("mpu9250", "MPU-9250", 2000, 16, 0, 100.0),
])
def test_every_variant_and_full_scale_is_configured_and_scaled_through_the_driver(
        tmp_path: Path, services: ServiceProcesses, bus, sim: SimVehicle, socket_dir: Path, variant: str, part: str,
        gyro_dps: int, accel_g: int, dlpf: int, rate_hz: float) -> None:
    i2c = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    chip = i2c.add(Mpu9250Chip(variant=variant, vehicle=sim, seed=5))
    with i2c:
        probe = DriverProbe(bus, "imu")
        profile = write_profile(tmp_path, name="imu", kind="imu_mpu9250", settings={
            "chip": variant, "gyro_range_dps": gyro_dps, "accel_range_g": accel_g,
            "dlpf_cfg": dlpf, "rate_hz": rate_hz, "calibrate_samples": 20}, devices=on(i2c, "imu"))
        start_driver(services, profile, "imu")
        health = probe.wait_health(lambda d, s: d.get("calibration") == "calibrated", message="calibrated")
        assert (health["chip"], health["who_am_i"]) == (part, f"0x{mpu.VARIANTS[variant].who_am_i:02x}")
        assert (health["gyro_range_dps"], health["accel_range_g"]) == (str(gyro_dps), str(accel_g))
        # the configuration registers as the driver wrote them
        assert chip.peek(mpu.GYRO_CONFIG) == mpu.fs_config(mpu.GYRO_RANGE_DPS.index(gyro_dps))
        assert chip.peek(mpu.ACCEL_CONFIG) == mpu.fs_config(mpu.ACCEL_RANGE_G.index(accel_g))
        assert chip.dlpf_cfg == dlpf
        internal_hz = 1000.0 if 1 <= dlpf <= 6 else 8000.0
        assert chip.peek(mpu.SMPLRT_DIV) == round(internal_hz / rate_hz) - 1
        # the accelerometer's own DLPF register exists on the MPU-6500/9250 only
        assert chip.peek(mpu.ACCEL_CONFIG2) == (0 if variant == "mpu6050" else dlpf)
        assert not chip.asleep   # the MPU-6050 powers up asleep: woken by the driver
        # the variant's own temperature formula (MPU-6050: /340 + 36.53; 6500/9250: /333.87 + 21)
        assert float(health["temperature_c"]) == pytest.approx(25.0, abs=0.5)

        sim.set_wheel_speed("left", 1.0)
        sim.set_wheel_speed("right", 0.5)  # 0.75 m/s turning right at 1 rad/s: 0.75 m/s^2 to the right
        wait_until(lambda: probe.states[-1][0].psi_dot > 0.9, message="the turn to show")
        truth = sim.snapshot()
        turning = probe.wait_states(40, since=probe.state_count())[-40:]
        # scaled with the configured full scale: a wrong FS (a factor 2 or more) misses by far
        assert mean_of(turning, "psi_dot") == pytest.approx(truth.yaw_rate, abs=0.01)
        assert mean_of(turning, "y_ddot") == pytest.approx(truth.accel_y, abs=0.06)
        assert abs(mean_of(turning, "z_ddot")) < 0.06 and abs(mean_of(turning, "phi_dot")) < 0.005


@pytest.mark.parametrize(("kind", "chip_spec", "chip", "settings", "expected"), [
    ("imu_mpu9250", "mpu6500@0x68", 0x68, {"chip": "mpu9250"},
     ["WHO_AM_I 0x70 (MPU-6500)", 'chip = "mpu9250" expects 0x71', "0x68 on mock:", 'set chip = "mpu6500"']),
    ("imu_mpu9250", "bno055@0x28", 0x28, {},
     ["WHO_AM_I 0x00, not an MPU-6050/6500/9250", "0x28 on mock:"]),
    ("imu_bno055", "mpu9250@0x68", 0x68, {}, ["CHIP_ID 0x00, not a BNO055 (0xA0)", "0x68 on mock:"]),
])
def test_wrong_chip_identity_stops_the_service_with_a_clear_error(
        tmp_path: Path, services: ServiceProcesses, socket_dir: Path, kind: str, chip_spec: str, chip: int,
        settings: dict, expected: list[str]) -> None:
    from u2sa_hw.mocks.i2c_bus import build_chip

    i2c = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    i2c.add(build_chip(chip_spec, seed=1))
    with i2c:
        profile = write_profile(tmp_path, name="imu", kind=kind, settings=settings, devices=on(i2c, "imu", chip))
        proc = start_driver(services, profile, "imu")
        assert proc.wait(timeout=20) != 0
    log = (tmp_path / "imu.stderr").read_text()
    for text in expected:
        assert text in log


def test_mpu9250_counts_and_survives_eio_and_nack(tmp_path: Path, services: ServiceProcesses, bus,
                                                   socket_dir: Path) -> None:
    i2c = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    chip = i2c.add(Mpu9250Chip(seed=3))
    with i2c:
        probe = DriverProbe(bus, "imu")
        raw_records: list[RawI2c] = []
        bus.transport.subscribe(raw_channel("imu"), RawI2c, lambda _c, m: raw_records.append(m))
        profile = write_profile(tmp_path, name="imu", kind="imu_mpu9250",
                                settings={"calibrate_samples": 20, "record_raw": True}, devices=on(i2c, "imu"))
        start_driver(services, profile, "imu")
        probe.wait_health(lambda d, s: s == "ok", message="a calibrated, running IMU")

        chip.eio_every(4)  # every 4th transaction fails: retried at once, no sample lost
        health = probe.wait_health(lambda d, s: int(d["i2c_errors"]) >= 10, message="EIO faults counted")
        assert health["port"] == "open" and health["status"] == "ok" and int(health["retried_samples"]) >= 10
        chip.eio_every(0)
        count = probe.state_count()
        probe.wait_states(20, since=count)
        raw = list(raw_records)  # every transaction on RAW.imu, failed ones included
        assert raw and all(r.device == "imu" and r.address in (0x68, mpu.AK8963_ADDRESS) for r in raw)
        # this bus has no AK8963: the magnetometer's set-up tries are there too, each NACKed
        assert all(not r.ok for r in raw if r.address == mpu.AK8963_ADDRESS)
        raw = [r for r in raw if r.address == 0x68]
        bursts = [r for r in raw if r.register_address == mpu.BURST_START and r.op == 0]
        assert any(not r.ok for r in bursts) and any(r.ok and r.length == 14 for r in bursts)

        chip.nack(True)  # the chip stops answering: samples missed, then the chip is reopened with backoff
        down = probe.wait_health(lambda d, s: d["port"] == "down", message="the port to be marked down")
        assert down["status"] == "degraded" and "no ACK from 0x68" in down["port_error"]
        assert int(down["missed_samples"]) >= 10
        chip.reset()  # as if it had lost power: asleep, unconfigured
        chip.nack(False)
        back = probe.wait_health(lambda d, s: d["port"] == "open" and int(d["reinits"]) >= 1,
                                 message="the chip reopened and set up again")
        assert int(back["port_losses"]) >= 1
        assert chip.peek(mpu.GYRO_CONFIG) == mpu.fs_config(1) and not chip.asleep
        count = probe.state_count()
        after = probe.wait_states(30, since=count)[-30:]
        assert abs(mean_of(after, "psi_dot")) < 0.002  # the bias calibration survived the reopen


def test_mpu9250_recovers_when_the_bus_server_is_killed_and_restarted(
        tmp_path: Path, services: ServiceProcesses, bus, socket_dir: Path) -> None:
    sock = socket_dir / "bus.sock"

    def serve() -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.mocks.i2c_bus", "--socket", str(sock),
                                 "--chip", "mpu9250@0x68"], cwd=REPO, stdout=subprocess.PIPE, text=True)
        assert "serving" in proc.stdout.readline()
        return proc

    server = serve()
    try:
        probe = DriverProbe(bus, "imu")
        profile = write_profile(tmp_path, name="imu", kind="imu_mpu9250", settings={"calibrate_samples": 20},
                                devices={"imu": f"mock+i2c://{sock}/0x68"})
        start_driver(services, profile, "imu")
        probe.wait_health(lambda d, s: s == "ok", message="a running IMU")
        server.kill()
        server.wait()
        down = probe.wait_health(lambda d, s: d["port"] == "down", message="the lost bus in health")
        assert down["status"] == "degraded" and "mock:" in down["port_error"]
        count = probe.state_count()
        server = serve()
        back = probe.wait_health(lambda d, s: d["port"] == "open" and s == "ok", message="the driver back")
        assert int(back["port_losses"]) >= 1 and int(back["reinits"]) >= 1
        probe.wait_states(20, since=count)
    finally:
        server.kill()
        server.wait()


def test_bno055_attitude_rates_linear_acceleration_and_calibration(
        tmp_path: Path, services: ServiceProcesses, bus, sim: SimVehicle, socket_dir: Path) -> None:
    i2c = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    chip = i2c.add(Bno055Chip(vehicle=sim, seed=5, calibrated_after_s=1.0))
    with i2c:
        probe = DriverProbe(bus, "ahrs")
        profile = write_profile(tmp_path, name="ahrs", kind="imu_bno055", settings={},
                                devices=on(i2c, "ahrs", bno.I2C_ADDRESS))
        start_driver(services, profile, "ahrs")
        first = probe.wait_states(1)[0][0]
        assert not first.has("psi") and first.has("phi") and first.has("theta")  # SYS calibration 0: no heading
        assert chip.mode == bno.MODE_NDOF and chip.peek(bno.UNIT_SEL) == bno.UNIT_GYR_RPS | bno.UNIT_EUL_RAD
        health = probe.wait_health(lambda d, s: d.get("calib_sys") == "3", message="the fusion calibrated")
        assert health["sys_status"] == "fusion running" and health["heading"] == "published"
        assert health["calibration"] == "sys 3 gyr 3 acc 3 mag 3" and health["calibrated"] == "True"
        wait_until(lambda: probe.states[-1][0].has("psi"), message="heading published")
        level = probe.wait_states(20, since=probe.state_count())[-20:]
        assert mean_of(level, "psi") == pytest.approx(2.5, abs=0.01)
        assert abs(mean_of(level, "phi")) < 0.01 and abs(mean_of(level, "theta")) < 0.01
        msg = level[-1][0]
        assert msg.reference_frame == "FRD" and msg.psi_sigma == pytest.approx(0.05)

        sim.set_wheel_speed("left", 1.0)
        sim.set_wheel_speed("right", 0.5)
        wait_until(lambda: probe.states[-1][0].psi_dot > 0.9, message="the turn to show")
        truth = sim.snapshot()
        turning = probe.wait_states(30, since=probe.state_count())[-30:]
        assert mean_of(turning, "psi_dot") == pytest.approx(truth.yaw_rate, abs=0.01)
        assert mean_of(turning, "y_ddot") == pytest.approx(truth.accel_y, abs=0.05)
        assert abs(mean_of(turning, "z_ddot")) < 0.05  # the chip removed gravity
        psi = [m.psi for m, _ in turning]
        assert all(-math.pi <= p < math.pi for p in psi)


def test_bno055_is_set_up_again_after_it_resets_itself(tmp_path: Path, services: ServiceProcesses, bus,
                                                       socket_dir: Path) -> None:
    i2c = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    chip = i2c.add(Bno055Chip(seed=2, reset_time_s=0.3))
    with i2c:
        probe = DriverProbe(bus, "ahrs")
        profile = write_profile(tmp_path, name="ahrs", kind="imu_bno055", settings={},
                                devices=on(i2c, "ahrs", bno.I2C_ADDRESS))
        start_driver(services, profile, "ahrs")
        probe.wait_states(10)
        i2c.transact(OP_WRITE, bno.I2C_ADDRESS, bno.SYS_TRIGGER, 1, bytes((bno.TRIGGER_RST_SYS,)))
        back = probe.wait_health(lambda d, s: int(d["reinits"]) >= 1 and d["port"] == "open",
                                 message="the chip set up again after its reset")
        assert int(back["i2c_errors"]) > 0
        assert chip.mode == bno.MODE_NDOF and chip.peek(bno.UNIT_SEL) == bno.UNIT_GYR_RPS | bno.UNIT_EUL_RAD
        probe.wait_states(20, since=probe.state_count())
