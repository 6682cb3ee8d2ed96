"""The State Estimator's navigation filter: an extended Kalman filter (filterpy) in local NED.

State (8): north, east, down (m), v_north, v_east, v_down (m/s), psi (rad, clockwise from
north, kept in [-pi, pi)), yaw rate r (rad/s).

Process model: constant velocity and constant yaw rate, driven by white acceleration
noise (``accel_noise`` horizontal, ``vertical_accel_noise``, ``yaw_accel_noise``, each a
noise density whose square is the spectral density of the continuous white-noise Q, as
filterpy's ``Q_continuous_white_noise``). The model is linear (F depends only on dt).
A wheeled vehicle's odometry should report its lateral speed (y_dot = 0 in FRD) too: the
constant-velocity model alone lets the velocity vector lag in a turn.

Measurements come in groups (:class:`Measurement`), each updating only the components it
carries: NED position, NED velocity, body (FRD) velocity -- forward = vn cos psi + ve sin psi,
right = -vn sin psi + ve cos psi, down = vd, the one non-linear model, hence the EKF --
heading (innovation wrapped to [-pi, pi]) and yaw rate. Body-frame horizontal velocities
wait for the first heading measurement (a compass, an IMU, or a GPS course sent as psi). Before an update the group's
squared Mahalanobis distance y' S^-1 y is compared with the chi-square quantile of
``gate_probability`` for the group's size; a group beyond it is rejected (an outlier).

Position and heading components are set directly from their first measurement (no huge
initial covariance to tame); velocities and yaw rate start at 0 with a wide prior.
This module is pure: no bus, no clock; the caller passes times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from u2sa_hw.geo import wrap_angle

N, E, D, VN, VE, VD, PSI, R = range(8)
STATE_NAMES = ("north", "east", "down", "v_north", "v_east", "v_down", "psi", "yaw_rate")
INITIAL_VELOCITY_SIGMA = 2.0      # m/s, prior before any velocity information
INITIAL_YAW_RATE_SIGMA = 0.5      # rad/s
INITIAL_UNKNOWN_SIGMA = 1000.0    # m, position before its first measurement
INITIAL_HEADING_SIGMA = math.pi   # rad, heading before its first measurement

# Measurement kinds and the components each may carry.
KIND_COMPONENTS: dict[str, tuple[str, ...]] = {
    "position": ("north", "east", "down"),
    "velocity_ned": ("v_north", "v_east", "v_down"),
    "velocity_body": ("forward", "right", "down"),
    "heading": ("psi",),
    "yaw_rate": ("yaw_rate",),
}
_LINEAR_INDEX = {"north": N, "east": E, "down": D, "v_north": VN, "v_east": VE, "v_down": VD,
                 "psi": PSI, "yaw_rate": R}
_DIRECT_INIT_KINDS = ("position", "heading")


@dataclass(frozen=True)
class Measurement:
    """One measured group: *kind* (a key of ``KIND_COMPONENTS``), its components, values, sigmas."""

    kind: str
    components: tuple[str, ...]
    values: tuple[float, ...]
    sigmas: tuple[float, ...]

    def __post_init__(self) -> None:
        allowed = KIND_COMPONENTS.get(self.kind)
        if allowed is None:
            raise ValueError(f"unknown measurement kind {self.kind!r}; known: {', '.join(KIND_COMPONENTS)}")
        bad = [c for c in self.components if c not in allowed]
        if bad or not self.components or not len(self.values) == len(self.components) == len(self.sigmas):
            raise ValueError(f"{self.kind} measurement: components {self.components} must be a non-empty "
                             f"subset of {allowed} with one value and one sigma each")

    def subset(self, keep: list[int]) -> "Measurement":
        """This measurement restricted to the components at positions *keep*."""
        return Measurement(self.kind, tuple(self.components[i] for i in keep),
                           tuple(self.values[i] for i in keep), tuple(self.sigmas[i] for i in keep))


@dataclass(frozen=True)
class UpdateResult:
    """What :meth:`NavigationEkf.update` did: ``"accepted"``, ``"initialised"``, ``"rejected"`` or ``"deferred"``.

    ``deferred``: a body-frame horizontal velocity arrived before any heading; it cannot be
    rotated into NED yet and is dropped (not an outlier).
    """

    outcome: str
    mahalanobis2: float = 0.0
    threshold: float = math.inf


class NavigationEkf:
    """Constant-velocity / constant-yaw-rate EKF over (N, E, D, vN, vE, vD, psi, r)."""

    def __init__(self, *, accel_noise: float = 0.5, vertical_accel_noise: float = 0.2,
                 yaw_accel_noise: float = 2.0, gate_probability: float = 0.999) -> None:
        self.accel_noise = accel_noise
        self.vertical_accel_noise = vertical_accel_noise
        self.yaw_accel_noise = yaw_accel_noise
        self.gate_probability = gate_probability
        self.kf = ExtendedKalmanFilter(dim_x=8, dim_z=1)
        self.kf.x = np.zeros((8, 1))
        self.kf.P = np.diag([INITIAL_UNKNOWN_SIGMA**2] * 3 + [INITIAL_VELOCITY_SIGMA**2] * 3
                            + [INITIAL_HEADING_SIGMA**2, INITIAL_YAW_RATE_SIGMA**2])
        self.time: float | None = None
        self._thresholds: dict[tuple[float, int], float] = {}
        self.initialised: set[int] = set()
        self.observed: set[int] = set()

    # -- prediction -----------------------------------------------------------------------
    def predict_to(self, t: float) -> None:
        """Propagate the state to time *t* (s, any monotonic clock); earlier times are ignored."""
        if self.time is None:
            self.time = t
            return
        dt = t - self.time
        if dt <= 0.0:
            return
        f = np.eye(8)
        q = np.zeros((8, 8))
        # filterpy's Q_continuous_white_noise(dim=2) per axis, written out: it is 20x faster
        q11, q12, q22 = dt**3 / 3.0, dt**2 / 2.0, dt
        for pos, vel, noise in ((N, VN, self.accel_noise), (E, VE, self.accel_noise),
                                (D, VD, self.vertical_accel_noise), (PSI, R, self.yaw_accel_noise)):
            f[pos, vel] = dt
            spectral = noise * noise
            q[pos, pos], q[pos, vel], q[vel, pos], q[vel, vel] = (q11 * spectral, q12 * spectral,
                                                                  q12 * spectral, q22 * spectral)
        self.kf.F = f
        self.kf.Q = q
        self.kf.predict()
        self.kf.x[PSI, 0] = wrap_angle(self.kf.x[PSI, 0])
        self.time = t

    # -- measurement models ---------------------------------------------------------------
    def _h_and_jacobian(self, m: Measurement) -> tuple[np.ndarray, np.ndarray]:
        x = self.kf.x[:, 0]
        h = np.zeros((len(m.components), 1))
        jac = np.zeros((len(m.components), 8))
        c, s = math.cos(x[PSI]), math.sin(x[PSI])
        for row, comp in enumerate(m.components):
            if m.kind == "velocity_body" and comp == "forward":
                h[row, 0] = x[VN] * c + x[VE] * s
                jac[row, [VN, VE, PSI]] = (c, s, -x[VN] * s + x[VE] * c)
            elif m.kind == "velocity_body" and comp == "right":
                h[row, 0] = -x[VN] * s + x[VE] * c
                jac[row, [VN, VE, PSI]] = (-s, c, -x[VN] * c - x[VE] * s)
            else:
                idx = VD if (m.kind == "velocity_body" and comp == "down") else _LINEAR_INDEX[comp]
                h[row, 0] = x[idx]
                jac[row, idx] = 1.0
        return h, jac

    @staticmethod
    def _residual_fn(m: Measurement) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """z - h(x) for *m*, with heading rows wrapped to [-pi, pi] (filterpy's ``residual``)."""
        wrap_rows = [i for i, comp in enumerate(m.components) if comp == "psi"]

        def residual(z: np.ndarray, hx: np.ndarray) -> np.ndarray:
            y = np.subtract(z, hx)
            for i in wrap_rows:
                y[i, 0] = wrap_angle(y[i, 0])
            return y
        return residual

    def gate_threshold(self, dof: int) -> float:
        """The chi-square quantile of ``gate_probability`` for *dof* components (inf: gate off)."""
        if self.gate_probability >= 1.0 or self.gate_probability <= 0.0:
            return math.inf
        key = (self.gate_probability, dof)
        if key not in self._thresholds:
            self._thresholds[key] = float(chi2.ppf(self.gate_probability, dof))
        return self._thresholds[key]

    # -- update ---------------------------------------------------------------------------
    def update(self, m: Measurement, *, gate: bool = True) -> UpdateResult:
        """Fold *m* into the state; components never measured before initialise directly."""
        if m.kind == "velocity_body" and PSI not in self.initialised:
            keep = [i for i, comp in enumerate(m.components) if comp == "down"]
            if not keep:
                return UpdateResult("deferred")
            m = m.subset(keep)
        if m.kind in _DIRECT_INIT_KINDS:
            fresh = [i for i, comp in enumerate(m.components) if _LINEAR_INDEX[comp] not in self.initialised]
            if fresh:
                self.reset_to(m.subset(fresh))
                rest = [i for i in range(len(m.components)) if i not in fresh]
                if not rest:
                    return UpdateResult("initialised")
                m = m.subset(rest)
        z = np.array(m.values, dtype=float).reshape(-1, 1)
        r_mat = np.diag(np.square(np.array(m.sigmas, dtype=float)))
        residual = self._residual_fn(m)
        hx, jac = self._h_and_jacobian(m)
        y = residual(z, hx)
        s_mat = jac @ self.kf.P @ jac.T + r_mat
        d2 = float((y.T @ np.linalg.solve(s_mat, y))[0, 0])
        threshold = self.gate_threshold(len(m.components))
        if gate and not d2 <= threshold:   # also catches a NaN distance
            return UpdateResult("rejected", d2, threshold)
        self.kf.update(z, HJacobian=lambda _x: jac, Hx=lambda _x: hx, R=r_mat, residual=residual)
        self.kf.x[PSI, 0] = wrap_angle(self.kf.x[PSI, 0])
        self._mark_observed(m)
        return UpdateResult("accepted", d2, threshold)

    def reset_to(self, m: Measurement) -> None:
        """Set the components of a position or heading measurement directly (forgetting correlations)."""
        if m.kind not in _DIRECT_INIT_KINDS:
            raise ValueError(f"only {', '.join(_DIRECT_INIT_KINDS)} can be set directly, not {m.kind}")
        for comp, value, sigma in zip(m.components, m.values, m.sigmas):
            idx = _LINEAR_INDEX[comp]
            self.kf.x[idx, 0] = wrap_angle(value) if idx == PSI else value
            self.kf.P[idx, :] = 0.0
            self.kf.P[:, idx] = 0.0
            self.kf.P[idx, idx] = sigma * sigma
            self.initialised.add(idx)
        self._mark_observed(m)

    def _mark_observed(self, m: Measurement) -> None:
        for comp in m.components:
            if m.kind == "velocity_body":
                self.observed.update({VN, VE} if comp != "down" else {VD})
                if comp != "down" and {N, E} <= self.initialised:
                    self.observed.add(PSI)   # heading from motion: odometry against positions
            else:
                idx = _LINEAR_INDEX[comp]
                self.observed.add(idx)
                if m.kind == "position":
                    self.observed.add(idx + 3)  # the velocity of a tracked position is estimated
                elif m.kind == "heading":
                    self.observed.add(R)

    # -- readout --------------------------------------------------------------------------
    def state(self) -> dict[str, tuple[float, float]]:
        """``{state name: (value, sigma)}`` for every observed state component."""
        x, p = self.kf.x[:, 0], self.kf.P
        return {STATE_NAMES[i]: (float(x[i]), math.sqrt(max(float(p[i, i]), 0.0))) for i in sorted(self.observed)}
