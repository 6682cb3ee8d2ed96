"""RC input and the hardware RC multiplexer (kind ``rc_mux``): the pilot's mode on ``RC_MODE``
and the autonomy-enable line into the mux.

The RC receiver's channel outputs are GPIO inputs; each pulse width is measured from the
edge timestamps (``drivers.rc_pulse.PulseMeter``) and the mode channel's pulses decide
the mode with hysteresis, debounce and a signal timeout (``drivers.rc_pulse.RcModeFilter``).

The autonomy-enable output goes into the mux, whose default side is the pilot (RC). It is
high only while ALL of these hold, and is driven low the moment one fails:

- the mode is autonomous (the pilot's switch, debounced);
- no FAILSAFE is active (dropped from the FAILSAFE callback itself, not the next loop);
- the service is healthy: the GPIO port is open and the mux's select read-back agrees;
- autonomy is armed: with ``require_rearm`` a failsafe, a loss of signal, a read-back
  mismatch, a (re)start and a re-opened GPIO port disarm it, and only the switch passing through manual arms it
  again, so nothing re-enables autonomy behind the pilot's back.

It drops on stop and kill too; a crashed service's request is released and the line falls
to the board's pull-down. ``RcMode`` goes out at ``publish_hz`` and on every change:
``mode`` is the pilot's switch (0 manual, 1 autonomous, 2 no signal), ``autonomy_enabled``
the enable line, so the vehicle is under autonomous control only when both say so;
``pulse_us`` holds the last valid width of each configured channel in config order
(0 when it has none within the signal timeout).
"""

from __future__ import annotations

import threading
import time
from typing import Any, Mapping, NamedTuple

from drivers.gpio_lines import GpioLineSet, check_chip, config_problem, note_restart_needed, parse_line_map
from drivers.rc_pulse import MODE_AUTONOMOUS, MODE_MANUAL, MODE_NAMES, MODE_NO_SIGNAL, PulseMeter, RcModeFilter
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import Sensor
from u2sa_hw.config import ConfigError, field
from u2sa_hw.ports.gpio_port import GpioPort


class RcSetup(NamedTuple):
    """What the config says, checked: channel lines by name, enable and select lines, the pulse meter
    and the mode filter."""

    channels: dict[str, int]
    enable_line: int
    select_line: int
    meter: PulseMeter
    filter: RcModeFilter


