"""Drivers declare what the rest of the system needs of their device (u2sa_hw/ports/declared.py):
the mock kinds that stand in for it, what a mock mirrors of their wiring, what the probe expects
and how a replay feeds it. The mock catalog, ``u2sa check`` and replay use only these and the
device address, never a driver's setting names (DESIGN.md section 4)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Mapping

import pytest

from u2sa_hw.mocks.catalog import CATALOG, DeviceSpec, build
from u2sa_hw.mocks.sim_context import DeviceError, MockContext
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw import registry
from u2sa_hw.check.device_checks import mock_for_kind
from u2sa_hw.check.targets import expectation
from u2sa_hw.ports import declared
from u2sa_hw.ports.address import parse_address

DRIVER_KINDS = sorted(kind for kind, target in registry.SERVICE_KINDS.items() if target.startswith("u2sa_hw.drivers."))


def _context(tmp_path: Path) -> MockContext:
    return MockContext(vehicle=SimVehicle(origin_lat=29.19, origin_lon=-81.05), device_dir=tmp_path,
                       can_udp_port=17_990)


def _spec(kind: str, mock: str, address: str, config: Mapping[str, Any], *, name: str = "dev",
          service: str = "svc", **extra: Any) -> DeviceSpec:
    return DeviceSpec(name=name, mock=mock, service=service, service_config=dict(config),
                      address=parse_address(address, device=name), kind=kind, **extra)


# ---- every driver declares ------------------------------------------------------------------------
@pytest.mark.parametrize("kind", DRIVER_KINDS)
def test_every_driver_with_a_device_declares_its_mocks_and_what_the_probe_expects(kind: str) -> None:
    cls = registry.resolve_kind(kind)
    assert declared.declares_devices(cls)
    kinds = declared.mock_kinds(cls)
    assert kinds and all(k in CATALOG for k in kinds), f"{kind}: MOCK_KINDS {kinds} must name catalog kinds"
    for name in ("mock_wiring", "probe_expectation"):
        assert callable(getattr(cls, name, None)), f"{kind} declares no {name}"
    assert isinstance(declared.probe_expectation(cls, {}), dict)


@pytest.mark.parametrize("kind, mock", [
    ("gps_nmea", "nmea_gps"), ("compass_serial", "nmea_compass"), ("imu_mpu9250", "mpu9250"),
    ("imu_bno055", "bno055"), ("pwm_servo", "pca9685"), ("rc_mux", "rc_receiver"), ("gpio_output", "gpio_chip"),
    ("gpio_input", "gpio_chip"), ("odrive_can", "odrive"), ("vesc_can", "vesc"),
])
def test_the_no_mock_fix_names_the_mock_the_driver_declares_first(kind: str, mock: str) -> None:
    assert mock_for_kind(kind) == mock


def test_a_kind_that_declares_no_mock_gets_a_placeholder_fix() -> None:
    assert mock_for_kind("control") == "..." and mock_for_kind("no_such_kind") == "..."


@pytest.mark.parametrize("kind, config, expected", [
    ("gps_nmea", {}, {"protocol": "NMEA"}),
    ("compass_serial", {}, {"protocol": "NMEA"}),
    ("compass_serial", {"format": "OS5000"}, {"protocol": "OS5000"}),
    ("imu_mpu9250", {"chip": "mpu6500"}, {"chip": "mpu", "variant": "mpu6500"}),
    ("imu_mpu9250", {}, {"chip": "mpu", "variant": "auto"}),
    ("imu_bno055", {}, {"chip": "bno055", "variant": "auto"}),
    ("pwm_servo", {}, {"chip": "pca9685"}),
    ("odrive_can", {"node_ids": [3, 4]}, {"protocol": "odrive", "nodes": [3, 4]}),
    ("vesc_can", {"controller_ids": [10, 11]}, {"protocol": "vesc", "nodes": [10, 11]}),
    ("rc_mux", {}, {}), ("gpio_output", {}, {}), ("gpio_input", {}, {}), ("control", {}, {}),
])
def test_the_probe_expects_what_the_driver_declares(kind: str, config: dict[str, Any],
                                                    expected: dict[str, Any]) -> None:
    assert expectation(kind, config) == expected


def test_a_serial_replay_groups_bursts_by_the_drivers_declared_gap() -> None:
    for kind in ("gps_nmea", "compass_serial"):
        cls = registry.resolve_kind(kind)
        assert declared.replay_options(cls, "gps", {}) == {"burst_gap_s": 0.05}   # the driver's default
        assert declared.replay_options(cls, "gps", {"epoch_gap_s": 0.2}) == {"burst_gap_s": 0.2}


def test_declarations_get_the_drivers_defaults_under_a_partial_config() -> None:
    wiring = declared.mock_wiring(registry.resolve_kind("odrive_can"), "wheels", "wheels", {"node_ids": [5, 6]})
    assert wiring == {"actuators": ["left", "right"], "ids": [5, 6], "directions": [1, 1], "wheel_radius_m": [0.1, 0.1],
                      "firmware": "0.6", "command_limit_turns_per_s": 2.0}


# ---- the catalog uses the declaration, not the setting names ----------------------------------------
class RenamedRcDriver(declared.DeviceDeclarations):
    """A third-party RC driver whose settings are named unlike rc_mux's."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("rc_receiver",)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        return {"lines": dict(config["receiver_lines"]), "mode_channel": config["switch"],
                "enable_line": config["autonomy_line"], "select_line": None}


