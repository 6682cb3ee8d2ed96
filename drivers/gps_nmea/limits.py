"""The physical range of every value the GPS driver reads, with the reason for each bound.

A value outside its range is not a measurement (a corrupted sentence that still passed
its 8-bit checksum, a firmware fault) and is dropped, never clamped: ``u2sa_hw.drivers.gps_nmea.fix``
records the kind, the driver counts it in health (``out_of_range``) and logs each kind once.

The bounds for speed and altitude are the civil export limits every GNSS receiver obeys
(COCOM: a receiver stops giving a solution above 1,000 knots or above 18,000 m), so a
larger value cannot come from a working receiver; the altitude floor is below any place
a GNSS solution can be had (the Dead Sea shore is at -430 m).
"""

from __future__ import annotations

from typing import NamedTuple


class Limit(NamedTuple):
    """Inclusive range of one value (units in the name)."""

    low: float
    high: float


LAT_DEG = Limit(-90.0, 90.0)
LON_DEG = Limit(-180.0, 180.0)
ALT_M = Limit(-1000.0, 18000.0)             # MSL altitude; COCOM ceiling
GEOID_SEP_M = Limit(-120.0, 120.0)          # EGM96 spans -107 .. +85 m
SPEED_MPS = Limit(0.0, 1000.0 * 1852.0 / 3600.0)   # COCOM: 1,000 knots = 514.4 m/s
ANGLE_DEG = Limit(0.0, 360.0)               # course, true heading (360 is read as 0)
DOP = Limit(0.0, 99.0)                      # > 0; receivers send 99.9 / 99.99 for "invalid" (gpsd ignores >= 99)
SIGMA_M = Limit(0.0, 10000.0)               # GST: > 0; beyond 10 km the "fix" carries no position
SATELLITES = Limit(0.0, 255.0)              # NMEA 4.11 GGA/GNS count, used satellites of all systems
GGA_QUALITY = Limit(0.0, 9.0)
DATE_YEAR = Limit(1980.0, 2200.0)           # GPS time starts in 1980


def within(value: float | None, limit: Limit, *, open_low: bool = False) -> bool:
    """True when *value* (not None) is within *limit*; ``open_low`` excludes the low end (sigmas, DOPs)."""
    if value is None or not (limit.low <= value <= limit.high):   # NaN fails both comparisons
        return False
    return not (open_low and value == limit.low)
