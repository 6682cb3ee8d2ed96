"""Actuator outputs as the mocks see them, and how they move the simulated vehicle.

Every actuator output of a simulation is watched at the device, never on the bus:

* a CAN motor: the setpoint the mock ODrive/VESC node applies (on each setpoint frame, and
  when its own watchdog or command timeout stops the motor), through :class:`MotorInput`;
* a PWM output: the pulse width the PCA9685 chip model or the sysfs PWM mock produces,
  sampled by :class:`OutputPoller`;
* a GPIO output: the level of the line on the mock chip (its output callback).

:class:`OutputLog` keeps, per output, a timeline of (time, value, neutral) changes, which
the scenario runner reads to say when each output went neutral and moved again.

A PWM output listed in the profile's ``[safety] hardware_mux`` is physically wired through
the RC mux: what reaches the servo or ESC is the pilot's RC channel while the mux selects
the pilot and the SBC's pulse while it selects autonomy (:class:`PwmFeed`). Nothing else is
switched by the simulated mux, as no real mux can cut a CAN frame or an I2C write.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

NEUTRAL_TOLERANCE_PCT = 1.0    # a PWM output within this of its neutral pulse counts as neutral
POLL_HZ = 200.0                # PWM outputs are sampled this often (the resolution of the measured times)


@dataclass(frozen=True)
class OutputChange:
    """One change of an output: monotonic ns, value (% of full scale, or a GPIO level), neutral or not."""

    t_ns: int
    value: float
    neutral: bool


class OutputLog:
    """Per output name, the changes of its value as the device saw them; thread-safe."""

    def __init__(self, *, max_changes: int = 50_000) -> None:
        self._lock = threading.Lock()
        self._changes: dict[str, list[OutputChange]] = {}
        self._kinds: dict[str, str] = {}
        self._max = max_changes

    def declare(self, name: str, kind: str) -> None:
        """Make *name* (of *kind*: can, pwm, gpio) known, neutral at start."""
        with self._lock:
            self._kinds.setdefault(name, kind)
            self._changes.setdefault(name, [OutputChange(time.monotonic_ns(), 0.0, True)])

    def record(self, name: str, value: float, *, neutral: bool, t_ns: int | None = None) -> None:
        """Note *value* for *name* when it differs from the last one noted."""
        with self._lock:
            changes = self._changes.setdefault(name, [])
            if changes and changes[-1].value == value and changes[-1].neutral == neutral:
                return
            if len(changes) >= self._max:
                del changes[: self._max // 2]
            changes.append(OutputChange(time.monotonic_ns() if t_ns is None else t_ns, float(value), neutral))

    def names(self) -> list[str]:
        """Every output seen, in the order they were declared."""
        with self._lock:
            return list(self._changes)

    def kind(self, name: str) -> str:
        """can, pwm or gpio."""
        with self._lock:
            return self._kinds.get(name, "?")

    def timeline(self, name: str) -> list[OutputChange]:
        """A copy of *name*'s changes, oldest first."""
        with self._lock:
            return list(self._changes.get(name, ()))

    def current(self, name: str) -> OutputChange | None:
        """The last change of *name*."""
        with self._lock:
            changes = self._changes.get(name)
            return changes[-1] if changes else None


class MotorInput:
    """What one CAN motor node drives: forwards to the routed vehicle and logs the setpoint as % of full scale."""

    def __init__(self, routed: Any, *, actuator: str, log: OutputLog) -> None:
        self._routed = routed
        self.actuator = actuator
        self._log = log
        log.declare(actuator, "can")

    def __getattr__(self, name: str) -> Any:   # model, snapshot(), max_speed of the vehicle
        return getattr(self._routed, name)

    def set_wheel_speed(self, side: str, speed_mps: float) -> None:
        """A wheel node's output (m/s); logged as % of the vehicle's top speed."""
        self._log.record(self.actuator, round(100.0 * speed_mps / self._routed.max_speed, 3), neutral=speed_mps == 0)
        self._routed.set_input(side, speed_mps)

    def set_thrust(self, side: str, fraction: float) -> None:
        """A thruster node's output (-1..1)."""
        self._log.record(self.actuator, round(100.0 * fraction, 3), neutral=fraction == 0)
        self._routed.set_input(side, fraction)


