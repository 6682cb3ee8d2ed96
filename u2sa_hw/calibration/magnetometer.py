"""Hard- and soft-iron calibration of a magnetometer by an ellipsoid fit (numpy least squares).

A magnetometer on a vehicle measures ``m = A h + b``: the local field ``h`` (a constant
magnitude in every orientation) distorted by the vehicle's soft iron and the sensor's scale
and misalignment (``A``) and offset by its hard iron (``b``). Turned through every
orientation, the readings lie on an ellipsoid. :func:`fit_ellipsoid` fits the general
quadric ``x' M x + 2 v' x = 1`` to the readings and returns the centre ``b`` and the
symmetric matrix ``W`` that maps the ellipsoid onto a sphere of the mean field strength:
the corrected reading is ``W (m - b)``.

The result is trusted only when the readings cover the sphere of directions
(:func:`coverage`, the share of 26 equal-ish direction bins holding a reading: a vehicle
turned only in the horizontal plane covers the equator alone, and the vertical axis is then
not determined) and when the corrected magnitudes are nearly constant (``residual``: their
standard deviation over their mean).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

MIN_SAMPLES = 50
MIN_COVERAGE = 0.6          # share of the direction bins
MAX_RESIDUAL = 0.05         # std/mean of the corrected field magnitude

# 26 bin centres: the cube's faces, edges and corners, normalised (an even enough cover for a check)
_BINS = np.array([v for v in ((x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1))
                  if v != (0, 0, 0)], dtype=float)
_BINS /= np.linalg.norm(_BINS, axis=1, keepdims=True)


class CalibrationError(ValueError):
    """The samples cannot give a calibration; the message says why and what to do."""


@dataclass(frozen=True)
class MagCalibration:
    """A fitted hard/soft-iron correction: ``corrected = matrix @ (raw - offset)``."""

    offset: tuple[float, float, float]
    matrix: tuple[tuple[float, float, float], ...]
    field_strength: float       # mean magnitude of the corrected readings (the raw readings' unit)
    residual: float             # std / mean of the corrected magnitudes
    coverage: float             # share of direction bins with a reading
    samples: int

    def apply(self, raw: Sequence[float]) -> tuple[float, float, float]:
        """One raw reading corrected."""
        v = np.asarray(self.matrix) @ (np.asarray(raw, dtype=float) - np.asarray(self.offset))
        return float(v[0]), float(v[1]), float(v[2])

    def problems(self, *, min_coverage: float = MIN_COVERAGE) -> list[str]:
        """Why this result should not be saved (empty when it is good)."""
        out = []
        if self.coverage < min_coverage:
            out.append(f"coverage {self.coverage:.0%} is below {min_coverage:.0%}: turn the vehicle through more "
                       "orientations (roll and pitch it too, not only a level turn)")
        if self.residual > MAX_RESIDUAL:
            out.append(f"residual {self.residual:.3f} is above {MAX_RESIDUAL}: the field changed while turning "
                       "(move away from steel and running motors) or the sensor is saturating")
        return out

    def as_config(self) -> dict[str, list[float]]:
        """The config fields that hold it: ``mag_offset`` (3) and ``mag_matrix`` (9, row-major)."""
        return {"mag_offset": [float(x) for x in self.offset],
                "mag_matrix": [float(x) for row in self.matrix for x in row]}


def coverage(directions: np.ndarray) -> float:
    """Share of the 26 direction bins that hold at least one of *directions* (rows, any length)."""
    d = np.asarray(directions, dtype=float)
    if d.size == 0:
        return 0.0
    norms = np.linalg.norm(d, axis=1)
    d = d[norms > 0] / norms[norms > 0, None]
    nearest = np.argmax(d @ _BINS.T, axis=1)
    return len(set(nearest.tolist())) / len(_BINS)


def fit_ellipsoid(samples: Sequence[Sequence[float]]) -> MagCalibration:
    """Fit hard and soft iron to raw readings (rows of x, y, z); CalibrationError when it cannot."""
    m = np.asarray(samples, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise CalibrationError("magnetometer samples must be rows of three values (x, y, z)")
    m = m[np.all(np.isfinite(m), axis=1)]
    if len(m) < MIN_SAMPLES:
        raise CalibrationError(f"{len(m)} finite samples; at least {MIN_SAMPLES} are needed: keep turning the vehicle")
    scale = float(np.max(np.abs(m))) or 1.0       # condition the least squares
    x, y, z = (m / scale).T
    design = np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z])
    coef, *_ = np.linalg.lstsq(design, np.ones(len(m)), rcond=None)
    a, b, c, f, g, h, p, q, r = coef
    quad = np.array([[a, h, g], [h, b, f], [g, f, c]])
    lin = np.array([p, q, r])
    try:
        centre = -np.linalg.solve(quad, lin)
    except np.linalg.LinAlgError:
        raise CalibrationError("the readings do not determine an ellipsoid (all in one plane?): "
                               "turn the vehicle through more orientations") from None
    k = 1.0 + float(lin @ np.linalg.solve(quad, lin))
    shape = quad / k
    eigval, eigvec = np.linalg.eigh(shape)
    if not np.isfinite(k) or k == 0 or np.any(eigval <= 0):
        raise CalibrationError("the readings fit no ellipsoid (a hyperboloid): too few orientations or a "
                               "disturbed field; turn the vehicle slowly through every orientation")
    sqrt_shape = eigvec @ np.diag(np.sqrt(eigval)) @ eigvec.T      # maps the ellipsoid to the unit sphere
    offset = centre * scale
    unit = (sqrt_shape @ (m / scale - centre).T).T
    radius = np.linalg.norm(unit, axis=1)
    corrected_scale = float(np.mean(np.linalg.norm((m - offset), axis=1)))   # keep the raw unit's magnitude
    matrix = sqrt_shape * corrected_scale / scale
    magnitudes = radius * corrected_scale
    mean = float(np.mean(magnitudes))
    residual = float(np.std(magnitudes) / mean) if mean > 0 else math.inf
    return MagCalibration(tuple(float(v) for v in offset), tuple(tuple(float(v) for v in row) for row in matrix),
                          mean, residual, coverage(m - offset), len(m))
