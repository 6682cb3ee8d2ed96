"""What the mocks of one simulation share: the vehicle, the buses, the device directory, seeds.

:class:`MockContext` hands out one mock I2C bus per real bus, one mock GPIO chip per real
chip and one UDP port per real CAN bus, so devices on the same real bus meet on the same
mock one. :class:`RoutedVehicle` is the vehicle as the actuator outputs drive it (each model
input by name), optionally *held* (motors turn, the vehicle does not move: a vehicle on
blocks, for bench measurements). The context also keeps the :class:`OutputLog` of every
actuator output and the PWM/GPIO feeds (:mod:`u2sa_hw.mocks.actuation`).
"""

from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path
from typing import Any

from u2sa_hw.mocks.actuation import Feeds, MotorInput, OutputLog, OutputPoller
from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.rc_receiver import MuxMock, RcReceiverMock
from u2sa_hw.mocks.vehicle_sim import ACKERMANN_MAX_STEER_RAD, SimVehicle

MODEL_INPUTS = {"differential": ("left", "right"), "twin_thruster": ("left", "right"),
                "ackermann": ("steering", "throttle")}

CAN_GROUP = "239.74.163.2"   # python-can's default IPv4 group for udp_multicast
MAX_SOCKET_PATH = 100        # sun_path holds 108 bytes; keep a margin


class DeviceError(ValueError):
    """A ``[devices.NAME]`` table cannot be simulated; the message names the table and the fix."""


def device_dir_for(preferred: Path) -> Path:
    """*preferred* (created), or a fresh short directory in /tmp when Unix socket paths there would be too long."""
    if len(str(preferred.resolve() / "gpiochip0.sock")) <= MAX_SOCKET_PATH:
        preferred.mkdir(parents=True, exist_ok=True)
        return preferred.resolve()
    return Path(tempfile.mkdtemp(prefix="u2sa-sim-"))


def _mock_path(address: str) -> str | None:
    return address[len("mock:"):] if address.startswith("mock:") else None


class RoutedVehicle:
    """The SimVehicle as the actuator outputs drive it: each model input by name, optionally *held*.

    Inputs are ``left``/``right`` (differential: wheel surface speed in m/s; twin_thruster:
    thrust -1..1) and ``steering``/``throttle`` (ackermann). CAN motor nodes set them through
    :class:`u2sa_hw.mocks.actuation.MotorInput`, PWM outputs through the output poller
    (``set_fraction``). No RC mux sits here: the simulated mux switches only the PWM outputs
    wired through it (:class:`u2sa_hw.mocks.actuation.PwmFeed`). A GPIO output that *drives*
    ``enable`` (a motor contactor) cuts the propulsion while at its safe level.
    """

    def __init__(self, vehicle: SimVehicle) -> None:
        self.vehicle = vehicle
        self._lock = threading.Lock()
        self._inputs: dict[str, float] = {}
        self._held = False
        self._enabled = True

    def __getattr__(self, name: str) -> Any:   # snapshot(), model, max_speed, ... of the real vehicle
        return getattr(self.vehicle, name)

    # -- what the actuator mocks call ----------------------------------------------------------
    def set_input(self, name: str, value: float) -> None:
        """Set model input *name* in its own unit (see the class docstring)."""
        if name not in MODEL_INPUTS[self.vehicle.model]:
            raise ValueError(f"SimVehicle: a {self.vehicle.model} vehicle has no input {name!r}; its inputs are "
                             f"{', '.join(MODEL_INPUTS[self.vehicle.model])}")
        with self._lock:
            self._inputs[name] = float(value)
            self._apply()

    def set_fraction(self, name: str, fraction: float) -> None:
        """Set model input *name* from a -1..1 fraction of full scale (what a PWM output gives)."""
        f = max(-1.0, min(1.0, fraction))
        model = self.vehicle.model
        scale = {"differential": self.vehicle.max_speed, "twin_thruster": 1.0}.get(model, 1.0)
        self.set_input(name, f * (ACKERMANN_MAX_STEER_RAD if name == "steering" else scale))

    def set_wheel_speed(self, side: str, speed_mps: float) -> None:
        """A wheel's output (m/s surface speed)."""
        self.set_input(side, speed_mps)

    def set_thrust(self, side: str, fraction: float) -> None:
        """A thruster's output (-1..1)."""
        self.set_input(side, fraction)

    # -- the bench and the contactor -----------------------------------------------------------
    def hold(self, on: bool) -> None:
        """Hold the vehicle still whatever the motors are told (wheels in the air)."""
        with self._lock:
            self._held = bool(on)
            self._apply()

    def enable(self, on: bool) -> None:
        """A motor contactor on a GPIO output: propulsion only while on."""
        with self._lock:
            self._enabled = bool(on)
            self._apply()

    def inputs(self) -> dict[str, float]:
        """The inputs last set, by name."""
        with self._lock:
            return dict(self._inputs)

    def _apply(self) -> None:
        v, model = self.vehicle, self.vehicle.model
        still = self._held or not self._enabled
        get = self._inputs.get
        if model == "ackermann":
            v.set_steering(0.0 if self._held else get("steering", 0.0))
            v.set_throttle(0.0 if still else get("throttle", 0.0))
            return
        setter = v.set_wheel_speed if model == "differential" else v.set_thrust
        for side in ("left", "right"):
            setter(side, 0.0 if still else get(side, 0.0))


