"""Register semantics of the mock MPU-9250 family, AK8963, BNO055 and PCA9685, read the
way a driver reads them: through the I2C port and the mock bus socket."""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Callable, Iterator

import pytest

from conftest import wait_until
from u2sa_hw.mocks.bno055_chip import Bno055Chip
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Ak8963Chip, Mpu9250Chip
from u2sa_hw.mocks.pca9685_chip import Pca9685Chip
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.ports.errors import PortIOError
from u2sa_hw.ports.i2c.port import I2cPort, open_i2c
from u2sa_hw.protocols import bno055 as bno
from u2sa_hw.protocols import mpu9250 as mpu
from u2sa_hw.protocols import pca9685 as pca

G = 9.80665


class ScriptedVehicle:
    """A vehicle whose truth the test sets; counts snapshots and can change on each one."""

    def __init__(self, **truth: float) -> None:
        self.truth = dict(roll=0.0, pitch=0.0, yaw=0.0, roll_rate=0.0, pitch_rate=0.0, yaw_rate=0.0,
                          accel_x=0.0, accel_y=0.0, accel_z=-G)
        self.truth.update(truth)
        self.snapshots = 0
        self.on_snapshot: Callable[[int, dict], None] | None = None

    def snapshot(self) -> SimpleNamespace:
        self.snapshots += 1
        if self.on_snapshot:
            self.on_snapshot(self.snapshots, self.truth)
        return SimpleNamespace(t=float(self.snapshots), **self.truth)


@pytest.fixture
def bus() -> Iterator[MockI2cBus]:
    """An empty mock bus on a short socket path."""
    tmp = Path(tempfile.mkdtemp(prefix="i2c", dir="/tmp"))
    mock = MockI2cBus(socket_path=str(tmp / "bus.sock"))
    with mock:
        yield mock
    shutil.rmtree(tmp, ignore_errors=True)


def port_to(bus: MockI2cBus, address: int) -> I2cPort:
    return open_i2c(device="chip-test", bus=bus.address, address=address)


def burst(port: I2cPort) -> mpu.RawSample:
    return mpu.decode_burst(port.read_block(mpu.BURST_START, mpu.BURST_LENGTH))


# ---- MPU family -----------------------------------------------------------------------
@pytest.mark.parametrize("variant,who,pwr", [("mpu6050", 0x68, 0x40), ("mpu6500", 0x70, 0x01),
                                             ("mpu9250", 0x71, 0x01)])
def test_mpu_identity_and_power_up(bus: MockI2cBus, variant: str, who: int, pwr: int) -> None:
    bus.add(Mpu9250Chip(variant=variant))
    port = port_to(bus, 0x68)
    assert port.read_byte(mpu.WHO_AM_I) == who
    assert port.read_byte(mpu.PWR_MGMT_1) == pwr
    port.write_byte(mpu.WHO_AM_I, 0x00)  # read-only
    assert port.read_byte(mpu.WHO_AM_I) == who


def test_mpu6050_is_asleep_until_woken(bus: MockI2cBus) -> None:
    chip = bus.add(Mpu9250Chip(variant="mpu6050"))
    port = port_to(bus, 0x68)
    assert port.read_block(mpu.BURST_START, 14) == bytes(14)  # never sampled while asleep
    port.write_byte(mpu.PWR_MGMT_1, 0x01)
    awake = burst(port)
    assert abs(awake.az - 16384) < 300
    temp_c = awake.temp / 340 + 36.53
    assert abs(temp_c - 25.0) < 0.5
    port.write_byte(mpu.PWR_MGMT_1, mpu.PWR1_SLEEP)
    samples = chip.samples
    assert burst(port) == awake  # asleep: the registers hold the last sample
    assert chip.samples == samples


