"""Geoid separation (EGM96, m) anywhere on earth from the built-in 10-degree table.

Used when a receiver leaves the GGA/GNS geoid-separation field empty (older SiRF, some
MTK and Garmin units): without it the ellipsoid height would equal the MSL height, an
error of up to 100 m. Bilinear interpolation of the 10-degree EGM96 grid in
:mod:`u2sa_hw.drivers.gps_nmea.geoid_egm96`, as gpsd does; against the full EGM96 model the error is
about 3 m RMS and at most about 24 m (measured at 20,000 random points; largest where the
geoid is rough: the Andes, the Himalaya, Indonesia), against the up to 107 m that
ignoring the missing field would cost.
"""

from __future__ import annotations

import math

from u2sa_hw.drivers.gps_nmea.geoid_egm96 import GEOID_10DEG, GRID_STEP_DEG

_ROWS = len(GEOID_10DEG)
_COLS = len(GEOID_10DEG[0])


def geoid_separation(lat_deg: float, lon_deg: float) -> float | None:
    """EGM96 geoid height N (m, geoid above the WGS84 ellipsoid) at *lat_deg*, *lon_deg*.

    Ellipsoid height = MSL height + N. None when either coordinate is not a finite number
    or the latitude is outside +-90; any finite longitude is wrapped into [-180, 180).
    """
    if not (math.isfinite(lat_deg) and math.isfinite(lon_deg)) or abs(lat_deg) > 90.0:
        return None
    lon = (lon_deg + 180.0) % 360.0 - 180.0
    y = (lat_deg + 90.0) / GRID_STEP_DEG
    x = (lon + 180.0) / GRID_STEP_DEG
    i = min(int(y), _ROWS - 2)
    j = min(int(x), _COLS - 2)
    fy, fx = y - i, x - j
    south, north = GEOID_10DEG[i], GEOID_10DEG[i + 1]
    lower = south[j] + (south[j + 1] - south[j]) * fx
    upper = north[j] + (north[j + 1] - north[j]) * fx
    return lower + (upper - lower) * fy
