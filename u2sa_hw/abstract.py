"""The abstract layer (requirements A1, A2): Sensor and Actuator services.

A proprioceptive sensor publishes State Information with its sensor name and only the
fields it measures (the presence vector says which). An exteroceptive sensor publishes
Object Descriptions. An actuator acts only on commands addressed to its name, maps
-100..100 % to its hardware, goes neutral on stop, on kill, on a failsafe, and when
commands stop arriving for ``command_timeout_s``.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config import field
from u2sa_hw.messages import as_type
from u2sa_hw.service import U2SAService


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
    """A service that acts on Percentage Commands addressed to its name(s)."""

    SERVICE_TYPE: ClassVar[str] = "actuator"
    CONFIG = (
        field("command_timeout_s", 0.5, "no command for this long -> neutral (0 disables)"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.failsafe_active = False
        self.failsafe_sources: dict[str, str] = {}  # source -> reason, for every source holding one
        self.commands_received = 0
        self.commands_ignored = 0
        self._last_command: float | None = None
        self._timed_out = False
        self.register_subscriber(ch.ACTUATOR_CMD, t.ActuatorCommand, self._on_actuator_command)
        self.register_subscriber(ch.FAILSAFE, t.Failsafe, self._on_failsafe)

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

    # -- machinery --------------------------------------------------------------------------
    def _on_actuator_command(self, msg: Any) -> None:
        base = as_type(msg, t.ActuatorCommand)
        if base.actuator_name not in self.actuator_names():
            return
        if self.failsafe_active:
            self.commands_ignored += 1
            return
        self.commands_received += 1
        self._last_command = time.monotonic()
        self._timed_out = False
        if isinstance(msg, t.PercentageCommand):
            pct = msg.percentage
            if pct != pct:  # NaN: refuse rather than drive
                self.commands_ignored += 1
                self.error(f"NaN percentage for {base.actuator_name} ignored")
                return
            self.on_percentage(base.actuator_name, max(-100.0, min(100.0, pct)))
        else:
            self.on_command(msg)

    def _on_failsafe(self, msg: t.Failsafe) -> None:
        # Several services may hold a failsafe (the HSM, an e-stop input): a clear from one
        # must not lower another's, so the actuator stays safe while any source holds one.
        source = msg.header.source or "?"
        if msg.active:
            self.failsafe_sources[source] = msg.reason
        else:
            self.failsafe_sources.pop(source, None)
        active = bool(self.failsafe_sources)
        if active and not self.failsafe_active:
            self.logger.warning("FAILSAFE from %s: %s -> neutral", source, msg.reason)
            self.neutral()
        elif not active and self.failsafe_active:
            self.logger.info("failsafe cleared by %s", source)
        self.failsafe_active = active
        self.status = "degraded" if active else "ok"

    def check_command_timeout(self) -> bool:
        """Go neutral once when commands stopped arriving; True while timed out. Call from ``run``."""
        timeout = float(self.config.get("command_timeout_s"))
        if timeout <= 0 or self._last_command is None:
            return False
        if time.monotonic() - self._last_command > timeout:
            if not self._timed_out:
                self._timed_out = True
                self.logger.warning("no command for %.2f s -> neutral", timeout)
                self.neutral()
            return True
        return False

    def health_details(self) -> dict[str, Any]:
        """Command counters and failsafe/timeout state."""
        return {"commands": self.commands_received, "ignored": self.commands_ignored,
                "failsafe": self.failsafe_active, "failsafe_sources": ",".join(sorted(self.failsafe_sources)),
                "command_timed_out": self._timed_out}

    def kill(self) -> None:
        """Neutral, then release."""
        try:
            self.neutral()
        finally:
            super().kill()