@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_mpu_full_scale_changes_scaling(bus: MockI2cBus, index: int) -> None:
    rate = ScriptedVehicle(yaw_rate=math.radians(100.0), pitch_rate=math.radians(-40.0), roll_rate=math.radians(10.0),
                           accel_x=0.5 * G, accel_y=-0.25 * G)
    bus.add(Mpu9250Chip(vehicle=rate, gyro_noise_dps=0.0, accel_noise_g=0.0, gyro_bias_dps=(0.0, 0.0, 0.0)))
    port = port_to(bus, 0x68)
    port.write_byte(mpu.ACCEL_CONFIG, mpu.fs_config(index))
    port.write_byte(mpu.GYRO_CONFIG, mpu.fs_config(index))
    s = burst(port)
    a, w = mpu.ACCEL_LSB_PER_G[index], mpu.GYRO_LSB_PER_DPS[index]
    assert (s.ax, s.ay, s.az) == (round(0.5 * a), round(0.25 * a), round(a))  # chip y = -body y, z = up
    assert (s.gx, s.gy, s.gz) == (round(10.0 * w), round(40.0 * w), round(-100.0 * w))


def test_mpu_gyro_bias_shows_at_rest_and_config_registers_store(bus: MockI2cBus) -> None:
    bus.add(Mpu9250Chip(gyro_bias_dps=(1.0, -2.0, 0.5), gyro_noise_dps=0.0))
    port = port_to(bus, 0x68)
    s = burst(port)
    assert (s.gx, s.gy, s.gz) == (131, -262, round(0.5 * 131))
    port.write_byte(mpu.CONFIG, 0x03)
    port.write_byte(mpu.SMPLRT_DIV, 4)
    assert port.read_block(mpu.SMPLRT_DIV, 2) == bytes([4, 3])
    assert bus.chip(0x68).dlpf_cfg == 3


def test_mpu_burst_is_one_instant_but_byte_reads_are_not(bus: MockI2cBus) -> None:
    moving = ScriptedVehicle()

    def advance(n: int, truth: dict) -> None:  # every snapshot is a new instant
        truth["accel_x"] = n * 0.01 * G
        truth["roll_rate"] = math.radians(n)

    moving.on_snapshot = advance
    chip = bus.add(Mpu9250Chip(vehicle=moving, gyro_noise_dps=0.0, accel_noise_g=0.0, gyro_bias_dps=(0, 0, 0)))
    port = port_to(bus, 0x68)
    for _ in range(5):
        s = burst(port)
        n = moving.snapshots
        assert s.ax == round(n * 0.01 * 16384) and s.gx == round(n * 131)
    before = chip.samples
    port.read_byte(mpu.ACCEL_XOUT_H)
    port.read_byte(mpu.ACCEL_XOUT_L)
    assert chip.samples == before + 2  # separate reads see separate samples: drivers must burst


def test_mpu_device_reset_restores_defaults(bus: MockI2cBus) -> None:
    bus.add(Mpu9250Chip())
    port = port_to(bus, 0x68)
    port.write_byte(mpu.GYRO_CONFIG, 0x18)
    port.write_byte(mpu.PWR_MGMT_1, mpu.PWR1_DEVICE_RESET)
    assert port.read_byte(mpu.GYRO_CONFIG) == 0
    assert port.read_byte(mpu.PWR_MGMT_1) == 0x01


def test_mpu_sees_the_simulated_vehicle_turn(bus: MockI2cBus) -> None:
    vehicle = SimVehicle(origin_lat=52.0, origin_lon=4.0)
    bus.add(Mpu9250Chip(vehicle=vehicle, gyro_bias_dps=(0.0, 0.0, 0.0)))
    port = port_to(bus, 0x68)
    assert abs(burst(port).gz) < 30
    vehicle.set_wheel_speed("left", 1.0)
    vehicle.set_wheel_speed("right", 0.5)  # right turn: r = 1 rad/s clockwise
    vehicle.step(0.1)
    s = burst(port)
    assert abs(s.gz - round(-math.degrees(1.0) * 131)) < 30  # chip z up: a right turn reads negative
    assert abs(s.ay - round(-0.75 * 1.0 / G * 16384)) < 200  # centripetal +y body (right) is -y chip


