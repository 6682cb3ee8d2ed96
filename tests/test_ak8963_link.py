"""The MPU-9250's AK8963 goes through the IMU device's address and tap: its transactions are on
``RAW.<device>`` (chip address 0x0c), it follows an address change of the device, and a recording
replays into the same magnetometer values and heading.

The real driver runs in this process (``sample_once`` by hand, no service loop) against the chip
models on the mock I2C bus; replay uses the replay I2C bus of ``u2sa replay`` on a log written here.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import wait_until

from u2sa_hw.drivers.imu.ak8963 import mag_address, to_chip_axes
from u2sa_hw.drivers.imu.mpu9250 import Mpu9250ImuDriver
from u2sa_hw.hil.replay_buses import ReplayI2cDevice
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Ak8963Chip, Mpu9250Chip, OrientedVehicle, ned_to_body
from u2sa_hw import channels as ch
from u2sa_hw.ports.address import parse_address
from u2sa_hw.ports.i2c.wire import OP_READ, OP_WRITE
from u2sa_hw.protocols import mpu9250 as mpu
from u2sa_hw.recording.mcap_log import McapLogWriter
from u2sa_hw.profile.vehicle import VehicleProfile

EARTH_UT = (20.0, 0.0, 45.0)      # the chip model's default field (NED, µT)
SETTINGS = {"device": "ins", "calibrate_samples": 0, "retries": 1,
            "mag_offset": [0.001, 0.0, 0.0]}   # "calibrated" (a heading), yet the field as measured


@pytest.fixture
def socket_dir() -> Iterator[Path]:
    """A short directory for Unix sockets (tmp_path can exceed the 108-byte limit)."""
    path = Path(tempfile.mkdtemp(prefix="ak", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


def mpu_bus(path: Path, *, yaw: float, noise_ut: float = 0.0, seed: int = 0) -> tuple[MockI2cBus, Ak8963Chip]:
    """A mock bus with an MPU-9250 and its AK8963, the board still at heading *yaw*."""
    bus = MockI2cBus(socket_path=str(path))
    imu = bus.add(Mpu9250Chip(vehicle=OrientedVehicle(yaw=yaw), seed=seed))
    ak = bus.add(Ak8963Chip(parent=imu, noise_ut=noise_ut, seed=seed))  # type: ignore[arg-type]
    return bus, ak  # type: ignore[return-value]


class Driver:
    """The MPU-9250 driver of service ``imu`` on device ``ins`` at *address*, publishing into a list."""

    def __init__(self, address: str, **settings: Any) -> None:
        self.profile = VehicleProfile(path=None, devices={"ins": {"address": address}})
        self.svc = Mpu9250ImuDriver("imu", profile=self.profile, settings={**SETTINGS, **settings})
        self.published: list[tuple[str, Any]] = []
        self.svc.transport.publish = self._publish  # type: ignore[method-assign]
        self.svc.setup()

    def _publish(self, channel: str, msg: Any) -> bool:
        self.published.append((channel, msg))
        return True

    def sample(self, n: int) -> list[tuple[Any, float | None]]:
        """*n* samples: the magnetometer's field (µT, AK8963 axes) and psi of each."""
        out = []
        for _ in range(n):
            before = len(self.published)
            self.svc.sample_once()
            states = [m for c, m in self.published[before:] if c == ch.STATE_INFO]
            assert len(states) == 1, "one sample published"
            out.append((self.svc.mag.last if self.svc.mag else None, states[0].get("psi")))
        return out

    def raw(self, channel: str = "RAW.ins") -> list[Any]:
        return [m for c, m in self.published if c == channel]

    def close(self) -> None:
        self.svc.kill()
        self.svc.transport.stop()


def expected_chip_field(yaw: float) -> tuple[float, float, float]:
    body = ned_to_body(EARTH_UT, 0.0, 0.0, yaw)
    return body[0], -body[1], -body[2]


