"""State Estimator (requirement S1; thesis 3.2.3.1, 4.5.2.2).

In pass-through mode each State Information received on ``STATE_INFO`` has its present
fields copied into the running estimate, which is published on ``STATE_ESTIMATE`` (the
thesis's FlightGear and UGV estimators). Sensors are registered by name on their first
message and reported in health.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config import field
from u2sa_hw.messages import STATE_FIELDS
from u2sa_hw.service import U2SAService


class StateEstimator(U2SAService):
    """Fuses State Information from any number of sensors into STATE_ESTIMATE."""

    SERVICE_TYPE: ClassVar[str] = "state_estimator"
    CONFIG = (
        field("mode", "passthrough", "passthrough: copy present fields of each message into the estimate"),
        field("sensor_timeout_s", 2.0, "a sensor silent for this long is reported in health"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.estimate = t.StateInformation()
        self.estimate.sensor_name = name
        self.estimate.reference_frame = "NED"
        self.sensors: dict[str, float] = {}
        self.register_subscriber(ch.STATE_INFO, t.StateInformation)
        self.register_publisher(ch.STATE_ESTIMATE, t.StateInformation)

    def callback(self, data: Any) -> None:
        """Fold a State Information into the estimate and publish it (pass-through)."""
        if not isinstance(data, t.StateInformation):
            super().callback(data)
            return
        if data.sensor_name not in self.sensors:
            self.logger.info("new sensor '%s' (fields: %s)", data.sensor_name, ", ".join(data.present_fields()))
        self.sensors[data.sensor_name] = time.monotonic()
        self.copy_present(data, self.estimate)
        self.estimate.header.timestamp_us = data.header.timestamp_us
        if data.reference_frame:
            self.estimate.reference_frame = data.reference_frame
        self.publish(ch.STATE_ESTIMATE, self.estimate)
        self.estimate.header.timestamp_us = 0

    @staticmethod
    def copy_present(src: t.StateInformation, dst: t.StateInformation) -> None:
        """Copy every field present in *src* into *dst* (marking it present there)."""
        pv = src.presence_vector
        for bit, name in enumerate(STATE_FIELDS):
            if pv >> bit & 1:
                setattr(dst, name, getattr(src, name))
        dst.presence_vector |= pv

    def health_details(self) -> dict[str, Any]:
        """Known sensors and the silent ones."""
        now = time.monotonic()
        timeout = float(self.config.get("sensor_timeout_s"))
        silent = [n for n, seen in self.sensors.items() if now - seen > timeout]
        if silent and self.status == "ok":
            self.status = "degraded"
        elif not silent and self.status == "degraded":
            self.status = "ok"
        return {"mode": self.config.get("mode"), "sensors": ",".join(sorted(self.sensors)),
                "silent_sensors": ",".join(sorted(silent))}
