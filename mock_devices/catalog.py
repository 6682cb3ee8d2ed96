"""Mock kinds a vehicle profile's ``[devices.NAME]`` tables can name, and how each is built.

A device table names a mock kind and the service that uses the device::

    [devices.gps]
    mock = "nmea_gps"            # a kind below
    service = "gps"              # default: the device's own name
    options = { rate_hz = 5 }    # the mock class's keyword options (lists become tuples)
    sides = ["left", "right"]    # CAN motor mocks only: which side of the vehicle each controller drives
    drives = { rudder = "steering" }   # PWM and GPIO outputs: actuator name -> the vehicle model input it moves

The mock mirrors the service's own effective config (its defaults, the profile's
``settings``, its config file): the ODrive mocks take the service's ``node_ids``,
``directions`` and ``wheel_radius_m``, the RC receiver its ``channels`` and
``enable_line``, an I2C chip the service's ``address``. The service's *real* device
address picks the mock's address under the simulation's device directory
(``/dev/u2sa/gps`` -> ``<dir>/gps``, I2C bus 1 -> ``<dir>/i2c-1.sock`` shared by every chip
on bus 1, ``/dev/gpiochip0`` -> ``<dir>/gpiochip0.sock``, CAN ``can0`` -> python-can
``udp_multicast`` on the simulation's UDP port, ``/sys/class/pwm/pwmchip0`` -> the
directory ``<dir>/pwmchip0``) and each build returns the settings that point the service
at it (``overrides``). Every actuator output is logged and moves the vehicle through
:mod:`mock_devices.actuation`: CAN motors by their side, PWM outputs named like a model
input (``steering``, ``throttle``, ``left``, ``right``) or listed in ``drives``, GPIO
outputs listed in ``drives`` (``enable``: a motor contactor). A pwm_servo service with
both PCA9685 and sysfs channels takes one
table of each kind; the second builds on the channels the first rewrote.
"""

from __future__ import annotations

import inspect
import os
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

from mock_devices.actuation import GpioFeed, PwmFeed
from mock_devices.bno055_chip import Bno055Chip
from mock_devices.i2c_bus import MockI2cBus
from mock_devices.mpu9250_chip import Ak8963Chip, Mpu9250Chip
from mock_devices.nmea_gps import NmeaGpsDevice
from mock_devices.odrive_node import OdriveCanNode
from mock_devices.pca9685_chip import Pca9685Chip
from mock_devices.rc_receiver import MuxMock, RcReceiverMock
from mock_devices.serial_compass import NmeaCompassDevice, Os5000CompassDevice
from mock_devices.sim_context import CAN_GROUP, MODEL_INPUTS, DeviceError, MockContext
from mock_devices.sysfs_pwm import SysfsPwmChip
from mock_devices.vesc_node import VescCanNode
from u2sa_hw.ports.pwm_port import is_real_sysfs

SERIAL_KINDS = {"nmea_gps": NmeaGpsDevice, "nmea_compass": NmeaCompassDevice, "os5000_compass": Os5000CompassDevice}
COMPASS_FORMATS = {"nmea_compass": "nmea", "os5000_compass": "os5000"}


@dataclass(frozen=True)
class DeviceSpec:
    """One ``[devices.NAME]`` table with the effective config of the service that uses it."""

    name: str
    mock: str
    service: str
    service_config: Mapping[str, Any]
    options: dict[str, Any] = field(default_factory=dict)
    sides: tuple[str, ...] = ()
    drives: dict[str, str] = field(default_factory=dict)
    where: str = ""

    def fail(self, text: str) -> DeviceError:
        """A DeviceError prefixed with where the table is."""
        return DeviceError(f"{self.where or 'devices.' + self.name}: {text}")

    def setting(self, key: str) -> Any:
        """The service's value of *key*; DeviceError when the service has no such setting."""
        if key not in self.service_config:
            raise self.fail(f"service '{self.service}' has no setting '{key}' (is it the right service for a "
                            f"{self.mock} mock? set service = \"...\" in the table)")
        return self.service_config[key]


@dataclass
class MockDevice:
    """A built mock: what it is, where the driver finds it, the settings that point the service there."""

    name: str
    mock: str
    service: str
    address: str
    overrides: dict[str, Any]
    parts: list[Any]
    detail: str = ""


Builder = Callable[[DeviceSpec, MockContext], MockDevice]


