"""Dual quaternion blending (deformation.kinematics.dual_quaternion) against closed forms.

Reference: Kavan et al., ACM TOG 27(4), 2008, doi:10.1145/1409625.1409627.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.kinematics.dual_quaternion import blend_apply, from_transforms, quat_multiply
from deformation.kinematics.transforms import apply, axis_angle_matrix, from_rotation_translation, rotation_about_point

# Points are ~100 mm from the origin; quaternion algebra rounds to ~1e-16 relative.
ATOL = 1e-12


def _random_rigid(rng, n: int) -> np.ndarray:
    r = Rotation.random(n, random_state=rng).as_matrix()
    return np.stack([from_rotation_translation(r[i], rng.normal(0.0, 50.0, 3)) for i in range(n)])


def _wxyz(r: Rotation) -> np.ndarray:
    x, y, z, w = r.as_quat()
    return np.array([w, x, y, z])


def test_quat_multiply_hamilton_rules():
    one, i, j, k = np.eye(4)
    np.testing.assert_array_equal(quat_multiply(i, j), k)
    np.testing.assert_array_equal(quat_multiply(j, i), -k)
    np.testing.assert_array_equal(quat_multiply(j, k), i)
    np.testing.assert_array_equal(quat_multiply(k, i), j)
    np.testing.assert_array_equal(quat_multiply(i, i), -one)
    np.testing.assert_array_equal(quat_multiply(one, k), k)


def test_quat_multiply_composes_rotations():
    rng = np.random.default_rng(500)
    a, b = Rotation.random(random_state=rng), Rotation.random(random_state=rng)
    prod = quat_multiply(_wxyz(a), _wxyz(b))
    # q(a) q(b) is the rotation "b first, then a", up to the quaternion's sign.
    expected = _wxyz(a * b)
    assert min(np.abs(prod - expected).max(), np.abs(prod + expected).max()) < 1e-15
    # Broadcasts over leading axes.
    qs = np.stack([_wxyz(r) for r in Rotation.random(5, random_state=rng)])
    np.testing.assert_allclose(
        quat_multiply(qs, qs[::-1]), [quat_multiply(p, q) for p, q in zip(qs, qs[::-1])], rtol=0, atol=0
    )


def test_from_transforms_gives_unit_dual_quaternions():
    rng = np.random.default_rng(501)
    t = _random_rigid(rng, 6)
    dq = from_transforms(t)
    assert dq.shape == (6, 8)
    qr, qd = dq[:, :4], dq[:, 4:]
    np.testing.assert_allclose(np.linalg.norm(qr, axis=1), 1.0, rtol=0, atol=1e-15)
    # Unit dual quaternion: real part ⟂ dual part.
    np.testing.assert_allclose(np.sum(qr * qd, axis=1), 0.0, rtol=0, atol=1e-12)
    # t = 2 q_d q_r*.
    conj = qr * np.array([1.0, -1.0, -1.0, -1.0])
    t_back = 2.0 * quat_multiply(qd, conj)
    np.testing.assert_allclose(t_back[:, 0], 0.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(t_back[:, 1:], t[:, :3, 3], rtol=0, atol=ATOL)


def test_one_hot_weights_reproduce_each_transform():
    rng = np.random.default_rng(502)
    t = _random_rigid(rng, 4)
    dq = from_transforms(t)
    pts = rng.normal(0.0, 100.0, size=(40, 3))
    which = rng.integers(0, 4, size=40)
    weights = np.eye(4)[which]
    moved, rot = blend_apply(weights, dq, pts)
    for n in range(40):
        np.testing.assert_allclose(moved[n], apply(t[which[n]], pts[n]), rtol=0, atol=ATOL)
        np.testing.assert_allclose(rot[n], t[which[n], :3, :3], rtol=0, atol=1e-14)


def test_equal_transforms_blend_to_that_transform():
    rng = np.random.default_rng(503)
    t = _random_rigid(rng, 1)
    dq = from_transforms(np.repeat(t, 3, axis=0))
    pts = rng.normal(0.0, 100.0, size=(20, 3))
    w = rng.dirichlet(np.ones(3), size=20)
    moved, _ = blend_apply(w, dq, pts)
    np.testing.assert_allclose(moved, apply(t[0], pts), rtol=0, atol=ATOL)


def test_pure_translations_blend_linearly():
    t = np.stack(
        [
            from_rotation_translation(np.eye(3), (10.0, 0.0, -4.0)),
            from_rotation_translation(np.eye(3), (0.0, 20.0, 6.0)),
        ]
    )
    a = np.linspace(0.0, 1.0, 7)
    pts = np.tile([[1.0, 2.0, 3.0]], (7, 1))
    moved, rot = blend_apply(np.column_stack([1 - a, a]), from_transforms(t), pts)
    expected = pts + (1 - a)[:, None] * t[0, :3, 3] + a[:, None] * t[1, :3, 3]
    np.testing.assert_allclose(moved, expected, rtol=0, atol=ATOL)
    np.testing.assert_allclose(rot, np.broadcast_to(np.eye(3), rot.shape), rtol=0, atol=0)


@pytest.mark.parametrize("theta", [20.0, 90.0, 150.0, 175.0])
def test_identity_and_rotation_about_c_blend_to_a_rotation_about_c(theta):
    # Identity and a rotation about the line (c, n) both lie in span{1, n + ε c×n};
    # their normalised blend is a rotation about the same line by
    #   φ(a) = 2 atan2(a sin(θ/2), (1 − a) + a cos(θ/2)),
    # which is 0 at a = 0, θ at a = 1, θ/2 at a = ½, and increasing in between.
    rng = np.random.default_rng(504)
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    c = np.array([30.0, -70.0, 45.0])
    t = np.stack([np.eye(4), rotation_about_point(axis_angle_matrix(n, theta), c)])
    dq = from_transforms(t)
    a = np.linspace(0.0, 1.0, 21)
    w = np.column_stack([1 - a, a])
    on_axis = c + 25.0 * n
    for p in (c, on_axis):
        moved, _ = blend_apply(w, dq, np.tile(p, (len(a), 1)))
        np.testing.assert_allclose(moved, np.tile(p, (len(a), 1)), rtol=0, atol=ATOL)
    off_axis = rng.normal(0.0, 60.0, 3)
    moved, rot = blend_apply(w, dq, np.tile(off_axis, (len(a), 1)))
    half = np.radians(theta) / 2
    phi = np.degrees(2 * np.arctan2(a * np.sin(half), (1 - a) + a * np.cos(half)))
    for m in range(len(a)):
        expected = rotation_about_point(axis_angle_matrix(n, phi[m]), c)
        np.testing.assert_allclose(rot[m], expected[:3, :3], rtol=0, atol=1e-13)
        np.testing.assert_allclose(moved[m], apply(expected, off_axis), rtol=0, atol=ATOL)
    # The blended angle, read from the returned rotation, runs from 0 to θ and never turns back.
    angle = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angle[0] == pytest.approx(0.0, abs=1e-6) and angle[-1] == pytest.approx(theta, abs=1e-9)
    assert angle[10] == pytest.approx(theta / 2, abs=1e-9)
    assert np.all(np.diff(angle) > 0)
    assert np.all((angle >= -1e-9) & (angle <= theta + 1e-9))


def test_antipodal_quaternions_blend_to_the_same_transform():
    rng = np.random.default_rng(505)
    t = _random_rigid(rng, 3)
    dq = from_transforms(t)
    pts = rng.normal(0.0, 100.0, size=(30, 3))
    w = rng.dirichlet(np.ones(3), size=30)
    ref_moved, ref_rot = blend_apply(w, dq, pts)
    for flip in ([0], [1], [2], [0, 2], [0, 1, 2]):
        dq_flipped = dq.copy()
        dq_flipped[flip] *= -1.0  # q and −q: the same rigid transform
        moved, rot = blend_apply(w, dq_flipped, pts)
        np.testing.assert_allclose(moved, ref_moved, rtol=0, atol=ATOL)
        np.testing.assert_allclose(rot, ref_rot, rtol=0, atol=1e-13)


def test_antipodal_pair_of_one_rotation_is_not_cancelled():
    # The same rotation stored as q and −q, weighted half and half: a naive sum would be 0.
    t = np.stack([rotation_about_point(axis_angle_matrix((0, 0, 1), 60.0), (5.0, 5.0, 0.0))] * 2)
    dq = from_transforms(t)
    dq[1] *= -1.0
    p = np.array([[15.0, 5.0, 2.0]])
    moved, rot = blend_apply(np.array([[0.5, 0.5]]), dq, p)
    np.testing.assert_allclose(moved, apply(t[0], p), rtol=0, atol=ATOL)
    np.testing.assert_allclose(rot[0], t[0, :3, :3], rtol=0, atol=1e-14)


def test_blended_rotations_are_orthonormal():
    rng = np.random.default_rng(506)
    t = _random_rigid(rng, 5)
    pts = rng.normal(0.0, 100.0, size=(200, 3))
    w = rng.dirichlet(np.full(5, 0.5), size=200)
    moved, rot = blend_apply(w, from_transforms(t), pts)
    assert moved.shape == (200, 3) and rot.shape == (200, 3, 3)
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", rot, rot), np.broadcast_to(np.eye(3), rot.shape), rtol=0, atol=1e-14
    )
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, rtol=0, atol=1e-14)
    assert np.all(np.isfinite(moved))