def test_the_magnetometer_address_is_the_imus_with_chip_0x0c() -> None:
    for mpu_url, mag_url in (("i2c://1/0x68", "i2c://1/0x0c"), ("i2c://3/0x69", "i2c://3/0x0c"),
                             ("mock+i2c:///run/sim/i2c-1.sock/0x68", "mock+i2c:///run/sim/i2c-1.sock/0x0c")):
        assert mag_address(parse_address(mpu_url, device="imu")).url == mag_url


def test_the_magnetometer_reads_are_on_the_devices_raw_channel(lcm_url: str, socket_dir: Path) -> None:
    bus, ak = mpu_bus(socket_dir / "bus.sock", yaw=0.7)
    with bus:
        driver = Driver(f"mock+i2c://{bus.socket_path}/0x68", record_raw=True)
        try:
            driver.sample(5)
            health = driver.svc.health_details()
            raws = driver.raw()
        finally:
            driver.close()
    assert health["magnetometer"] == "continuous 100 Hz, 16-bit", health
    assert health["mag_address"] == f"mock+i2c://{bus.socket_path}/0x0c" and health["mag_samples"] == 5
    assert not driver.raw("RAW.imu") and not driver.raw("RAW.imu-mag"), "RAW.<device>, not the service's name"
    assert {r.device for r in raws} == {"ins"}
    mag = [r for r in raws if r.address == mpu.AK8963_ADDRESS]
    reads = [r for r in mag if r.op == OP_READ and r.register_address == mpu.AK8963_SAMPLE_START]
    assert len(reads) == 5 and all(r.ok and r.length == mpu.AK8963_SAMPLE_LENGTH for r in reads)
    # what the tap holds is what the chip answered
    answered = [bytes(t.data) for t in ak.history if t.op == OP_READ and t.register == mpu.AK8963_SAMPLE_START]
    assert [bytes(r.data) for r in reads] == answered
    assert any(r.op == OP_WRITE and r.register_address == mpu.AK8963_CNTL1 for r in mag), "the set-up is tapped too"
    assert any(r.address == mpu.I2C_ADDRESS for r in raws), "the MPU's own transactions beside them"


def test_recording_off_taps_nothing_and_heading_still_comes(lcm_url: str, socket_dir: Path) -> None:
    bus, _ = mpu_bus(socket_dir / "bus.sock", yaw=0.7)
    with bus:
        driver = Driver(f"mock+i2c://{bus.socket_path}/0x68")
        try:
            (_, psi), = driver.sample(1)
        finally:
            driver.close()
    assert not [c for c, _ in driver.published if c.startswith("RAW.")]
    assert psi == pytest.approx(0.7, abs=0.03)   # accel noise tilts it a little


def test_the_magnetometer_follows_an_address_change_of_the_device(lcm_url: str, socket_dir: Path) -> None:
    bus_a, ak_a = mpu_bus(socket_dir / "a.sock", yaw=0.0)
    bus_b, ak_b = mpu_bus(socket_dir / "b.sock", yaw=1.5)
    with bus_a:
        driver = Driver(f"mock+i2c://{bus_a.socket_path}/0x68")
        try:
            (field, psi), = driver.sample(1)
            assert to_chip_axes(field) == pytest.approx(expected_chip_field(0.0), abs=0.15)
            assert psi == pytest.approx(0.0, abs=0.03)   # accel noise tilts it a little
            old_port = driver.svc.mag.port
            assert old_port is not None and old_port.is_open

            # the device moves to bus b, which is not up yet: the old magnetometer port goes with the MPU's
            driver.profile.devices["ins"]["address"] = f"mock+i2c://{bus_b.socket_path}/0x68"
            assert driver.svc.port.refresh()
            driver.svc.sample_once()
            assert not old_port.is_open and driver.svc.mag.port is None
            health = driver.svc.health_details()
            assert health["port"] == "down" and "closed with the MPU's port" in health["magnetometer"]
            seen_on_a = len(ak_a.history)

            with bus_b:
                def sampled_on_b() -> bool:
                    driver.svc.sample_once()
                    return driver.svc.port.state == "open"
                wait_until(sampled_on_b, timeout=10, message="the IMU reopened on bus b")
                (field, psi), = driver.sample(1)
                health = driver.svc.health_details()
        finally:
            driver.close()
    assert health["mag_address"] == f"mock+i2c://{bus_b.socket_path}/0x0c"
    assert health["magnetometer"] == "continuous 100 Hz, 16-bit"
    assert len(ak_a.history) == seen_on_a, "nothing more reached the old bus's magnetometer"
    assert any(t.op == OP_READ and t.register == mpu.AK8963_SAMPLE_START for t in ak_b.history)
    assert to_chip_axes(field) == pytest.approx(expected_chip_field(1.5), abs=0.15)
    assert psi == pytest.approx(1.5, abs=0.03)   # accel noise tilts it a little


