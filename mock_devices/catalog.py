"""Mock kinds a vehicle profile's ``[devices.NAME]`` tables can name, and how each is built.

A device table gives the device's real address, the mock kind that stands in for it and,
when it cannot be found from the services, the service that uses it::

    [devices.gps]
    address = "serial:///dev/u2sa/gps?baud=9600"
    mock = "nmea_gps"            # a kind below
    options = { rate_hz = 5 }    # the mock class's keyword options (lists become tuples)
    sides = ["left", "right"]    # CAN motor mocks only: which side of the vehicle each controller drives
    drives = { rudder = "steering" }   # PWM and GPIO outputs: actuator name -> the vehicle model input it moves

Each builder works from the device's real address (a :class:`~u2sa_hw.profile.devices.DeviceEntry`)
and returns the device's *mock address*, which is all the simulation changes in its copy of
the profile (docs/ports.md): ``serial:///dev/u2sa/gps`` -> ``mock+serial://<dir>/gps`` (a
pty), ``i2c://1/0x68`` -> ``mock+i2c://<dir>/i2c-1.sock/0x68`` (one mock bus per real bus,
shared by every chip on it), ``gpio://gpiochip0/...`` -> ``mock+gpio://<dir>/gpiochip0.sock/...``,
``can://socketcan/can0`` -> ``mock+can://udp_multicast/<group>?port=N`` (one UDP port per real
bus), ``pwm://pwmchip0/N`` -> ``mock+pwm://<dir>/pwmchip0/N`` (a sysfs-shaped directory),
``pca9685://1/0x40/N`` -> ``mock+pca9685://<dir>/i2c-1.sock/0x40/N``. An address that is
already a mock is used as it is.

The mock mirrors its service's wiring as the service's driver declares it (what only the
driver and the device know between them; :mod:`u2sa_hw.ports.declared`): the driver class,
found by the service's kind through the registry, names the mock kinds that stand in for its
device (``MOCK_KINDS``) and gives ``mock_wiring(service, device, config)`` in the mocks'
vocabulary (a CAN motor's controllers with their ids, directions and wheel radii, the RC
receiver's channel lines and mux lines, a PWM output's pulse range), so nothing here reads a
driver's setting names. Every actuator output is logged and moves the
vehicle through :mod:`u2sa_hw.mocks.actuation`: CAN motors by their side, PWM outputs named
like a model input (``steering``, ``throttle``, ``left``, ``right``) or listed in ``drives``,
GPIO outputs listed in ``drives`` (``enable``: a motor contactor).

The mock kinds are one table, :data:`u2sa_hw.registry.MOCK_DEVICES` (kind -> ``"module:Class"``,
the builder here that wires it, a description), imported only when a mock of the kind is built.
The builders hold no per-family branch: a class says what it needs (a serial mock its ``PROTOCOL``,
a CAN node ``wiring_options(wiring, node_id=)``), so a new serial or CAN motor mock is its module
and one table line (docs/adding-a-device.md); :func:`entry_problems` checks an entry against what
its builder needs (:data:`BUILDERS`, ``tests/test_mock_table.py``).
"""

from __future__ import annotations

import inspect
import os
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping, NamedTuple

from u2sa_hw.mocks.actuation import GpioFeed, PwmFeed
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Ak8963Chip
from u2sa_hw.mocks.rc_receiver import MuxMock
from u2sa_hw.mocks.sim_context import CAN_GROUP, MODEL_INPUTS, DeviceError, MockContext
from u2sa_hw.ports import declared
from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.registry import MOCK_DEVICES, resolve_mock


