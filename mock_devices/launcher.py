"""Start the mock devices a vehicle profile names, all around ONE simulated vehicle.

``u2sa mock`` and ``u2sa sim`` use :class:`MockLauncher`; tests and benchmarks use it as a
library::

    profile = load_profile("examples/ground_vehicle/vehicle.toml")
    mocks = MockLauncher(profile, device_dir=Path("/tmp/sim"), service_configs=configs)
    mocks.start()
    mocks.addresses       # {"gps": "mock+serial:///tmp/sim/gps?baud=9600", "wheels": "mock+can://udp_multicast/..."}
    mocks.set_mode_switch(True)   # the pilot flips the RC mode switch to autonomous
    mocks.stop()

The ``[simulation]`` table sets the vehicle model (see :class:`SimulationSettings`); the
origin is the profile's ``[vehicle].origin``. Each ``[devices.NAME]`` table is built by
:mod:`u2sa_hw.mocks.catalog`. *service_configs* maps a service name to its effective
config; without it the mocks read the profile's ``settings`` and the service's config
file (``u2sa sim`` passes the full config with the service kind's defaults).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.mocks.catalog import CATALOG, DeviceSpec, MockDevice, build
from u2sa_hw.mocks.sim_context import MODEL_INPUTS, DeviceError, MockContext
from u2sa_hw.mocks.vehicle_sim import MODELS, SimVehicle
from u2sa_hw.profile.vehicle import VehicleProfile

DEFAULT_CAN_UDP_PORT = 43113   # python-can's udp_multicast default


@dataclass(frozen=True)
class SimulationSettings:
    """The profile's ``[simulation]`` table (every key optional)."""

    model: str = "differential"      # differential, twin_thruster or ackermann
    track_width: float = 0.5         # m
    wheel_base: float = 0.6          # m (ackermann)
    max_speed: float = 2.0           # m/s
    start_north: float = 0.0         # m, from start = { north, east, heading_deg }
    start_east: float = 0.0
    start_heading_deg: float = 0.0   # clockwise from north
    rate_hz: float = 100.0           # simulation steps per second
    can_udp_port: int = DEFAULT_CAN_UDP_PORT   # UDP port of the first simulated CAN bus
    seed: int = 1                    # base of every mock's noise seed
    timeout_s: float = 120.0         # u2sa sim gives up after this long

    @classmethod
    def from_table(cls, table: Any, *, where: str) -> "SimulationSettings":
        """Parse and check ``[simulation]``; DeviceError names the key and the fix."""
        if table is None:
            return cls()
        if not isinstance(table, dict):
            raise DeviceError(f"{where}: [simulation] must be a table")
        table = dict(table)
        start = table.pop("start", {})
        if not isinstance(start, dict) or set(start) - {"north", "east", "heading_deg"}:
            raise DeviceError(f"{where} [simulation]: start must be a table like "
                              "{ north = 0.0, east = 0.0, heading_deg = 90.0 }")
        table.update({f"start_{k}": v for k, v in start.items()})
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise DeviceError(f"{where} [simulation]: unknown key(s) {', '.join(unknown)}; known: model, "
                              "track_width, wheel_base, max_speed, start, rate_hz, can_udp_port, seed, timeout_s")
        values: dict[str, Any] = {}
        for name, value in table.items():
            kind = type(getattr(cls, name))
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if not isinstance(value, kind) or isinstance(value, bool):
                raise DeviceError(f"{where} [simulation]: {name.replace('start_', 'start.')} must be "
                                  f"{kind.__name__}, got {value!r}")
            values[name] = value
        settings = cls(**values)
        if settings.model not in MODELS:
            raise DeviceError(f"{where} [simulation]: model must be one of {', '.join(MODELS)}, got {settings.model!r}")
        for name in ("track_width", "wheel_base", "max_speed", "rate_hz", "timeout_s"):
            if not getattr(settings, name) > 0:
                raise DeviceError(f"{where} [simulation]: {name} must be > 0")
        if not 1024 <= settings.can_udp_port <= 65000:
            raise DeviceError(f"{where} [simulation]: can_udp_port must be in 1024..65000")
        from u2sa_hw.profile.numbers import checked

        for name, value in values.items():   # every number's range (u2sa_hw/profile/numbers.py)
            if isinstance(value, (int, float)):
                checked(f"simulation.{name.replace('start_', 'start.')}", value, f"{where} [simulation]", DeviceError)
        return settings

    def make_vehicle(self, profile: VehicleProfile) -> SimVehicle:
        """The SimVehicle at the profile's origin and the configured start."""
        o = profile.origin
        return SimVehicle(origin_lat=o.lat, origin_lon=o.lon, origin_alt=o.alt, model=self.model,
                          track_width=self.track_width, wheel_base=self.wheel_base, max_speed=self.max_speed,
                          start_north=self.start_north, start_east=self.start_east,
                          start_yaw=math.radians(self.start_heading_deg))


