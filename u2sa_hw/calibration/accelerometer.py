"""Accelerometer offsets, scales and misalignment from six still poses.

The vehicle (or the board) is held still with each axis in turn pointing up and down:
``+x``, ``-x``, ``+y``, ``-y``, ``+z``, ``-z``. Each pose's mean reading is the sensor's
response to gravity along that axis, ``a = K g_true + o``. With the six poses the twelve
unknowns of ``K`` (3x3: scales on the diagonal, misalignment off it) and ``o`` are found by
least squares; the correction is ``K^-1 (a - o)``.

A pose counts when its samples are still (standard deviation under ``MAX_STILL_STD`` m/s^2)
and it is recognised by the axis its mean points along; :class:`PoseCollector` keeps the
best still window of each pose as the operator turns the vehicle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

G = 9.80665
POSES = ("+x", "-x", "+y", "-y", "+z", "-z")
MAX_STILL_STD = 0.05        # m/s^2 over a pose's window
MIN_ALIGNMENT = 0.9         # cosine between a pose's mean and its axis
MAX_RESIDUAL = 0.05         # m/s^2: the corrected poses' largest error against gravity


class CalibrationError(ValueError):
    """The poses cannot give a calibration; the message says why and what to do."""


def _truth(pose: str) -> np.ndarray:
    v = np.zeros(3)
    v["xyz".index(pose[1])] = G if pose[0] == "+" else -G
    return v


def pose_of(mean: Sequence[float]) -> str | None:
    """The pose a still mean reading shows (the axis pointing up), or None when none is clear."""
    v = np.asarray(mean, dtype=float)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 0.5 * G:
        return None
    i = int(np.argmax(np.abs(v)))
    if abs(v[i]) / n < MIN_ALIGNMENT:
        return None
    return ("+" if v[i] > 0 else "-") + "xyz"[i]


@dataclass
class PoseCollector:
    """Keeps the stillest window of samples for each of the six poses."""

    window: int = 50
    means: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    stds: dict[str, float] = field(default_factory=dict)
    _buf: list[tuple[float, float, float]] = field(default_factory=list)

    def add(self, sample: Sequence[float]) -> str | None:
        """Add one reading (m/s^2); returns the pose just captured or improved, if any."""
        s = tuple(float(v) for v in sample)
        if len(s) != 3 or not all(np.isfinite(s)):
            return None
        self._buf.append(s)   # type: ignore[arg-type]
        if len(self._buf) < self.window:
            return None
        block = np.asarray(self._buf[-self.window:])
        del self._buf[:-self.window]
        std = float(np.max(np.std(block, axis=0)))
        if std > MAX_STILL_STD:
            return None
        mean = block.mean(axis=0)
        pose = pose_of(mean)
        if pose is None or std >= self.stds.get(pose, np.inf):
            return None
        self.means[pose], self.stds[pose] = (float(mean[0]), float(mean[1]), float(mean[2])), std
        return pose

    @property
    def missing(self) -> list[str]:
        """Poses not captured yet."""
        return [p for p in POSES if p not in self.means]


@dataclass(frozen=True)
class AccelCalibration:
    """``corrected = matrix @ (raw - offset)`` (matrix = K^-1)."""

    offset: tuple[float, float, float]
    matrix: tuple[tuple[float, float, float], ...]
    residual: float            # m/s^2, largest error of a corrected pose against gravity

    def apply(self, raw: Sequence[float]) -> tuple[float, float, float]:
        """One raw reading corrected."""
        v = np.asarray(self.matrix) @ (np.asarray(raw, dtype=float) - np.asarray(self.offset))
        return float(v[0]), float(v[1]), float(v[2])

    def problems(self) -> list[str]:
        """Why this result should not be saved (empty when it is good)."""
        if self.residual > MAX_RESIDUAL:
            return [f"residual {self.residual:.3f} m/s^2 is above {MAX_RESIDUAL}: a pose was not still or not level; "
                    "repeat the poses on a level surface"]
        return []

    def as_config(self) -> dict[str, list[float]]:
        """The config fields that hold it: ``accel_offset`` (3) and ``accel_matrix`` (9, row-major)."""
        return {"accel_offset": [float(x) for x in self.offset],
                "accel_matrix": [float(x) for row in self.matrix for x in row]}


def fit_six_pose(means: dict[str, Sequence[float]]) -> AccelCalibration:
    """Fit offset, scales and misalignment to the mean reading of each of the six poses."""
    missing = [p for p in POSES if p not in means]
    if missing:
        raise CalibrationError(f"poses missing: {', '.join(missing)}; "
                               "hold the vehicle still with each axis up and down")
    rows, rhs = [], []
    for pose in POSES:
        t = _truth(pose)
        a = np.asarray(means[pose], dtype=float)
        for i in range(3):     # a_i = K_i . t + o_i  -> unknowns K (9, row-major) then o (3)
            row = np.zeros(12)
            row[3 * i:3 * i + 3] = t
            row[9 + i] = 1.0
            rows.append(row)
            rhs.append(a[i])
    sol, *_ = np.linalg.lstsq(np.asarray(rows), np.asarray(rhs), rcond=None)
    k, o = sol[:9].reshape(3, 3), sol[9:]
    try:
        inv = np.linalg.inv(k)
    except np.linalg.LinAlgError:
        raise CalibrationError("the poses do not determine the axes (two poses alike?)") from None
    residual = max(float(np.linalg.norm(inv @ (np.asarray(means[p], dtype=float) - o) - _truth(p))) for p in POSES)
    return AccelCalibration(tuple(float(v) for v in o), tuple(tuple(float(v) for v in row) for row in inv), residual)
