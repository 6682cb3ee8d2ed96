"""Servos and ESCs on PWM outputs (Linux sysfs PWM or a PCA9685 on I2C) as one Actuator.

One service drives several channels; each channel is an actuator name that Percentage
Commands address. The channels are the service's ``channels`` config field, a list of
tables (in the vehicle profile's ``settings`` or the service's own TOML file, so they are
enumerated and changed over the bus like every other field; a change applies at the
next start)::

    channels = [
      { name = "rudder", min_us = 1100, max_us = 1900 },            # device "rudder"
      { name = "throttle", device = "esc", reverse = true, slew_percent_per_s = 50 },
    ]

with each channel's output a device of the profile (``device``, default the channel's name)::

    [devices.rudder]
    address = "pca9685://1/0x40/0"      # I2C adapter 1, chip 0x40, output 0
    [devices.esc]
    address = "pwm://pwmchip0/1"        # /sys/class/pwm/pwmchip0, channel 1

Keys: ``name`` (required), ``device``; ``min_us`` 1000, ``neutral_us`` 1500, ``max_us``
2000, ``reverse`` false, ``frame_hz`` 50, ``slew_percent_per_s`` 0 (no limit) (optional).
The old profile form's ``address`` and ``channel`` keys are errors that name the device to
write instead.

-100..100 % maps piecewise linearly: 0 % is ``neutral_us``, +100 % ``max_us``, -100 %
``min_us`` (reversed with ``reverse``), so an ESC with an off-centre neutral still stops
at 0 %. With a slew limit the output moves toward the command by at most that many
percent per second, stepped ``update_hz`` times a second. Neutral is immediate, never
slewed: on start, on stop and kill, on a failsafe and when commands stop arriving for
``command_timeout_s``. After the final neutral the outputs keep producing the neutral
pulse (an ESC stays armed at stop, a servo holds centre) unless ``release_on_exit``.

A channel whose chip goes away is reopened with backoff and set to the output it should
have; the others keep working (each output holds a
:class:`~u2sa_hw.ports.device_link.DeviceLink`). With ``record_raw`` each channel's writes
are published as ``RawPwmWrite`` on ``RAW.<device>``.
"""

from __future__ import annotations

import logging
import threading
import time
import typing
from dataclasses import dataclass
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import Actuator
from u2sa_hw.config.fields import ConfigError, field
from u2sa_hw.config.keys import old_form_fix
from u2sa_hw.ports.address import AddressError, DeviceAddress
from u2sa_hw.ports.declared import DeviceDeclarations
from u2sa_hw.ports.device_link import DeviceLink
from u2sa_hw.ports.errors import PortError, PortUnavailable
from u2sa_hw.ports.pwm.port import PwmChannel

log = logging.getLogger(__name__)
OLD_FORM_KEYS = ("address", "channel")     # a channel table's keys of the old profile form
OLD_FORM_EXAMPLE = "pca9685://1/0x40/0"   # a channel's device address, for the old form's error