def file_service_config(profile: VehicleProfile, service: str) -> dict[str, Any]:
    """The service's profile ``settings`` overlaid with its config file (no kind defaults)."""
    spec = profile.services.get(service)
    if spec is None:
        return {}
    values = dict(spec.settings)
    if spec.config_path.exists():
        try:
            values.update(tomllib.loads(spec.config_path.read_text()))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise DeviceError(f"{spec.config_path}: cannot read the config of service '{service}': {exc}") from None
    return values


def device_specs(profile: VehicleProfile, configs: Mapping[str, Mapping[str, Any]] | None = None) -> list[DeviceSpec]:
    """Every device of *profile* (the one resolver, ``u2sa_hw.profile.devices.resolve_devices``) that names a
    mock, checked."""
    from u2sa_hw.profile.devices import resolve_devices
    from u2sa_hw.profile.vehicle import ProfileError

    try:
        entries = resolve_devices(profile, configs=configs).entries
    except ProfileError as exc:
        raise DeviceError(str(exc)) from None
    specs = []
    for entry in entries.values():
        where = f"{profile.path} [devices.{entry.table or entry.name}]"
        if entry.mock is None:
            continue   # a device with no stand-in: its service cannot run in simulation
        if entry.mock not in CATALOG:
            raise DeviceError(f"{where}: mock = {entry.mock!r} is not a mock kind; known: {', '.join(sorted(CATALOG))}")
        if not entry.service:
            continue   # no service opens it: nothing to stand in for
        service = entry.service
        config = configs[service] if configs is not None and service in configs else file_service_config(profile,
                                                                                                           service)
        specs.append(DeviceSpec(name=entry.name, mock=entry.mock, service=service, service_config=config,
                                address=entry.address, options=dict(entry.options), sides=entry.sides,
                                drives=dict(entry.drives), where=where, kind=profile.services[service].kind))
    return specs


def hardware_mux(profile: VehicleProfile) -> dict[str, str]:
    """The profile's ``[safety] hardware_mux`` (actuator -> RC channel): the outputs wired through the RC mux."""
    try:
        from u2sa_hw.safety.config import load_safety
    except ImportError:   # the safety table's parser is not there yet: read the table as it is
        table = profile.raw.get("safety", {})
        mux = table.get("hardware_mux", {}) if isinstance(table, dict) else {}
        if not isinstance(mux, dict):
            raise DeviceError(f"{profile.path} [safety]: hardware_mux must be a table like "
                              "{ steering = \"steering\" } (actuator -> RC channel)") from None
        return {str(k): str(v) for k, v in mux.items()}
    return dict(load_safety(profile).hardware_mux)


def check_actuation(profile: VehicleProfile, context: MockContext) -> None:
    """DeviceError unless a device drives every input of the vehicle model and every muxed output is PWM."""
    where = str(profile.path or "the vehicle profile")
    model = context.vehicle.model
    missing = [name for name in MODEL_INPUTS[model] if name not in context.fed]
    if missing:
        fed = ", ".join(f"{i} by devices.{d}" for i, d in context.fed.items()) or "nothing"
        raise DeviceError(f"{where}: [simulation] model = '{model}' moves by {' and '.join(MODEL_INPUTS[model])}, "
                          f"but no device drives {' or '.join(missing)} (driven: {fed}); name a PWM channel "
                          f"'{missing[0]}', add drives = {{ <channel> = \"{missing[0]}\" }} to its [devices] table, "
                          "or give CAN motor mocks sides (docs/simulation.md)")
    pwm = {feed.actuator for feed in context.feeds.pwm}
    for actuator in context.hardware_mux:
        if actuator not in pwm:
            raise DeviceError(f"{where} [safety] hardware_mux: '{actuator}' is not a PWM output of any [devices] "
                              f"table (PWM outputs: {', '.join(sorted(pwm)) or 'none'}); a hardware RC mux switches "
                              "PWM lines only, so list only PWM outputs wired through it")
    if context.hardware_mux and not context.muxes:
        raise DeviceError(f"{where} [safety] hardware_mux lists outputs but no rc_receiver device has a mux "
                          "(the rc service needs an enable_line)")


