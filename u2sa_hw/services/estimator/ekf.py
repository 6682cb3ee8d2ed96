"""The State Estimator's navigation filter: an extended Kalman filter in local NED.

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

The predict and update steps are filterpy's ``ExtendedKalmanFilter.predict``/``update``
written out on preallocated arrays (P = F P F' + Q; K = P H' S^-1 with the Joseph-form
covariance update). The estimator runs them a few hundred times a second, and filterpy's
copies and checks cost more than the arithmetic; importing it (and scipy.stats for the
gate) would also cost the estimator process 70 MB and a second at start.
``tests/test_estimator_ekf.py`` runs filterpy's filter beside this one on the same
measurements and requires the same state and covariance, and checks :func:`chi2_quantile`
against scipy's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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


def chi2_quantile(p: float, dof: int) -> float:
    """The *p*-quantile of the chi-square distribution with *dof* (>= 1) degrees of freedom.

    Bisection on the closed-form survival function of an integer-dof chi-square (a finite
    sum, with erfc for odd dof), to 1e-12 relative: the outlier gate needs three values.
    """
    if not 0.0 < p < 1.0 or dof < 1:
        raise ValueError(f"chi2_quantile needs 0 < p < 1 and dof >= 1, got p={p!r}, dof={dof!r}")
    target = 1.0 - p
    lo, hi = 0.0, float(dof) + 10.0
    while _chi2_sf(hi, dof) > target:
        lo, hi = hi, 2.0 * hi
    while hi - lo > 1e-12 * hi:
        mid = 0.5 * (lo + hi)
        if _chi2_sf(mid, dof) > target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _chi2_sf(x: float, dof: int) -> float:
    """P(X > x) for X chi-square with integer *dof*."""
    half = 0.5 * x
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= half / i
            total += term
        return math.exp(-half) * total
    total = math.erfc(math.sqrt(half))
    if dof > 1:
        term = math.sqrt(half) / math.gamma(1.5)
        series = term
        for i in range(1, (dof - 1) // 2):
            term *= half / (i + 0.5)
            series += term
        total += math.exp(-half) * series
    return total


def _inverse(s: np.ndarray) -> np.ndarray:
    """The inverse of a small innovation covariance (closed form up to 2x2: numpy's call costs more)."""
    if s.shape == (1, 1):
        return 1.0 / s
    if s.shape == (2, 2):
        a, b, c, d = s[0, 0], s[0, 1], s[1, 0], s[1, 1]
        return np.array([[d, -b], [-c, a]]) / (a * d - b * c)
    return np.linalg.inv(s)


_POS = np.array([N, E, D, PSI])
_VEL = np.array([VN, VE, VD, R])


class NavigationEkf:
    """Constant-velocity / constant-yaw-rate EKF over (N, E, D, vN, vE, vD, psi, r)."""

    def __init__(self, *, accel_noise: float = 0.5, vertical_accel_noise: float = 0.2,
                 yaw_accel_noise: float = 2.0, gate_probability: float = 0.999) -> None:
        self.accel_noise = accel_noise
        self.vertical_accel_noise = vertical_accel_noise
        self.yaw_accel_noise = yaw_accel_noise
        self.gate_probability = gate_probability
        self.x = np.zeros(8)
        self.P = np.diag([INITIAL_UNKNOWN_SIGMA**2] * 3 + [INITIAL_VELOCITY_SIGMA**2] * 3
                         + [INITIAL_HEADING_SIGMA**2, INITIAL_YAW_RATE_SIGMA**2])
        self._eye = np.eye(8)
        self._f = np.eye(8)
        # Q(dt) = dt^3/3 Q3 + dt^2/2 Q2 + dt Q1 (filterpy's Q_continuous_white_noise(dim=2) per (pos, vel) pair),
        # kept as one (3, 64) array so that Q is a single dot product
        q = np.zeros((3, 8, 8))
        for pos, vel, noise in zip(_POS, _VEL, (accel_noise, accel_noise, vertical_accel_noise, yaw_accel_noise)):
            spectral = noise * noise
            q[0, pos, pos] = spectral
            q[1, pos, vel] = q[1, vel, pos] = spectral
            q[2, vel, vel] = spectral
        self._q = q.reshape(3, 64)
        self.time: float | None = None
        self._thresholds: dict[tuple[float, int], float] = {}
        self._linear_rows: dict[tuple[str, ...], tuple[np.ndarray, list[int]]] = {}
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
        f = self._f
        f[_POS, _VEL] = dt
        self.x = f @ self.x
        self.P = f @ self.P @ f.T + np.dot((dt * dt * dt / 3.0, dt * dt / 2.0, dt), self._q).reshape(8, 8)
        self.x[PSI] = wrap_angle(self.x[PSI])
        self.time = t

    # -- measurement models ---------------------------------------------------------------
    def _model(self, m: Measurement) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """h(x), its Jacobian H and the rows holding a heading (wrapped innovations) for *m*."""
        x = self.x
        if m.kind != "velocity_body":
            rows = self._linear_rows.get(m.components)
            if rows is None:
                idx = np.array([_LINEAR_INDEX[c] for c in m.components])
                rows = self._linear_rows[m.components] = (idx, [i for i, c in enumerate(m.components) if c == "psi"])
            idx, wrap_rows = rows
            return x[idx], self._eye[idx], wrap_rows
        h = np.zeros(len(m.components))
        jac = np.zeros((len(m.components), 8))
        c, s = math.cos(x[PSI]), math.sin(x[PSI])
        for row, comp in enumerate(m.components):
            if comp == "forward":
                h[row] = x[VN] * c + x[VE] * s
                jac[row, [VN, VE, PSI]] = (c, s, -x[VN] * s + x[VE] * c)
            elif comp == "right":
                h[row] = -x[VN] * s + x[VE] * c
                jac[row, [VN, VE, PSI]] = (-s, c, -x[VN] * c - x[VE] * s)
            else:
                h[row] = x[VD]
                jac[row, VD] = 1.0
        return h, jac, []

    def gate_threshold(self, dof: int) -> float:
        """The chi-square quantile of ``gate_probability`` for *dof* components (inf: gate off)."""
        if self.gate_probability >= 1.0 or self.gate_probability <= 0.0:
            return math.inf
        key = (self.gate_probability, dof)
        if key not in self._thresholds:
            self._thresholds[key] = chi2_quantile(self.gate_probability, dof)
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
        if len(m.components) == 1 and m.kind != "velocity_body":
            return self._update_one(m, gate=gate)
        hx, jac, wrap_rows = self._model(m)
        y = np.array(m.values, dtype=float) - hx
        for i in wrap_rows:
            y[i] = wrap_angle(y[i])
        r_mat = np.diag(np.square(np.array(m.sigmas, dtype=float)))
        p = self.P
        pht = p @ jac.T
        s_inv = _inverse(jac @ pht + r_mat)
        d2 = float(y @ s_inv @ y)
        threshold = self.gate_threshold(len(m.components))
        if gate and not d2 <= threshold:   # also catches a NaN distance
            return UpdateResult("rejected", d2, threshold)
        k = pht @ s_inv
        self.x += k @ y
        i_kh = self._eye - k @ jac
        self.P = i_kh @ p @ i_kh.T + k @ r_mat @ k.T   # Joseph form, as filterpy: stays symmetric and positive
        self.x[PSI] = wrap_angle(self.x[PSI])
        self._mark_observed(m)
        return UpdateResult("accepted", d2, threshold)

    def _update_one(self, m: Measurement, *, gate: bool) -> UpdateResult:
        """:meth:`update` for one directly measured component: H selects state *i*, S and K are scalars.

        The Joseph form reduces to P - p p' / S here (p = P[:, i], K = p / S), exactly symmetric.
        """
        i = _LINEAR_INDEX[m.components[0]]
        y = m.values[0] - float(self.x[i])
        if i == PSI:
            y = wrap_angle(y)
        p_col = self.P[:, i].copy()
        s = float(p_col[i]) + m.sigmas[0] * m.sigmas[0]
        d2 = y * y / s
        threshold = self.gate_threshold(1)
        if gate and not d2 <= threshold:
            return UpdateResult("rejected", d2, threshold)
        self.x += p_col * (y / s)
        self.P -= np.outer(p_col, p_col) / s
        self.x[PSI] = wrap_angle(self.x[PSI])
        self._mark_observed(m)
        return UpdateResult("accepted", d2, threshold)

    def reset_to(self, m: Measurement) -> None:
        """Set the components of a position or heading measurement directly (forgetting correlations)."""
        if m.kind not in _DIRECT_INIT_KINDS:
            raise ValueError(f"only {', '.join(_DIRECT_INIT_KINDS)} can be set directly, not {m.kind}")
        for comp, value, sigma in zip(m.components, m.values, m.sigmas):
            idx = _LINEAR_INDEX[comp]
            self.x[idx] = wrap_angle(value) if idx == PSI else value
            self.P[idx, :] = 0.0
            self.P[:, idx] = 0.0
            self.P[idx, idx] = sigma * sigma
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
        x, p = self.x, self.P
        return {STATE_NAMES[i]: (float(x[i]), math.sqrt(max(float(p[i, i]), 0.0))) for i in sorted(self.observed)}
