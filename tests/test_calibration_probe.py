"""``u2sa check --probe`` warns about an uncalibrated magnetometer/accelerometer (defaults in its config)."""

from __future__ import annotations

from pathlib import Path

import tomli_w

from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Ak8963Chip, Mpu9250Chip
from u2sa_hw.check.probe import probe_profile
from u2sa_hw.profile.loader import load_profile


def _profile(tmp_path: Path, variant: str) -> Path:
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f"""\
[vehicle]
name = "bench"
config_dir = "config"

[services.imu]
kind = "imu_mpu9250"

[devices.imu]
address = "mock+i2c://{tmp_path}/i2c-1.sock/0x68"
service = "imu"
""")
    return profile


def test_probe_warns_until_the_sensors_are_calibrated(tmp_path: Path) -> None:
    bus = MockI2cBus(socket_path=str(tmp_path / "i2c-1.sock"))
    imu = bus.add(Mpu9250Chip(address=0x68))
    bus.add(Ak8963Chip(parent=imu))
    imu.write_register(0x37, 0x02)       # bypass on, as a running driver leaves it: the AK8963 answers
    profile = _profile(tmp_path, "mpu9250")
    with bus:
        (result,) = probe_profile(load_profile(profile), seconds=0.1)
        assert result.ok and len(result.warnings) == 2, result
        assert "uncalibrated magnetometer" in result.warnings[0] and "u2sa calibrate compass" in result.warnings[0]
        assert "uncalibrated accelerometer" in result.warnings[1] and "u2sa calibrate imu" in result.warnings[1]
        assert str(result).count("\nprobe warn imu: uncalibrated") == 2

        config = tmp_path / "config" / "imu.toml"
        config.parent.mkdir()
        config.write_text(tomli_w.dumps({"accel_offset": [0.1, 0.0, -0.2]}))
        (result,) = probe_profile(load_profile(profile), seconds=0.1)
        assert result.ok and [w.split(" (")[0] for w in result.warnings] == ["uncalibrated magnetometer"]

        config.write_text(tomli_w.dumps({"accel_offset": [0.1, 0.0, -0.2],
                                         "mag_matrix": [1.1, 0, 0, 0, 1, 0, 0, 0, 1]}))
        (result,) = probe_profile(load_profile(profile), seconds=0.1)
        assert result.ok and result.warnings == ()


def test_an_mpu6500_has_no_magnetometer_to_warn_about(tmp_path: Path) -> None:
    bus = MockI2cBus(socket_path=str(tmp_path / "i2c-1.sock"))
    bus.add(Mpu9250Chip(address=0x68, variant="mpu6500"))
    with bus:
        (result,) = probe_profile(load_profile(_profile(tmp_path, "mpu6500")), seconds=0.1)
    assert result.ok and [w.split(" (")[0] for w in result.warnings] == ["uncalibrated accelerometer"]
