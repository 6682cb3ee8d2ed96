"""The abstract layer (requirements A1, A2): Sensor and Actuator services.

A proprioceptive sensor publishes State Information with its sensor name and only the
fields it measures (the presence vector says which). An exteroceptive sensor publishes
Object Descriptions. An actuator acts only on commands addressed to its name, maps
-100..100 % to its hardware, obeys the pilot's RC switch (the software mux), and goes
neutral on stop, on kill, on a failsafe, on a stale RC mode and when commands stop
arriving for ``command_timeout_s`` (docs/safety.md). Its health counts the commands and RC_MODEs it
took late (``taken_late``: its bus handling was held up; u2sa_hw/safety/late_take.py).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, ClassVar, Mapping

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import ConfigError, field
from u2sa_hw.messages import as_type
from u2sa_hw.safety.config import load_safety
from u2sa_hw.safety.gate import AUTONOMOUS, MANUAL, CommandGate
from u2sa_hw.safety.late_take import LateTakeWatch
from u2sa_hw.service.contract import U2SAService

MAX_COMMAND_TIMEOUT_S = 0.5   # the dead-man's longest: the field's bound and check_config's


class Sensor(U2SAService):
    """A service that measures; its unique name is its sensor name."""

    SERVICE_TYPE: ClassVar[str] = "sensor"
    SENSOR_KIND: ClassVar[str] = "sensor"

    @property
    def sensor_name(self) -> str:
        """The sensor's unique name (the service name)."""
        return self.name


class ProprioceptiveSensor(Sensor):
    """A sensor of the vehicle's own state: publishes State Information on ``STATE_INFO``."""

    SENSOR_KIND: ClassVar[str] = "proprioceptive"

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.register_publisher(ch.STATE_INFO, t.StateInformation)

    def publish_state(self, msg: t.StateInformation) -> bool:
        """Publish *msg* as this sensor's measurement (sensor name and a default frame filled in)."""
        msg.sensor_name = self.name
        if not msg.reference_frame:
            msg.reference_frame = "NED"
        return self.publish(ch.STATE_INFO, msg)


class ExteroceptiveSensor(Sensor):
    """A sensor of the environment: publishes Object Descriptions (or extensions) on ``OBJECTS``."""

    SENSOR_KIND: ClassVar[str] = "exteroceptive"

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.register_publisher(ch.OBJECTS, t.ObjectDescription)

    def publish_object(self, obj: Any) -> bool:
        """Publish an ObjectDescription or any extension of it, with this sensor as its source."""
        as_type(obj, t.ObjectDescription).source = self.name
        return self.publish(ch.OBJECTS, obj)