class RenamedVescDriver(declared.DeviceDeclarations):
    """A third-party VESC driver with one table per motor."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("vesc",)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        motors = config["motors"]
        return {"actuators": [m["name"] for m in motors], "ids": [m["can"] for m in motors],
                "directions": [m["sign"] for m in motors], "wheel_radius_m": [0.2] * len(motors),
                "max_erpm": 9000.0, "pole_pairs": 14, "gear_ratio": 3.0}


@pytest.fixture
def renamed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(registry.SERVICE_KINDS, "renamed_rc", f"{__name__}:RenamedRcDriver")
    monkeypatch.setitem(registry.SERVICE_KINDS, "renamed_vesc", f"{__name__}:RenamedVescDriver")


def test_a_driver_with_renamed_settings_still_gets_a_correct_rc_mock(tmp_path: Path, renamed: None) -> None:
    ctx = _context(tmp_path)
    spec = _spec("renamed_rc", "rc_receiver", "gpio://gpiochip0/5,13,21",
                 {"receiver_lines": {"throttle": 5, "flight_mode": 13}, "switch": "flight_mode", "autonomy_line": 21,
                  "channels": "ignored=1", "enable_line": 4})   # rc_mux's names mean nothing to this driver
    device = build(spec, ctx)
    rc = ctx.rc_receivers["dev"]
    assert rc.lines == {"throttle": 5, "flight_mode": 13} and rc.mode_channel == "flight_mode"
    assert [mux.enable_line for _, mux in ctx.muxes] == [21]
    assert device.detail == "throttle=5, flight_mode=13; mux enable line 21"


def test_a_driver_with_renamed_settings_still_gets_correct_can_nodes(tmp_path: Path, renamed: None) -> None:
    ctx = _context(tmp_path)
    spec = _spec("renamed_vesc", "vesc", "can://socketcan/can0",
                 {"motors": [{"name": "port", "can": 7, "sign": 1}, {"name": "starboard", "can": 8, "sign": -1}]},
                 sides=("left", "right"))
    device = build(spec, ctx)
    port, starboard = ctx.can_nodes["port"], ctx.can_nodes["starboard"]
    assert (port.controller_id, starboard.controller_id, starboard.direction) == (7, 8, -1)
    assert (port.max_erpm, port.pole_pairs, port.gear_ratio) == (9000.0, 14, 3.0)
    assert device.detail == "port id 7 left, starboard id 8 right"


# ---- the messages name the table and the fix ---------------------------------------------------------
def test_a_mock_that_does_not_stand_in_for_the_services_driver_names_the_fix(tmp_path: Path) -> None:
    spec = _spec("gps_nmea", "odrive", "can://socketcan/can0", {}, name="gps", service="gps", where="[devices.gps]")
    with pytest.raises(DeviceError, match=r"\[devices.gps\]: mock odrive does not stand in for service 'gps' "
                                          r"\(gps_nmea: its device's mock is nmea_gps\); .*set service = \"...\" in "
                                          r"the table or mock = \"nmea_gps\""):
        build(spec, _context(tmp_path))


def test_a_compass_mock_speaking_another_protocol_names_the_setting(tmp_path: Path) -> None:
    spec = _spec("compass_serial", "os5000_compass", "serial:///dev/u2sa/compass", {"format": "nmea"},
                 where="[devices.compass]")
    with pytest.raises(DeviceError, match=r"mock os5000_compass speaks 'os5000' but service 'svc' has "
                                          r"format = 'nmea'; make them agree"):
        build(spec, _context(tmp_path))


def test_a_pwm_output_no_channel_uses_names_the_channel_table_fix(tmp_path: Path) -> None:
    spec = _spec("pwm_servo", "pca9685", "pca9685://1/0x40/0", {"channels": [{"name": "rudder"}]}, name="esc",
                 service="drive", where="[devices.esc]")
    with pytest.raises(DeviceError, match=r"\[devices.esc\]: no channel of service 'drive' uses device 'esc' "
                                          r"\(channels: rudder\); set device = \"esc\" in the channel's table"):
        build(spec, _context(tmp_path))


def test_a_bad_line_map_is_the_drivers_own_error(tmp_path: Path) -> None:
    spec = _spec("gpio_output", "gpio_chip", "gpio://gpiochip0", {"outputs": "lamp"}, service="lights")
    with pytest.raises(DeviceError, match=r"service 'lights': config 'outputs' item 'lamp' is not name=value"):
        build(spec, _context(tmp_path))


def test_an_imu_is_replayed_with_its_own_settings_on_a_paced_bus() -> None:
    """A replayed IMU keeps its recorded sample rate (its configuration writes match the recording): the replay
    bus paces its data reads (paced=true), so it samples back to back at any replay rate."""
    from u2sa_hw.hil.replay_buses import ReplayI2cDevice, make_device
    from u2sa_hw.hil.replay_plan import DevicePlan, ServicePlan
    from u2sa_hw.ports.address import parse_address
    from u2sa_hw.ports.declared import declared_class, replay_options

    assert replay_options(declared_class("imu_mpu9250"), "imu", {}) == {}
    dev = DevicePlan(name="imu", kind="i2c", records=0)
    for fast in (True, False):
        device = make_device(dev, Path("/nonexistent"), ServicePlan("imu", "imu_mpu9250", {}), fast=fast)
        assert isinstance(device, ReplayI2cDevice) and device.config_changes() == {}
        address = parse_address(device.mock_address(parse_address("i2c://1/0x68", device="imu")), device="imu")
        assert address.i2c_paced and address.i2c_timeout and address.chip_address == 0x68