@dataclass(frozen=True)
class ServoChannelSpec:
    """One output: its actuator name, its device, pulse limits (µs) and behaviour."""

    name: str
    device: str = ""
    min_us: float = 1000.0
    neutral_us: float = 1500.0
    max_us: float = 2000.0
    reverse: bool = False
    frame_hz: float = 50.0
    slew_percent_per_s: float = 0.0

    @property
    def device_name(self) -> str:
        """The output's device: ``device``, else the channel's name."""
        return self.device or self.name

    @property
    def period_ns(self) -> int:
        """The PWM frame period."""
        return round(1e9 / self.frame_hz)

    def pulse_us(self, percent: float) -> float:
        """The pulse for *percent* (-100..100), piecewise linear through neutral."""
        p = max(-100.0, min(100.0, -percent if self.reverse else percent)) / 100.0
        span = (self.max_us - self.neutral_us) if p >= 0 else (self.neutral_us - self.min_us)
        return self.neutral_us + p * span

    @classmethod
    def from_table(cls, table: Any, *, where: str) -> "ServoChannelSpec":
        """Build and check a spec from one config table; ConfigError names *where*, the key and the fix."""
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: must be a table like {{ name = \"rudder\", device = \"rudder\" }}, "
                              f"got {table!r}")
        known = typing.get_type_hints(cls)
        for key in (k for k in OLD_FORM_KEYS if k in table):
            device = str(table.get("device") or table.get("name") or "NAME")
            raise ConfigError(f"{where}: '{key}' is the old form: " + str(old_form_fix(
                key, device=device, example=OLD_FORM_EXAMPLE, name_it="in the channel's table")))
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(known)})")
        missing = [k for k in ("name",) if k not in table]
        if missing:
            raise ConfigError(f"{where}: missing {', '.join(missing)}")
        values: dict[str, Any] = {}
        for key, value in table.items():
            kind = known[key]
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise ConfigError(f"{where}: '{key}' must be {kind.__name__}, got {type(value).__name__} {value!r}")
            values[key] = value
        spec = cls(**values)
        spec._check(where)
        return spec

    def _check(self, where: str) -> None:
        if not self.name:
            raise ConfigError(f"{where}: 'name' must not be empty")
        if not 0 < self.frame_hz <= 2000:
            raise ConfigError(f"{where}: 'frame_hz' must be in (0, 2000], got {self.frame_hz} (servos: 50)")
        if not 0 <= self.min_us <= self.neutral_us <= self.max_us or self.min_us == self.max_us:
            raise ConfigError(f"{where}: need 0 <= min_us <= neutral_us <= max_us and min_us < max_us, got "
                              f"{self.min_us}/{self.neutral_us}/{self.max_us}")
        if self.max_us * 1000 > self.period_ns:
            raise ConfigError(f"{where}: max_us {self.max_us} does not fit a {self.frame_hz} Hz frame "
                              f"({self.period_ns / 1000:.0f} us); lower frame_hz or max_us")
        if self.slew_percent_per_s < 0:
            raise ConfigError(f"{where}: 'slew_percent_per_s' must be >= 0 (0: no limit)")


def parse_channels(tables: Any, *, service: str) -> list[ServoChannelSpec]:
    """Every channel of the ``channels`` config field, checked together (names, outputs, shared frames)."""
    if not isinstance(tables, list) or not tables:
        raise ConfigError(f"{service}: config 'channels' must list at least one channel, e.g. channels = "
                          '[{ name = "rudder" }] with [devices.rudder] address = "pca9685://1/0x40/0"')
    specs = [ServoChannelSpec.from_table(tab, where=f"{service}: channels[{i}]") for i, tab in enumerate(tables)]
    names: set[str] = set()
    devices: dict[str, str] = {}
    for s in specs:
        if s.name in names:
            raise ConfigError(f"{service}: two channels are called '{s.name}'; actuator names must be unique")
        names.add(s.name)
        other_device = devices.setdefault(s.device_name, s.name)
        if other_device != s.name:
            raise ConfigError(f"{service}: channels '{other_device}' and '{s.name}' both use device '{s.device_name}'; "
                              "give each actuator its own device")
    return specs


def resolve_outputs(specs: list[ServoChannelSpec], *, service: str, profile: Any) -> list[DeviceAddress]:
    """Each channel's address (its device's ``[devices.NAME]``), checked across every output of the
    service: a PWM kind, no output (sysfs chip/channel, PCA9685 chip/channel) used twice, one frame rate per
    PCA9685. ConfigError names the channel, the address and the fix (sysfs has no exclusivity: two
    writers on one pin would fight over an ESC line)."""
    from u2sa_hw.profile.devices import device_address

    addresses: list[DeviceAddress] = []
    outputs: dict[tuple[Any, ...], tuple[ServoChannelSpec, DeviceAddress]] = {}
    frames: dict[tuple[Any, ...], ServoChannelSpec] = {}
    for spec in specs:
        where = f"{service}: channel '{spec.name}'"
        try:
            address = device_address(profile, spec.device_name)
        except AddressError as exc:
            raise ConfigError(f"{where}: {exc} (e.g. \"pca9685://1/0x40/0\" or \"pwm://pwmchip0/0\")") from None
        if address.kind not in ("pwm", "pca9685"):
            raise ConfigError(f"{where}: device '{spec.device_name}' has the {address.kind} address {address.url}; "
                              "a PWM output needs pwm:// or pca9685://")
        other, other_address = outputs.setdefault(address.output_id, (spec, address))
        if other is not spec:
            raise ConfigError(f"{service}: channels '{other.name}' and '{spec.name}' are one output "
                              f"({other_address.url} and {address.url}); give each actuator its own output")
        frame = address.shared_frame_id
        if frame is not None:
            first = frames.setdefault(frame, spec)
            if first.period_ns != spec.period_ns:
                raise ConfigError(f"{service}: channels '{first.name}' and '{spec.name}' are on one PCA9685 "
                                  f"({address.url}) but ask {first.frame_hz} and {spec.frame_hz} Hz; all its "
                                  "channels share one frame")
        addresses.append(address)
    return addresses