def test_ak8963_behind_bypass(bus: MockI2cBus) -> None:
    vehicle = ScriptedVehicle(yaw=math.radians(90.0))
    imu = bus.add(Mpu9250Chip(vehicle=vehicle))
    bus.add(Ak8963Chip(parent=imu, asa=(128, 128, 128), noise_ut=0.0))
    imu_port, mag = port_to(bus, 0x68), port_to(bus, 0x0C)
    with pytest.raises(PortIOError):
        mag.read_byte(mpu.AK8963_WIA)  # hidden until BYPASS_EN
    imu_port.write_byte(mpu.INT_PIN_CFG, mpu.INT_PIN_CFG_BYPASS_EN)
    assert mag.read_byte(mpu.AK8963_WIA) == 0x48
    mag.write_byte(mpu.AK8963_CNTL1, 0x0F)
    assert mag.read_block(mpu.AK8963_ASAX, 3) == bytes([128, 128, 128])
    mag.write_byte(mpu.AK8963_CNTL1, 0x00)
    assert mag.read_block(mpu.AK8963_ASAX, 3) == bytes(3)  # fuse ROM only readable in fuse mode
    mag.write_byte(mpu.AK8963_CNTL1, 0x16)  # continuous 100 Hz, 16-bit
    data = mag.read_block(mpu.AK8963_ST1, 8)  # ST1, HXL..HZH, ST2
    assert data[0] & 0x01
    hx, hy, hz = (int.from_bytes(data[i:i + 2], "little", signed=True) * 0.15 for i in (1, 3, 5))
    # facing east, the 20 uT north field lies along body -y = chip +y = mag +x; 45 uT down = mag +z
    assert (round(hx), round(hy), round(hz)) == (20, 0, 45)


# ---- BNO055 ---------------------------------------------------------------------------
def bno_in_mode(bus: MockI2cBus, mode: int, **kwargs) -> tuple[Bno055Chip, I2cPort]:
    chip = bus.add(Bno055Chip(**kwargs))
    port = port_to(bus, 0x28)
    port.write_byte(bno.OPR_MODE, mode)
    return chip, port


def test_bno_identity_and_config_mode(bus: MockI2cBus) -> None:
    bus.add(Bno055Chip())
    port = port_to(bus, 0x28)
    assert port.read_block(bno.CHIP_ID, 4) == bytes([0xA0, 0xFB, 0x32, 0x0F])
    assert port.read_byte(bno.OPR_MODE) == bno.MODE_CONFIG
    assert port.read_byte(bno.SYS_STATUS) == bno.STATUS_IDLE
    assert port.read_block(bno.DATA_REGISTERS.start, 0x2C) == bytes(0x2C)  # nothing measured in CONFIG
    port.write_byte(bno.UNIT_SEL, 0x00)
    assert port.read_byte(bno.UNIT_SEL) == 0x00
    port.write_byte(bno.OPR_MODE, bno.MODE_NDOF)
    assert port.read_byte(bno.SYS_STATUS) == bno.STATUS_FUSION_RUNNING
    port.write_byte(bno.UNIT_SEL, 0x06)  # ignored outside CONFIG mode
    assert port.read_byte(bno.UNIT_SEL) == 0x00
    port.write_byte(bno.OPR_MODE, bno.MODE_AMG)
    assert port.read_byte(bno.SYS_STATUS) == bno.STATUS_RUNNING_NO_FUSION


