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
covariance update), each (kind, components) model built once; where H selects states, P H'
and H P H' are picked from P. The estimator runs them a few hundred times a second: per-call
allocations and numpy calls are its cost (bench/estimator.py), and filterpy's copies and checks
cost more than the arithmetic; importing it (and scipy.stats for the gate) would also cost the
process 70 MB and a second at start. ``tests/test_estimator_ekf.py`` runs filterpy's filter
beside this one and checks :func:`chi2_quantile` against scipy's; ``tests/test_estimator_reference.py``
compares with the textbook formulas.
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


_POS, _VEL = np.array([N, E, D, PSI]), np.array([VN, VE, VD, R])
_EYE = np.eye(8)


@dataclass(frozen=True)
class _Plan:
    """What an update of one (kind, components) needs that does not change between updates."""

    kind: str
    components: tuple[str, ...]
    index: np.ndarray                 # state rows of a linear model (empty for velocity_body)
    states: tuple[int, ...]           # the same as a tuple
    jac: np.ndarray                   # H of a linear model; velocity_body's own H, refilled per update
    wrap_rows: tuple[int, ...]        # rows holding a heading (wrapped innovations)
    single: int                       # the state index of a one-component linear model, else -1
    observes: frozenset[int]          # states an accepted update makes observed
    motion_heading: bool              # velocity_body with a horizontal part: heading observed once N, E are
    needs_heading: bool               # velocity_body: waits for the first heading
    direct: bool                      # position or heading: a component's first measurement sets it


