"""RC input and the hardware RC multiplexer (kind ``rc_mux``): the pilot's mode on ``RC_MODE``
and the autonomy-enable line into the mux.

The RC receiver's channel outputs are GPIO inputs; each pulse width is measured from the
edge timestamps (``u2sa_hw.drivers.rc_mux.pulse.PulseMeter``) and the mode channel's pulses decide
the mode with hysteresis, debounce and a signal timeout (``u2sa_hw.drivers.rc_mux.pulse.RcModeFilter``).

The autonomy-enable output goes into the mux, whose default side is the pilot (RC). It is
high only while ALL of these hold, and is driven low the moment one fails:

- the mode is autonomous (the pilot's switch; leaving autonomy for manual takes one frame,
  anything else ``debounce_frames`` frames alike);
- no FAILSAFE is held by any source (u2sa_hw/failsafe.py; dropped from the FAILSAFE
  callback itself, not the next loop);
- the service is healthy: the GPIO port is open and the mux's select read-back agrees;
- every pre-arm check holds (``[safety.prearm]``, u2sa_hw/safety/prearm.py): a refusal
  names the failed check in ``RcMode.blocked_by``, health and the log; a check lost while
  autonomous takes the profile's ``on_check_lost`` action: ``neutral`` disarms (the line
  drops, the pilot has the hardware-muxed outputs at once), ``hold`` keeps the line but sets
  ``RcMode.hold`` so every output goes neutral until the pilot re-arms;
- autonomy is armed: with ``require_rearm`` a failsafe, a loss of signal, a read-back
  mismatch, a lost pre-arm check, a (re)start and a re-opened GPIO port disarm it, and only
  the switch held at manual for ``debounce_frames`` frames arms it again, so nothing
  re-enables autonomy behind the pilot's back.

With a ``[safety.manual_mixer]`` in the profile the service is also the software half of
the mux: in manual it publishes the sticks, mixed, on ``MANUAL_CMD`` at ``manual_hz``
(drivers/rc_mux/manual.py) for the actuators no hardware mux can switch.

It drops on stop and kill too; a crashed service's request is released and the line falls
to the board's pull-down. ``RcMode`` goes out at ``publish_hz`` and on every change:
``mode`` is the pilot's switch (0 manual, 1 autonomous, 2 no signal), ``autonomy_enabled``
the enable line, so the vehicle is under autonomous control only when both say so;
``pulse_us`` holds the last valid width of each configured channel in config order
(0 when it has none within the signal timeout).

Time. Everything is judged on the port's device clock (CLOCK_MONOTONIC on a real chip, the
recorded edge stamps on a replay chip), in the order of the edges' stamps: before an edge is
taken, whatever falls due up to its stamp happens first, at its own time -- the signal timeout
and the read-back mismatch when they expire, and the timed messages (``RC_MODE`` at
``publish_hz``, ``MANUAL_CMD`` at ``manual_hz``) on a fixed grid of the recorded clock
(:class:`u2sa_hw.drivers.rc_mux.pulse.DueGrid`), each with the state as of its due time. A change of what
``RcMode`` says (mode, enable line, arming, hold, read-back mismatch, the reason autonomy is
blocked) is published at once, as its own message. Live, a timed message waits for an edge
stamped after its due time (or ``TIMED_HOLD_NS`` past it on the clock), so a delivery latency
cannot leave an earlier edge out of it. So what is published depends on the edges and their
stamps, not on how the loop batched its reads: a replay gives the live messages.

On a replay chip (a device clock) the Health, FAILSAFE and STATE_ESTIMATE the pre-arm checks
and the failsafe read come from the chip too, the recorded ones, in order with the edges
(:meth:`u2sa_hw.ports.gpio.port.GpioPort.take_recorded_bus`), and the loop's own stall is not
judged (the replaying machine's load is not the vehicle's): the decision is the recorded one.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Mapping, NamedTuple

from u2sa_hw.drivers.rc_mux.declarations import RcMuxDeclarations
from u2sa_hw.drivers.gpio.lines import (GpioLineSet, check_gpio_device, legacy_gpio_address, note_restart_needed,
                                parse_line_map)
from u2sa_hw.drivers.rc_mux.manual import ManualSticks
from u2sa_hw.drivers.rc_mux.clock import TIMED_HOLD_NS, RcMuxClock
from u2sa_hw.drivers.rc_mux.enable import RcMuxEnable
from u2sa_hw.drivers.rc_mux.pulse import MODE_MANUAL, MODE_NAMES, MODE_NO_SIGNAL, DueGrid, PulseMeter, RcModeFilter
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import Sensor
from u2sa_hw.config.configurator import MAX_RATE_HZ, ConfigError, field
from u2sa_hw.failsafe import FailsafeSources
from u2sa_hw.ports.device_link import device_setting
from u2sa_hw.ports.gpio.port import GpioPort
from u2sa_hw.safety.config import load_safety
from u2sa_hw.safety.prearm import CheckFailure, PrearmChecks
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


class RcMuxDriver(RcMuxDeclarations, RcMuxEnable, RcMuxClock, Sensor):
    """RC pulse measurement, mux mode on RC_MODE, and the autonomy-enable line into the mux."""

    CONFIG = (
        field("device", "", "the chip's lines: its [devices.NAME] table (address gpio://CHIP/LINES) and "
                            "RAW.<device> (empty: the service name)"),
        field("chip", "", 'old form of the address: "/dev/gpiochipN" (gpiodetect lists them) or "mock:/path/to.sock"'),
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
        field("record_raw", False, "publish every edge and write as RawGpioEdge/RawGpioWrite on RAW.<device>"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        c = self.config
        self.channels, self.enable_line, self.select_line, self.meter, self.filter = self.parse_config(c)
        self.mode_line = self.channels[c["mode_channel"]]
        self.names_by_line = {line: n for n, line in self.channels.items()}
        self.widths: dict[str, tuple[float, int]] = {}  # channel -> (width us, falling edge ns)
        self.enabled = False      # what the enable line was last driven to
        self.armed = not c["require_rearm"]
        self.failsafes = FailsafeSources()
        self.safety = check_wiring(self.profile) if self.profile.path else load_safety(self.profile)
        self.sticks = ManualSticks(self.safety.manual_mixer) if self.safety.manual_mixer else None
        self.prearm = PrearmChecks.from_profile(self.profile)
        self.prearm_failures: list[CheckFailure] = []
        self.hold = False
        self.checks_lost = self.stalls = 0
        self.timed_skipped = 0   # timed messages left out because the loop was more than a period behind
        stale_ns = int((self.safety.rc_mode_timeout_s - 1.0 / c["publish_hz"]) * 1e9) - TIMED_HOLD_NS
        self.stall_after_ns = max(20_000_000, min(self.filter.signal_timeout_ns, stale_ns))
        self.select_level: int | None = None
        self.mismatch, self._mismatch_since = False, None
        self.mismatches = self.enable_changes = 0
        self.signal_losses = 0  # times the mode went from manual/autonomous to no signal
        self.clock_ns: int | None = None   # the device clock: the latest time judged (GpioPort.now_ns)
        self.mode_grid, self.manual_grid = DueGrid(c["publish_hz"]), DueGrid(c["manual_hz"])
        self._origin_ns = 0                # the recorded clock's zero on the device clock (a replay chip's)
        self._origin_of: Any = lambda: 0   # where the open port says it is
        self._device_clock = False         # the port is a replay chip: its clock, no wall-clock judgments
        self._recorded_bus: tuple[str, ...] = ()   # bus channels the replay chip hands over instead of the bus
        self._next_publish_ns: int | None = None   # the next RC_MODE due (None: the clock has not started)
        self._next_manual_ns: int | None = None    # the next MANUAL_CMD due (None: not in manual)
        self._published: tuple | None = None       # what the last RcMode said (its state_key)
        self._settled: tuple | None = None         # what the last settle left (RcMuxClock._settle_inputs)
        self._stopping = False
        self._enable_lock = threading.RLock()
        inputs = list(self.channels.values()) + ([self.select_line] if self.select_line >= 0 else [])
        self.gpio = GpioLineSet(self, inputs=inputs, initial_outputs=lambda: {self.enable_line: 0},
                                record_raw=c["record_raw"], on_open=self._on_open)
        self.device = self.gpio.device
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

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> dict[str, str | None]:
        """The GPIO lines of the receiver and the mux (see DeviceLink); old form: ``chip`` and the lines."""
        try:
            lines = [*parse_line_map(str(config.get("channels", "")), service=service, key="channels").values(),
                     int(config.get("enable_line", -1)), int(config.get("select_line", -1))]
        except (ConfigError, TypeError, ValueError):
            lines = []
        legacy = legacy_gpio_address(config, lines) if str(config.get("chip", "")).strip() else None
        return {device_setting(config, service): legacy}

    def on_config_change(self, name: str, value: Any) -> None:
        """require_rearm and select_mismatch_ms apply at once; lines and thresholds at the next start."""
        note_restart_needed(self, name, live=("require_rearm", "select_mismatch_ms"))

    def _on_open(self, port: GpioPort) -> None:
        # runs inside the opener (under the line set's lock, so not under _enable_lock: lock order
        # is _enable_lock -> line set); the port was requested with the enable line low
        self.enabled = False
        if self.config["require_rearm"]:
            self.armed = False  # the lines were lost (or never held): the pilot re-arms
        self.meter.reset()
        self._device_clock = bool(getattr(port, "device_clock", False))
        self._origin_of = port.clock_origin_ns
        if self._device_clock:   # a replay chip: its clock, not the wall clock's time so far
            self.clock_ns, self._next_publish_ns, self._next_manual_ns = None, None, None
            wanted = RECORDED_BUS + ((ch.STATE_ESTIMATE,) if self.prearm.needs_estimate else ())
            taken = port.take_recorded_bus(wanted)
            if taken:   # the recorded inputs replace what the replay bus says: start from none of them
                self._recorded_bus = taken
                self.prearm = PrearmChecks.from_profile(self.profile)
                self.failsafes = FailsafeSources()
        self.select_level = port.get(self.select_line) if self.select_line >= 0 else None

    # -- the loop ------------------------------------------------------------------------
    def run(self) -> None:
        """Measure pulses, follow the mode, drive the enable line and publish until stopped."""
        self.logger.info("%s; manual mixer: %s; on a lost check: %s", self.prearm.describe(),
                         f"{self.sticks.spec.kind} -> {', '.join(self.sticks.spec.actuators)}" if self.sticks else "none",
                         self.safety.on_check_lost)
        last_loop_ns = time.monotonic_ns()
        while self.wait(0.0):
            port = self.gpio.port()
            if port is None:
                self.wait(min(0.05, max(0.01, self.gpio.retry_in())))
            else:
                # each edge (and a replay chip's tick or recorded bus input) in order, whatever falls
                # due before it first, at its own time: what is published depends on the stamps, not
                # on how the reads batched them
                events = self.gpio.read_events(port, 0.02)
                wall_ns = time.monotonic_ns()
                for event in events:
                    self._take(event, wall_ns)
            # after the wait, before anything is published: a stall anywhere in the loop is caught here
            # (on the wall clock: the actuators judge RC_MODE by it; not in a replay, whose load is not the
            # vehicle's)
            if not self._device_clock:
                last_loop_ns = self._check_stall(last_loop_ns)
            # the device clock (CLOCK_MONOTONIC on a real chip; the port down: the wall clock)
            up = port is not None and port.is_open
            if up or not self._device_clock:
                self._step(port.now_ns() if up else time.monotonic_ns(), time.monotonic_ns())
            else:
                self._settle(self.clock_ns)   # a replay chip gone: said at once (its clock went with it)

    def _check_stall(self, last_loop_ns: int) -> int:
        """A loop gap longer than the signal timeout, or long enough that the actuators may have seen
        RC_MODE go stale (the process was stopped or starved), is a signal loss: autonomy must not come
        back without the pilot."""
        now_ns = time.monotonic_ns()
        gap_ns = now_ns - last_loop_ns
        if gap_ns > self.stall_after_ns:
            self.stalls += 1
            with self._enable_lock:
                if self.config["require_rearm"] and self.armed:
                    self.armed = False
                    self.logger.warning("RC service stalled for %.0f ms: disarmed (switch through manual to re-arm)",
                                        gap_ns / 1e6)
                self.update_enable()
        return now_ns

    def _on_edge(self, line: int, rising: bool, timestamp_ns: int) -> None:
        if line == self.select_line:
            self.select_level = int(rising)
            return
        pulse = self.meter.feed(line, rising, timestamp_ns)
        if pulse is None:
            return
        self.widths[self.names_by_line[line]] = (pulse.width_us, pulse.end_ns)
        if line != self.mode_line:
            return
        if self.filter.on_frame(pulse.width_us, pulse.end_ns):
            self._mode_changed(pulse.end_ns)
        if self.filter.manual_confirmed and (not self.armed or self.hold) and not self.failsafes.active:
            with self._enable_lock:
                self.armed, self.hold = True, False
            self.logger.info("armed: the switch is at manual")

    def _mode_changed(self, at_ns: int) -> None:
        mode = self.filter.mode
        if mode == MODE_NO_SIGNAL:
            self.signal_losses += 1
            self.logger.warning("RC mode %s: no valid mode pulse for %.0f ms (signal loss %d)", MODE_NAMES[mode],
                                self.filter.signal_timeout_ns / 1e6, self.signal_losses)
        else:
            self.logger.info("RC mode %s", MODE_NAMES[mode])
        with self._enable_lock:
            if mode == MODE_NO_SIGNAL and self.config["require_rearm"]:
                self.armed = False
        if mode == MODE_MANUAL and self.sticks is not None:
            self.publish_manual(at_ns)  # the pilot has the software-muxed outputs from the first manual frame
            self._next_manual_ns = self.manual_grid.after(at_ns, self._origin_ns)
        else:
            self._next_manual_ns = None

    def _check_select(self, now_ns: int) -> None:
        """The read-back against the enable line at *now_ns*: a disagreement starts (its expiry makes it a
        mismatch, :meth:`_advance`), or ends."""
        if self.select_level is None:
            return
        if self.select_level == int(self.enabled):
            if self.mismatch:
                self.logger.info("mux select read-back agrees again (%s)", "autonomous" if self.enabled else "rc")
                self.mismatch = False
            self._mismatch_since = None
            return
        if self._mismatch_since is None:
            self._mismatch_since = now_ns
        elif not self.mismatch and now_ns - self._mismatch_since > self.config["select_mismatch_ms"] * 1e6:
            self.mismatch = True
            self.mismatches += 1
            with self._enable_lock:
                if self.config["require_rearm"]:
                    self.armed = False
            self.error(f"{self.device}: mux select line {self.select_line} reads "
                       f"{'autonomous' if self.select_level else 'rc'} but autonomy enable is "
                       f"{'high' if self.enabled else 'low'}; check the mux wiring and its mode channel")

    def _refresh_status(self) -> None:
        if self._stopping:
            return
        bad = not self.gpio.is_open or self.mismatch or self.filter.mode == MODE_NO_SIGNAL
        self.status = "degraded" if bad else "ok"

    def pulse_widths_us(self, at_ns: int | None = None) -> list[int]:
        """Each channel's last valid width (us, config order) as of *at_ns* (default: the device clock now);
        0 when none within the signal timeout."""
        if at_ns is None:
            at_ns = self.clock_ns if self.clock_ns is not None else time.monotonic_ns()
        widths = []
        for name in self.channels:
            last = self.widths.get(name)
            widths.append(round(last[0]) if last and at_ns - last[1] <= self.filter.signal_timeout_ns else 0)
        return widths

    def publish_manual(self, at_ns: int | None = None) -> None:
        """Publish the sticks as of *at_ns*, mixed, on MANUAL_CMD (one PercentageCommand per mixed actuator)."""
        if self.sticks is None:
            return
        widths = dict(zip(self.channels, self.pulse_widths_us(at_ns)))
        for cmd in self.sticks.commands(widths):
            self.publish(ch.MANUAL_CMD, cmd)

    def publish_mode(self, at_ns: int | None = None) -> bool:
        """Publish the RcMode as of *at_ns* (default: now) on RC_MODE."""
        msg = t.RcMode()
        with self._enable_lock:
            self._published = self.state_key()
            msg.mode, msg.mode_name = self.filter.mode, self.filter.mode_name
            msg.autonomy_enabled, msg.select_mismatch = self.enabled, self.mismatch
            allowed, why = self.autonomy_allowed()
            msg.armed, msg.hold = self.armed, self.hold
        msg.blocked_by = "" if allowed else why
        msg.pulse_us = self.pulse_widths_us(at_ns)
        msg.num_channels = len(msg.pulse_us)
        return self.publish(ch.RC_MODE, msg)

    def kill(self) -> None:
        """Drop the enable line, release the lines, then stop."""
        with self._enable_lock:
            self._stopping = True
            self.update_enable()
        try:
            self.publish_mode()
        finally:
            self.gpio.close()
            super().kill()

    def health_details(self) -> dict[str, Any]:
        """Mode, enable line and why, read-back, pulse counters and each channel's width."""
        allowed, why = self.autonomy_allowed()
        details: dict[str, Any] = {
            **self.gpio.health(), "mode": self.filter.mode_name, "autonomy_enabled": self.enabled,
            "enable_blocked_by": "" if allowed else why, "armed": self.armed, "hold": self.hold,
            "failsafe": self.failsafe_active, "failsafe_sources": ",".join(sorted(self.failsafes.held())),
            "prearm_failed": "; ".join(f.reason for f in self.prearm_failures), "checks_lost": self.checks_lost, "stalls": self.stalls,
            "timed_skipped": self.timed_skipped,
            "manual_commands": self.sticks.sent if self.sticks else 0,
            "select_readback": "none" if self.select_level is None else self.select_level,
            "select_mismatch": self.mismatch, "select_mismatches": self.mismatches,
            "mode_frames": self.filter.frames, "mode_changes": self.filter.changes,
            "signal_losses": self.signal_losses,
            "enable_changes": self.enable_changes, "pulses": self.meter.pulses,
            "rejected": self.meter.rejected_total,
            "rejected_kinds": ",".join(f"{k}:{n}" for k, n in sorted(self.meter.rejected.items())),
        }
        for name, width in zip(self.channels, self.pulse_widths_us()):
            details[f"{name}_us"] = width
        return details