def test_bno_euler_gyro_and_linear_acceleration(bus: MockI2cBus) -> None:
    vehicle = ScriptedVehicle(yaw=math.radians(-30.0), roll=math.radians(10.0), pitch=math.radians(5.0),
                              yaw_rate=math.radians(20.0), accel_x=1.5)
    vehicle.truth["accel_y"] = -G * math.sin(vehicle.truth["roll"]) * math.cos(vehicle.truth["pitch"])
    vehicle.truth["accel_z"] = -G * math.cos(vehicle.truth["roll"]) * math.cos(vehicle.truth["pitch"])
    vehicle.truth["accel_x"] = 1.5 + G * math.sin(vehicle.truth["pitch"])
    chip = bus.add(Bno055Chip(vehicle=vehicle, accel_noise_ms2=0.0, gyro_noise_dps=0.0))
    port = port_to(bus, 0x28)
    port.write_byte(bno.UNIT_SEL, 0x00)  # m/s^2, dps, degrees, Windows
    port.write_byte(bno.OPR_MODE, bno.MODE_NDOF)
    heading, roll, pitch = bno.decode_vector(port.read_block(bno.EUL_HEADING_LSB, 6))
    assert (heading, roll, pitch) == (330 * 16, 10 * 16, 5 * 16)
    assert bno.decode_vector(port.read_block(bno.GYR_DATA_X_LSB, 6)) == (0, 0, -20 * 16)
    assert bno.decode_vector(port.read_block(bno.LIA_DATA_X_LSB, 6)) == (150, 0, 0)
    grv = bno.decode_vector(port.read_block(bno.GRV_DATA_X_LSB, 6))
    assert math.isclose(math.sqrt(sum(c * c for c in grv)), 981, abs_tol=2)
    w, x, y, z = bno.decode_quaternion(port.read_block(bno.QUA_DATA_W_LSB, 8))
    assert math.isclose(w * w + x * x + y * y + z * z, 1.0, abs_tol=1e-3)
    assert math.isclose(math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))) % 360, 330, abs_tol=0.1)
    port.write_byte(bno.OPR_MODE, bno.MODE_CONFIG)
    port.write_byte(bno.UNIT_SEL, bno.UNIT_EUL_RAD | bno.UNIT_ORI_ANDROID | bno.UNIT_GYR_RPS)
    port.write_byte(bno.OPR_MODE, bno.MODE_NDOF)
    heading, roll, pitch = bno.decode_vector(port.read_block(bno.EUL_HEADING_LSB, 6))
    assert (heading, roll, pitch) == (round(math.radians(330) * 900), round(math.radians(10) * 900),
                                      round(-math.radians(5) * 900))
    assert bno.decode_vector(port.read_block(bno.GYR_DATA_X_LSB, 6))[2] == round(-math.radians(20) * 900)
    assert chip.samples >= 5


def test_bno_calibration_status_progresses(bus: MockI2cBus) -> None:
    chip, port = bno_in_mode(bus, bno.MODE_CONFIG, calibrated_after_s=0.3)
    first = port.read_byte(bno.CALIB_STAT)
    assert first != 0xFF and bno.split_calib_stat(first)["gyr"] == 3
    assert port.read_byte(bno.CALIB_STAT) == first  # no fusion, no progress
    port.write_byte(bno.OPR_MODE, bno.MODE_NDOF)
    wait_until(lambda: port.read_byte(bno.CALIB_STAT) == 0xFF, timeout=10, message="BNO055 fully calibrated")
    chip.set_calibration(sys=1, gyr=2, acc=3, mag=0)
    assert bno.split_calib_stat(port.read_byte(bno.CALIB_STAT)) == dict(sys=1, gyr=2, acc=3, mag=0)
    chip.calibrate()
    assert port.read_byte(bno.CALIB_STAT) == 0xFF


def test_bno_pages_and_reset(bus: MockI2cBus) -> None:
    chip, port = bno_in_mode(bus, bno.MODE_CONFIG, reset_time_s=0.2)
    port.write_byte(bno.PAGE_ID, 1)
    assert port.read_byte(bno.PAGE_ID) == 1
    assert port.read_byte(0x08) == 0x0D  # page 1 ACC_Config, not ACC_DATA
    port.write_byte(0x08, 0x0C)
    assert port.read_byte(0x08) == 0x0C
    port.write_byte(bno.PAGE_ID, 0)
    assert port.read_byte(bno.CHIP_ID) == 0xA0
    port.write_byte(bno.OPR_MODE, bno.MODE_NDOF)
    port.write_byte(bno.SYS_TRIGGER, bno.TRIGGER_RST_SYS)
    with pytest.raises(PortIOError):
        port.read_byte(bno.CHIP_ID)  # booting: the chip does not answer

    def answers() -> bool:
        try:
            return port.read_byte(bno.CHIP_ID) == 0xA0
        except PortIOError:
            return False

    wait_until(answers, timeout=10, message="BNO055 back from reset")
    assert port.read_byte(bno.OPR_MODE) == bno.MODE_CONFIG