class Actuator(U2SAService):
    """A service that acts on Percentage Commands addressed to its name(s), as the pilot's switch allows.

    The software RC mux lives here (:mod:`u2sa_hw.safety.gate`): autonomous commands
    (``ACTUATOR_CMD``) are obeyed only while the newest ``RC_MODE`` grants autonomy, manual
    commands (``MANUAL_CMD``, the pilot's sticks) only in manual and only for outputs not
    wired through the hardware mux (the profile's ``[safety] hardware_mux``); the outputs
    go neutral when the authority changes, on a failsafe from any source, on a stale
    ``RC_MODE``, and when no obeyed command arrived for ``command_timeout_s`` (the dead-man).
    """

    SERVICE_TYPE: ClassVar[str] = "actuator"
    CONFIG = (
        field("command_timeout_s", 0.25, "dead-man: no obeyed command for this long -> neutral (0 < s <= 0.5; "
                                         "0 = off, allowed only with rc_gating = false)", ge=0, le=MAX_COMMAND_TIMEOUT_S),
        field("rc_gating", True, "obey commands only as the pilot's RC switch allows; false only on a bench "
                                 "without an RC receiver, never on a vehicle", remote=False),
    )
    MAX_COMMAND_TIMEOUT_S: ClassVar[float] = MAX_COMMAND_TIMEOUT_S

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        problem = self._dead_man_problem(self.config["command_timeout_s"])
        if problem:
            raise ConfigError(problem)
        if not self.config["rc_gating"]:
            self.logger.warning("rc_gating = false: autonomous commands are obeyed without the pilot's switch "
                                "(bench only; never on a vehicle)")
        self.safety = load_safety(self.profile)
        self.gate = CommandGate(rc_mode_timeout_s=self.safety.rc_mode_timeout_s,
                                rc_gating=bool(self.config["rc_gating"]))
        self.commands_received = 0
        self.late_takes = LateTakeWatch()   # commands and RC_MODEs taken late: bus handling held up (observed only)
        # One command is admitted and applied, or the authority changes and the outputs go neutral,
        # never interleaved: a command admitted just before a failsafe cannot land after its neutral.
        # Order: this lock, then the driver's own (drivers call check_command_timeout outside theirs).
        self._authority_lock = threading.RLock()
        self._stopping = False
        self._last_command: float | None = None
        self._timed_out = False
        self.register_subscriber(ch.ACTUATOR_CMD, t.ActuatorCommand, self._on_autonomous_command)
        self.register_subscriber(ch.MANUAL_CMD, t.ActuatorCommand, self._on_manual_command)
        self.register_subscriber(ch.FAILSAFE, t.Failsafe, self._on_failsafe)
        self.register_subscriber(ch.RC_MODE, t.RcMode, self._on_rc_mode)

    @classmethod
    def declared_actuators(cls, name: str, config: Mapping[str, Any]) -> set[str]:
        """The actuator names a service of this kind called *name* answers to with *config* (for
        checking a profile before anything starts); default: the service name."""
        return {name}

    def _dead_man_problem(self, value: Any, *, rc_gating: bool | None = None) -> str | None:
        gate = getattr(self, "gate", None)   # running: what the gate enforces, not what a file says
        gating = rc_gating if rc_gating is not None else (gate.rc_gating if gate else bool(self.config["rc_gating"]))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"service '{self.name}': command_timeout_s must be a number of seconds, got {value!r}"
        if 0 < value <= self.MAX_COMMAND_TIMEOUT_S or (value == 0 and not gating):
            return None
        return (f"service '{self.name}': command_timeout_s = {value!r} is out of range; the dead-man must be in "
                f"(0, {self.MAX_COMMAND_TIMEOUT_S}] s (default 0.25); only a bench with rc_gating = false may turn "
                "it off with 0")

    def check_config(self) -> None:
        """Refuse a dead-man outside (0, 0.5] s (rc_gating is ``remote=False``: a remote switch for the
        software RC mux would defeat it); subclasses add their checks and call this."""
        problem = self._dead_man_problem(self.config["command_timeout_s"])
        if problem:
            raise ConfigError(problem)
        super().check_config()

    # -- for subclasses -------------------------------------------------------------------
    def actuator_names(self) -> set[str]:
        """The names this service answers to (default: its service name)."""
        return {self.name}

    def on_percentage(self, actuator: str, percent: float) -> None:
        """Drive *actuator* to *percent* (-100..100, already clamped)."""
        raise NotImplementedError

    def neutral(self) -> None:
        """Put every output in its neutral (safe) state."""
        raise NotImplementedError

    def on_command(self, msg: Any) -> None:
        """A command addressed to us that is not a Percentage Command; logged by default."""
        self.logger.warning("unhandled actuator command %s for %s", type(msg).__name__,
                            as_type(msg, t.ActuatorCommand).actuator_name)

    @property
    def failsafe_active(self) -> bool:
        """True while any source holds a failsafe."""
        return self.gate.failsafes.active

    @property
    def failsafe_sources(self) -> dict[str, str]:
        """Source -> reason for every source holding a failsafe."""
        return self.gate.failsafes.held()

    @property
    def commands_ignored(self) -> int:
        """Commands addressed to us that were not obeyed (no authority, failsafe, NaN)."""
        return self.gate.dropped_total()

    # -- machinery --------------------------------------------------------------------------
    def _on_autonomous_command(self, msg: Any) -> None:
        self._on_command_from(AUTONOMOUS, msg)

    def _on_manual_command(self, msg: Any) -> None:
        if as_type(msg, t.ActuatorCommand).actuator_name in self.safety.hardware_mux:
            return  # the pilot drives this output by wire through the hardware mux
        self._on_command_from(MANUAL, msg)

    def _on_command_from(self, source: str, msg: Any) -> None:
        base = as_type(msg, t.ActuatorCommand)
        if base.actuator_name not in self.actuator_names():
            return
        with self._authority_lock:
            if self._stopping:
                return   # kill() sent the final neutral: nothing may follow it
            self.late_takes.took(int(base.header.timestamp_us))   # here: a wait on this lock is a hold-up too
            now = time.monotonic()
            self._follow_authority(now)
            if self.gate.admit(source, now):
                self._apply(base, msg, now)

    def _apply(self, base: Any, msg: Any, now: float) -> None:
        if isinstance(msg, t.PercentageCommand):
            pct = msg.percentage
            if not math.isfinite(pct):  # NaN or inf: refuse rather than drive
                self.gate.count_drop("not_finite")
                self.error(f"{pct} percentage for {base.actuator_name} ignored")
                return
            self.commands_received += 1
            self._last_command = now
            self._timed_out = False
            self.on_percentage(base.actuator_name, max(-100.0, min(100.0, pct)))
        else:
            self.commands_received += 1
            self._last_command = now
            self._timed_out = False
            self.on_command(msg)

    def _on_rc_mode(self, msg: t.RcMode) -> None:
        self.late_takes.took(int(msg.header.timestamp_us))
        now = time.monotonic()
        self.gate.on_rc_mode(msg, now)
        self._follow_authority(now)

    def _on_failsafe(self, msg: t.Failsafe) -> None:
        change = self.gate.failsafes.apply_message(msg)
        source = msg.header.source or "?"
        if change.edge and change.active_after:
            self.logger.warning("FAILSAFE from %s: %s -> neutral", source, msg.reason)
        elif change.edge:
            self.logger.info("failsafe cleared by %s", source)
        self._follow_authority(time.monotonic())
        if change.active_after:
            self.status = "degraded"   # back to "ok" is the driver's call (its port may be down too)

    def _follow_authority(self, now: float) -> None:
        """Neutral at once when the authority changed (a failsafe, the switch, a stale RC_MODE)."""
        with self._authority_lock:
            new = self.gate.changed(now)
            if new is None:
                return
            self._last_command = None  # the new authority starts from neutral; its first command re-arms the dead-man
            self._timed_out = False
            if new.source is None:
                self.logger.warning("outputs neutral: %s", new.why)
            else:
                self.logger.info("commands now from %s (outputs neutral until its first command)", new.source)
            self.neutral()

    def check_command_timeout(self) -> bool:
        """Apply the stale-RC_MODE check and the dead-man; True while timed out. Call from ``run`` often."""
        with self._authority_lock:
            now = time.monotonic()
            self._follow_authority(now)
            timeout = float(self.config.get("command_timeout_s"))
            if self._last_command is None or timeout <= 0:
                return False
            if now - self._last_command > timeout:
                if not self._timed_out:
                    self._timed_out = True
                    self.logger.warning("no command for %.2f s -> neutral (dead-man)", timeout)
                    self.neutral()
                return True
            return False

    def health_details(self) -> dict[str, Any]:
        """Command counters, who has authority and why not, drops by kind, failsafe/timeout state."""
        auth = self.gate.current
        return {"commands": self.commands_received, "ignored": self.commands_ignored,
                "dropped": self.gate.drops_text(), "authority": auth.source or "none",
                "neutral_because": auth.why, "failsafe": self.failsafe_active,
                "failsafe_sources": ",".join(sorted(self.failsafe_sources)),
                "command_timed_out": self._timed_out, "rc_gating": self.gate.rc_gating,
                "rc_mode_stale": self.gate.stale_rc_modes, **self.late_takes.details()}

    def kill(self) -> None:
        """Neutral, then release; no command is obeyed after this neutral."""
        try:
            with self._authority_lock:
                self._stopping = True
                self.neutral()
        finally:
            super().kill()