class MockContext:
    """Shared parts of one simulation; mock builders ask it for buses, chips and paths."""

    def __init__(self, *, vehicle: SimVehicle, device_dir: Path, can_udp_port: int, seed: int = 0,
                 hardware_mux: dict[str, str] | None = None) -> None:
        self.vehicle = vehicle
        self.actuated = RoutedVehicle(vehicle)
        self.hardware_mux = dict(hardware_mux or {})   # actuator -> RC channel, [safety] hardware_mux
        self.outputs = OutputLog()
        self.feeds = Feeds()
        self.fed: dict[str, str] = {}   # model input -> the device table that drives it
        self._poller: OutputPoller | None = None
        self.device_dir = Path(device_dir)
        self.can_udp_port = int(can_udp_port)
        self.i2c_buses: dict[str, MockI2cBus] = {}
        self.gpio_chips: dict[str, MockGpioChip] = {}
        self.can_ports: dict[str, int] = {}
        self.rc_receivers: dict[str, RcReceiverMock] = {}
        self.muxes: list[tuple[RcReceiverMock, MuxMock]] = []
        self.can_nodes: dict[str, Any] = {}
        self.pwm_chips: dict[str, list[Any]] = {}   # device -> the mock PWM chip(s) its output is on
        self.pca9685_chips: dict[tuple[str, int], Any] = {}   # (bus socket, chip address) -> the chip model
        self.sysfs_chips: dict[str, Any] = {}   # directory -> the sysfs-shaped chip
        self._chip_owner: dict[tuple[str, int], str] = {}
        self._seed = int(seed)

    def path(self, name: str) -> str:
        """A path for a device node (pty link, socket) in the device directory."""
        return str(self.device_dir / name)

    def next_seed(self) -> int:
        """A fresh noise seed for the next device (reproducible runs)."""
        self._seed += 1
        return self._seed

    def i2c_bus(self, real: str) -> MockI2cBus:
        """The mock bus standing in for I2C bus *real* ("1", "/dev/i2c-1" or an existing "mock:<path>")."""
        real = real.strip()
        path = _mock_path(real) or self.path(f"i2c-{real.removeprefix('/dev/i2c-')}.sock")
        if path not in self.i2c_buses:
            self.i2c_buses[path] = MockI2cBus(socket_path=path)
        return self.i2c_buses[path]

    def add_chip(self, bus: MockI2cBus, chip: Any, *, device: str) -> Any:
        """Put *chip* on *bus*; DeviceError when two devices claim one address."""
        key = (bus.socket_path, chip.address)
        if key in self._chip_owner:
            raise DeviceError(f"devices.{device}: I2C address 0x{chip.address:02x} on {bus.address} is already "
                              f"taken by devices.{self._chip_owner[key]}; give one of the services another address")
        self._chip_owner[key] = device
        return bus.add(chip)

    def gpio_chip(self, real: str) -> MockGpioChip:
        """The mock chip standing in for GPIO chip *real* ("/dev/gpiochip0" or "mock:<path>")."""
        real = real.strip()
        if not real:
            raise DeviceError("a GPIO service has an empty 'chip'; set the real chip (e.g. /dev/gpiochip0)")
        path = _mock_path(real) or self.path(f"{os.path.basename(real)}.sock")
        if path not in self.gpio_chips:
            self.gpio_chips[path] = MockGpioChip(socket_path=path)
        return self.gpio_chips[path]

    def can_port(self, real: str) -> int:
        """The UDP port of the simulated bus standing in for CAN bus *real* ("socketcan:can0")."""
        if real not in self.can_ports:
            self.can_ports[real] = self.can_udp_port + len(self.can_ports)
        return self.can_ports[real]

    def attach_mux(self, rc: RcReceiverMock, mux: MuxMock) -> None:
        """Note *mux*: the PWM outputs of ``hardware_mux`` pass through it."""
        self.muxes.append((rc, mux))

    def motor_input(self, actuator: str) -> MotorInput:
        """What a CAN motor node driving *actuator* is given as its vehicle (logs its setpoints)."""
        return MotorInput(self.actuated, actuator=actuator, log=self.outputs)

    def feed(self, model_input: str, *, device: str) -> None:
        """Note that *device* drives *model_input*; DeviceError when another device already does."""
        model = self.vehicle.model
        if model_input not in MODEL_INPUTS[model]:
            raise DeviceError(f"devices.{device}: drives {model_input!r}, which a {model} vehicle does not have; "
                              f"its inputs are {', '.join(MODEL_INPUTS[model])} (or 'enable' for a GPIO output)")
        if model_input in self.fed and self.fed[model_input] != device:
            raise DeviceError(f"devices.{device}: {model_input!r} is already driven by "
                              f"devices.{self.fed[model_input]}; "
                              "one output per model input")
        self.fed[model_input] = device

    def feed_enable(self, *, device: str) -> None:
        """Note that a GPIO output of *device* is the motor contactor: propulsion off until it is set."""
        if "enable" in self.fed and self.fed["enable"] != device:
            raise DeviceError(f"devices.{device}: 'enable' is already driven by devices.{self.fed['enable']}")
        self.fed["enable"] = device
        self.actuated.enable(False)

    def start_routing(self) -> None:
        """Wire the muxed PWM outputs to their mux and start sampling the outputs."""
        mux = self.muxes[0][1] if self.muxes else None
        for feed in self.feeds.pwm:
            feed.rc_channel = self.hardware_mux.get(feed.actuator)
            feed.mux = mux
        self._poller = OutputPoller(self.feeds, routed=self.actuated, log=self.outputs).start()

    def start_shared(self) -> None:
        """Start the buses and chips (before the devices, so drivers find them)."""
        self.device_dir.mkdir(parents=True, exist_ok=True)
        for bus in self.i2c_buses.values():
            bus.start()
        for chip in self.gpio_chips.values():
            chip.start()

    def stop_shared(self) -> None:
        """Stop the output sampling, the buses and chips (removes their sockets)."""
        if self._poller is not None:
            self._poller.stop()
            self._poller = None
        for bus in self.i2c_buses.values():
            bus.stop()
        for chip in self.gpio_chips.values():
            chip.stop()