def test_bno_imu_mode_heading_is_relative(bus: MockI2cBus) -> None:
    vehicle = ScriptedVehicle(yaw=math.radians(100.0))
    _, port = bno_in_mode(bus, bno.MODE_IMU, vehicle=vehicle)
    vehicle.truth["yaw"] = math.radians(110.0)
    heading = bno.decode_vector(port.read_block(bno.EUL_HEADING_LSB, 6))[0]
    assert heading == 10 * 16


# ---- PCA9685 --------------------------------------------------------------------------
def test_pca_power_on_state_and_prescale_needs_sleep(bus: MockI2cBus) -> None:
    chip = bus.add(Pca9685Chip())
    port = port_to(bus, 0x40)
    assert port.read_byte(pca.MODE1) == 0x11 and port.read_byte(pca.MODE2) == 0x04
    assert port.read_byte(pca.PRE_SCALE) == 0x1E
    assert chip.pulse_widths_us() == [0.0] * 16
    port.write_byte(pca.PRE_SCALE, 121)  # asleep at power-on: taken
    assert port.read_byte(pca.PRE_SCALE) == 121
    port.write_byte(pca.MODE1, 0x01)
    port.write_byte(pca.PRE_SCALE, 50)  # awake: ignored
    assert port.read_byte(pca.PRE_SCALE) == 121
    port.write_byte(pca.MODE1, 0x11)
    port.write_byte(pca.PRE_SCALE, 1)  # below the minimum: reads 3
    assert port.read_byte(pca.PRE_SCALE) == 3


def test_pca_auto_increment_and_all_led(bus: MockI2cBus) -> None:
    chip = bus.add(Pca9685Chip())
    port = port_to(bus, 0x40)
    port.write_byte(pca.MODE1, 0x01)  # awake, AI off
    reg = pca.led_register(2)
    port.write_block(reg, bytes([0x11, 0x22, 0x33, 0x04]))  # without AI every byte lands on ON_L
    assert port.read_byte(reg) == 0x04 and port.read_byte(reg + 1) == 0
    port.write_byte(pca.MODE1, 0x21)
    port.write_block(reg, pca.led_bytes(0, 300))
    assert port.read_block(reg, 4) == pca.led_bytes(0, 300)
    assert math.isclose(chip.pulse_width_us(2), 300 * 31 / 25e6 * 1e6)  # prescale 30 at power-on
    port.write_block(pca.ALL_LED_ON_L, pca.led_bytes(0, 1000))
    assert {chip.high_counts(ch) for ch in range(16)} == {1000}
    assert port.read_block(pca.ALL_LED_ON_L, 4) == bytes(4)  # write-only
    port.write_byte(pca.MODE2, pca.MODE2_OUTDRV | pca.MODE2_INVRT)
    assert math.isclose(chip.pulse_width_us(0), 3096 * 31 / 25e6 * 1e6)


def test_pca_sleep_sets_restart_and_restart_resumes(bus: MockI2cBus) -> None:
    chip = bus.add(Pca9685Chip())
    port = port_to(bus, 0x40)
    port.write_byte(pca.MODE1, 0x21)
    port.write_block(pca.led_register(0), pca.led_bytes(0, 307))
    running = chip.pulse_width_us(0)
    assert running > 0
    port.write_byte(pca.MODE1, 0x31)  # sleep while running
    assert port.read_byte(pca.MODE1) & pca.MODE1_RESTART and chip.pulse_width_us(0) == 0
    woke = time.monotonic()
    port.write_byte(pca.MODE1, 0x21)
    assert chip.pulse_width_us(0) == 0  # awake but waiting for RESTART
    wait_until(lambda: time.monotonic() - woke > 2 * pca.WAKE_DELAY_S, message="oscillator settle time")
    port.write_byte(pca.MODE1, 0xA1)
    assert not port.read_byte(pca.MODE1) & pca.MODE1_RESTART
    assert chip.pulse_width_us(0) == running
