"""A calibration as the drivers hold and apply it, and the tilt-compensated heading.

A correction is ``corrected = matrix @ (raw - offset)``, stored in a service's config as an
offset field (3 numbers) and a matrix field (9 numbers, row-major): ``mag_offset`` /
``mag_matrix`` (µT, body FRD) and ``accel_offset`` / ``accel_matrix`` (m/s^2, body FRD).
The defaults, zero offset and identity matrix, mean "not calibrated".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

ZERO3 = [0.0, 0.0, 0.0]
IDENTITY9 = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
# The ranges of the config fields that hold a correction: far past any real sensor's (a magnetometer
# reads a few thousand µT or mG at most; a fitted matrix stays near the identity), yet finite.
MAX_MAG_OFFSET = 100000.0
MAX_MATRIX_ENTRY = 1000.0
MIN_DETERMINANT = 1e-6   # a matrix this close to singular would blow noise up (or flip an axis to zero)


def determinant3(m: Sequence[float]) -> float:
    """The determinant of a row-major 3x3 matrix (the drivers apply a correction without numpy)."""
    return (m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
            + m[2] * (m[3] * m[7] - m[4] * m[6]))


@dataclass(frozen=True)
class Correction:
    """``matrix @ (raw - offset)``; identity/zero is no correction (``calibrated`` False)."""

    offset: tuple[float, float, float]
    matrix: tuple[float, ...]   # 9, row-major

    @classmethod
    def from_config(cls, offset: Sequence[float], matrix: Sequence[float], *, what: str) -> "Correction":
        """Check and build; ValueError naming *what* (e.g. ``"mag_offset/mag_matrix"``) and the rule."""
        o = [float(v) for v in offset]
        m = [float(v) for v in matrix]
        if len(o) != 3 or len(m) != 9:
            raise ValueError(f"{what}: the offset needs 3 numbers and the matrix 9 (row-major), got {len(o)} and "
                             f"{len(m)}; run 'u2sa calibrate' or reset them to {ZERO3} and {IDENTITY9}")
        if not all(math.isfinite(v) for v in o + m):
            raise ValueError(f"{what}: every number must be finite")
        det = determinant3(m)
        if det <= MIN_DETERMINANT:
            raise ValueError(f"{what}: the matrix's determinant is {det:.3g}; it must be positive (a singular or "
                             "mirroring matrix is not a calibration)")
        return cls((o[0], o[1], o[2]), tuple(m))

    @property
    def calibrated(self) -> bool:
        """False for the defaults (zero offset, identity matrix)."""
        return list(self.offset) != ZERO3 or list(self.matrix) != IDENTITY9

    def apply(self, raw: Sequence[float]) -> tuple[float, float, float]:
        """One raw vector corrected."""
        d = [raw[i] - self.offset[i] for i in range(3)]
        m = self.matrix
        return (m[0] * d[0] + m[1] * d[1] + m[2] * d[2],
                m[3] * d[0] + m[4] * d[1] + m[5] * d[2],
                m[6] * d[0] + m[7] * d[1] + m[8] * d[2])


def tilt_compensated_heading(force: Sequence[float], mag: Sequence[float]) -> float | None:
    """Magnetic heading (rad, clockwise from magnetic north, in [-pi, pi)) from body FRD vectors.

    *force* is the accelerometer's specific force (m/s^2, ``(0, 0, -g)`` level and still) and
    gives roll and pitch; *mag* is the corrected field. The field is levelled by that roll and
    pitch and the heading is ``atan2(-east part, north part)``. None when either vector is
    zero or not finite. The tilt is right only while the vehicle does not accelerate: a
    sustained acceleration a tilts the estimate by about atan(a / g).
    """
    fx, fy, fz = force
    if not all(math.isfinite(v) for v in (fx, fy, fz)) or fx * fx + fy * fy + fz * fz == 0.0:
        return None
    return heading_at_attitude(math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz)), mag)


def heading_at_attitude(roll: float, pitch: float, mag: Sequence[float]) -> float | None:
    """Magnetic heading (rad in [-pi, pi)) of a body FRD field *mag* levelled by *roll* and *pitch* (rad)."""
    mx, my, mz = mag
    if not all(math.isfinite(v) for v in (roll, pitch, mx, my, mz)) or mx * mx + my * my + mz * mz == 0.0:
        return None
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    north = mx * cp + my * sr * sp + mz * cr * sp
    east = my * cr - mz * sr
    heading = math.atan2(-east, north)
    return (heading + math.pi) % (2 * math.pi) - math.pi
