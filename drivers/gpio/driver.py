"""Digital GPIO as U2SA services: outputs as an Actuator, inputs (e-stop, bumpers) as a Sensor.

:class:`GpioOutputDriver` (kind ``gpio_output``): every configured output line is an
actuator name. A Percentage Command of 50 % or more switches it on (level 1), anything
less off; neutral is the line's configured safe level, taken on start, stop, kill, a
FAILSAFE and when commands stop arriving for ``command_timeout_s``.

:class:`GpioInputDriver` (kind ``gpio_input``): digital inputs with edge events,
debounced (a level must hold ``debounce_ms`` before it counts). What an input publishes
depends on its role:

- lines in ``failsafe_on`` (e-stops) publish ``Failsafe`` (active) on ``FAILSAFE`` when
  they become active, again every ``failsafe_repeat_s`` while held, and (with
  ``clear_on_release``) ``Failsafe`` (not active) when released; while the chip cannot be
  read, an e-stop's state is unknown and that too holds the failsafe;
- lines with a ``positions`` entry (bumpers) publish an ``ObjectDescription`` on
  ``OBJECTS`` (object_type ``bumper``, level 3, reference_frame ``FRD``, x/y/z = the
  bumper's place on the body) when hit, and every ``bumper_repeat_s`` while held;
- every line's state is in the health details (``<name>`` = ``active``/``inactive``).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Mapping

from u2sa_hw.drivers.gpio.lines import (GpioLineSet, check_gpio_device, note_restart_needed, parse_levels,
                                        parse_line_map, parse_names, parse_positions)
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import Actuator, ExteroceptiveSensor
from u2sa_hw.config.fields import MAX_TIMEOUT_S, ConfigError, field
from u2sa_hw.ports.declared import DeviceDeclarations
from u2sa_hw.ports.device_link import device_setting
from u2sa_hw.ports.gpio.wire import BIASES
from u2sa_hw.ports.gpio.port import GpioPort

ON_THRESHOLD_PERCENT = 50.0
BUMPER_LEVEL = 3  # ObjectDescription level: avoid at all costs (we are touching it)

_DEVICE = (field("device", "", "the chip's lines: its [devices.NAME] table (address gpio://CHIP/LINES) and "
                               "RAW.<device> (empty: the service name)"),
           field("device_name", "", "old name of the device setting"))


def _used_gpio(service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
    """The one GPIO device of a gpio_output/gpio_input service (``device``, else the service's name)."""
    return (device_setting(config, service),)
_RAW = field("record_raw", False, "publish every edge, write and late clock look as RawGpioEdge/"
             "RawGpioWrite/RawGpioClockRead on RAW.<device>")


class GpioOutputDriver(DeviceDeclarations, Actuator):
    """Digital output lines, each an actuator: >= 50 % on, else off; neutral = its safe level."""

    MOCK_KINDS = ("gpio_chip",)   # u2sa_hw/ports/declared.py
    CONFIG = (
        field("outputs", "", "name=line,... each name is an actuator name"),
        field("safe_levels", "", "name=level,... the neutral level of each output (unlisted: 0)"),
        *_DEVICE, _RAW,
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        c = self.config
        self.lines_by_name, self.safe_levels = self.parse_config(c)
        self.levels = dict(self.safe_levels)  # what each line was last driven to (or opened with)
        self.unapplied = 0  # writes (commands or neutral) that could not reach the chip
        self.gpio = GpioLineSet(self, initial_outputs=self._initial_outputs, record_raw=c["record_raw"],
                                on_open=self._on_open)
        self.device = self.gpio.device

    def parse_config(self, c: Mapping[str, Any]) -> tuple[dict[str, int], dict[str, int]]:
        """Lines by name and the safe level of each; ConfigError names the field and the fix."""
        lines = parse_line_map(c["outputs"], service=self.name, key="outputs")
        if not lines:
            raise ConfigError(f"service '{self.name}': no output lines configured; set outputs = \"lamp=17\"")
        check_gpio_device(self, c, list(lines.values()))
        safe = parse_levels(c["safe_levels"], known=list(lines), service=self.name, key="safe_levels")
        return lines, {n: safe.get(n, 0) for n in lines}

    def check_config(self) -> None:
        """Refuse a config the service cannot start with (the dead-man as every actuator)."""
        super().check_config()
        self.parse_config(self.config)

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        """The output lines' GPIO device."""
        return _used_gpio(service, config)

    @classmethod
    def declared_actuators(cls, name: str, config: Mapping[str, Any]) -> set[str]:
        """The output names of ``outputs``."""
        return set(parse_line_map(config["outputs"], service=name, key="outputs"))

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """``outputs`` (name -> line) and each one's ``safe_levels``; a ConfigError names the setting."""
        lines = parse_line_map(str(config["outputs"]), service=service, key="outputs")
        safe = parse_levels(str(config["safe_levels"]), known=list(lines), service=service, key="safe_levels")
        return {"outputs": lines, "safe_levels": {n: safe.get(n, 0) for n in lines}}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """Nothing: a GPIO chip has no identity to read."""
        return {}

    def _initial_outputs(self) -> dict[int, int]:
        return {self.lines_by_name[n]: v for n, v in self.safe_levels.items()}  # a (re)opened port starts safe

    def _on_open(self, port: GpioPort) -> None:
        self.levels = dict(self.safe_levels)

    def on_config_change(self, name: str, value: Any) -> None:
        """Lines and levels apply at the next start."""
        note_restart_needed(self, name)

    def actuator_names(self) -> set[str]:
        """The configured output names."""
        return set(self.lines_by_name)

    def _drive(self, name: str, level: int) -> None:
        if self.gpio.set(self.lines_by_name[name], level):
            self.levels[name] = level
        else:
            self.unapplied += 1  # the chip is down or the write failed: the line is not at this level

    def on_percentage(self, actuator: str, percent: float) -> None:
        """On at 50 % and above, off below."""
        self._drive(actuator, 1 if percent >= ON_THRESHOLD_PERCENT else 0)

    def neutral(self) -> None:
        """Every output to its safe level."""
        for name, level in self.safe_levels.items():
            self._drive(name, level)

    def run(self) -> None:
        """Keep the port open (noticing a lost chip without waiting for a write) and apply the command timeout."""
        while self.wait(0.05):
            port = self.gpio.port()
            if port is not None:
                self.gpio.read_edges(port, 0.0)  # no inputs: raises (and marks the port lost) only if the chip is gone
            self.check_command_timeout()
            if self.failsafe_active:
                continue
            self.status = "ok" if self.gpio.is_open else "degraded"

    def kill(self) -> None:
        """Neutral, then release the lines."""
        try:
            super().kill()
        finally:
            self.gpio.close()

    def health_details(self) -> dict[str, Any]:
        """Command counters, port state, unapplied writes and each output's level ("unknown" while down)."""
        known = self.gpio.is_open  # with the chip gone, nobody knows what the lines are doing
        return {**super().health_details(), **self.gpio.health(), "unapplied": self.unapplied,
                **{n: v if known else "unknown" for n, v in self.levels.items()}}


class DebouncedInput:
    """A line's level that changes only after the raw level held for *debounce_ns* (pure logic)."""

    def __init__(self, *, level: int, debounce_ns: int, at_ns: int) -> None:
        self.level = self.raw = level
        self.debounce_ns = debounce_ns
        self.raw_since_ns = at_ns

    def edge(self, rising: bool, timestamp_ns: int) -> None:
        """An edge on the line (bounces included)."""
        self.raw, self.raw_since_ns = int(rising), timestamp_ns

    def settle(self, now_ns: int) -> bool:
        """Adopt the raw level once it has held long enough; True when the debounced level changed."""
        if self.raw != self.level and now_ns - self.raw_since_ns >= self.debounce_ns:
            self.level = self.raw
            return True
        return False


@dataclass
class _Announce:
    """When a repeated message was last sent (monotonic s), and whether it is being held."""

    held: bool = False
    last_s: float = 0.0


class GpioInputDriver(DeviceDeclarations, ExteroceptiveSensor):
    """Digital inputs with edge events: e-stops command the failsafe, bumpers report contacts."""

    MOCK_KINDS = ("gpio_chip",)   # u2sa_hw/ports/declared.py
    CONFIG = (
        field("inputs", "", "name=line,... e.g. estop=4,bump_front=22"),
        field("active_low", "", "names of inputs that are active at level 0 (e.g. normally-closed e-stops)"),
        field("bias", "as-is", "as-is, pull-up, pull-down or disabled (every line)", choices=BIASES),
        field("debounce_ms", 10.0, "a level must hold this long before it counts", ge=0, le=200),
        field("failsafe_on", "", "names of inputs that command a FAILSAFE while active (e-stops)"),
        field("failsafe_repeat_s", 1.0, "re-send the active failsafe this often while held", gt=0, le=1.0),
        field("clear_on_release", True, "publish a cleared failsafe when every e-stop is released"),
        field("positions", "", "name=x:y:z,... body-frame (FRD, m) place of each bumper; these publish OBJECTS"),
        field("bumper_repeat_s", 0.5, "re-send a held bumper's object this often", ge=0, le=MAX_TIMEOUT_S),
        *_DEVICE, _RAW,
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        c = self.config
        self.lines_by_name, self.active_low, self.estops, self.bumpers = self.parse_config(c)
        self.names_by_line = {line: n for n, line in self.lines_by_name.items()}
        self.inputs: dict[str, DebouncedInput] = {}
        self.failsafe = _Announce()
        self.failsafe_reason = ""
        self.held_bumpers = {n: _Announce() for n in self.bumpers}
        self.failsafes_sent = self.objects_sent = 0
        self.edge_counts: Counter[str] = Counter()
        self.clock_ns: int | None = None   # the device clock: the latest time judged
        if self.estops:
            self.register_publisher(ch.FAILSAFE, t.Failsafe)
        self.gpio = GpioLineSet(self, inputs=list(self.lines_by_name.values()), bias=c["bias"],
                                record_raw=c["record_raw"], on_open=self._read_levels)
        self.device = self.gpio.device

    def parse_config(self, c: Mapping[str, Any]) -> tuple[dict[str, int], set[str], list[str],
                                                           dict[str, tuple[float, float, float]]]:
        """Lines by name, active-low names, e-stop names, bumper positions; ConfigError names the field."""
        lines = parse_line_map(c["inputs"], service=self.name, key="inputs")
        if not lines:
            raise ConfigError(f"service '{self.name}': no input lines configured; set inputs = \"estop=4\"")
        check_gpio_device(self, c, list(lines.values()))
        if c["bias"] not in BIASES:
            raise ConfigError(f"service '{self.name}': config 'bias' must be one of {', '.join(BIASES)}, "
                              f"got {c['bias']!r}")
        for key in ("debounce_ms", "failsafe_repeat_s", "bumper_repeat_s"):
            if c[key] < 0:
                raise ConfigError(f"service '{self.name}': config '{key}' must be >= 0, got {c[key]}")
        known = list(lines)
        return (lines, set(parse_names(c["active_low"], known=known, service=self.name, key="active_low")),
                parse_names(c["failsafe_on"], known=known, service=self.name, key="failsafe_on"),
                parse_positions(c["positions"], known=known, service=self.name, key="positions"))

    def check_config(self) -> None:
        """Refuse a config the service cannot start with."""
        self.parse_config(self.config)

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        """The input lines' GPIO device."""
        return _used_gpio(service, config)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """No outputs: a test drives the mock chip's inputs."""
        return {"outputs": {}}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """Nothing: a GPIO chip has no identity to read."""
        return {}

    def _read_levels(self, port: GpioPort) -> None:
        """After every (re)open: the present levels, since edges before the open are not seen."""
        if getattr(port, "device_clock", False):   # a replay chip: its clock, not the wall clock's time so far
            self.clock_ns = None
        now, debounce = port.now_ns() or time.monotonic_ns(), int(self.config["debounce_ms"] * 1e6)
        self.inputs = {name: DebouncedInput(level=port.get(line), debounce_ns=debounce, at_ns=now)
                       for name, line in self.lines_by_name.items()}
        self.logger.info("inputs of %s: %s", self.device,
                         ", ".join(f"{n} {'active' if self.is_active(n) else 'inactive'}" for n in self.inputs))

    def on_config_change(self, name: str, value: Any) -> None:
        """Repeat intervals and clear_on_release apply at once; lines, roles and debounce at the next start."""
        note_restart_needed(self, name, live=("failsafe_repeat_s", "bumper_repeat_s", "clear_on_release"))

    def is_active(self, name: str) -> bool:
        """The debounced state of input *name* (active-low lines inverted)."""
        state = self.inputs.get(name)
        return state is not None and bool(state.level) != (name in self.active_low)

    def run(self) -> None:
        """Read edges, settle them, publish failsafes and bumper hits until stopped.

        Time is the port's device clock (``GpioPort.now_ns``: CLOCK_MONOTONIC on a real chip, the
        edge and tick stamps on a replay chip), and each edge is taken in order with the debounce
        settled at its own stamp first, so what is published does not depend on read batching.
        """
        while self.wait(0.0):
            port = self.gpio.port()
            if port is None:
                self.inputs = {}
                self.wait(min(0.1, max(0.02, self.gpio.retry_in())))
                self._step(time.monotonic_ns())
            else:
                for event in self.gpio.read_events(port, 0.02):
                    self._step(event.timestamp_ns)
                    name = self.names_by_line.get(getattr(event, "line", -1), "")
                    if name in self.inputs:
                        self.edge_counts[name] += 1
                        self.inputs[name].edge(event.rising, event.timestamp_ns)
                self._step(port.look_ns() if port.is_open else time.monotonic_ns())
            self.status = "ok" if self.gpio.is_open else "degraded"

    def _step(self, now_ns: int | None) -> None:
        """Settle every input and announce at *now_ns* on the device clock (None, a replay chip that has
        sent nothing yet: the wall clock, so a held e-stop is repeated whatever the chip does)."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        self.clock_ns = now_ns if self.clock_ns is None else max(self.clock_ns, now_ns)
        for name, state in list(self.inputs.items()):
            if state.settle(self.clock_ns):
                self.logger.info("%s %s", name, "active" if self.is_active(name) else "inactive")
        self._announce(self.clock_ns / 1e9)

    def _announce(self, now: float) -> None:
        active = [n for n in self.estops if self.is_active(n)]
        reason = ""
        if active:
            reason = f"e-stop {', '.join(active)} active on {self.device}"
        elif self.estops and not self.gpio.is_open:
            reason = f"e-stop input {self.device} cannot be read ({self.gpio.reconnecting.state})"
        if reason and (not self.failsafe.held or reason != self.failsafe_reason
                       or now - self.failsafe.last_s >= self.config["failsafe_repeat_s"]):
            if not self.failsafe.held or reason != self.failsafe_reason:
                self.logger.warning("FAILSAFE: %s", reason)
            self._send_failsafe(True, reason, now)
        elif not reason and self.failsafe.held:
            self.logger.info("e-stops released on %s", self.device)
            if self.config["clear_on_release"]:
                self._send_failsafe(False, f"e-stops released on {self.device}", now)
            self.failsafe.held = False
        self.failsafe_reason = reason
        for name, position in self.bumpers.items():
            held = self.held_bumpers[name]
            if not self.is_active(name):
                held.held = False
            elif not held.held or now - held.last_s >= self.config["bumper_repeat_s"]:
                self._send_bumper(name, position)
                held.held, held.last_s = True, now

    def _send_failsafe(self, active: bool, reason: str, now: float) -> None:
        msg = t.Failsafe()
        msg.active, msg.reason, msg.service = active, reason, self.name
        self.publish(ch.FAILSAFE, msg)
        self.failsafes_sent += 1
        self.failsafe.held, self.failsafe.last_s = active, now

    def _send_bumper(self, name: str, position: tuple[float, float, float]) -> None:
        state = self.inputs[name]
        obj = t.ObjectDescription()
        # the header time is when the edge happened (monotonic edge stamp moved to the wall clock)
        obj.header.timestamp_us = (time.time_ns() - (time.monotonic_ns() - state.raw_since_ns)) // 1000
        obj.uid, obj.object_type, obj.level = f"{self.name}.{name}", "bumper", BUMPER_LEVEL
        obj.reference_frame = "FRD"
        obj.x, obj.y, obj.z = position
        self.publish_object(obj)
        self.objects_sent += 1

    def kill(self) -> None:
        """Release the lines, then stop."""
        try:
            self.gpio.close()
        finally:
            super().kill()

    def health_details(self) -> dict[str, Any]:
        """Port state, each input's state and edge count, what was sent."""
        details: dict[str, Any] = {**self.gpio.health(), "failsafe": self.failsafe.held,
                                   "failsafe_reason": self.failsafe_reason, "failsafes_sent": self.failsafes_sent,
                                   "objects_sent": self.objects_sent}
        for name in self.lines_by_name:
            state = self.inputs.get(name)
            details[name] = "unknown" if state is None else ("active" if self.is_active(name) else "inactive")
            details[f"{name}_edges"] = self.edge_counts[name]
        return details
