"""Least-squares rigid fit (deformation.kinematics.rigid_fit)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.kinematics.rigid_fit import fit_rigid, rigid_residuals


def _transform(rotvec_deg, translation) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    t[:3, 3] = translation
    return t


def _apply(t, p):
    return p @ t[:3, :3].T + t[:3, 3]


@pytest.mark.parametrize(
    "rotvec_deg, translation",
    [
        ([0, 0, 0], [0, 0, 0]),
        ([10, -20, 30], [5.0, -3.0, 12.0]),
        ([0, 179.0, 0], [-40, 2, 1]),
        ([90, 0, 0], [0.001, 0, 0]),
    ],
)
def test_recovers_known_transform(rotvec_deg, translation):
    rng = np.random.default_rng(0)
    src = rng.normal(0.0, 20.0, size=(50, 3)) + [100.0, -50.0, 30.0]
    truth = _transform(rotvec_deg, translation)
    dst = _apply(truth, src)
    fitted = fit_rigid(src, dst)
    # Exact data: the fit is exact up to float64 rounding on ~100 mm coordinates.
    np.testing.assert_allclose(fitted, truth, rtol=0, atol=1e-10)
    assert rigid_residuals(fitted, src, dst).max() < 1e-10
    assert np.isclose(np.linalg.det(fitted[:3, :3]), 1.0, atol=1e-12)


def test_template_to_scan_direction():
    src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    dst = src + [10.0, 0, 0]
    t = fit_rigid(src, dst)
    np.testing.assert_allclose(t @ [0, 0, 0, 1], [10, 0, 0, 1], atol=1e-12)  # T @ [src, 1] = dst


def test_reflection_guard_returns_a_rotation():
    # Target = mirror image of the source: the best orthogonal map is a
    # reflection; the fit must still return a proper rotation.
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 3))
    dst = src * [1.0, 1.0, -1.0]
    t = fit_rigid(src, dst)
    assert np.isclose(np.linalg.det(t[:3, :3]), 1.0, atol=1e-12)
    np.testing.assert_allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-12)
    assert rigid_residuals(t, src, dst).mean() > 0.1  # a reflection cannot be fitted exactly


def test_noisy_fit_is_close_and_weights_select_points():
    rng = np.random.default_rng(2)
    src = rng.normal(0.0, 30.0, size=(2000, 3))
    truth = _transform([5, 10, -15], [1, 2, 3])
    dst = _apply(truth, src) + rng.normal(0.0, 0.1, size=src.shape)
    fitted = fit_rigid(src, dst)
    # 0.1 mm noise over 2000 points spread ±30 mm: rotation error ~ 0.1/(30 sqrt(2000)) rad.
    angle = np.degrees(Rotation.from_matrix(fitted[:3, :3] @ truth[:3, :3].T).magnitude())
    assert angle < 0.01
    np.testing.assert_allclose(fitted[:3, 3], truth[:3, 3], atol=0.02)
    # Outliers with zero weight are ignored exactly.
    dst_out = _apply(truth, src)
    dst_out[:100] += 50.0
    w = np.ones(len(src))
    w[:100] = 0.0
    np.testing.assert_allclose(fit_rigid(src, dst_out, weights=w), truth, atol=1e-10)


def test_degenerate_inputs_raise():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        fit_rigid(line, line + 1.0)
    with pytest.raises(ValueError, match="at least 3"):
        fit_rigid(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="shape"):
        fit_rigid(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="weights"):
        fit_rigid(np.eye(3), np.eye(3), weights=[1, -1, 1])
