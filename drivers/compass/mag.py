"""Heading from an OS5000's own field values, corrected by this system's calibration.

With ``raw_field = true`` (and ``format = "os5000"`` with the compass's Mx/My/Mz outputs
enabled, ``<esc>X``), the driver does not take the compass's ``C`` heading: it corrects
the field ``(Mx, My, Mz)`` with ``mag_offset``/``mag_matrix`` (``matrix @ (raw - offset)``,
the unit of the sentence, mG) and levels it with the sentence's pitch and roll (level when
the sentence has none). This is the choice for a compass whose own hard/soft-iron
calibration cannot be run on the vehicle, or to calibrate it with ``u2sa calibrate
compass`` like the MPU-9250. The OS5000's field axes are taken as its pitch/roll axes:
x forward, y right, z down (FRD). Uncalibrated (zero/identity), the compass's own heading is
used. ``calibration_stream_s`` set over the bus publishes the raw field on
``CAL.<service>`` (State Information x, y, z in mG) for that many seconds.
"""

from __future__ import annotations

import math
import time
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.calibration.correction import IDENTITY9, MAX_MAG_OFFSET, MAX_MATRIX_ENTRY, ZERO3, Correction, heading_at_attitude
from u2sa_hw.config.fields import ConfigError, field

from u2sa_hw.drivers.compass.os5000_format import Os5000Reading

CAL_PREFIX = "CAL."
MAX_FIELD_MG = 1e6    # 100 G: far beyond any compass's range (the Earth's field is 250-650 mG)
CONFIG = (
    field("raw_field", False, "os5000: heading from the sentence's Mx/My/Mz corrected by mag_offset/mag_matrix "
                              "(u2sa calibrate compass) instead of the compass's own C heading"),
    field("mag_offset", list(ZERO3), "raw_field: hard iron (the sentence's field unit, mG; FRD)", item_type=float, ge=-MAX_MAG_OFFSET, le=MAX_MAG_OFFSET),
    field("mag_matrix", list(IDENTITY9), "raw_field: soft iron, 9 numbers row-major; identity with a zero offset = "
                                         "uncalibrated (the compass's own heading is used)", item_type=float, ge=-MAX_MATRIX_ENTRY, le=MAX_MATRIX_ENTRY),
    field("calibration_stream_s", 0.0, "raw_field: seconds to publish the raw field on CAL.<service> for u2sa "
                                       "calibrate (0: off; only a change over the bus starts it)", ge=0, le=3600),
)


class CompassFieldHeading:
    """The calibration of one serial compass service and its CAL stream."""

    def __init__(self, service: Any) -> None:
        self.service = service
        self.correction = Correction((0.0, 0.0, 0.0), tuple(IDENTITY9))
        self.stream_until = 0.0

    def load(self) -> None:
        """Build the correction from the config; ConfigError naming the fields."""
        cfg = self.service.config
        try:
            self.correction = Correction.from_config(cfg.get("mag_offset"), cfg.get("mag_matrix"),
                                                     what=f"service '{self.service.name}': mag_offset/mag_matrix")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

    @property
    def enabled(self) -> bool:
        """``raw_field`` on (os5000 only)."""
        return bool(self.service.config.get("raw_field"))

    def on_config_change(self, name: str, value: Any) -> None:
        """Apply a new calibration at once; start or stop the stream."""
        if name in ("mag_offset", "mag_matrix"):
            self.load()
        elif name == "calibration_stream_s":
            self.stream_until = time.monotonic() + float(value) if float(value) > 0 else 0.0

    def heading(self, reading: Os5000Reading, *, pitch: float | None, roll: float | None) -> float | None:
        """Magnetic heading (deg, 0..360) from the corrected field, or None (no field, uncalibrated, raw_field
        off); also streams the raw field while asked to."""
        if not self.enabled or None in (reading.mag_x, reading.mag_y, reading.mag_z):
            return None
        if abs(pitch or 0.0) > 90.0 or abs(roll or 0.0) > 180.0:
            return None    # an impossible attitude (dropped and counted by the driver) cannot level the field
        raw = (float(reading.mag_x), float(reading.mag_y), float(reading.mag_z))  # type: ignore[arg-type]
        if not all(abs(v) < MAX_FIELD_MG for v in raw):
            return None    # not a field reading (the parser already refused non-finite values)
        self._stream(raw)
        if not self.correction.calibrated:
            return None
        psi = heading_at_attitude(math.radians(roll or 0.0), math.radians(pitch or 0.0), self.correction.apply(raw))
        return None if psi is None else math.degrees(psi) % 360.0

    def _stream(self, raw: tuple[float, float, float]) -> None:
        if not self.stream_until:
            return
        if time.monotonic() >= self.stream_until:
            self.stream_until = 0.0
            return
        msg = t.StateInformation()
        msg.sensor_name, msg.reference_frame = self.service.name, "FRD"
        msg.set(x=raw[0], y=raw[1], z=raw[2])
        self.service.publish(CAL_PREFIX + self.service.name, msg)

    def details(self) -> dict[str, Any]:
        """Health: whether the field heading is used and calibrated."""
        if not self.enabled:
            return {}
        return {"mag_calibrated": "yes" if self.correction.calibrated else "no",
                "calibration_stream": "on" if self.stream_until else "off"}