class MockLauncher:
    """Builds, starts and stops every mock device of a profile around one SimVehicle."""

    def __init__(self, profile: VehicleProfile, *, device_dir: Path,
                 service_configs: Mapping[str, Mapping[str, Any]] | None = None,
                 can_udp_port: int | None = None, check_inputs: bool = False) -> None:
        where = str(profile.path or "the vehicle profile")
        self.profile = profile
        self.settings = SimulationSettings.from_table(profile.raw.get("simulation"), where=where)
        self.vehicle = self.settings.make_vehicle(profile)
        self.context = MockContext(vehicle=self.vehicle, device_dir=device_dir, seed=self.settings.seed,
                                   can_udp_port=can_udp_port or self.settings.can_udp_port,
                                   hardware_mux=hardware_mux(profile))
        self.devices: list[MockDevice] = []
        for spec in device_specs(profile, service_configs):
            self.devices.append(build(spec, self.context))
        if not self.devices:
            raise DeviceError(f"{where}: no [devices.NAME] table names a mock (e.g. mock = \"nmea_gps\"); "
                              "see docs/simulation.md")
        if check_inputs:
            check_actuation(profile, self.context)
        self._started: list[Any] = []

    @property
    def addresses(self) -> dict[str, str]:
        """Device name -> its mock address (what the simulation copy of the profile gives it)."""
        return {device.name: device.address for device in self.devices}

    @property
    def outputs(self) -> Any:
        """The OutputLog: every actuator output's changes as the devices saw them."""
        return self.context.outputs

    @property
    def actuated(self) -> Any:
        """The vehicle as the motor mocks drive it (route, hold)."""
        return self.context.actuated

    def device(self, name: str) -> MockDevice:
        """The built device *name*; KeyError lists them."""
        for device in self.devices:
            if device.name == name:
                return device
        raise KeyError(f"no mock device '{name}' (devices: {', '.join(d.name for d in self.devices)})")

    def start(self) -> None:
        """Start the vehicle, the shared buses and chips, then every device; all or nothing."""
        try:
            self.vehicle.start(rate_hz=self.settings.rate_hz)
            self.context.start_shared()
            for device in self.devices:
                for part in device.parts:
                    part.start()
                    self._started.append(part)
            self.context.start_routing()
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Stop every device, the buses and the vehicle (safe to call twice)."""
        for part in reversed(self._started):
            try:
                part.stop()
            except Exception:   # noqa: BLE001 - keep stopping the others
                pass
        self._started.clear()
        self.context.stop_shared()
        self.vehicle.stop()

    def set_mode_switch(self, autonomous: bool) -> None:
        """The pilot flips the RC mode switch on every RC receiver."""
        for rc in self.context.rc_receivers.values():
            rc.set_mode_switch(autonomous)

    def set_sticks(self, **positions: float) -> None:
        """The pilot moves sticks (RC channel name -> -1..1) on every RC receiver that has those channels."""
        for rc in self.context.rc_receivers.values():
            rc.set_sticks(**{k: v for k, v in positions.items() if k in rc.lines})

    def signal_loss(self, on: bool) -> None:
        """Every RC receiver stops (on) or resumes its pulses: the pilot's link lost and back."""
        for rc in self.context.rc_receivers.values():
            rc.signal_loss(on)

    def rc_stalls(self) -> list[tuple[int, int]]:
        """Every RC receiver mock's stalls, in time order: (their end, ns beyond a frame period), monotonic ns (see
        :attr:`u2sa_hw.mocks.rc_receiver.RcReceiverMock.stalls`)."""
        return sorted(s for rc in self.context.rc_receivers.values() for s in list(rc.stalls))

    def describe(self) -> list[str]:
        """One line per device: name, mock kind, address, what it stands in for."""
        width = max(len(d.name) for d in self.devices)
        return [f"{d.name:<{width}}  {d.mock:<14} {d.address}" + (f"  ({d.detail})" if d.detail else "")
                for d in self.devices]
