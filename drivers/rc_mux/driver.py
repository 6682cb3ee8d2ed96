"""RC input and the hardware RC multiplexer (kind ``rc_mux``): the pilot's mode on ``RC_MODE``
and the autonomy-enable line into the mux -- the service around :class:`u2sa_hw.drivers.rc_mux.state.MuxState`.

Every decision is the state's (pure, time passed in; drivers/rc_mux/state.py and the modules it
names): the pulse widths and the mode (``pulse.py``), the signal timeout, the autonomy-enable
verdict (``enable.py``: failsafes held per source, pre-arm checks, arming, ``on_check_lost``), the
select read-back (``readback.py``) and what is due when on the device clock (``clock.py``). This
service is thin: it opens the GPIO port (``GpioLineSet``), hands the state every edge, tick and
recorded bus input with its stamp, the bus's FAILSAFE, Health and STATE_ESTIMATE with the host's
CLOCK_MONOTONIC, and the loop's looks at the clocks; it drives the enable line when the state says
so, publishes the ``RcMode`` and ``MANUAL_CMD`` (the sticks through ``[safety.manual_mixer]``,
``manual.py``) it returns, logs its notes and reports its health. One lock serialises the calls
into the state: the loop's, a FAILSAFE callback's (which drops the line at once, not at the next
loop turn) and the health thread's.

The enable line is high only while all of these hold: the mode is autonomous, no FAILSAFE is
held, the GPIO port is open and the select read-back agrees, every pre-arm check holds, and the
pilot armed through manual (docs/drivers-gpio-rc.md, docs/safety.md). It drops on stop and kill
too; a crashed service's request is released and the line falls to the board's pull-down.
``RcMode`` goes out at ``publish_hz`` on a fixed grid of the device clock and on every change:
``mode`` is the pilot's switch (0 manual, 1 autonomous, 2 no signal), ``autonomy_enabled`` the
enable line, so the vehicle is under autonomous control only when both say so.

Time. Everything is judged on the port's device clock (CLOCK_MONOTONIC on a real chip, the
recorded edge stamps on a replay chip), in the order of the edges' stamps, so a replay gives the
live messages. On a replay chip the Health, FAILSAFE and STATE_ESTIMATE the pre-arm checks and the
failsafe read come from the chip too, the recorded ones, in order with the edges
(:meth:`u2sa_hw.ports.gpio.port.GpioPort.take_recorded_bus`), and the loop's own stall is not
judged (the replaying machine's load is not the vehicle's): the decision is the recorded one.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Mapping, NamedTuple

from u2sa_hw.drivers.rc_mux.declarations import RcMuxDeclarations
from u2sa_hw.drivers.gpio.lines import GpioLineSet, check_gpio_device, note_restart_needed, parse_line_map
from u2sa_hw.drivers.rc_mux.health import health_details
from u2sa_hw.drivers.rc_mux.manual import ManualSticks
from u2sa_hw.drivers.rc_mux.outputs import ManualReport, ModeReport, Output
from u2sa_hw.drivers.rc_mux.pulse import PulseMeter, RcModeFilter
from u2sa_hw.drivers.rc_mux.state import MuxState
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import Sensor
from u2sa_hw.config.fields import MAX_RATE_HZ, ConfigError, field
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.ports.gpio.port import GpioPort
from u2sa_hw.ports.gpio.wire import BusInput, ClockTick, EdgeEvent
from u2sa_hw.safety.config import load_safety
from u2sa_hw.safety.prearm import PrearmChecks
from u2sa_hw.safety.wiring import check_wiring


MAX_PULSE_US = 5000.0   # an RC pulse is 1-2 ms in a 20 ms frame: anything longer is not one
MAX_GPIO_LINE = 1023    # a line offset of a gpiochip (a Pi's has 54-58)
RECORDED_BUS = (ch.HEALTH, ch.FAILSAFE)   # what a replay chip hands over (and STATE_ESTIMATE when checked)


class RcSetup(NamedTuple):
    """What the config says, checked: channel lines by name, enable and select lines, the pulse meter
    and the mode filter."""

    channels: dict[str, int]
    enable_line: int
    select_line: int
    meter: PulseMeter
    filter: RcModeFilter


class RcMuxDriver(RcMuxDeclarations, Sensor):
    """RC pulse measurement, mux mode on RC_MODE, and the autonomy-enable line into the mux: the service around
    :class:`u2sa_hw.drivers.rc_mux.state.MuxState`."""

    CONFIG = (
        field("device", "", "the chip's lines: its [devices.NAME] table (address gpio://CHIP/LINES) and "
                            "RAW.<device> (empty: the service name)"),
        field("channels", "throttle=5,steering=6,mode=13",
              "name=line,... the receiver channels (RcMode.pulse_us order)"),
        field("mode_channel", "mode", "the channel of the pilot's manual/autonomous switch"),
        field("enable_line", 21, "output line: autonomy enable into the mux (high = autonomy allowed)", ge=0, le=MAX_GPIO_LINE),
        field("select_line", -1, "input line: the mux's select read-back, 1 = autonomous (-1: none)", ge=-1, le=MAX_GPIO_LINE),
        field("min_pulse_us", 800.0, "shorter pulses are rejected", gt=0, le=MAX_PULSE_US),
        field("max_pulse_us", 2200.0, "longer pulses are rejected", gt=0, le=MAX_PULSE_US),
        field("autonomous_above_us", 1700.0, "mode pulse above this asks for autonomous", gt=0, le=MAX_PULSE_US),
        field("manual_below_us", 1300.0, "mode pulse below this asks for manual", gt=0, le=MAX_PULSE_US),
        field("debounce_frames", 3, "consecutive frames needed to change the mode", ge=1, le=100),
        field("signal_timeout_ms", 100.0, "no valid mode pulse for this long -> no signal (5 frames at 50 Hz)", gt=0,
              le=1000),
        field("select_mismatch_ms", 500.0, "read-back disagreeing this long is a mismatch (> signal timeout)", gt=0,
              le=2000),
        field("require_rearm", True, "after failsafe, signal loss, mismatch or start: switch to manual to re-arm",
              remote=False),
        field("publish_hz", 20.0, "RcMode messages per second (plus one on every change); actuators go neutral "
                                  "when the newest is older than [safety] rc_mode_timeout_ms", gt=0, le=MAX_RATE_HZ),
        field("manual_hz", 25.0, "MANUAL_CMD commands per second in manual (with a [safety.manual_mixer])", gt=0, le=MAX_RATE_HZ),
        field("device_name", "", "old name of the device setting"),
        field("record_raw", False, "publish every edge, write and late clock look as RawGpioEdge/RawGpioWrite/"
              "RawGpioClockRead on RAW.<device>"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        c = self.config
        self.channels, self.enable_line, self.select_line, self.meter, self.filter = self.parse_config(c)
        self.safety = check_wiring(self.profile) if self.profile.path else load_safety(self.profile)
        self.sticks = ManualSticks(self.safety.manual_mixer) if self.safety.manual_mixer else None
        prearm = PrearmChecks.from_profile(self.profile)
        self._stopping = False
        self._status_said = ""   # the state's status as last carried over (the contract sets its own too)
        # every call into the state holds it; the port's own lock is taken after it (a write of the line),
        # never before (the opener's on_open does not take it)
        self._lock = threading.RLock()
        self._origin_of: Any = lambda: 0   # where the open port says the recorded clock's zero is
        self._recorded_bus: tuple[str, ...] = ()   # bus channels the replay chip hands over instead of the bus
        inputs = list(self.channels.values()) + ([self.select_line] if self.select_line >= 0 else [])
        self.gpio = GpioLineSet(self, inputs=inputs, initial_outputs=lambda: {self.enable_line: 0},
                                record_raw=c["record_raw"], on_open=self._on_open)
        self.device = self.gpio.device
        self.state = MuxState(channels=self.channels, mode_channel=c["mode_channel"], meter=self.meter,
                              filter=self.filter, prearm=prearm,
                              drive_enable=self._drive_enable,
                              select_line=self.select_line if self.select_line >= 0 else None,
                              on_check_lost=self.safety.on_check_lost, require_rearm=bool(c["require_rearm"]),
                              select_mismatch_ms=float(c["select_mismatch_ms"]), publish_hz=c["publish_hz"],
                              manual_hz=c["manual_hz"], manual=self.sticks is not None,
                              rc_mode_timeout_s=self.safety.rc_mode_timeout_s, device=self.device)
        self.register_publisher(ch.RC_MODE, t.RcMode)
        if self.sticks is not None:
            self.register_publisher(ch.MANUAL_CMD, t.PercentageCommand)
        self.register_subscriber(ch.FAILSAFE, t.Failsafe, self._on_failsafe)
        self.register_subscriber(ch.HEALTH, t.Health, self._on_health)
        if self.prearm.needs_estimate:
            self.register_subscriber(ch.STATE_ESTIMATE, t.StateInformation, self._on_estimate)

    def parse_config(self, c: Mapping[str, Any]) -> RcSetup:
        """Check the config and build the pulse meter and mode filter; ConfigError names the field."""
        name = self.name
        channels = parse_line_map(c["channels"], service=name, key="channels")
        if c["mode_channel"] not in channels:
            raise ConfigError(f"service '{name}': mode_channel {c['mode_channel']!r} is not one of the channels "
                              f"({', '.join(channels) or 'none'}); add it to 'channels' as name=line")
        enable, select, used = int(c["enable_line"]), int(c["select_line"]), set(channels.values())
        if enable < 0 or enable in used or select in used | {enable}:
            raise ConfigError(f"service '{name}': enable_line {enable} and select_line {select} must be distinct "
                              f"lines, not RC channel lines {sorted(used)}; enable_line is required")
        if c["publish_hz"] <= 0 or c["select_mismatch_ms"] <= 0 or c["manual_hz"] <= 0:
            raise ConfigError(f"service '{name}': publish_hz, manual_hz and select_mismatch_ms must be > 0")
        check_gpio_device(self, c, [*used, enable, *([select] if select >= 0 else [])])
        try:
            return RcSetup(channels, enable, select,
                           PulseMeter(lines=used, min_us=c["min_pulse_us"], max_us=c["max_pulse_us"]),
                           RcModeFilter(autonomous_above_us=c["autonomous_above_us"],
                                        manual_below_us=c["manual_below_us"], debounce_frames=c["debounce_frames"],
                                        signal_timeout_ns=int(c["signal_timeout_ms"] * 1e6)))
        except ValueError as exc:
            raise ConfigError(f"service '{name}': {exc}") from None

    def check_config(self) -> None:
        """Refuse a config the service cannot start with."""
        self.parse_config(self.config)

    def on_config_change(self, name: str, value: Any) -> None:
        """require_rearm and select_mismatch_ms apply at once; lines and thresholds at the next start."""
        with self._lock:
            self.state.set_live(require_rearm=bool(self.config["require_rearm"]),
                                select_mismatch_ms=float(self.config["select_mismatch_ms"]))
        note_restart_needed(self, name, live=("require_rearm", "select_mismatch_ms"))

    # -- what the state says, for readers (health, the bench) -----------------------------------
    @property
    def prearm(self) -> PrearmChecks:
        """The pre-arm checks the state judges with."""
        return self.state.gate.prearm

    @property
    def clock_ns(self) -> int | None:
        """The device clock: the latest time judged (None: not started)."""
        return self.state.clock_ns

    @property
    def enabled(self) -> bool:
        """What the enable line was last driven to."""
        return self.state.enabled

    def autonomy_allowed(self) -> tuple[bool, str]:
        """Whether the enable line may be high, and if not the first reason why not."""
        with self._lock:
            return self.state.autonomy_allowed()

    # -- the port and the bus -----------------------------------------------------------------------
    def _on_open(self, port: GpioPort) -> None:
        # runs inside the opener, under the line set's lock, so not under self._lock (lock order: self._lock ->
        # line set); the port was requested with the enable line low
        self._origin_of = port.clock_origin_ns
        device_clock = bool(getattr(port, "device_clock", False))
        prearm = None
        if device_clock:   # a replay chip: its clock, not the wall clock's time so far
            wanted = RECORDED_BUS + ((ch.STATE_ESTIMATE,) if self.prearm.needs_estimate else ())
            taken = port.take_recorded_bus(wanted)
            if taken:   # the recorded inputs replace what the replay bus says: start from none of them
                self._recorded_bus = taken
                prearm = PrearmChecks.from_profile(self.profile)
        self.state.port_opened(device_clock=device_clock, prearm=prearm,
                               select_level=port.get(self.select_line) if self.select_line >= 0 else None)

    def _drive_enable(self, level: bool) -> bool:
        return self.gpio.set(self.enable_line, int(level))

    def _on_failsafe(self, msg: t.Failsafe) -> None:
        if ch.FAILSAFE not in self._recorded_bus:   # on a replay chip the recorded ones come with the edges
            self._judge(self.state.on_failsafe, msg, host_ns=time.monotonic_ns())

    def _on_health(self, msg: t.Health) -> None:
        if ch.HEALTH not in self._recorded_bus:
            with self._lock:
                self.state.on_health(msg, now_s=time.monotonic())

    def _on_estimate(self, msg: t.StateInformation) -> None:
        if ch.STATE_ESTIMATE not in self._recorded_bus:
            with self._lock:
                self.state.on_estimate(msg, now_s=time.monotonic())

    # -- the loop ------------------------------------------------------------------------
    def run(self) -> None:
        """Measure pulses, follow the mode, drive the enable line and publish until stopped."""
        self.logger.info("%s; manual mixer: %s; on a lost check: %s", self.prearm.describe(),
                         f"{self.sticks.spec.kind} -> {', '.join(self.sticks.spec.actuators)}" if self.sticks else "none",
                         self.safety.on_check_lost)
        self._judge(self.state.loop_looked, time.monotonic_ns())
        while self.wait(0.0):
            port = self.gpio.port()
            if port is None:
                self.wait(min(0.05, max(0.01, self.gpio.retry_in())))
            else:
                # each edge (and a replay chip's tick or recorded bus input) in order, whatever falls due
                # before it first, at its own time: what is published depends on the stamps, not on how
                # the reads batched them
                events = self.gpio.read_events(port, 0.02)
                host_ns = time.monotonic_ns()
                with self._lock:
                    if self.state.clock_ns is None:   # the clock starts with these: its zero as the port says now
                        self.state.clock_origin(self._origin_of())
                for event in events:
                    self._take(event, host_ns)
            # after the wait, before anything is published: a stall anywhere in the loop is caught here (on
            # the host clock: the actuators judge RC_MODE by it; not in a replay, whose load is not the vehicle's)
            if not self.state.device_clock:
                self._judge(self.state.loop_looked, time.monotonic_ns())
            # the device clock (CLOCK_MONOTONIC on a real chip; the port down: the host's); a look long after the
            # last edge is tapped (RawGpioClockRead), so a replay judges at this very time
            if port is not None and port.is_open:
                self._judge(self.state.step, port.look_ns(), host_ns=time.monotonic_ns())
            elif not self.state.device_clock:
                self._judge(self.state.step, time.monotonic_ns(), host_ns=time.monotonic_ns())
            else:
                self._judge(self.state.settle_now, host_ns=time.monotonic_ns())   # a replay chip gone: said at once

    def _take(self, event: Any, host_ns: int) -> None:
        """One event from the chip, handed to the state at its stamp."""
        if isinstance(event, EdgeEvent):
            self._judge(self.state.take_edge, event.line, event.rising, event.timestamp_ns, host_ns=host_ns)
        elif isinstance(event, ClockTick):
            self._judge(self.state.take_tick, event.timestamp_ns, step=event.step, host_ns=host_ns)
        elif isinstance(event, BusInput):
            try:
                msg, _ = REGISTRY.decode(event.data, ch.base_type(event.channel))
            except MalformedMessage:
                return
            self._judge(self.state.take_bus, event.channel, msg, event.timestamp_ns, host_ns=host_ns)

    def _judge(self, call: Callable[..., list[Output]], *args: Any, **kwargs: Any) -> None:
        """One call into the state with the port's state as it is now, then what it says to do."""
        with self._lock:
            self.state.port_open = self.gpio.is_open
            outputs = call(*args, **kwargs)
            if not self._stopping and self.state.status != self._status_said:
                self.status = self._status_said = self.state.status
        self._carry_out(outputs)

    def _carry_out(self, outputs: list[Output]) -> None:
        for out in outputs:
            if isinstance(out, ModeReport):
                self.publish(ch.RC_MODE, rc_mode_message(out))
            elif isinstance(out, ManualReport):
                if self.sticks is not None:
                    for cmd in self.sticks.commands(out.widths_us):
                        self.publish(ch.MANUAL_CMD, cmd)
            elif out.level == "error":
                self.error(out.text)
            else:
                self.logger.log(logging.WARNING if out.level == "warning" else logging.INFO, "%s", out.text)

    def kill(self) -> None:
        """Drop the enable line, release the lines, then stop."""
        with self._lock:
            self._stopping = True
            self.state.port_open = self.gpio.is_open
            outputs = self.state.stop(host_ns=time.monotonic_ns())
        try:
            self._carry_out(outputs)
        finally:
            self.gpio.close()
            super().kill()

    def health_details(self) -> dict[str, Any]:
        """The port's fields, then the state's: mode, enable line and why, read-back, counters, each channel's width."""
        with self._lock:
            clock_ns = self.state.clock_ns
            details = health_details(self.state, at_ns=time.monotonic_ns() if clock_ns is None else clock_ns,
                                     manual_commands=self.sticks.sent if self.sticks else 0)
        return {**self.gpio.health(), **details}


def rc_mode_message(report: ModeReport) -> t.RcMode:
    """The ``RcMode`` that says *report*."""
    msg = t.RcMode()
    msg.mode, msg.mode_name = report.mode, report.mode_name
    msg.autonomy_enabled, msg.select_mismatch = report.autonomy_enabled, report.select_mismatch
    msg.armed, msg.hold, msg.blocked_by = report.armed, report.hold, report.blocked_by
    msg.pulse_us = list(report.pulse_us)
    msg.num_channels = len(msg.pulse_us)
    return msg