@dataclass
class PwmFeed:
    """One PWM output: where its pulse is read, its calibration, what it drives, whether the mux switches it."""

    actuator: str
    read_us: Callable[[], float]          # the SBC's pulse on this output, 0 = no pulse
    min_us: float = 1000.0
    neutral_us: float = 1500.0
    max_us: float = 2000.0
    reverse: bool = False
    drives: str | None = None             # vehicle input: steering, throttle, left, right (None: nothing)
    rc_channel: str | None = None         # [safety] hardware_mux: the RC channel the mux passes in manual
    mux: Any = None                       # the MuxMock, when rc_channel is set

    def pulse_us(self) -> float:
        """The pulse that reaches the servo or ESC (after the mux, for a muxed output)."""
        if self.rc_channel is not None and self.mux is not None and self.mux.selected != "autonomous":
            return self.mux.rc_pulse_us(self.rc_channel) or 0.0
        return self.read_us()

    def percent(self, us: float) -> float:
        """-100..100 from a pulse, through the channel's own calibration; 0 for no pulse."""
        if us <= 0:
            return 0.0
        span = (self.max_us - self.neutral_us) if us >= self.neutral_us else (self.neutral_us - self.min_us)
        p = max(-100.0, min(100.0, 100.0 * (us - self.neutral_us) / span)) if span > 0 else 0.0
        return -p if self.reverse else p


@dataclass
class GpioFeed:
    """One GPIO output line: its level is logged; with drives = "enable" it gates the propulsion."""

    actuator: str
    chip: Any
    line: int
    safe_level: int = 0
    drives: str | None = None


@dataclass
class Feeds:
    """Every PWM and GPIO output of a simulation."""

    pwm: list[PwmFeed] = field(default_factory=list)
    gpio: list[GpioFeed] = field(default_factory=list)


class OutputPoller:
    """Samples the PWM outputs at POLL_HZ: logs each and hands the driven ones to the vehicle."""

    def __init__(self, feeds: Feeds, *, routed: Any, log: OutputLog, hz: float = POLL_HZ) -> None:
        self.feeds = feeds
        self.routed = routed
        self.log = log
        self.period = 1.0 / hz
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        for feed in feeds.pwm:
            log.declare(feed.actuator, "pwm")
        for gpio in feeds.gpio:
            log.declare(gpio.actuator, "gpio")
            log.record(gpio.actuator, gpio.safe_level, neutral=True)

    def start(self) -> "OutputPoller":
        """Watch the GPIO lines and start sampling the PWM outputs."""
        for gpio in self.feeds.gpio:
            gpio.chip.on_output(lambda line, value, t_ns, g=gpio: self._on_gpio(g, line, value, t_ns))
            self._on_gpio(gpio, gpio.line, gpio.chip.read_output(gpio.line), time.monotonic_ns())
        if self.feeds.pwm:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="pwm-outputs", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop sampling."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def sample(self) -> None:
        """One pass over the PWM outputs (the thread calls it; tests may too)."""
        for feed in self.feeds.pwm:
            try:
                us = feed.pulse_us()
            except (OSError, ValueError):
                us = 0.0
            pct = feed.percent(us)
            self.log.record(feed.actuator, round(pct, 2), neutral=abs(pct) < NEUTRAL_TOLERANCE_PCT)
            if feed.drives is not None:
                self.routed.set_fraction(feed.drives, pct / 100.0)

    def _on_gpio(self, gpio: GpioFeed, line: int, value: int, t_ns: int) -> None:
        if line != gpio.line or value < 0:
            return
        self.log.record(gpio.actuator, value, neutral=value == gpio.safe_level, t_ns=t_ns)
        if gpio.drives == "enable":
            self.routed.enable(value != gpio.safe_level)

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            self.sample()
            next_t += self.period
            if time.monotonic() - next_t > 1.0:
                next_t = time.monotonic()