@dataclass(frozen=True)
class DeviceSpec:
    """One device (its real address and mock kind) with the kind and effective config of the service that uses it."""

    name: str
    mock: str
    service: str
    service_config: Mapping[str, Any]
    address: DeviceAddress
    kind: str = ""                         # the service's kind: its driver declares the wiring
    options: dict[str, Any] = field(default_factory=dict)
    sides: tuple[str, ...] = ()
    drives: dict[str, str] = field(default_factory=dict)
    where: str = ""

    def fail(self, text: str) -> DeviceError:
        """A DeviceError prefixed with where the table is."""
        return DeviceError(f"{self.where or 'devices.' + self.name}: {text}")

    def wiring(self) -> dict[str, Any]:
        """What the service's driver declares a mock of this device mirrors (``mock_wiring``); DeviceError
        when the mock kind is not one that stands in for the driver's device, or the driver refuses its config."""
        try:
            cls = declared.declared_class(self.kind)
        except LookupError as exc:
            raise self.fail(f"service '{self.service}': {exc}") from None
        kinds = declared.mock_kinds(cls)
        if self.mock not in kinds:
            stands = (f"its device's mock is {' or '.join(kinds)}" if kinds else "its driver declares no mock")
            fix = f" or mock = \"{kinds[0]}\"" if kinds else ""
            raise self.fail(f"mock {self.mock} does not stand in for service '{self.service}' ({self.kind}: {stands}); "
                            f"is it the right service for a {self.mock} mock? set service = \"...\" in the table{fix}")
        try:
            return declared.mock_wiring(cls, self.service, self.name, self.service_config)
        except ValueError as exc:   # the driver's ConfigError: names the setting and the fix
            raise self.fail(str(exc)) from None


@dataclass
class MockDevice:
    """A built mock: what it is, its mock address (where the driver finds it) and the parts to start."""

    name: str
    mock: str
    service: str
    address: str
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
    """A GPS or compass on a pty: ``<dir>/<basename of the real device path>``."""
    address = _need(spec, "serial")
    wiring = spec.wiring()
    cls = resolve_mock(spec.mock)
    expected, speaks = getattr(cls, "PROTOCOL", None), wiring.get("protocol")
    if expected and speaks is not None and speaks != expected:
        raise spec.fail(f"mock {spec.mock} speaks '{expected}' but service '{spec.service}' has "
                        f"{declared.source_of(wiring, 'protocol')} = {speaks!r}; make them agree")
    real = address.serial_path
    if address.mock:
        link = real
    else:
        base = os.path.basename(real.rstrip("/")) if not address.is_serial_url else ""
        link = ctx.path(base or spec.name)
    spec = _seeded(spec, ctx)
    device = construct(spec, cls, ctx.vehicle, link_path=link, name=spec.name)
    params = {k: v for k, v in address.params.items() if k not in ("usb", "serial")}
    mock = make_address("serial", link, params=params, mock=True, device=spec.name)
    return MockDevice(spec.name, spec.mock, spec.service, mock.url, [device], f"pty for {real}")


def _need(spec: DeviceSpec, *kinds: str) -> DeviceAddress:
    """The device's address, if it is of one of *kinds*; DeviceError says which the mock needs."""
    if spec.address.kind not in kinds:
        raise spec.fail(f"mock {spec.mock} stands in for a {' or '.join(kinds)} device, but the address is "
                        f"{spec.address.url}; pick the mock of that kind (u2sa mock --list-kinds)")
    return spec.address