def _plan(kind: str, components: tuple[str, ...]) -> _Plan:
    """The :class:`_Plan` of a valid (kind, components)."""
    if kind == "velocity_body":
        horizontal = any(c != "down" for c in components)
        observes = frozenset({VN, VE} if horizontal else set()) | frozenset({VD} if "down" in components else set())
        return _Plan(kind, components, np.zeros(0, dtype=int), (), np.zeros((len(components), 8)), (), -1,
                     observes, horizontal, True, False)
    states = tuple(_LINEAR_INDEX[c] for c in components)
    extra = {i + 3 for i in states} if kind == "position" else {R} if kind == "heading" else set()
    return _Plan(kind, components, np.array(states), states, _EYE[list(states)],
                 tuple(i for i, c in enumerate(components) if c == "psi"), states[0] if len(states) == 1 else -1,
                 frozenset(states) | frozenset(extra), False, False, kind in _DIRECT_INIT_KINDS)


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
        self._f = np.eye(8)
        self._f_flat = (_POS * 8 + _VEL).tolist()
        # Q(dt) = dt^3/3 Q3 + dt^2/2 Q2 + dt Q1 (filterpy's Q_continuous_white_noise(dim=2) per (pos, vel) pair),
        # kept as one (3, 64) array so that Q is a single dot product
        q = np.zeros((3, 8, 8))
        for pos, vel, noise in zip(_POS, _VEL, (accel_noise, accel_noise, vertical_accel_noise, yaw_accel_noise)):
            spectral = noise * noise
            q[0, pos, pos] = spectral
            q[1, pos, vel] = q[1, vel, pos] = spectral
            q[2, vel, vel] = spectral
        self._q = q.reshape(3, 64)
        self._coeffs = np.empty(3)
        self._q_now = np.empty(64)
        self._q_now_8x8 = self._q_now.reshape(8, 8)
        self._tmp = np.empty((8, 8))   # scratch: the filter runs a few hundred times a second
        self.time: float | None = None
        self._thresholds: dict[tuple[float, int], float] = {}
        self._plans: dict[tuple[str, tuple[str, ...]], _Plan] = {}
        self.initialised: set[int] = set()
        self.observed: set[int] = set()
        self.mahalanobis2 = 0.0          # of the latest gated update
        self.threshold = math.inf

    # -- prediction -----------------------------------------------------------------------
    def predict_to(self, t: float) -> None:
        """Propagate the state to time *t* (s, any monotonic clock); earlier times are ignored."""
        if self.time is None:
            self.time = t
            return
        dt = t - self.time
        if dt <= 0.0:
            return
        f, p, tmp, coeffs = self._f, self.P, self._tmp, self._coeffs
        f.put(self._f_flat, dt)
        x = self.x = f @ self.x
        np.dot(f, p, out=tmp)
        np.dot(tmp, f.T, out=p)
        coeffs[0], coeffs[1], coeffs[2] = dt * dt * dt / 3.0, dt * dt / 2.0, dt
        np.dot(coeffs, self._q, out=self._q_now)
        p += self._q_now_8x8
        x[PSI] = wrap_angle(x.item(PSI))
        self.time = t

    # -- measurement models ---------------------------------------------------------------
    def plan(self, kind: str, components: tuple[str, ...]) -> _Plan:
        """The cached model of a (kind, components) group."""
        plan = self._plans.get((kind, components))
        if plan is None:
            plan = self._plans[(kind, components)] = _plan(kind, components)
        return plan

    def _body_model(self, plan: _Plan) -> tuple[list[float], np.ndarray]:
        """h(x) and H of a body-frame velocity at the current state (H is the plan's array, refilled)."""
        vn, ve, psi, vd = self.x.item(VN), self.x.item(VE), self.x.item(PSI), self.x.item(VD)
        c, s = math.cos(psi), math.sin(psi)
        h = []
        jac = plan.jac
        for row, comp in enumerate(plan.components):
            if comp == "forward":
                h.append(vn * c + ve * s)
                jac[row, VN], jac[row, VE], jac[row, PSI] = c, s, -vn * s + ve * c
            elif comp == "right":
                h.append(-vn * s + ve * c)
                jac[row, VN], jac[row, VE], jac[row, PSI] = -s, c, -vn * c - ve * s
            else:
                h.append(vd)
                jac[row, VD] = 1.0
        return h, jac

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
        outcome = self.update_values(m.kind, m.components, m.values, m.sigmas, gate=gate)
        gated = outcome in ("accepted", "rejected")
        return UpdateResult(outcome, self.mahalanobis2, self.threshold) if gated else UpdateResult(outcome)

    def update_values(self, kind: str, components: tuple[str, ...], values: tuple[float, ...],
                      sigmas: tuple[float, ...], *, gate: bool = True) -> str:
        """:meth:`update` of a valid measurement given by parts; the outcome (d2 in ``mahalanobis2``)."""
        plan = self.plan(kind, components)
        if plan.needs_heading and PSI not in self.initialised or \
                plan.direct and not self.initialised.issuperset(plan.states):
            return self._update_first(Measurement(kind, components, values, sigmas), gate=gate)
        if plan.single >= 0:
            return self._update_one(plan, values[0], sigmas[0], gate=gate)
        return self._update_group(plan, values, sigmas, gate=gate)

    def _update_first(self, m: Measurement, *, gate: bool) -> str:
        """:meth:`update` before a heading (body velocities) or with components never measured (positions, heading)."""
        if m.kind == "velocity_body" and PSI not in self.initialised:
            keep = [i for i, comp in enumerate(m.components) if comp == "down"]
            if not keep:
                return "deferred"
            m = m.subset(keep)
        if m.kind in _DIRECT_INIT_KINDS:
            fresh = [i for i, comp in enumerate(m.components) if _LINEAR_INDEX[comp] not in self.initialised]
            if fresh:
                self.reset_to(m.subset(fresh))
                rest = [i for i in range(len(m.components)) if i not in fresh]
                if not rest:
                    return "initialised"
                m = m.subset(rest)
        plan = self.plan(m.kind, m.components)
        if plan.single >= 0:
            return self._update_one(plan, m.values[0], m.sigmas[0], gate=gate)
        return self._update_group(plan, m.values, m.sigmas, gate=gate)

    def _update_group(self, plan: _Plan, values: tuple[float, ...], sigmas: tuple[float, ...], *, gate: bool) -> str:
        """A group's update: K = P H' S^-1 and the Joseph-form covariance, with the gate on y' S^-1 y."""
        x, p, linear = self.x, self.P, not plan.needs_heading
        if linear:   # H selects rows: P H' and H P H' are columns and entries of P (the same numbers)
            jac = plan.jac
            y = np.array(values, dtype=float) - x[plan.index]
            pht = p[:, plan.index]
            s_mat = pht[plan.index]
        else:
            hx, jac = self._body_model(plan)
            y = np.array([v - h for v, h in zip(values, hx)])
            pht = p @ jac.T
            s_mat = jac @ pht
        for i in plan.wrap_rows:
            y[i] = wrap_angle(y.item(i))
        r = np.array(sigmas, dtype=float)
        r *= r
        s_mat.flat[::len(r) + 1] += r
        if len(r) == 2:   # closed form: numpy's inverse costs more than the arithmetic
            a, b, c, d = s_mat.ravel().tolist()
            det = a * d - b * c
            i00, i01, i10, i11 = d / det, -b / det, -c / det, a / det
            s_inv = np.array(((i00, i01), (i10, i11)))
            y0, y1 = y.tolist()
            d2 = self.mahalanobis2 = (y0 * i00 + y1 * i10) * y0 + (y0 * i01 + y1 * i11) * y1
        else:
            s_inv = np.linalg.inv(s_mat)
            d2 = self.mahalanobis2 = float(y @ s_inv @ y)
        threshold = self.threshold = self.gate_threshold(len(r))
        if gate and not d2 <= threshold:   # also catches a NaN distance
            return "rejected"
        k = pht @ s_inv
        x += k @ y
        i_kh = _EYE - k @ jac
        tmp = self._tmp
        np.dot(i_kh, p, out=tmp)
        np.dot(tmp, i_kh.T, out=p)
        p += (k * r) @ k.T   # Joseph form, as filterpy: stays symmetric and positive
        x[PSI] = wrap_angle(x.item(PSI))
        self._observe(plan)
        return "accepted"

    def _update_one(self, plan: _Plan, value: float, sigma: float, *, gate: bool) -> str:
        """The update of one directly measured component: H selects state *i*, S and K are scalars.

        The Joseph form reduces to P - p p' / S here (p = P[:, i], K = p / S), exactly symmetric.
        """
        i, x, p = plan.single, self.x, self.P
        y = value - x.item(i)
        if i == PSI:
            y = wrap_angle(y)
        p_col = p[:, i].copy()
        s = p_col.item(i) + sigma * sigma
        d2 = self.mahalanobis2 = y * y / s
        threshold = self.threshold = self.gate_threshold(1)
        if gate and not d2 <= threshold:
            return "rejected"
        x += p_col * (y / s)
        tmp = self._tmp
        np.multiply(p_col[:, None], p_col, out=tmp)
        tmp /= s
        p -= tmp
        x[PSI] = wrap_angle(x.item(PSI))
        self._observe(plan)
        return "accepted"

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
        self._observe(self.plan(m.kind, m.components))

    def _observe(self, plan: _Plan) -> None:
        observed = self.observed
        if not observed.issuperset(plan.observes):
            observed |= plan.observes
        if plan.motion_heading and PSI not in observed and {N, E} <= self.initialised:
            observed.add(PSI)   # heading from motion: odometry against positions

    # -- readout --------------------------------------------------------------------------
    def state(self) -> dict[str, tuple[float, float]]:
        """``{state name: (value, sigma)}`` for every observed state component."""
        x, var = self.x.tolist(), self.P.diagonal().tolist()
        return {STATE_NAMES[i]: (x[i], math.sqrt(max(var[i], 0.0))) for i in sorted(self.observed)}