def construct(spec: DeviceSpec, cls: type, *args: Any, **kwargs: Any) -> Any:
    """``cls(*args, **kwargs, **options)``; a wrong option becomes a DeviceError listing the valid ones."""
    options = {k: tuple(v) if isinstance(v, list) else v for k, v in spec.options.items()}
    merged = {**kwargs, **options}
    params = inspect.signature(cls).parameters
    unknown = sorted(set(options) - set(params))
    if unknown:
        valid = ", ".join(n for n, p in params.items() if p.kind == p.KEYWORD_ONLY and n not in kwargs)
        raise spec.fail(f"unknown option(s) {', '.join(unknown)} for {cls.__name__}; valid: {valid}")
    try:
        return cls(*args, **merged)
    except (TypeError, ValueError) as exc:
        raise spec.fail(f"{cls.__name__}: {exc}") from None


def _seeded(spec: DeviceSpec, ctx: MockContext) -> DeviceSpec:
    """*spec* with a noise seed of its own unless its options give one."""
    return spec if "seed" in spec.options else replace(spec, options={**spec.options, "seed": ctx.next_seed()})


# ---- serial ---------------------------------------------------------------------------------
def build_serial(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """A GPS or compass on a pty: ``<dir>/<basename of the service's port>``."""
    port = str(spec.setting("port")).strip()
    if not port:
        raise spec.fail(f"service '{spec.service}' has an empty 'port'; set the real device path "
                        "(e.g. /dev/u2sa/gps) in its settings")
    expected = COMPASS_FORMATS.get(spec.mock)
    if expected and spec.service_config.get("format", expected) != expected:
        raise spec.fail(f"mock {spec.mock} speaks '{expected}' but service '{spec.service}' has "
                        f"format = {spec.service_config.get('format')!r}; make them agree")
    link = ctx.path(os.path.basename(port.rstrip("/")) or spec.name)
    spec = _seeded(spec, ctx)
    device = construct(spec, SERIAL_KINDS[spec.mock], ctx.vehicle, link_path=link, name=spec.name)
    return MockDevice(spec.name, spec.mock, spec.service, link, {"port": link}, [device], f"pty for {port}")


# ---- I2C ------------------------------------------------------------------------------------
def build_imu_chip(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """An MPU-60x0/9250 (+ AK8963) or BNO055 on the mock bus standing in for the service's ``bus``."""
    bus: MockI2cBus = ctx.i2c_bus(str(spec.setting("bus")))
    address = int(spec.setting("address"))
    spec = _seeded(spec, ctx)
    if spec.mock == "bno055":
        chip = construct(spec, Bno055Chip, address=address, vehicle=ctx.vehicle)
        parts = [chip]
    else:
        chip = construct(spec, Mpu9250Chip, address=address, vehicle=ctx.vehicle,
                         variant=spec.options.get("variant", spec.mock))
        parts = [chip]
        if chip.variant.has_magnetometer:  # the MPU-9250's AK8963
            parts.append(Ak8963Chip(parent=chip, seed=int(spec.options["seed"])))
    for part in parts:
        ctx.add_chip(bus, part, device=spec.name)
    return MockDevice(spec.name, spec.mock, spec.service, bus.address, {"bus": bus.address}, [],
                      f"chip 0x{address:02x} on {bus.address}")


def _pwm_channels(spec: DeviceSpec, ctx: MockContext, what: str) -> list[dict[str, Any]]:
    """The service's channels, as an earlier PWM mock of the same service left them (mixed chips)."""
    channels = ctx.pwm_channels.get(spec.service, spec.setting("channels"))
    if not isinstance(channels, list) or not channels:
        raise spec.fail(f"service '{spec.service}' has no 'channels' to put on {what}")
    return [dict(table) if isinstance(table, dict) else table for table in channels]


def build_pca9685(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """PCA9685 chips for every ``pca9685:<bus>:<addr>`` channel of a pwm_servo service."""
    channels = _pwm_channels(spec, ctx, "a PCA9685")
    rewritten, chips, made = [], [], {}
    _check_drives(spec, [str(t.get("name", "")) for t in channels if isinstance(t, dict)])
    for index, table in enumerate(channels):
        table = dict(table)
        address = str(table.get("address", ""))
        if address.startswith("pca9685:"):
            bus_text, _, chip_text = address[len("pca9685:"):].rpartition(":")
            try:
                chip_address = int(chip_text, 0)
            except ValueError:
                raise spec.fail(f"channels[{index}].address {address!r}: the chip address after the last ':' "
                                "must be a number like 0x40") from None
            bus = ctx.i2c_bus(bus_text)
            key = (bus.socket_path, chip_address)
            if key not in made:   # channels of one chip share it
                made[key] = ctx.add_chip(bus, construct(spec, Pca9685Chip, address=chip_address), device=spec.name)
                chips.append(made[key])
            table["address"] = f"pca9685:{bus.address}:0x{chip_address:02x}"
            chip = made[key]
            _pwm_feed(spec, ctx, table, index, lambda chip=chip, n=int(table.get("channel", 0)): chip.pulse_width_us(n))
        rewritten.append(table)
    if not chips and not any(str(t.get("address", "")).startswith("pca9685:mock:") for t in rewritten):
        raise spec.fail(f"no channel of service '{spec.service}' has a pca9685:<bus>:<address> address")
    ctx.pwm_chips[spec.name] = chips
    ctx.pwm_channels[spec.service] = rewritten
    addresses = sorted({t["address"] for t in rewritten if str(t["address"]).startswith("pca9685:")})
    return MockDevice(spec.name, spec.mock, spec.service, ", ".join(addresses), {"channels": rewritten}, [],
                      f"{len(rewritten)} channel(s)")


def build_sysfs_pwm(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """Sysfs-shaped chip directories for every sysfs channel (``/sys/class/pwm/pwmchipN``) of a pwm_servo
    service: ``<dir>/pwmchipN``; a path outside /sys is already a mock chip and is used as it is."""
    channels = _pwm_channels(spec, ctx, "a sysfs PWM chip")
    rewritten, wanted, feeds = [], {}, []
    _check_drives(spec, [str(t.get("name", "")) for t in channels if isinstance(t, dict)])
    for index, table in enumerate(channels):
        address = str(table.get("address", "")).strip() if isinstance(table, dict) else ""
        if not address:
            raise spec.fail(f"channels[{index}] of service '{spec.service}' has no address")
        if not address.startswith("pca9685:"):
            path = ctx.path(os.path.basename(address.rstrip("/"))) if is_real_sysfs(address) else address
            channel = table.get("channel", 0)
            if isinstance(channel, bool) or not isinstance(channel, int) or channel < 0:
                raise spec.fail(f"channels[{index}].channel must be a channel number, got {channel!r}")
            wanted[path] = max(wanted.get(path, 0), channel + 1)
            table = {**table, "address": path}
            feeds.append((table, index, path, channel))
        rewritten.append(table)
    if not wanted:
        raise spec.fail(f"no channel of service '{spec.service}' has a sysfs PWM address "
                        "(/sys/class/pwm/pwmchipN); PCA9685 channels take mock = \"pca9685\"")
    npwm = spec.options.get("npwm")
    chips = [construct(replace(spec, options={k: v for k, v in spec.options.items() if k != "npwm"}), SysfsPwmChip,
                       path=path, npwm=max(int(npwm or 0), count), name=f"{spec.name}:{os.path.basename(path)}")
             for path, count in sorted(wanted.items())]
    by_path = {str(chip.path): chip for chip in chips}
    for table, index, path, channel in feeds:
        _pwm_feed(spec, ctx, table, index, lambda chip=by_path[path], n=channel: chip.pulse_width_us(n))
    ctx.pwm_chips.setdefault(spec.name, []).extend(chips)
    ctx.pwm_channels[spec.service] = rewritten
    return MockDevice(spec.name, spec.mock, spec.service, ", ".join(sorted(wanted)), {"channels": rewritten}, chips,
                      f"{sum(1 for t in rewritten if not str(t['address']).startswith('pca9685:'))} channel(s)")


def _model_input(spec: DeviceSpec, ctx: MockContext, actuator: str) -> str | None:
    """The vehicle input *actuator* drives: its ``drives`` entry, else an input of the same name, else None."""
    if actuator in spec.drives:
        return spec.drives[actuator]
    return actuator if actuator in MODEL_INPUTS[ctx.vehicle.model] else None


def _check_drives(spec: DeviceSpec, actuators: list[str]) -> None:
    unknown = sorted(set(spec.drives) - set(actuators))
    if unknown:
        raise spec.fail(f"drives names {', '.join(unknown)}, which service '{spec.service}' does not have; "
                        f"its outputs are {', '.join(actuators) or 'none'}")


def _pwm_feed(spec: DeviceSpec, ctx: MockContext, table: dict[str, Any], index: int, read: Any) -> None:
    """Log a PWM channel's output and, when it drives a model input, move the vehicle with it."""
    name = str(table.get("name", f"channel{index}"))
    drives = _model_input(spec, ctx, name)
    if drives is not None:
        ctx.feed(drives, device=spec.name)
    try:
        feed = PwmFeed(name, read, min_us=float(table.get("min_us", 1000.0)),
                       neutral_us=float(table.get("neutral_us", 1500.0)), max_us=float(table.get("max_us", 2000.0)),
                       reverse=bool(table.get("reverse", False)), drives=drives)
    except (TypeError, ValueError):
        raise spec.fail(f"channels[{index}]: min_us, neutral_us and max_us must be numbers") from None
    ctx.feeds.pwm.append(feed)


# ---- GPIO -----------------------------------------------------------------------------------
def parse_lines(text: str, spec: DeviceSpec) -> dict[str, int]:
    """``"throttle=5,mode=13"`` -> ``{"throttle": 5, "mode": 13}``."""
    result = {}
    for item in filter(None, (p.strip() for p in str(text).split(","))):
        name, sep, line = item.partition("=")
        if not sep or not line.strip().isdigit():
            raise spec.fail(f"service '{spec.service}': channels item {item!r} must be name=line")
        result[name.strip()] = int(line)
    return result


def build_rc_receiver(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """An RC receiver with real pulse trains on the service's chip, and the mux on its enable line."""
    chip = ctx.gpio_chip(str(spec.setting("chip")))
    lines = parse_lines(spec.setting("channels"), spec)
    mode_channel = str(spec.service_config.get("mode_channel", "mode"))
    rc = construct(spec, RcReceiverMock, chip, lines=lines, mode_channel=mode_channel)
    parts: list[Any] = [rc]
    detail = ", ".join(f"{n}={line}" for n, line in lines.items())
    enable = spec.service_config.get("enable_line")
    if enable is not None and int(enable) >= 0:
        select = int(spec.service_config.get("select_line", -1))
        mux = MuxMock(chip, rc, enable_line=int(enable), select_line=select if select >= 0 else None)
        parts.append(mux)
        ctx.attach_mux(rc, mux)
        detail += f"; mux enable line {enable}" + (f", select line {select}" if select >= 0 else "")
    ctx.rc_receivers[spec.name] = rc
    return MockDevice(spec.name, spec.mock, spec.service, chip.address, {"chip": chip.address}, parts, detail)


def build_gpio_chip(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """A bare mock chip for gpio_input/gpio_output services (drive inputs from Python)."""
    chip = ctx.gpio_chip(str(spec.setting("chip")))
    outputs = parse_lines(spec.service_config.get("outputs", ""), spec)
    _check_drives(spec, list(outputs))
    safe = parse_lines(spec.service_config.get("safe_levels", ""), spec)
    for name, line in outputs.items():
        drives = spec.drives.get(name)
        if drives is not None and drives != "enable":
            raise spec.fail(f"drives.{name} = {drives!r}: a GPIO output can only drive \"enable\" (a motor "
                            "contactor: propulsion only while the line is off its safe level)")
        if drives is not None:
            ctx.feed_enable(device=spec.name)
        ctx.feeds.gpio.append(GpioFeed(name, chip, line, safe_level=safe.get(name, 0), drives=drives))
    detail = ", ".join(f"{n}={line}" + (" (enable)" if spec.drives.get(n) else "") for n, line in outputs.items())
    return MockDevice(spec.name, spec.mock, spec.service, chip.address, {"chip": chip.address}, [], detail)


# ---- CAN ------------------------------------------------------------------------------------
def _sides(spec: DeviceSpec, names: list[str]) -> list[str]:
    if spec.sides:
        sides = list(spec.sides)
    else:
        sides = ["left" if "left" in n.lower() else "right" if "right" in n.lower() else "" for n in names]
    if len(sides) != len(names) or any(s not in ("left", "right") for s in sides):
        raise spec.fail(f"cannot tell which side each of {names} drives; add sides = [\"left\", \"right\"] "
                        "(one per controller) to the table")
    return sides


def build_can_motors(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """One ODrive or VESC node per controller of the service, on the simulated CAN bus."""
    interface, channel = str(spec.setting("interface")), str(spec.setting("channel"))
    port = ctx.can_port(f"{interface}:{channel}")
    names = list(spec.setting("actuators"))
    ids_key = "node_ids" if spec.mock == "odrive" else "controller_ids"
    ids = list(spec.setting(ids_key))
    directions = list(spec.service_config.get("directions", [1] * len(names)))
    radii = list(spec.service_config.get("wheel_radius_m", [0.1] * len(names)))
    sides = _sides(spec, names)
    bus = {"interface": "udp_multicast", "channel": CAN_GROUP, "bus_options": {"port": port}}
    nodes = []
    if spec.drives:
        raise spec.fail("drives is for PWM and GPIO outputs; a CAN motor drives the side sides = [...] gives it")
    for name, can_id, side, direction, radius in zip(names, ids, sides, directions, radii):
        ctx.feed(side, device=spec.name)
        if spec.mock == "odrive":
            # the driver limits its commands to max_turns_per_s; the node's own limit sits above it
            defaults = {"firmware": str(spec.service_config.get("firmware", "0.6")),
                        "vel_limit": float(spec.service_config.get("max_turns_per_s", 2.0)) * 1.25}
            node = construct(spec, OdriveCanNode, ctx.motor_input(name), side=side, node_id=int(can_id),
                             direction=int(direction),
                             wheel_radius_m=float(radius), **bus, **defaults)
        else:
            defaults = {"max_erpm": float(spec.service_config.get("max_erpm", 7000.0)),
                        "pole_pairs": int(spec.service_config.get("pole_pairs", 7)),
                        "gear_ratio": float(spec.service_config.get("gear_ratio", 1.0))}
            node = construct(spec, VescCanNode, ctx.motor_input(name), side=side, controller_id=int(can_id),
                             direction=int(direction), wheel_radius_m=float(radius), **bus, **defaults)
        nodes.append(node)
        ctx.can_nodes[name] = node
    overrides = {"interface": "udp_multicast", "channel": CAN_GROUP, "udp_port": port, "bitrate": 0}
    detail = ", ".join(f"{n} id {i} {s}" for n, i, s in zip(names, ids, sides))
    return MockDevice(spec.name, spec.mock, spec.service, f"udp_multicast:{CAN_GROUP} port {port}", overrides,
                      nodes, detail)


CATALOG: dict[str, tuple[Builder, str]] = {
    "nmea_gps": (build_serial, "NMEA 0183 GNSS receiver on a pty (port)"),
    "nmea_compass": (build_serial, "NMEA HDG/HDM/HDT compass on a pty (port)"),
    "os5000_compass": (build_serial, "OceanServer OS5000 compass on a pty (port)"),
    "mpu9250": (build_imu_chip, "MPU-9250 + AK8963 on the mock I2C bus (bus, address)"),
    "mpu6500": (build_imu_chip, "MPU-6500 on the mock I2C bus (bus, address)"),
    "mpu6050": (build_imu_chip, "MPU-6050 on the mock I2C bus (bus, address)"),
    "bno055": (build_imu_chip, "BNO055 on the mock I2C bus (bus, address)"),
    "pca9685": (build_pca9685, "PCA9685 PWM chips for the pca9685: channels of a pwm_servo service (channels)"),
    "sysfs_pwm": (build_sysfs_pwm, "sysfs-shaped PWM chip directories for the /sys/class/pwm channels of a "
                                   "pwm_servo service (channels)"),
    "rc_receiver": (build_rc_receiver, "RC receiver pulse trains and the RC mux on a mock GPIO chip "
                                       "(chip, channels, mode_channel, enable_line, select_line)"),
    "gpio_chip": (build_gpio_chip, "a mock GPIO chip (chip)"),
    "odrive": (build_can_motors, "ODrive CANSimple nodes, one per controller (interface, channel, actuators, "
                                 "node_ids, directions, wheel_radius_m, firmware)"),
    "vesc": (build_can_motors, "VESC nodes, one per controller (interface, channel, actuators, controller_ids, "
                               "directions, max_erpm)"),
}


def build(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """Build the mock of *spec* (not started); DeviceError names an unknown kind."""
    entry = CATALOG.get(spec.mock)
    if entry is None:
        raise spec.fail(f"unknown mock kind {spec.mock!r}; known: {', '.join(sorted(CATALOG))}")
    return entry[0](spec, ctx)