# ---- I2C ------------------------------------------------------------------------------------
def build_imu_chip(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """A chip (an MPU-60x0/9250 (+ AK8963), a BNO055) on the mock bus standing in for the device's I2C bus; a
    class that takes a ``variant`` gets the mock kind (``mpu6500``) unless the options give one."""
    real = _need(spec, "i2c")
    spec.wiring()   # the mock kind stands in for the service's chip
    bus: MockI2cBus = ctx.i2c_bus(str(real.i2c_bus))
    address = real.chip_address
    spec = _seeded(spec, ctx)
    cls = resolve_mock(spec.mock)
    takes_variant = "variant" in inspect.signature(cls).parameters
    variant = {"variant": spec.options.get("variant", spec.mock)} if takes_variant else {}
    chip = construct(spec, cls, address=address, vehicle=ctx.vehicle, **variant)
    parts = [chip]
    if getattr(getattr(chip, "variant", None), "has_magnetometer", False):  # an MPU-9250's AK8963
        parts.append(Ak8963Chip(parent=chip, seed=int(spec.options["seed"])))
    for part in parts:
        ctx.add_chip(bus, part, device=spec.name)
    mock = make_address("i2c", bus.socket_path, (address,), mock=True, device=spec.name)
    return MockDevice(spec.name, spec.mock, spec.service, mock.url, [], f"chip 0x{address:02x} on {bus.address}")


# ---- PWM ------------------------------------------------------------------------------------
def _pwm_output(spec: DeviceSpec) -> dict[str, Any]:
    """The output this device is, as the servo driver declares it (its actuator and pulse range), with
    ``drives`` checked against the service's actuators."""
    wiring = spec.wiring()
    _check_drives(spec, [str(name) for name in wiring.get("actuators", ())])
    return wiring


def build_pca9685(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """The PCA9685 chip (one per bus and chip address, shared by its outputs) for one pwm_servo output."""
    real = _need(spec, "pca9685")
    table = _pwm_output(spec)
    bus = ctx.i2c_bus(str(real.i2c_bus))
    key = (bus.socket_path, real.chip_address)
    parts: list[Any] = []
    chip = ctx.pca9685_chips.get(key)
    if chip is None:   # outputs of one chip share it
        chip = ctx.pca9685_chips[key] = ctx.add_chip(bus, construct(spec, resolve_mock(spec.mock), address=real.chip_address),
                                                     device=spec.name)
    ctx.pwm_chips.setdefault(spec.name, []).append(chip)
    channel = real.pwm_channel
    _pwm_feed(spec, ctx, table, lambda chip=chip, n=channel: chip.pulse_width_us(n))
    mock = make_address("pca9685", bus.socket_path, (real.chip_address, channel), mock=True, device=spec.name)
    return MockDevice(spec.name, spec.mock, spec.service, mock.url, parts,
                      f"output {channel} of 0x{real.chip_address:02x} on {bus.address}")


def build_sysfs_pwm(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """A sysfs-shaped chip directory (``<dir>/pwmchipN``, shared by its outputs) for one pwm_servo output;
    a mock directory is used as it is."""
    real = _need(spec, "pwm")
    table = _pwm_output(spec)
    path = real.pwm_chip if real.mock else ctx.path(os.path.basename(real.pwm_chip.rstrip("/")))
    channel = real.pwm_channel
    parts: list[Any] = []
    chip = ctx.sysfs_chips.get(path)
    if chip is None:   # as many channels as its outputs use (or options.npwm)
        npwm = max(int(spec.options.get("npwm") or 0), channel + 1)
        options = {k: v for k, v in spec.options.items() if k != "npwm"}
        chip = ctx.sysfs_chips[path] = construct(replace(spec, options=options), resolve_mock(spec.mock), path=path,
                                                 npwm=npwm, name=f"{spec.name}:{os.path.basename(path)}")
        parts.append(chip)
    elif channel >= chip.npwm:   # built, not started yet: another output of the chip widens it
        chip.npwm = channel + 1
    ctx.pwm_chips.setdefault(spec.name, []).append(chip)
    _pwm_feed(spec, ctx, table, lambda chip=chip, n=channel: chip.pulse_width_us(n))
    mock = make_address("pwm", path, (channel,), mock=True, device=spec.name)
    return MockDevice(spec.name, spec.mock, spec.service, mock.url, parts, f"channel {channel} of {path}")


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


def _pwm_feed(spec: DeviceSpec, ctx: MockContext, table: dict[str, Any], read: Any) -> None:
    """Log a PWM output (*table*: its declared actuator and pulse range) and, when it drives a model input,
    move the vehicle with it."""
    name = str(table.get("actuator", spec.name))
    drives = _model_input(spec, ctx, name)
    if drives is not None:
        ctx.feed(drives, device=spec.name)
    try:
        feed = PwmFeed(name, read, min_us=float(table.get("min_us", 1000.0)),
                       neutral_us=float(table.get("neutral_us", 1500.0)), max_us=float(table.get("max_us", 2000.0)),
                       reverse=bool(table.get("reverse", False)), drives=drives)
    except (TypeError, ValueError):
        raise spec.fail(f"channel '{name}': min_us, neutral_us and max_us must be numbers") from None
    ctx.feeds.pwm.append(feed)


# ---- GPIO -----------------------------------------------------------------------------------
def _gpio_mock(spec: DeviceSpec, chip: Any, real: DeviceAddress) -> str:
    return make_address("gpio", chip.socket_path, real.lines, mock=True, device=spec.name).url


def build_rc_receiver(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """An RC receiver with real pulse trains on the device's chip, and the mux on its enable line."""
    real = _need(spec, "gpio")
    wiring = spec.wiring()
    chip = ctx.gpio_chip(real.gpio_chip)
    lines = {str(n): int(line) for n, line in dict(wiring.get("lines", {})).items()}
    rc = construct(spec, resolve_mock(spec.mock), chip, lines=lines, mode_channel=str(wiring.get("mode_channel", "mode")))
    parts: list[Any] = [rc]
    detail = ", ".join(f"{n}={line}" for n, line in lines.items())
    enable, select = wiring.get("enable_line"), wiring.get("select_line")
    if enable is not None:
        mux = MuxMock(chip, rc, enable_line=int(enable), select_line=None if select is None else int(select))
        parts.append(mux)
        ctx.attach_mux(rc, mux)
        detail += f"; mux enable line {enable}" + (f", select line {select}" if select is not None else "")
    ctx.rc_receivers[spec.name] = rc
    return MockDevice(spec.name, spec.mock, spec.service, _gpio_mock(spec, chip, real), parts, detail)


def build_gpio_chip(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """A bare mock chip for gpio_input/gpio_output services (drive inputs from Python)."""
    real = _need(spec, "gpio")
    wiring = spec.wiring()
    chip = ctx.gpio_chip(real.gpio_chip)
    outputs = {str(n): int(line) for n, line in dict(wiring.get("outputs", {})).items()}
    _check_drives(spec, list(outputs))
    safe = dict(wiring.get("safe_levels", {}))
    for name, line in outputs.items():
        drives = spec.drives.get(name)
        if drives is not None and drives != "enable":
            raise spec.fail(f"drives.{name} = {drives!r}: a GPIO output can only drive \"enable\" (a motor "
                            "contactor: propulsion only while the line is off its safe level)")
        if drives is not None:
            ctx.feed_enable(device=spec.name)
        ctx.feeds.gpio.append(GpioFeed(name, chip, line, safe_level=safe.get(name, 0), drives=drives))
    detail = ", ".join(f"{n}={line}" + (" (enable)" if spec.drives.get(n) else "") for n, line in outputs.items())
    return MockDevice(spec.name, spec.mock, spec.service, _gpio_mock(spec, chip, real), [], detail)


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
    """One node of the mock kind's class per controller of the service, on the simulated bus of the device's CAN
    bus; the class turns the driver's declared wiring into its own keywords (``wiring_options``: an ODrive's
    firmware and speed limit, a VESC's ERPM scale)."""
    real = _need(spec, "can")
    wiring = spec.wiring()
    cls = resolve_mock(spec.mock)
    port = ctx.can_port(f"{real.can_interface}:{real.can_channel}")
    names = [str(n) for n in wiring["actuators"]]
    ids = list(wiring["ids"])
    directions = list(wiring.get("directions", [1] * len(names)))
    radii = list(wiring.get("wheel_radius_m", [0.1] * len(names)))
    sides = _sides(spec, names)
    bus = {"interface": "udp_multicast", "channel": CAN_GROUP, "bus_options": {"port": port}}
    nodes = []
    if spec.drives:
        raise spec.fail("drives is for PWM and GPIO outputs; a CAN motor drives the side sides = [...] gives it")
    for name, can_id, side, direction, radius in zip(names, ids, sides, directions, radii):
        ctx.feed(side, device=spec.name)
        node = construct(spec, cls, ctx.motor_input(name), side=side, direction=int(direction),
                         wheel_radius_m=float(radius), **bus, **cls.wiring_options(wiring, node_id=int(can_id)))
        nodes.append(node)
        ctx.can_nodes[name] = node
    mock = make_address("can", CAN_GROUP, params={"port": port}, mock=True, backend="udp_multicast", device=spec.name)
    detail = ", ".join(f"{n} id {i} {s}" for n, i, s in zip(names, ids, sides))
    return MockDevice(spec.name, spec.mock, spec.service, mock.url, nodes, detail)


class MockBuilder(NamedTuple):
    """How the catalog builds one family of mocks, and what a mock class must take to be built that way."""

    build: Builder
    needs: tuple[str, ...]   # keyword parameters (or class attributes) the class must have


BUILDERS: dict[str, MockBuilder] = {
    "serial": MockBuilder(build_serial, ("link_path", "name", "seed")),
    "can_motor": MockBuilder(build_can_motors, ("side", "direction", "wheel_radius_m", "interface", "channel",
                                                "bus_options", "wiring_options")),
    "i2c_chip": MockBuilder(build_imu_chip, ("address", "vehicle", "seed")),
    "pca9685": MockBuilder(build_pca9685, ("address",)),
    "sysfs_pwm": MockBuilder(build_sysfs_pwm, ("path", "npwm", "name")),
    "rc_receiver": MockBuilder(build_rc_receiver, ("lines", "mode_channel")),
    "gpio_chip": MockBuilder(build_gpio_chip, ()),
}
"""Builder name (a :data:`u2sa_hw.registry.MOCK_DEVICES` entry's ``build``) -> the builder."""


def _takes(cls: type, name: str) -> bool:
    """True when *cls* takes keyword *name* or has it as an attribute."""
    return name in inspect.signature(cls).parameters or hasattr(cls, name)


def entry_problems(kind: str) -> list[str]:
    """What is wrong with mock kind *kind*'s table entry: an unknown builder, a target that is not a class, a
    class without what its builder needs, no description (empty when it is fine; an ImportError surfaces)."""
    entry = MOCK_DEVICES[kind]
    builder = BUILDERS.get(entry.build)
    if builder is None:
        return [f"{kind}: build {entry.build!r} is not a builder ({', '.join(BUILDERS)})"]
    cls = resolve_mock(kind)
    if not isinstance(cls, type):
        return [f"{kind}: {entry.target} is not a class"]
    problems = [f"{kind}: {cls.__name__} lacks {need!r}, which the {entry.build} builder needs"
                for need in builder.needs if not _takes(cls, need)]
    return problems + ([f"{kind}: no description"] if not entry.what.strip() else [])


CATALOG: dict[str, tuple[Builder, str]] = {kind: (BUILDERS[entry.build].build, entry.what)
                                           for kind, entry in MOCK_DEVICES.items()}
"""Mock kind -> (builder, description), read off :data:`u2sa_hw.registry.MOCK_DEVICES`."""


def build(spec: DeviceSpec, ctx: MockContext) -> MockDevice:
    """Build the mock of *spec* (not started); DeviceError names an unknown kind."""
    entry = CATALOG.get(spec.mock)
    if entry is None:
        raise spec.fail(f"unknown mock kind {spec.mock!r}; known: {', '.join(sorted(CATALOG))}")
    return entry[0](spec, ctx)
