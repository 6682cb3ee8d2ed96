"""What the mocks of one simulation share: the vehicle, the buses, the device directory, seeds.

:class:`MockContext` hands out one mock I2C bus per real bus, one mock GPIO chip per real
chip and one UDP port per real CAN bus, so devices on the same real bus meet on the same
mock one. :class:`RoutedVehicle` is the vehicle as the actuator mocks see it: behind the
RC multiplexer (when the mux selects the pilot, the pilot's sticks drive the vehicle and
the motor controllers' commands wait) and optionally *held* (motors turn, the vehicle
does not move: a vehicle on blocks, for bench measurements).
"""

from __future__ import annotations

import math
import os
import tempfile
import threading
from pathlib import Path
from typing import Any

from mock_devices.gpio_chip import MockGpioChip
from mock_devices.i2c_bus import MockI2cBus
from mock_devices.rc_receiver import MuxMock, RcFrame, RcReceiverMock
from mock_devices.vehicle_sim import ACKERMANN_MAX_STEER_RAD, SimVehicle

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
    """The SimVehicle behind the RC mux: autonomous commands pass only while the mux selects them."""

    _INPUTS = {"set_wheel_speed": "differential", "set_thrust": "twin_thruster",
               "set_steering": "ackermann", "set_throttle": "ackermann"}

    def __init__(self, vehicle: SimVehicle) -> None:
        self.vehicle = vehicle
        self._lock = threading.Lock()
        self._auto: dict[tuple[str, ...], float] = {}
        self._source = "autonomous"
        self._pilot = (0.0, 0.0)   # throttle, steering, -1..1
        self._held = False

    def __getattr__(self, name: str) -> Any:   # snapshot(), model, max_speed, ... of the real vehicle
        return getattr(self.vehicle, name)

    # -- what the motor mocks call -----------------------------------------------------------
    def set_wheel_speed(self, side: str, speed_mps: float) -> None:
        """A wheel controller's output (m/s surface speed)."""
        self._command("set_wheel_speed", side, value=speed_mps)

    def set_thrust(self, side: str, fraction: float) -> None:
        """A thruster controller's output (-1..1)."""
        self._command("set_thrust", side, value=fraction)

    def set_steering(self, angle_rad: float) -> None:
        """A steering servo's output (rad)."""
        self._command("set_steering", value=angle_rad)

    def set_throttle(self, fraction: float) -> None:
        """A throttle output (-1..1)."""
        self._command("set_throttle", value=fraction)

    def _command(self, method: str, *key: str, value: float) -> None:
        if self.vehicle.model != self._INPUTS[method]:
            getattr(self.vehicle, method)(*key, value)   # raises the vehicle's own error naming the model
        with self._lock:
            self._auto[(method, *key)] = value
            if self._source == "autonomous" and not self._held:
                getattr(self.vehicle, method)(*key, value)

    # -- the mux, the pilot and the bench ----------------------------------------------------
    @property
    def source(self) -> str:
        """Who drives: "autonomous" (the motor controllers) or "rc" (the pilot's sticks)."""
        return self._source

    def route(self, source: str, *, throttle: float | None = None, steering: float | None = None) -> None:
        """Select who drives, and update the pilot's sticks (-1..1)."""
        with self._lock:
            pilot = (self._pilot[0] if throttle is None else throttle, self._pilot[1] if steering is None else steering)
            changed = source != self._source or (source == "rc" and pilot != self._pilot)
            self._source, self._pilot = source, pilot
            if changed:
                self._apply()

    def hold(self, on: bool) -> None:
        """Hold the vehicle still whatever the motors are told (wheels in the air)."""
        with self._lock:
            self._held = bool(on)
            self._apply()

    def _apply(self) -> None:
        v, model = self.vehicle, self.vehicle.model
        if self._held or self._source == "rc":
            thr, steer = (0.0, 0.0) if self._held else self._pilot
            if model == "differential":
                v.set_wheel_speed("left", v.max_speed * max(-1.0, min(1.0, thr + steer)))
                v.set_wheel_speed("right", v.max_speed * max(-1.0, min(1.0, thr - steer)))
            elif model == "twin_thruster":
                v.set_thrust("left", max(-1.0, min(1.0, thr + steer)))
                v.set_thrust("right", max(-1.0, min(1.0, thr - steer)))
            else:
                v.set_throttle(thr)
                v.set_steering(steer * ACKERMANN_MAX_STEER_RAD)
            return
        for (method, *key), value in self._auto.items():
            getattr(v, method)(*key, value)
        for method, sides in (("set_wheel_speed", ("left", "right")), ("set_thrust", ("left", "right"))):
            if self._INPUTS[method] == model:
                for side in sides:
                    if (method, side) not in self._auto:
                        getattr(v, method)(side, 0.0)


def _stick(pulses: dict[str, float], name: str) -> float:
    us = pulses.get(name)
    return 0.0 if us is None or not math.isfinite(us) else max(-1.0, min(1.0, (us - 1500.0) / 500.0))


class MockContext:
    """Shared parts of one simulation; mock builders ask it for buses, chips and paths."""

    def __init__(self, *, vehicle: SimVehicle, device_dir: Path, can_udp_port: int, seed: int = 0) -> None:
        self.vehicle = vehicle
        self.actuated = RoutedVehicle(vehicle)
        self.device_dir = Path(device_dir)
        self.can_udp_port = int(can_udp_port)
        self.i2c_buses: dict[str, MockI2cBus] = {}
        self.gpio_chips: dict[str, MockGpioChip] = {}
        self.can_ports: dict[str, int] = {}
        self.rc_receivers: dict[str, RcReceiverMock] = {}
        self.muxes: list[tuple[RcReceiverMock, MuxMock]] = []
        self.can_nodes: dict[str, Any] = {}
        self.pwm_chips: dict[str, list[Any]] = {}
        self.pwm_channels: dict[str, list[dict[str, Any]]] = {}   # service -> its channels as rewritten so far
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
        """Route the actuated vehicle by *mux*'s choice, with *rc*'s sticks on the pilot's side."""
        self.muxes.append((rc, mux))
        self.actuated.route("rc")   # a mux powers up on the pilot's side

    def start_routing(self) -> None:
        """Follow each mux (after the muxes started, so their own listeners run first)."""
        for rc, mux in self.muxes:
            def on_frame(frame: RcFrame, mux: MuxMock = mux) -> None:
                pulses = frame.pulses_us or {}   # no signal: the sticks are let go
                self.actuated.route(mux.selected, throttle=_stick(pulses, "throttle"),
                                    steering=_stick(pulses, "steering"))

            rc.add_frame_listener(on_frame)
            rc.chip.on_output(lambda _line, _value, _t, mux=mux: self.actuated.route(mux.selected))

    def start_shared(self) -> None:
        """Start the buses and chips (before the devices, so drivers find them)."""
        self.device_dir.mkdir(parents=True, exist_ok=True)
        for bus in self.i2c_buses.values():
            bus.start()
        for chip in self.gpio_chips.values():
            chip.start()

    def stop_shared(self) -> None:
        """Stop the buses and chips (removes their sockets)."""
        for bus in self.i2c_buses.values():
            bus.stop()
        for chip in self.gpio_chips.values():
            chip.stop()
