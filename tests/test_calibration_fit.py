"""Calibration fits against a known truth: a magnetometer with hard iron, soft iron and noise, and
an accelerometer with offsets, scales and misalignment, recovered from what they would read."""

from __future__ import annotations

import numpy as np
import pytest

from u2sa_hw.calibration.accelerometer import G, POSES, PoseCollector, fit_six_pose, pose_of
from u2sa_hw.calibration.accelerometer import CalibrationError as AccelError
from u2sa_hw.calibration.magnetometer import CalibrationError, coverage, fit_ellipsoid

RNG = np.random.default_rng(7)
HARD_IRON = np.array([12.0, -30.0, 45.0])                      # uT
SOFT_IRON = np.array([[1.10, 0.05, -0.02], [0.05, 0.92, 0.03], [-0.02, 0.03, 1.04]])
FIELD = 48.0                                                    # uT


def orientations(n: int, *, level_only: bool = False) -> np.ndarray:
    """Field directions seen by a sensor turned through *n* orientations."""
    if level_only:
        a = RNG.uniform(0, 2 * np.pi, n)
        return np.column_stack([np.cos(a) * 0.9, np.sin(a) * 0.9, np.full(n, 0.43)])
    v = RNG.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def raw_mag(directions: np.ndarray, noise: float = 0.2) -> np.ndarray:
    h = directions * FIELD
    return h @ SOFT_IRON.T + HARD_IRON + RNG.normal(scale=noise, size=h.shape)


def test_ellipsoid_fit_recovers_the_hard_iron_and_makes_the_field_round() -> None:
    dirs = orientations(600)
    cal = fit_ellipsoid(raw_mag(dirs))
    assert np.allclose(cal.offset, HARD_IRON, atol=0.3)
    assert cal.coverage == 1.0 and cal.residual < 0.01 and not cal.problems()
    corrected = np.array([cal.apply(m) for m in raw_mag(dirs, noise=0.0)])
    magnitudes = np.linalg.norm(corrected, axis=1)
    assert np.std(magnitudes) / np.mean(magnitudes) < 0.005
    # the soft iron is removed up to a rotation: angles between readings are the true ones
    i, j = 0, 1
    true_cos = dirs[i] @ dirs[j]
    got_cos = corrected[i] @ corrected[j] / (magnitudes[i] * magnitudes[j])
    assert got_cos == pytest.approx(true_cos, abs=0.01)
    cfg = cal.as_config()
    assert len(cfg["mag_offset"]) == 3 and len(cfg["mag_matrix"]) == 9


def test_a_level_turn_alone_is_refused_for_its_coverage() -> None:
    with pytest.raises(CalibrationError):
        cal = fit_ellipsoid(raw_mag(orientations(400, level_only=True)))
        assert cal.problems()      # a fit that passes the algebra must still fail the coverage check
        raise CalibrationError(cal.problems()[0])
    assert coverage(orientations(400, level_only=True)) < 0.6


def test_too_few_or_bad_samples_are_refused_with_the_reason() -> None:
    with pytest.raises(CalibrationError, match="at least"):
        fit_ellipsoid(raw_mag(orientations(10)))
    with pytest.raises(CalibrationError, match="rows of three"):
        fit_ellipsoid([[1.0, 2.0]])
    samples = raw_mag(orientations(300))
    samples[::10] = np.nan                                    # a glitching sensor: NaNs are skipped
    assert fit_ellipsoid(samples).samples == 270


def test_a_disturbed_field_fails_the_residual_check() -> None:
    dirs = orientations(500)
    raw = raw_mag(dirs)
    raw[250:] += RNG.normal(scale=8.0, size=raw[250:].shape)   # motors started half way
    cal = fit_ellipsoid(raw)
    assert any("residual" in p for p in cal.problems())


K_TRUE = np.array([[1.02, 0.01, -0.015], [0.005, 0.97, 0.02], [0.01, -0.01, 1.03]])
O_TRUE = np.array([0.25, -0.4, 0.6])


def still_samples(pose: str, n: int = 60, noise: float = 0.01) -> np.ndarray:
    t = np.zeros(3)
    t["xyz".index(pose[1])] = G if pose[0] == "+" else -G
    return (K_TRUE @ t + O_TRUE) + RNG.normal(scale=noise, size=(n, 3))


def test_six_poses_recover_offsets_scales_and_misalignment() -> None:
    collector = PoseCollector(window=50)
    for pose in POSES:
        moving = still_samples(pose, 30, noise=1.0)           # being turned: not still, not taken
        for s in moving:
            collector.add(s)
        for s in still_samples(pose):
            collector.add(s)
    assert collector.missing == []
    cal = fit_six_pose(collector.means)
    assert np.allclose(cal.offset, O_TRUE, atol=0.01)
    assert np.allclose(np.asarray(cal.matrix), np.linalg.inv(K_TRUE), atol=0.003)
    assert cal.residual < 0.02 and not cal.problems()
    for pose in POSES:
        got = cal.apply(still_samples(pose, 1, noise=0.0)[0])
        assert np.linalg.norm(got) == pytest.approx(G, abs=0.01)


def test_missing_poses_and_unclear_poses() -> None:
    with pytest.raises(AccelError, match="poses missing: -z"):
        fit_six_pose({p: still_samples(p).mean(axis=0) for p in POSES[:-1]})
    assert pose_of([6.9, 6.9, 0.0]) is None and pose_of([0.0, 0.0, 1.0]) is None and pose_of([0, 0, -9.8]) == "-z"