class ServoOutput:
    """One channel at run time: its port (reopened with backoff), the command and the slewed output."""

    def __init__(self, spec: ServoChannelSpec, *, service: Any, record: bool) -> None:
        self.spec = spec
        self.target = 0.0  # commanded percent
        self.output = 0.0  # percent being output (slewed toward target)
        self.pulse_us: float | None = None  # pulse last written
        self.write_errors = 0
        self.last_error = ""  # the latest write or open failure, kept after recovery
        self.port: DeviceLink[PwmChannel] = DeviceLink(
            service, device=lambda: spec.device_name, raw_type=t.RawPwmWrite,
            options=lambda: {"period_ns": spec.period_ns}, on_open=self._on_open, record=lambda: record)
        problem = self.port.check()
        if problem:
            raise ConfigError(f"{service.name}: channel '{spec.name}': {problem} (e.g. \"pca9685://1/0x40/0\" or "
                              "\"pwm://pwmchip0/0\")")
        self.port.start()
        address = self.port.address
        if address is not None and address.kind not in ("pwm", "pca9685"):
            raise ConfigError(f"{service.name}: channel '{spec.name}': device '{spec.device_name}' has the "
                              f"{address.kind} address {address.url}; a PWM output needs pwm:// or pca9685://")

    def _on_open(self, pwm: PwmChannel) -> None:
        pulse = self.spec.pulse_us(self.output)
        pwm.set_pulse_us(pulse)
        pwm.enable(True)
        self.pulse_us = pulse

    def step(self, dt: float) -> None:
        """Move the output toward the target, by at most the slew limit over *dt* seconds."""
        limit = self.spec.slew_percent_per_s
        if limit <= 0:
            self.output = self.target
            return
        delta = max(-limit * dt, min(limit * dt, self.target - self.output))
        self.output += delta

    def write(self) -> None:
        """Put the output's pulse on the channel; a lost channel is marked for reopening."""
        pulse = self.spec.pulse_us(self.output)
        try:
            pwm = self.port.get()
        except PortUnavailable:
            if self.port.last_error is not None:
                self._note(str(self.port.last_error))
            return
        for attempt in (1, 2):  # once more at once: a PCA9685 channel reopens its bus on the next call
            try:
                pwm.set_pulse_us(pulse)
                self.pulse_us = pulse
                return
            except PortError as exc:  # closed, I/O, timeout, or (PCA9685) its bus cannot be reopened
                self.write_errors += 1
                self._note(str(exc))
                if attempt == 2:
                    self.port.lost(exc, port=pwm)

    def _note(self, error: str) -> None:
        if error != self.last_error:  # a failure repeated every update is logged once
            log.warning("%s: %s", self.spec.name, error)
        self.last_error = error