def test_an_mpu9250_without_its_ak8963_has_no_heading_and_says_so(lcm_url: str, socket_dir: Path) -> None:
    bus = MockI2cBus(socket_path=str(socket_dir / "bus.sock"))
    bus.add(Mpu9250Chip(vehicle=OrientedVehicle(yaw=0.3)))
    with bus:
        driver = Driver(f"mock+i2c://{bus.socket_path}/0x68")
        try:
            samples = driver.sample(3)
            health = driver.svc.health_details()
        finally:
            driver.close()
    assert [psi for _, psi in samples] == [None, None, None]
    assert health["magnetometer"].startswith("not answering") and "0x0c" in health["magnetometer"]
    assert health["mag_errors"] >= 1 and health["heading_deg"] == "" and health["samples"] == 3


def record_samples(bus: MockI2cBus, log_path: Path, n: int, **settings: Any) -> tuple[Driver, list[Any]]:
    """*n* samples of a driver on *bus* with its raw tap on, the taps written to *log_path* as RAW.ins."""
    with bus:
        live = Driver(f"mock+i2c://{bus.socket_path}/0x68", record_raw=True, **settings)
        try:
            recorded = live.sample(n)
        finally:
            live.close()
    log = McapLogWriter(log_path.parent, path=log_path)
    for k, record in enumerate(live.raw()):
        log.write("RAW.ins", record.encode(), time.time_ns() + k)
    log.close()
    return live, recorded


def test_a_recorded_mpu9250_replays_into_the_same_magnetometer_values(lcm_url: str, socket_dir: Path,
                                                                     tmp_path: Path) -> None:
    bus, _ = mpu_bus(socket_dir / "bus.sock", yaw=2.2, noise_ut=0.5, seed=4)   # noisy: every sample differs
    recorded_address = f"mock+i2c://{bus.socket_path}/0x68"
    live, recorded = record_samples(bus, tmp_path / "imu.mcap", 12)
    assert len({field for field, _ in recorded}) == 12 and all(psi is not None for _, psi in recorded)

    device = ReplayI2cDevice(name="ins", socket_path=socket_dir / "replay.sock", fast=False)
    device.preload(tmp_path / "imu.mcap", start_ns=0, end_ns=2 ** 63 - 1)
    device.start()
    try:
        replayed_address = device.mock_address(parse_address(recorded_address, device="ins"))
        for record in live.raw():   # as the player feeds them: each recorded data read releases one
            device.feed(record)
        replay = Driver(replayed_address)
        try:
            replayed = replay.sample(12)
            health = replay.svc.health_details()
        finally:
            replay.close()
    finally:
        device.stop()
    assert health["mag_address"] == replayed_address.replace("/0x68", "/0x0c")
    assert [field for field, _ in replayed] == [field for field, _ in recorded]
    assert [psi for _, psi in replayed] == [psi for _, psi in recorded]
    assert all(math.isfinite(psi) for _, psi in replayed)
    report = device.report()
    assert report["divergences"] == 0 and report["recorded_reads_left"] == 0, report
    assert report["gated_reads"] == 0 and device.pending() == 0, report   # every data read was released first


