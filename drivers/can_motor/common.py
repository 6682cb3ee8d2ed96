"""What the CAN motor drivers share: the bus, the actuator names, command timing, odometry.

:class:`CanMotorService` is an Actuator (Percentage Commands addressed to any of its
``actuators`` names; neutral on stop, kill, failsafe and command timeout) that drives one
motor controller per name on one CAN bus, and a wheel-odometry sensor: when two of its
wheels form a differential pair it publishes body speed and yaw rate (FRD) as State
Information. The bus is opened through :class:`~u2sa_hw.ports.ReconnectingPort`, so a lost
adapter is reported in health and reopened with backoff; with ``record_raw`` every frame is
published as ``RawCanFrame`` on ``RAW.<device>``.
Its settings, their check and :class:`~u2sa_hw.drivers.can_motor.settings.MotorSpec` are in
:mod:`u2sa_hw.drivers.can_motor.settings`.

One thread runs the bus: it receives frames (handed to :meth:`handle_frame`) and calls
:meth:`tick` every ``TICK_S`` for the controller's own work (re-sending setpoints, arming,
polling). Bus callbacks (commands, failsafe) run on the transport's thread; both paths take
``self.lock``. The vendor subclasses are ``u2sa_hw.drivers.can_motor.odrive.driver`` and ``u2sa_hw.drivers.can_motor.vesc.driver``.

The driver's time (:meth:`CanMotorService.now`: frame handling, ticks, silence, setpoint timing)
is the port's clock: ``time.monotonic()`` on a real bus, the recorded frames' times on a replay's
stamped bus (``clock=stamped``, :mod:`u2sa_hw.ports.can.clock`), so a replayed node is silent,
and its odometry restarted, only where the recording says so, however fast the replay runs.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any, ClassVar, Mapping

if TYPE_CHECKING:
    import can   # python-can loads when the port opens (u2sa_hw/ports/can/port.py)

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import Actuator
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence setters
from u2sa_hw.ports import PortClosed, PortError, PortIOError, PortUnavailable
from u2sa_hw.ports.can.port import CanPort
from u2sa_hw.ports.device_link import DeviceLink, device_setting

from u2sa_hw.drivers.can_motor.declarations import CanMotorDeclarations
from u2sa_hw.drivers.can_motor.diff_drive_odometry import BodyMotion, DiffDriveOdometry
from u2sa_hw.drivers.can_motor.settings import ODOMETRY_FIELDS, PORT_FIELDS, CanMotorSettings, MotorSpec
from u2sa_hw.drivers.can_motor.stall_trip import StallWatch, trip_gap_s

TICK_S = 0.01


class CanMotorService(CanMotorSettings, CanMotorDeclarations, Actuator):
    """Base of the CAN motor drivers (see the module docstring); its settings: drivers/can_motor/settings.py."""

    ID_FIELD: ClassVar[str] = "node_ids"

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.lock = threading.RLock()
        self.motors: dict[str, MotorSpec] = {}
        self.frames_rx = self.frames_tx = self.dropped = self.tx_failed = 0
        self.odometry_published = 0
        self.odometry: DiffDriveOdometry | None = None
        self._link: DeviceLink[CanPort] = DeviceLink(
            self, device=lambda: device_setting(self.config, self.name), raw_type=t.RawCanFrame,
            before_close=self._park_old_bus)
        self._current: CanPort | None = None
        self._reopen = False
        self.started_at = time.monotonic()  # since when a controller never heard counts as silent
        self._clock_seen = False             # a stamped port's first frame has restarted started_at
        self._reason = ""
        self._logged_drops: set[str] = set()
        self.stalls = StallWatch()   # this driver's own stalls, on time.monotonic(): drivers/can_motor/stall_trip.py
        self._silence_judged_from = 0.0   # time.monotonic(): no node is called silent before this
        self.check_settings(self.config.get)
        self._build()

    # -- config ------------------------------------------------------------------------------
    def check_config(self) -> None:
        """Refuse a config this driver cannot run with (the dead-man as every actuator). Offline (``u2sa check``
        builds the driver without its link, and checks the device addresses itself) the bus is not looked at."""
        super().check_config()
        self.check_settings(self.config.get)
        link = getattr(self, "_link", None)
        problem = link.check() if link is not None else None
        if problem:
            raise self._fail(f"{problem} (e.g. \"can://socketcan/can0?bitrate=500000\")")

    def _build(self) -> None:
        cfg = self.config
        self.motors = {n: MotorSpec(n, int(i), int(d), float(r)) for n, i, d, r in zip(
            cfg.get("actuators"), cfg.get(self.ID_FIELD), cfg.get("directions"), cfg.get("wheel_radius_m"))}
        self.odometry = DiffDriveOdometry(
            track_width_m=cfg.get("track_width_m"), source=cfg.get("odometry_source"),
            window_s=cfg.get("odometry_window_s")) if cfg.get("odometry") else None

    @property
    def device_name(self) -> str:
        """The bus's name in port errors and taps (``device``, else the service name)."""
        return device_setting(self.config, self.name)

    def actuator_names(self) -> set[str]:
        """The configured actuator names."""
        return set(self.motors)

    @classmethod
    def declared_actuators(cls, name: str, config: Mapping[str, Any]) -> set[str]:
        """The names of ``actuators``."""
        return {str(a) for a in config["actuators"]}

    def on_config_change(self, name: str, value: Any) -> None:
        """Bus fields reopen the port, odometry fields restart the odometry (checked by validate_config)."""
        with self.lock:
            if name in PORT_FIELDS:
                self._reopen = True
            if name in ODOMETRY_FIELDS:
                self._build()
            if name == "record_raw" and value:
                self._link.record_changed()

    # -- the bus -------------------------------------------------------------------------------
    def now(self) -> float:
        """The driver's time (s, ``time.monotonic()`` base): the open port's clock (a replay's recorded
        frame times on a stamped bus), else the wall clock."""
        port = self._current
        return port.now() if port is not None and port.is_open else time.monotonic()

    def send(self, msg: can.Message) -> bool:
        """Send one frame if the bus is open; False (counted) when it is not or the send failed."""
        port_holder = self._link
        if port_holder.state != "open":
            self.tx_failed += 1
            return False
        try:
            port = port_holder.get()  # open: returns the port without calling the opener
        except PortError:
            self.tx_failed += 1
            return False
        try:
            port.send(msg, timeout=0.05)
        except (PortClosed, PortIOError) as exc:
            self.tx_failed += 1
            if isinstance(exc, PortClosed):
                port_holder.lost(exc, port=port)
            self.error(str(exc))
            return False
        self.frames_tx += 1
        return True

    def setup(self) -> None:
        """Resolve the bus's address (opened by the run loop) and declare what we publish."""
        self.register_publisher(ch.STATE_INFO, t.StateInformation)
        self.started_at = self.now()
        self._link.start()

    def run(self) -> None:
        """Receive frames and tick the controllers until stopped; survive bus loss and bad frames."""
        next_tick = time.monotonic()
        while self.wait(0.0):
            if self._reopen:
                self._reopen = False
                self._link.refresh(force=True)   # _park_old_bus first: the old controllers get zero/idle
                with self.lock:
                    self.on_port_lost()
            holder = self._link
            try:
                port = holder.get()
            except PortUnavailable:
                self._tick_and_status()
                self.wait(min(0.1, max(0.01, holder.retry_in())))
                continue
            except PortClosed:
                break  # closed by kill()
            if port is not self._current:  # (re)opened: controllers get silent_after_s to be heard
                self._current = port
                self._clock_seen = False
                self.started_at = self.now()
            try:
                msg = port.recv(max(0.0, min(next_tick - time.monotonic(), TICK_S)))
            except (PortClosed, PortIOError) as exc:
                holder.lost(exc, port=port)
                self.error(str(exc))
                with self.lock:
                    self.on_port_lost()
                continue
            if msg is not None:
                if port.clock is not None and port.clock.started and not self._clock_seen:   # it starts here
                    self._clock_seen = True
                    self.started_at = self.now()
                self._dispatch(msg)
            if time.monotonic() >= next_tick:
                next_tick = time.monotonic() + TICK_S
                self._tick_and_status()

    def _park_old_bus(self, port: CanPort) -> None:
        """Before a changed bus (``device``, ``channel``...) is closed: zero (then, as on stop, idle) to the
        controllers on it, which would otherwise hold their last setpoint until their own watchdog fires,
        or for ever with it off. The new bus starts from zero too: a command must come again."""
        with self.lock:
            self.zero_outputs()
            self.release()
        self.logger.info("%s: outputs zeroed on the old bus before reopening", self.device_name)

    def _tick_and_status(self) -> None:
        stall = self.stalls.turn(time.monotonic())
        if stall is not None:   # the frames that queued meanwhile are read first: they say who is silent
            self._silence_judged_from = stall.end + float(self.config.get("silent_after_s"))
        if stall is not None and stall.duration >= self.stall_trip_gap_s():
            self.logger.warning("%s: this driver stalled (%s): a controller watchdog may have tripped; such a "
                                "trip is cleared at the pilot's next re-arm through manual", self.device_name,
                                stall.describe())
        self.check_command_timeout()
        now = self.now()
        with self.lock:
            self.tick(now)
            reasons = self.problems(now)
        if self._link.state not in ("open", "none"):
            reasons.insert(0, f"CAN bus {self._link.state}")
        if self.failsafe_active:
            reasons.insert(0, "failsafe")
        self._reason = "; ".join(reasons)
        if self.status != "stopping":
            status = "degraded" if reasons else "ok"
            if status != self.status:
                self.status = status
                self.publish_health()   # pre-arm reads it: a cleared trip must not wait for the next interval

    def _dispatch(self, msg: can.Message) -> None:
        self.frames_rx += 1
        if msg.is_error_frame:
            return
        try:
            with self.lock:
                self.handle_frame(msg, self.now())
        except ValueError as exc:  # the protocol modules' decode errors
            self.count_drop(type(exc).__name__, str(exc))

    def stall_trip_gap_s(self) -> float:
        """The shortest stall of this driver that can trip its controllers' watchdogs (hw_watchdog_timeout_s
        less command_period_s); with no watchdog on, silent_after_s (the stall is logged from there)."""
        cfg = self.config
        if cfg.get("hw_watchdog", False):
            return trip_gap_s(watchdog_timeout_s=float(cfg.get("hw_watchdog_timeout_s")),
                              command_period_s=float(cfg.get("command_period_s")))
        return float(cfg.get("silent_after_s"))

    @property
    def judging_silence(self) -> bool:
        """False for ``silent_after_s`` after a stall of this driver: a node whose frames waited in the socket
        while the driver was stopped is not silent, and is heard as soon as they are read."""
        return time.monotonic() >= self._silence_judged_from

    @property
    def link_up(self) -> bool:
        """The bus is open (frames go out and come in)."""
        return self._link.state == "open"

    def count_drop(self, kind: str, detail: str) -> None:
        """A frame that could not be decoded was dropped: counted, logged once per kind."""
        self.dropped += 1
        if kind not in self._logged_drops:
            self._logged_drops.add(kind)
            self.logger.warning("%s: dropping undecodable frames (counted in health; logged once): %s",
                                self.device_name, detail)

    def kill(self) -> None:
        """Neutral, let the controllers go (release), close the bus, then stop."""
        try:
            super().kill()  # Actuator.kill: neutral() first
            with self.lock:
                self.release()
        finally:
            self._link.close()

    # -- actuator --------------------------------------------------------------------------------
    def on_percentage(self, actuator: str, percent: float) -> None:
        """Drive *actuator* to *percent* at once (and keep re-sending it)."""
        with self.lock:
            self.set_output(actuator, percent)

    def neutral(self) -> None:
        """Every controller to zero output, sent at once."""
        with self.lock:
            self.zero_outputs()

    # -- odometry ----------------------------------------------------------------------------------
    def wheel_sample(self, name: str, stamp: float, *, position_m: float | None = None,
                     speed_mps: float | None = None) -> None:
        """A wheel's travel/speed at bus time *stamp* (s); publishes the body motion when a pair is complete."""
        odo, cfg = self.odometry, self.config
        if odo is None:
            return
        side = "left" if name == cfg.get("odometry_left") else "right" if name == cfg.get("odometry_right") else None
        if side is None:
            return
        motion = odo.update(side, stamp, position_m=position_m, speed_mps=speed_mps)
        if motion is not None:
            self._publish_motion(motion)

    def _publish_motion(self, motion: BodyMotion) -> None:
        cfg = self.config
        msg = t.StateInformation()
        msg.sensor_name = self.name
        msg.reference_frame = "FRD"
        wall = time.time()
        msg.header.timestamp_us = int((motion.t if abs(motion.t - wall) < 5.0 else wall) * 1e6)
        sigma_v, sigma_r = cfg.get("speed_sigma_mps"), cfg.get("yaw_rate_sigma_rad_s")
        msg.set(x_dot=motion.speed_mps, y_dot=0.0, psi_dot=motion.yaw_rate_rad_s,
                x_dot_sigma=sigma_v, y_dot_sigma=sigma_v, psi_dot_sigma=sigma_r)
        if self.publish(ch.STATE_INFO, msg):
            self.odometry_published += 1

    @staticmethod
    def frame_time(msg: can.Message) -> float:
        """The frame's bus timestamp (s) if the interface gave one, else wall time now."""
        return float(msg.timestamp) if msg.timestamp else time.time()

    # -- health -------------------------------------------------------------------------------------
    def health_details(self) -> dict[str, Any]:
        """Command state, bus state and counters, per-controller details, odometry counters."""
        details: dict[str, Any] = {
            **super().health_details(),
            "degraded_reason": self._reason,
            **(link := self._link.health()),
            # the same under the CAN names earlier versions published
            "bus": link["port"], "bus_error": link["port_error"], "bus_losses": link["port_losses"],
            "frames_rx": self.frames_rx,
            "frames_tx": self.frames_tx,
            "tx_failed": self.tx_failed,
            "dropped": self.dropped,
            **self.stalls.details(),
        }
        if self.odometry is not None:
            details.update(odometry_published=self.odometry_published, odometry_resets=self.odometry.resets,
                           odometry_unpaired=self.odometry.unpaired)
        with self.lock:
            details.update(self.motor_details())
        return details

    # -- for subclasses (called with self.lock held) -------------------------------------------------
    def handle_frame(self, msg: can.Message, now: float) -> None:
        """One received frame (our own echoes included on udp_multicast); ValueError = undecodable."""
        raise NotImplementedError

    def tick(self, now: float) -> None:
        """Periodic work: re-send setpoints, arm, poll, notice silence."""
        raise NotImplementedError

    def set_output(self, name: str, percent: float) -> None:
        """Set and send the setpoint of actuator *name* (-100..100 %)."""
        raise NotImplementedError

    def zero_outputs(self) -> None:
        """Set and send zero output on every controller."""
        raise NotImplementedError

    def release(self) -> None:
        """On the way out, after neutral: leave the controllers safe (e.g. ODrive IDLE)."""

    def on_port_lost(self) -> None:
        """The bus went away or is being reopened: drop state that depended on it."""

    def problems(self, now: float) -> list[str]:
        """Why the service is degraded (silent nodes, errors); empty when all is well."""
        return []

    def motor_details(self) -> dict[str, Any]:
        """Per-controller health details, keys prefixed with the actuator name."""
        return {}