class PwmServoDriver(DeviceDeclarations, Actuator):
    """Servos and ESCs on sysfs PWM or PCA9685 channels; see the module docstring."""

    MOCK_KINDS = ("pca9685", "sysfs_pwm")   # u2sa_hw/ports/declared.py
    CONFIG = (
        field("channels", [], "list of tables: name, device, min_us, neutral_us, max_us, reverse, "
                              "frame_hz, slew_percent_per_s (applied at the next start)"),
        field("update_hz", 50.0, "how often slewed outputs step and lost channels are retried", gt=0, le=1000),
        field("release_on_exit", False, "stop the pulses after the final neutral (default: hold neutral)"),
        field("record_raw", False, "publish every PWM write on RAW.<device> (default device: the channel name)"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.outputs: dict[str, ServoOutput] = {}
        self._lock = threading.RLock()

    def actuator_names(self) -> set[str]:
        """The channel names."""
        return set(self.outputs)

    @classmethod
    def declared_actuators(cls, name: str, config: typing.Mapping[str, Any]) -> set[str]:
        """The channel names of ``channels``."""
        return {spec.name for spec in parse_channels(config["channels"], service=name)}

    @classmethod
    def used_devices(cls, service: str, config: typing.Mapping[str, Any]) -> tuple[str, ...]:
        """One device per channel (``device``, else its name)."""
        try:
            specs = parse_channels(config.get("channels", []), service=service)
        except ConfigError:
            return ()
        return tuple(spec.device_name for spec in specs)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: typing.Mapping[str, Any]) -> dict[str, Any]:
        """The ``actuator`` whose output *device* is, its pulse range (``min_us``, ``neutral_us``, ``max_us``,
        ``reverse``) and every channel's name (``actuators``); a ConfigError names the table and the fix."""
        specs = parse_channels(config["channels"], service=service)
        for s in specs:
            if s.device_name == device:
                return {"actuator": s.name, "actuators": [c.name for c in specs], "min_us": s.min_us,
                        "neutral_us": s.neutral_us, "max_us": s.max_us, "reverse": s.reverse}
        raise ConfigError(f"no channel of service '{service}' uses device '{device}' (channels: "
                          f"{', '.join(s.name for s in specs)}); set device = \"{device}\" in the channel's table")

    @classmethod
    def probe_expectation(cls, config: typing.Mapping[str, Any]) -> dict[str, Any]:
        """A PCA9685 behind a pca9685:// address (a sysfs chip has no identity to read)."""
        return {"chip": "pca9685"}

    def check_config(self) -> None:
        """Refuse channels that cannot run (each channel's table, its device's address, one output and one
        PCA9685 frame per channel across the service) and the dead-man as every actuator; runs at start,
        in ``u2sa check`` and before every change over the bus, so a bad ``channels`` is never saved."""
        super().check_config()
        specs = parse_channels(self.config["channels"], service=self.name)
        resolve_outputs(specs, service=self.name, profile=self.profile)

    def setup(self) -> None:
        """Open the channels (checked by check_config) and output neutral."""
        specs = parse_channels(self.config["channels"], service=self.name)
        resolve_outputs(specs, service=self.name, profile=self.profile)
        record = bool(self.config["record_raw"])
        for spec in specs:
            self.outputs[spec.name] = ServoOutput(spec, service=self, record=record)
        self.neutral()
        self._update_status()

    def on_percentage(self, actuator: str, percent: float) -> None:
        """Set the channel's target; without a slew limit it is output at once."""
        with self._lock:
            out = self.outputs[actuator]
            out.target = percent
            if out.spec.slew_percent_per_s <= 0:
                out.step(0.0)
                out.write()

    def neutral(self) -> None:
        """Every channel to its neutral pulse at once (no slew)."""
        with self._lock:
            for out in self.outputs.values():
                out.target = out.output = 0.0
                out.write()

    def on_config_change(self, name: str, value: Any) -> None:
        """Channel changes take effect at the next start (outputs are not reshuffled under a running vehicle)."""
        if name == "channels":
            self.logger.warning("%s: new channels saved; they apply when the service restarts", self.name)

    def run(self) -> None:
        """Step slewed outputs, retry lost channels, enforce the command timeout."""
        last = time.monotonic()
        while self.wait(1.0 / float(self.config["update_hz"])):
            now = time.monotonic()
            dt, last = now - last, now
            self.check_command_timeout()
            with self._lock:
                for out in self.outputs.values():
                    out.step(dt)
                    out.write()
            self._update_status()

    def _update_status(self) -> None:
        down = any(out.port.state != "open" for out in self.outputs.values())
        self.status = "degraded" if down or self.failsafe_active else "ok"

    def health_details(self) -> dict[str, Any]:
        """Per channel: pulse, output and target percent, port state, errors (failed writes plus losses)
        and the last write or open failure."""
        details = super().health_details()
        for name, out in self.outputs.items():
            details[f"{name}.pulse_us"] = f"{out.pulse_us:.1f}" if out.pulse_us is not None else ""
            details[f"{name}.percent"] = f"{out.output:.1f}"
            details[f"{name}.target"] = f"{out.target:.1f}"
            details[f"{name}.port"] = out.port.state
            details[f"{name}.errors"] = out.write_errors + out.port.losses
            if out.last_error:
                details[f"{name}.last_error"] = out.last_error
        return details

    def kill(self) -> None:
        """Neutral, then (with ``release_on_exit``) stop the pulses and release the channels."""
        try:
            super().kill()
        finally:
            if self.config["release_on_exit"]:
                with self._lock:
                    for out in self.outputs.values():
                        out.port.close()
