"""Control System service (requirement S5; thesis 3.2.3.5, 4.6.2.5).

Subscribes ``NAV_POINT`` (the planner's body-frame point and desired speed),
``STATE_ESTIMATE`` (yaw rate and velocity), ``RC_MODE`` and ``FAILSAFE``. On each
navigation point it runs the control law (:mod:`.controller`: PID on heading and speed,
:mod:`.mixers` for the drive, rate limits) and publishes one ``PercentageCommand`` per
actuator on ``ACTUATOR_CMD``, addressed by actuator name; ``control_rate_hz`` is the least
it publishes: a cycle without a new point (:meth:`~.controller.VehicleController.refresh`)
goes out when nothing did for ``1 / control_rate_hz``. While ``RC_MODE`` is not
autonomous with the mux's autonomy enable on (or is silent), a failsafe is active, or
navigation points stop, the commands are neutral (0 %) and the integrators are reset; an
``RC_MODE`` or ``FAILSAFE`` that ends driving sends neutral at once, and neutral commands
keep going out at the control rate so every actuator sees the system alive and at rest.

A bad ``mixer`` or empty actuator name stops the service at start with the reason; changed
over the bus it is refused in the log and the running mixer is kept.
"""

from __future__ import annotations

import threading
import time
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import MAX_RATE_HZ, MAX_TIMEOUT_S, ConfigError, field
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.services.control.controller import RC_NAMES, ControlSettings, VehicleController
from u2sa_hw.services.control.mixers import MIXERS, Mixer, build_mixer
from u2sa_hw.services.control.pid import PidGains

_MIXER_FIELDS = ("mixer", "left_actuator", "right_actuator", "steering_actuator", "throttle_actuator")