def test_on_a_paced_replay_bus_the_imu_samples_as_fast_as_the_reads_are_released(socket_dir: Path,
                                                                                 tmp_path: Path) -> None:
    """The replay bus (paced=true) paces the data reads, so the driver's loop runs back to back: with its
    recorded rate_hz of 0.01 its timer would take 20 minutes for 12 samples; every one comes as it is released."""
    bus, _ = mpu_bus(socket_dir / "bus.sock", yaw=0.7)
    recorded_address = f"mock+i2c://{bus.socket_path}/0x68"
    live, recorded = record_samples(bus, tmp_path / "imu.mcap", 12, rate_hz=0.01)
    device = ReplayI2cDevice(name="ins", socket_path=socket_dir / "replay.sock", fast=True)
    device.preload(tmp_path / "imu.mcap", start_ns=0, end_ns=2 ** 63 - 1)
    device.start()
    try:
        replay = Driver(device.mock_address(parse_address(recorded_address, device="ins")), rate_hz=0.01)
        replay.svc.running = True   # as main() sets it before the loop
        loop = threading.Thread(target=replay.svc.run, daemon=True)
        loop.start()
        try:
            for record in live.raw():
                device.feed(record)
            wait_until(lambda: len([m for c, m in replay.published if c == ch.STATE_INFO]) >= 12, timeout=60,
                       message="12 samples from a driver whose own timer gives one every 100 s")
        finally:
            replay.svc.stop()
            device.stop()     # releases the read it holds past the recording
            loop.join(timeout=10)
            replay.close()
    finally:
        device.stop()
    psi = [m.get("psi") for c, m in replay.published if c == ch.STATE_INFO][:12]
    assert psi == [p for _, p in recorded] and device.report()["divergences"] == 0


def test_a_heading_outlives_its_field_by_0_1_s_of_samples_not_of_wall_time(socket_dir: Path) -> None:
    """When the AK8963 has no new field (DRDY low) the last one keeps the heading for MAG_MAX_AGE_S, counted in
    samples at rate_hz: at 50 Hz four samples keep it and the fifth drops it however fast they come (a
    replay reads them faster than live, or held up by its player, and must keep the same headings)."""
    bus, ak = mpu_bus(socket_dir / "bus.sock", yaw=0.4)
    with bus:
        driver = Driver(f"mock+i2c://{bus.socket_path}/0x68", rate_hz=50.0)
        try:
            assert driver.sample(1)[0][1] is not None
            ak.begin_transaction = lambda *_args: None   # no new measurement latched: DRDY stays low
            psi = [p for _, p in driver.sample(6)]
        finally:
            driver.close()
    assert all(p is not None for p in psi[:4]) and psi[4:] == [None, None], psi


def test_a_device_setting_changed_over_the_bus_reopens_the_imu_and_its_magnetometer_there(
        lcm_url: str, socket_dir: Path) -> None:
    bus_a, _ak_a = mpu_bus(socket_dir / "a.sock", yaw=0.0)
    bus_b, ak_b = mpu_bus(socket_dir / "b.sock", yaw=1.5)
    with bus_a, bus_b:
        driver = Driver(f"mock+i2c://{bus_a.socket_path}/0x68")
        driver.profile.devices["ins2"] = {"address": f"mock+i2c://{bus_b.socket_path}/0x68"}
        try:
            driver.sample(1)
            # what a ConfigChange for `device` does (u2sa param set imu device ins2), saved in the test's directory
            driver.svc.config.path = socket_dir / "imu.toml"
            assert driver.svc.config.set("device", "ins2")
            driver.svc.on_config_change("device", "ins2")
            wait_until(lambda: (driver.svc.sample_once(), driver.svc.port.state == "open")[1]
                       and driver.svc.port.device == "ins2", timeout=10, message="the IMU reopened on device ins2")
            (field, psi), = driver.sample(1)
            health = driver.svc.health_details()
        finally:
            driver.close()
    assert health["mag_address"] == f"mock+i2c://{bus_b.socket_path}/0x0c"
    assert any(t.op == OP_READ and t.register == mpu.AK8963_SAMPLE_START for t in ak_b.history)
    assert psi == pytest.approx(1.5, abs=0.03)
    assert driver.svc.where.endswith("b.sock")