class RcMuxDriver(Sensor):
    """RC pulse measurement, mux mode on RC_MODE, and the autonomy-enable line into the mux."""

    CONFIG = (
        field("chip", "", '"/dev/gpiochipN" (gpiodetect lists them) or "mock:/path/to.sock"'),
        field("channels", "throttle=5,steering=6,mode=13",
              "name=line,... the receiver channels (RcMode.pulse_us order)"),
        field("mode_channel", "mode", "the channel of the pilot's manual/autonomous switch"),
        field("enable_line", 21, "output line: autonomy enable into the mux (high = autonomy allowed)"),
        field("select_line", -1, "input line: the mux's select read-back, 1 = autonomous (-1: none)"),
        field("min_pulse_us", 800.0, "shorter pulses are rejected"),
        field("max_pulse_us", 2200.0, "longer pulses are rejected"),
        field("autonomous_above_us", 1700.0, "mode pulse above this asks for autonomous"),
        field("manual_below_us", 1300.0, "mode pulse below this asks for manual"),
        field("debounce_frames", 3, "consecutive frames needed to change the mode"),
        field("signal_timeout_ms", 250.0, "no valid mode pulse for this long -> no signal"),
        field("select_mismatch_ms", 500.0, "read-back disagreeing this long is a mismatch (> signal timeout)"),
        field("require_rearm", True, "after failsafe, signal loss, mismatch or start: switch to manual to re-arm"),
        field("publish_hz", 10.0, "RcMode messages per second (plus one on every change)"),
        field("device_name", "", "device name in port errors and RAW.<device> (empty: the service name)"),
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
        self.failsafe_active, self.failsafe_reason = False, ""
        self.select_level: int | None = None
        self.mismatch, self._mismatch_since = False, None
        self.mismatches = self.enable_changes = 0
        self.signal_losses = 0  # times the mode went from manual/autonomous to no signal
        self._stopping = False
        self._enable_lock = threading.RLock()
        self._changed = threading.Event()  # something a subscriber should hear about at once
        inputs = list(self.channels.values()) + ([self.select_line] if self.select_line >= 0 else [])
        self.device = c["device_name"].strip() or name
        self.gpio = GpioLineSet(self, chip=c["chip"], device=self.device, inputs=inputs,
                                initial_outputs=lambda: {self.enable_line: 0}, record_raw=c["record_raw"],
                                on_open=self._on_open)
        self.register_publisher(ch.RC_MODE, t.RcMode)
        self.register_subscriber(ch.FAILSAFE, t.Failsafe, self._on_failsafe)

    def parse_config(self, c: Mapping[str, Any]) -> RcSetup:
        """Check the config and build the pulse meter and mode filter; ConfigError names the field."""
        name = self.name
        check_chip(c["chip"], service=name)
        channels = parse_line_map(c["channels"], service=name, key="channels")
        if c["mode_channel"] not in channels:
            raise ConfigError(f"service '{name}': mode_channel {c['mode_channel']!r} is not one of the channels "
                              f"({', '.join(channels) or 'none'}); add it to 'channels' as name=line")
        enable, select, used = int(c["enable_line"]), int(c["select_line"]), set(channels.values())
        if enable < 0 or enable in used or select in used | {enable}:
            raise ConfigError(f"service '{name}': enable_line {enable} and select_line {select} must be distinct "
                              f"lines, not RC channel lines {sorted(used)}; enable_line is required")
        if c["publish_hz"] <= 0 or c["select_mismatch_ms"] <= 0:
            raise ConfigError(f"service '{name}': publish_hz and select_mismatch_ms must be > 0")
        try:
            return RcSetup(channels, enable, select,
                           PulseMeter(lines=used, min_us=c["min_pulse_us"], max_us=c["max_pulse_us"]),
                           RcModeFilter(autonomous_above_us=c["autonomous_above_us"],
                                        manual_below_us=c["manual_below_us"], debounce_frames=c["debounce_frames"],
                                        signal_timeout_ns=int(c["signal_timeout_ms"] * 1e6)))
        except ValueError as exc:
            raise ConfigError(f"service '{name}': {exc}") from None

    def validate_config(self, name: str, value: Any) -> str | None:
        """Refuse a change that would leave the service unable to start."""
        return config_problem(self, name, value, self.parse_config)

    def on_config_change(self, name: str, value: Any) -> None:
        """require_rearm and select_mismatch_ms apply at once; lines and thresholds at the next start."""
        note_restart_needed(self, name, live=("require_rearm", "select_mismatch_ms"))

    # -- the enable line -----------------------------------------------------------------
    def autonomy_allowed(self) -> tuple[bool, str]:
        """Whether the enable line may be high, and if not the first reason why not."""
        if self._stopping:
            return False, "stopping"
        if self.failsafe_active:
            return False, f"failsafe ({self.failsafe_reason or 'no reason given'})"
        if not self.gpio.is_open:
            return False, "GPIO port down"
        if self.mismatch:
            return False, "mux select read-back mismatch"
        if self.filter.mode != MODE_AUTONOMOUS:
            return False, f"mode {self.filter.mode_name}"
        if not self.armed:
            return False, "not armed (switch to manual to re-arm)"
        return True, ""

    def update_enable(self) -> None:
        """Drive the enable line to what :meth:`autonomy_allowed` says (safe from any thread)."""
        with self._enable_lock:
            want, why = self.autonomy_allowed()
            if want == self.enabled:
                return
            ok = self.gpio.set(self.enable_line, int(want))
            new = want if ok else False  # a failed write lost the port: the request is released, the line falls
            if new != self.enabled:
                self.enabled = new
                self.enable_changes += 1
                # Handing over to autonomy is normal operation; losing it is worth a warning.
                if new:
                    self.logger.info("autonomy enable HIGH (all conditions hold)")
                else:
                    self.logger.warning("autonomy enable low (%s)", why)
                self._changed.set()

    def _on_failsafe(self, msg: t.Failsafe) -> None:
        with self._enable_lock:
            if msg.active and not self.failsafe_active:
                self.logger.warning("FAILSAFE from %s: %s", msg.header.source or "?", msg.reason)
            self.failsafe_active, self.failsafe_reason = bool(msg.active), msg.reason
            if msg.active and self.config["require_rearm"]:
                self.armed = False
            self.update_enable()
            self._changed.set()

    def _on_open(self, port: GpioPort) -> None:
        # runs inside the opener (under the line set's lock, so not under _enable_lock: lock order
        # is _enable_lock -> line set); the port was requested with the enable line low
        self.enabled = False
        if self.config["require_rearm"]:
            self.armed = False  # the lines were lost (or never held): the pilot re-arms
        self.meter.reset()
        self.select_level = port.get(self.select_line) if self.select_line >= 0 else None

    # -- the loop ------------------------------------------------------------------------
    def run(self) -> None:
        """Measure pulses, follow the mode, drive the enable line and publish until stopped."""
        period = 1.0 / self.config["publish_hz"]
        next_publish = time.monotonic()
        while self.wait(0.0):
            port = self.gpio.port()
            if port is None:
                self.wait(min(0.05, max(0.01, self.gpio.retry_in())))
            else:
                for edge in self.gpio.read_edges(port, 0.02):
                    self._on_edge(edge.line, edge.rising, edge.timestamp_ns)
            now_ns = time.monotonic_ns()
            if self.filter.check_signal(now_ns):
                self._mode_changed()
            self._check_select(now_ns)
            self.update_enable()
            self._refresh_status()
            now = time.monotonic()
            if self._changed.is_set() or now >= next_publish:
                self._changed.clear()
                self.publish_mode()
                next_publish = max(next_publish + period, now)

    def _on_edge(self, line: int, rising: bool, timestamp_ns: int) -> None:
        if line == self.select_line:
            self.select_level = int(rising)
            return
        pulse = self.meter.feed(line, rising, timestamp_ns)
        if pulse is None:
            return
        self.widths[self.names_by_line[line]] = (pulse.width_us, pulse.end_ns)
        if line == self.mode_line and self.filter.on_frame(pulse.width_us, pulse.end_ns):
            self._mode_changed()

    def _mode_changed(self) -> None:
        mode = self.filter.mode
        if mode == MODE_NO_SIGNAL:
            self.signal_losses += 1
            self.logger.warning("RC mode %s: no valid mode pulse for %.0f ms (signal loss %d)", MODE_NAMES[mode],
                                self.filter.signal_timeout_ns / 1e6, self.signal_losses)
        else:
            self.logger.info("RC mode %s", MODE_NAMES[mode])
        with self._enable_lock:
            if mode == MODE_MANUAL:
                self.armed = True
            elif mode == MODE_NO_SIGNAL and self.config["require_rearm"]:
                self.armed = False
        self._changed.set()

    def _check_select(self, now_ns: int) -> None:
        if self.select_level is None:
            return
        if self.select_level == int(self.enabled):
            if self.mismatch:
                self.logger.info("mux select read-back agrees again (%s)", "autonomous" if self.enabled else "rc")
                self.mismatch = False
                self._changed.set()
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
            self._changed.set()

    def _refresh_status(self) -> None:
        if self._stopping:
            return
        bad = not self.gpio.is_open or self.mismatch or self.filter.mode == MODE_NO_SIGNAL
        self.status = "degraded" if bad else "ok"

    def pulse_widths_us(self) -> list[int]:
        """Each channel's last valid width (us, config order); 0 when none within the signal timeout."""
        now_ns, widths = time.monotonic_ns(), []
        for name in self.channels:
            last = self.widths.get(name)
            widths.append(round(last[0]) if last and now_ns - last[1] <= self.filter.signal_timeout_ns else 0)
        return widths

    def publish_mode(self) -> bool:
        """Publish the present RcMode on RC_MODE."""
        msg = t.RcMode()
        msg.mode, msg.mode_name = self.filter.mode, self.filter.mode_name
        msg.autonomy_enabled, msg.select_mismatch = self.enabled, self.mismatch
        msg.pulse_us = self.pulse_widths_us()
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
            "enable_blocked_by": "" if allowed else why, "armed": self.armed, "failsafe": self.failsafe_active,
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