class ControlSystem(U2SAService):
    """Navigation points to actuator percentages, by actuator name."""

    SERVICE_TYPE: ClassVar[str] = "control"
    CONFIG = (
        field("control_rate_hz", 20.0, "the least ACTUATOR_CMD cycles per second (each NAV_POINT makes one too)", gt=0, le=MAX_RATE_HZ),
        field("mixer", "differential", "differential, ackermann or twin_thruster", choices=tuple(MIXERS)),
        field("left_actuator", "left_wheel", "differential/twin_thruster: the left wheel or thruster's actuator name"),
        field("right_actuator", "right_wheel", "differential/twin_thruster: the right one's actuator name"),
        field("steering_actuator", "steering", "ackermann: the steering servo's actuator name (+100 % = full right)"),
        field("throttle_actuator", "throttle", "ackermann: the throttle's actuator name"),
        field("subsystem", "vehicle", "follow the navigation points of this subsystem"),
        field("heading_kp", 80.0, "turn % per rad of heading error", ge=0, le=10000.0),
        field("heading_ki", 5.0, "turn % per rad*s", ge=0, le=10000.0),
        field("heading_kd", 10.0, "turn % per rad/s (on the yaw rate when the estimate has it)", ge=0, le=10000.0),
        field("heading_integral_limit", 20.0, "largest turn % the heading integral may add", ge=0, le=100),
        field("turn_limit_pct", 100.0, "largest |turn| %", ge=0, le=100),
        field("speed_kp", 40.0, "throttle % per m/s of speed error", ge=0, le=10000.0),
        field("speed_ki", 20.0, "throttle % per m", ge=0, le=10000.0),
        field("speed_kd", 0.0, "throttle % per m/s^2", ge=0, le=10000.0),
        field("speed_integral_limit", 40.0, "largest throttle % the speed integral may add", ge=0, le=100),
        field("speed_feedforward", 50.0, "throttle % per m/s of desired speed (100 / top speed)", ge=0, le=10000.0),
        field("throttle_limit_pct", 100.0, "largest |throttle correction| % from the speed PID", ge=0, le=100),
        field("turn_speed_fraction", 0.25, "desired speed kept while the point is abeam or behind (ackermann > 0)", ge=0, le=1),
        field("rate_limit_pct_s", 200.0, "slew limit of every output, %/s (0: none); neutral is immediate", ge=0, le=100000.0),
        field("require_autonomy_enabled", True, "also require RC_MODE's autonomy_enabled (the mux's enable line)"),
        field("nav_timeout_s", 0.5, "no NAV_POINT for this long -> neutral", gt=0, le=MAX_TIMEOUT_S),
        field("rc_timeout_s", 0.25, "no RC_MODE for this long -> neutral (as the actuators, [safety] rc_mode_timeout_ms)", gt=0, le=MAX_TIMEOUT_S),
        field("estimate_timeout_s", 0.5, "an older STATE_ESTIMATE is not used (feedforward only)", gt=0, le=MAX_TIMEOUT_S),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._lock = threading.Lock()
        try:
            mixer = self._mixer()
        except ValueError as exc:
            where = f"{self.config.path} or " if self.config.path else ""
            raise ConfigError(f"{self.name}: {exc} (fix it in {where}the vehicle profile's settings)") from None
        self.controller = VehicleController(settings=self._settings(), mixer=mixer)
        self.commands_sent = 0
        self._last_cycle = -float("inf")   # monotonic time of the latest commands sent
        self._sent: dict[str, float] = {}
        self._logged_reason: str | None = None
        self.register_subscriber(ch.NAV_POINT, t.NavigationPoint, self._on_nav)
        self.register_subscriber(ch.STATE_ESTIMATE, t.StateInformation, self._on_estimate)
        self.register_subscriber(ch.RC_MODE, t.RcMode, self._on_rc_mode)
        self.register_subscriber(ch.FAILSAFE, t.Failsafe, self._on_failsafe)
        self.register_publisher(ch.ACTUATOR_CMD, t.PercentageCommand)

    # -- configuration -----------------------------------------------------------------------
    def _mixer(self) -> Mixer:
        c = self.config.get
        return build_mixer(str(c("mixer")), left=str(c("left_actuator")), right=str(c("right_actuator")),
                           steering=str(c("steering_actuator")), throttle=str(c("throttle_actuator")))

    def _settings(self) -> ControlSettings:
        c = self.config.get

        def f(name: str) -> float:
            return float(c(name))

        heading = PidGains(kp=f("heading_kp"), ki=f("heading_ki"), kd=f("heading_kd"),
                           output_limit=f("turn_limit_pct"), integral_limit=f("heading_integral_limit"))
        speed = PidGains(kp=f("speed_kp"), ki=f("speed_ki"), kd=f("speed_kd"),
                         output_limit=f("throttle_limit_pct"), integral_limit=f("speed_integral_limit"))
        return ControlSettings(heading=heading, speed=speed, speed_feedforward=f("speed_feedforward"),
                               turn_speed_fraction=f("turn_speed_fraction"), rate_limit_pct_s=f("rate_limit_pct_s"),
                               subsystem=str(c("subsystem")), nav_timeout_s=f("nav_timeout_s"),
                               require_autonomy_enabled=bool(c("require_autonomy_enabled")),
                               rc_timeout_s=f("rc_timeout_s"), estimate_timeout_s=f("estimate_timeout_s"))

    def on_config_change(self, name: str, value: Any) -> None:
        """Apply gains, limits and the mixer live; the controller restarts from neutral."""
        with self._lock:
            mixer = self.controller.mixer
            if name in _MIXER_FIELDS:
                try:
                    mixer = self._mixer()
                except ValueError as exc:
                    self.error(f"{name} = {value!r} not applied: {exc}; keeping the {mixer.kind} mixer")
                    return
            old = set(self.controller.mixer.actuators)
            self.controller.configure(settings=self._settings(), mixer=mixer)
        for gone in sorted(old - set(mixer.actuators)):
            self._send(gone, 0.0)   # an actuator dropped by the new mixer is left at rest

    # -- inputs -----------------------------------------------------------------------------
    def _on_nav(self, msg: t.NavigationPoint) -> None:
        with self._lock:
            now = time.monotonic()
            if self.controller.on_nav(msg, now):
                self._cycle(self.controller.step(now), now)

    def _on_estimate(self, msg: t.StateInformation) -> None:
        with self._lock:
            self.controller.on_estimate(msg, time.monotonic())

    def _on_rc_mode(self, msg: t.RcMode) -> None:
        with self._lock:
            before = self.controller.rc.msg.mode if self.controller.rc else None
            now = time.monotonic()
            self.controller.on_rc_mode(msg, now)
            self._neutral_at_once(now)
        if before != msg.mode:
            self.logger.info("RC mode %d (%s)", msg.mode, msg.mode_name or RC_NAMES.get(msg.mode, "unknown"))

    def _on_failsafe(self, msg: t.Failsafe) -> None:
        with self._lock:
            now = time.monotonic()
            change = self.controller.on_failsafe(msg, now)
            self._neutral_at_once(now)
        if change.edge and change.active_after:
            self.logger.warning("FAILSAFE from %s: %s -> neutral", msg.header.source or "?", msg.reason)
        elif change.edge:
            self.logger.info("failsafe cleared by %s", msg.header.source or "?")

    def _neutral_at_once(self, now: float) -> None:
        """While driving, an input that ends it (manual, the enable off, a failsafe) sends neutral now."""
        if not self.controller.neutral_reason and self.controller.why_neutral(now):
            self._cycle(self.controller.refresh(now), now)

    # -- output -----------------------------------------------------------------------------
    def _send(self, actuator: str, percent: float) -> None:
        cmd = t.PercentageCommand()
        cmd.base.actuator_name = actuator
        cmd.percentage = percent
        if self.publish(ch.ACTUATOR_CMD, cmd):
            self.commands_sent += 1

    def _cycle(self, outputs: dict[str, float], now: float) -> None:
        """Publish one cycle's commands (under the lock, so cycles go out in order); log a change of mode.

        Commands equal to the ones last sent (neutral in manual, a hold) go out at the control rate only.
        """
        if not self.running:
            return   # stopping: kill() sends the last word, neutral
        period = 1.0 / max(0.1, float(self.config.get("control_rate_hz")))
        if outputs != self._sent or now - self._last_cycle >= period:
            self._last_cycle, self._sent = now, outputs
            for actuator, percent in outputs.items():
                self._send(actuator, percent)
        reason = self.controller.neutral_reason
        kind = reason.split(" for ")[0]   # "NAV_POINT silent for 0.6 s": logged once, not each tenth of a second
        if kind != self._logged_reason:
            self._logged_reason = kind
            if reason:
                self.logger.info("neutral: %s", reason)
            else:
                self.logger.info("driving")

    def run(self) -> None:
        """Keep commands going out at ``control_rate_hz`` at least when navigation points do not come."""
        while True:
            period = 1.0 / max(0.1, float(self.config.get("control_rate_hz")))
            with self._lock:
                now = time.monotonic()
                if now - self._last_cycle >= period:
                    self._cycle(self.controller.refresh(now), now)
                due = self._last_cycle + period
            if not self.wait(max(0.0, due - time.monotonic())):
                return

    def kill(self) -> None:
        """Send neutral once more on the way out, then release."""
        self.running = False
        try:
            with self._lock:   # a callback's cycle in progress goes out before the neutral, none after it
                for actuator in self.controller.mixer.actuators:
                    self._send(actuator, 0.0)
        finally:
            super().kill()

    def health_details(self) -> dict[str, Any]:
        """Mixer, whether driving or why neutral, errors, outputs, commands sent."""
        with self._lock:
            details = self.controller.summary()
        return {"mixer": self.controller.mixer.kind, **details, "commands_sent": self.commands_sent}
