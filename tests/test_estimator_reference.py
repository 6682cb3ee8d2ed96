"""The estimator's optimised predict and update against the textbook EKF formulas, written plainly.

NavigationEkf predicts and updates on preallocated arrays, with H's structure used where it
selects states (bench/estimator.py measures why). Here the same steps are computed as in a
textbook -- F, Q, H and R as full matrices, x = F x, P = F P F' + Q, S = H P H' + R,
K = P H' S^-1, the Joseph-form covariance -- on random states, covariances and
measurements of every kind, and the two must agree to floating-point rounding, gate included.
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from u2sa_hw.geo import wrap_angle
from u2sa_hw.services.estimator.ekf import Measurement, NavigationEkf

INDEX = {"north": 0, "east": 1, "down": 2, "v_north": 3, "v_east": 4, "v_down": 5, "psi": 6, "yaw_rate": 7}
KINDS = [("position", ("north", "east", "down")), ("position", ("north", "east")), ("position", ("down",)),
         ("velocity_ned", ("v_north", "v_east")), ("velocity_ned", ("v_north", "v_east", "v_down")),
         ("velocity_body", ("forward", "right")), ("velocity_body", ("forward",)),
         ("velocity_body", ("forward", "right", "down")), ("velocity_body", ("down",)),
         ("heading", ("psi",)), ("yaw_rate", ("yaw_rate",))]
NOISE = {"accel_noise": 1.5, "vertical_accel_noise": 0.3, "yaw_accel_noise": 3.0}


def reference_predict(x: np.ndarray, p: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """x = F x, P = F P F' + Q for constant velocity and yaw rate driven by white acceleration."""
    f = np.eye(8)
    q = np.zeros((8, 8))
    pairs = ((0, 3, NOISE["accel_noise"]), (1, 4, NOISE["accel_noise"]), (2, 5, NOISE["vertical_accel_noise"]),
             (6, 7, NOISE["yaw_accel_noise"]))
    for pos, vel, density in pairs:
        f[pos, vel] = dt
        block = density ** 2 * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
        q[np.ix_([pos, vel], [pos, vel])] = block
    x = f @ x
    x[6] = wrap_angle(x[6])
    return x, f @ p @ f.T + q


def reference_model(x: np.ndarray, kind: str, components: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """h(x) and its Jacobian H, one row per component."""
    h, jac = np.zeros(len(components)), np.zeros((len(components), 8))
    c, s = math.cos(x[6]), math.sin(x[6])
    for row, comp in enumerate(components):
        if kind == "velocity_body" and comp == "forward":
            h[row] = x[3] * c + x[4] * s
            jac[row, 3], jac[row, 4], jac[row, 6] = c, s, -x[3] * s + x[4] * c
        elif kind == "velocity_body" and comp == "right":
            h[row] = -x[3] * s + x[4] * c
            jac[row, 3], jac[row, 4], jac[row, 6] = -s, c, -x[3] * c - x[4] * s
        else:
            i = 5 if kind == "velocity_body" else INDEX[comp]
            h[row], jac[row, i] = x[i], 1.0
    return h, jac


def reference_update(x: np.ndarray, p: np.ndarray, m: Measurement) -> tuple[np.ndarray, np.ndarray, float]:
    """The EKF update with the Joseph-form covariance; also the squared Mahalanobis distance of the innovation."""
    h, jac = reference_model(x, m.kind, m.components)
    y = np.array(m.values) - h
    for row, comp in enumerate(m.components):
        if comp == "psi":
            y[row] = wrap_angle(y[row])
    r = np.diag(np.array(m.sigmas) ** 2)
    s = jac @ p @ jac.T + r
    s_inv = np.linalg.inv(s)
    k = p @ jac.T @ s_inv
    x = x + k @ y
    x[6] = wrap_angle(x[6])
    i_kh = np.eye(8) - k @ jac
    return x, i_kh @ p @ i_kh.T + k @ r @ k.T, float(y @ s_inv @ y)


def random_filter(rng: np.random.Generator, *, gate_probability: float, scale: float = 1.0) -> NavigationEkf:
    """A filter at a random state with a random covariance (times *scale*), every component initialised."""
    ekf = NavigationEkf(gate_probability=gate_probability, **NOISE)
    ekf.x = rng.normal(0.0, 3.0, 8)
    ekf.x[6] = rng.uniform(-math.pi, math.pi)
    a = rng.normal(0.0, 1.0, (8, 8))
    ekf.P = scale * (a @ a.T + np.diag(rng.uniform(0.05, 2.0, 8)))
    ekf.time = 0.0
    ekf.initialised = set(range(8))
    return ekf


def random_measurement(rnd: random.Random, kind: str, components: tuple[str, ...]) -> Measurement:
    values = tuple(rnd.uniform(-3.2, 3.2) if c == "psi" else rnd.gauss(0.0, 3.0) for c in components)
    return Measurement(kind, components, values, tuple(rnd.uniform(0.05, 2.0) for _ in components))


def close(actual: np.ndarray, expected: np.ndarray) -> bool:
    return bool(np.allclose(actual, expected, rtol=1e-9, atol=1e-9 * max(1.0, float(np.abs(expected).max()))))


@pytest.mark.parametrize("seed", range(6))
def test_predict_and_update_equal_the_textbook_formulas(seed: int) -> None:
    rng, rnd = np.random.default_rng(seed), random.Random(seed)
    ekf = random_filter(rng, gate_probability=1.0)
    x, p, now = ekf.x.copy(), ekf.P.copy(), 0.0
    for step in range(60):
        dt = rnd.choice((0.003, 0.02, 0.1, 0.4))
        now += dt
        ekf.predict_to(now)
        x, p = reference_predict(x, p, dt)
        assert close(ekf.x, x) and close(ekf.P, p), f"seed {seed}: prediction {step} (dt {dt})"
        m = random_measurement(rnd, *rnd.choice(KINDS))
        result = ekf.update(m)
        x, p, d2 = reference_update(x, p, m)
        assert result.outcome == "accepted" and result.mahalanobis2 == pytest.approx(d2, rel=1e-9)
        assert close(ekf.x, x) and close(ekf.P, p), f"seed {seed}: update {step} ({m.kind} {m.components})"


@pytest.mark.parametrize("kind, components", KINDS)
def test_the_gate_rejects_what_the_textbook_distance_puts_beyond_the_quantile(kind: str,
                                                                              components: tuple[str, ...]) -> None:
    rng, rnd = np.random.default_rng(11), random.Random(11)
    rejected = 0
    for _ in range(40):
        ekf = random_filter(rng, gate_probability=0.9, scale=0.01)
        h, _ = reference_model(ekf.x, kind, components)
        spread = rnd.choice((0.1, 1.0, 5.0))   # innovations well inside, near and far beyond the gate
        sigmas = tuple(rnd.uniform(0.05, 0.3) for _ in components)
        m = Measurement(kind, components, tuple(float(v) + rnd.gauss(0.0, spread) for v in h), sigmas)
        x, p = ekf.x.copy(), ekf.P.copy()
        new_x, new_p, d2 = reference_update(x, p, m)
        result = ekf.update(m)
        beyond = d2 > ekf.gate_threshold(len(components))
        assert result.outcome == ("rejected" if beyond else "accepted")
        assert result.mahalanobis2 == pytest.approx(d2, rel=1e-9)
        if beyond:   # a rejected measurement leaves the filter as it was
            rejected += 1
            assert np.array_equal(ekf.x, x) and np.array_equal(ekf.P, p)
        else:
            assert close(ekf.x, new_x) and close(ekf.P, new_p)
    assert 0 < rejected < 40
