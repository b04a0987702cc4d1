"""Rigid 4x4 transforms (deformation.kinematics.transforms) against analytic references."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.kinematics.transforms import (
    apply,
    axis_angle_matrix,
    check_rigid,
    compose,
    from_rotation_translation,
    identity,
    interpolate,
    invert,
    is_rigid,
    rotation_about_point,
    rotation_angle_deg,
)

# Coordinates are ~100 mm; float64 rounding of one 4x4 product is then ~1e-14 mm.
ATOL = 1e-12


def _random_rigid(rng: np.random.Generator, *, scale_mm: float = 80.0) -> np.ndarray:
    r = Rotation.random(random_state=rng).as_matrix()
    return from_rotation_translation(r, rng.normal(0.0, scale_mm, 3))


def _rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# -- invert / compose -----------------------------------------------------------------------------


def test_invert_times_transform_is_identity():
    rng = np.random.default_rng(11)
    for _ in range(50):
        t = _random_rigid(rng)
        np.testing.assert_allclose(invert(t) @ t, np.eye(4), rtol=0, atol=ATOL)
        np.testing.assert_allclose(t @ invert(t), np.eye(4), rtol=0, atol=ATOL)


def test_invert_is_the_exact_rigid_inverse():
    rng = np.random.default_rng(12)
    t = _random_rigid(rng)
    inv = invert(t)
    # R^T and -R^T t, computed literally: the last row is exactly 0 0 0 1.
    np.testing.assert_array_equal(inv[:3, :3], t[:3, :3].T)
    np.testing.assert_array_equal(inv[:3, 3], -t[:3, :3].T @ t[:3, 3])
    np.testing.assert_array_equal(inv[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(inv, np.linalg.inv(t), rtol=0, atol=ATOL)
    np.testing.assert_allclose(invert(inv), t, rtol=0, atol=ATOL)


def test_invert_does_not_modify_its_input():
    t = _random_rigid(np.random.default_rng(13))
    before = t.copy()
    invert(t)
    np.testing.assert_array_equal(t, before)


def test_compose_applies_the_last_transform_first():
    # A: rotate 90° about z; B: translate by +10 along x.  The point x = (1, 0, 0):
    #   A @ B: translate first → (11, 0, 0), then rotate → (0, 11, 0);
    #   B @ A: rotate first → (0, 1, 0), then translate → (10, 1, 0).
    a = from_rotation_translation(_rz(90.0))
    b = from_rotation_translation(np.eye(3), (10.0, 0.0, 0.0))
    p = np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(apply(compose(a, b), p), [0.0, 11.0, 0.0], rtol=0, atol=ATOL)
    np.testing.assert_allclose(apply(compose(b, a), p), [10.0, 1.0, 0.0], rtol=0, atol=ATOL)
    np.testing.assert_allclose(apply(compose(a, b), p), apply(a, apply(b, p)), rtol=0, atol=ATOL)


def test_compose_of_many_equals_the_matrix_product():
    rng = np.random.default_rng(14)
    ts = [_random_rigid(rng) for _ in range(4)]
    np.testing.assert_array_equal(compose(), np.eye(4))
    np.testing.assert_array_equal(compose(ts[0]), ts[0])
    np.testing.assert_allclose(compose(*ts), ts[0] @ ts[1] @ ts[2] @ ts[3], rtol=0, atol=ATOL)


def test_apply_handles_point_arrays_of_any_leading_shape():
    rng = np.random.default_rng(15)
    t = _random_rigid(rng)
    pts = rng.normal(0.0, 50.0, size=(2, 5, 3))
    expected = np.einsum("ij,abj->abi", t[:3, :3], pts) + t[:3, 3]
    np.testing.assert_allclose(apply(t, pts), expected, rtol=0, atol=ATOL)
    np.testing.assert_array_equal(identity(), np.eye(4))


# -- rotations ----------------------------------------------------------------------------------------


def test_axis_angle_matrix_follows_the_right_hand_rule():
    # 90° about +z maps x → y, y → −x; 90° about +x maps y → z; 90° about +y maps z → x.
    ex, ey, ez = np.eye(3)
    np.testing.assert_allclose(axis_angle_matrix(ez, 90.0) @ ex, ey, rtol=0, atol=1e-15)
    np.testing.assert_allclose(axis_angle_matrix(ez, 90.0) @ ey, -ex, rtol=0, atol=1e-15)
    np.testing.assert_allclose(axis_angle_matrix(ex, 90.0) @ ey, ez, rtol=0, atol=1e-15)
    np.testing.assert_allclose(axis_angle_matrix(ey, 90.0) @ ez, ex, rtol=0, atol=1e-15)
    # The axis need not be unit length and is a fixed direction.
    np.testing.assert_allclose(axis_angle_matrix((0, 0, 7.0), 30.0), _rz(30.0), rtol=0, atol=1e-15)
    axis = np.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(axis_angle_matrix(axis, 73.0) @ axis, axis, rtol=0, atol=1e-14)


def test_axis_angle_matrix_matches_rodrigues_formula():
    rng = np.random.default_rng(16)
    for _ in range(20):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        theta = rng.uniform(-180.0, 180.0)
        k = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
        th = np.radians(theta)
        rodrigues = np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k
        np.testing.assert_allclose(axis_angle_matrix(n, theta), rodrigues, rtol=0, atol=1e-14)
        assert rotation_angle_deg(from_rotation_translation(rodrigues)) == pytest.approx(abs(theta), abs=1e-6)


def test_axis_angle_matrix_rejects_a_zero_axis():
    with pytest.raises(ValueError, match="non-zero"):
        axis_angle_matrix((0.0, 0.0, 0.0), 10.0)


def test_rotation_about_point_fixes_its_centre_and_rotates_about_it():
    rng = np.random.default_rng(17)
    for _ in range(20):
        r = Rotation.random(random_state=rng).as_matrix()
        c = rng.normal(0.0, 100.0, 3)
        t = rotation_about_point(r, c)
        assert is_rigid(t)
        np.testing.assert_allclose(apply(t, c), c, rtol=0, atol=ATOL)
        p = rng.normal(0.0, 100.0, size=(10, 3))
        np.testing.assert_allclose(apply(t, p), (p - c) @ r.T + c, rtol=0, atol=ATOL)
    # Explicit case: 90° about z through (1, 1, 0) sends (2, 1, 5) to (1, 2, 5).
    t = rotation_about_point(_rz(90.0), (1.0, 1.0, 0.0))
    np.testing.assert_allclose(apply(t, [2.0, 1.0, 5.0]), [1.0, 2.0, 5.0], rtol=0, atol=1e-14)


@pytest.mark.parametrize("deg", [0.0, 1e-3, 0.5, 45.0, 90.0, 135.0, 179.9])
def test_rotation_angle_deg(deg):
    t = from_rotation_translation(axis_angle_matrix((1.0, 2.0, -3.0), deg), (5.0, 0.0, 0.0))
    # arccos of the trace loses precision near 0° (~1e-6°); that bounds the tolerance.
    assert rotation_angle_deg(t) == pytest.approx(deg, abs=1e-5)
    assert rotation_angle_deg(from_rotation_translation(axis_angle_matrix((0, 1, 0), -deg))) == pytest.approx(
        deg, abs=1e-5
    )


# -- interpolation -------------------------------------------------------------------------------


def test_interpolate_returns_the_endpoints_exactly():
    rng = np.random.default_rng(18)
    t0, t1 = _random_rigid(rng), _random_rigid(rng)
    c = rng.normal(0.0, 100.0, 3)
    for centre in (None, c):
        np.testing.assert_array_equal(interpolate(t0, t1, 0.0, center=centre), t0)
        np.testing.assert_array_equal(interpolate(t0, t1, 1.0, center=centre), t1)
    out = interpolate(t0, t1, 0.0)
    out[0, 0] = 99.0  # a copy, not the caller's array
    assert t0[0, 0] != 99.0


def test_interpolate_midpoint_turns_half_the_relative_angle():
    rng = np.random.default_rng(19)
    for theta in (10.0, 60.0, 120.0, 170.0):
        t0 = _random_rigid(rng)
        axis = rng.normal(size=3)
        rel = from_rotation_translation(axis_angle_matrix(axis, theta), rng.normal(0.0, 30.0, 3))
        t1 = t0 @ rel
        for alpha in (0.25, 0.5, 0.8):
            ta = interpolate(t0, t1, alpha)
            assert is_rigid(ta, atol=1e-12)
            # Geodesic: t0⁻¹ ta turns by alpha·θ about the same axis.
            assert rotation_angle_deg(invert(t0) @ ta) == pytest.approx(alpha * theta, abs=1e-9)
            assert rotation_angle_deg(invert(ta) @ t1) == pytest.approx((1 - alpha) * theta, abs=1e-9)
            np.testing.assert_allclose(
                ta[:3, :3], t0[:3, :3] @ axis_angle_matrix(axis, alpha * theta), rtol=0, atol=1e-12
            )


def test_interpolate_moves_the_chosen_centre_on_a_straight_line():
    rng = np.random.default_rng(20)
    t0, t1 = _random_rigid(rng), _random_rigid(rng)
    c = rng.normal(0.0, 100.0, 3)
    c0, c1 = apply(t0, c), apply(t1, c)
    for alpha in np.linspace(0.0, 1.0, 11):
        ta = interpolate(t0, t1, alpha, center=c)
        np.testing.assert_allclose(apply(ta, c), (1 - alpha) * c0 + alpha * c1, rtol=0, atol=ATOL)
    # Without a centre, the world origin is the point that moves linearly (the translations blend).
    ta = interpolate(t0, t1, 0.3)
    np.testing.assert_allclose(ta[:3, 3], 0.7 * t0[:3, 3] + 0.3 * t1[:3, 3], rtol=0, atol=ATOL)
    # A different centre gives the same rotation but a different path of other points.
    other = interpolate(t0, t1, 0.3, center=c)
    np.testing.assert_allclose(other[:3, :3], ta[:3, :3], rtol=0, atol=1e-14)
    assert np.abs(other[:3, 3] - ta[:3, 3]).max() > 1e-3


def test_interpolate_rotation_about_a_fixed_centre_keeps_it_fixed():
    c = np.array([10.0, -20.0, 30.0])
    t1 = rotation_about_point(axis_angle_matrix((0, 0, 1), 80.0), c)
    ta = interpolate(identity(), t1, 0.5, center=c)
    np.testing.assert_allclose(ta, rotation_about_point(axis_angle_matrix((0, 0, 1), 40.0), c), rtol=0, atol=ATOL)


def test_interpolate_refuses_non_rigid_keyframes():
    with pytest.raises(ValueError, match="t1 is not rigid"):
        interpolate(identity(), np.diag([1.0, 1.0, -1.0, 1.0]), 0.5)


# -- validation --------------------------------------------------------------------------------------


def test_check_rigid_accepts_and_returns_float64():
    t = rotation_about_point(axis_angle_matrix((1, 1, 0), 30.0), (1, 2, 3)).tolist()
    out = check_rigid(t, name="pose")
    assert out.dtype == np.float64 and out.shape == (4, 4)
    np.testing.assert_array_equal(out, np.asarray(t))
    np.testing.assert_array_equal(check_rigid(np.eye(4, dtype=np.int64)), np.eye(4))


@pytest.mark.parametrize(
    "bad, fragment",
    [
        (np.diag([-1.0, 1.0, 1.0, 1.0]), "not rigid"),  # reflection (det −1)
        (np.array([[1.0, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "not rigid"),  # shear
        (np.diag([2.0, 2.0, 2.0, 1.0]), "not rigid"),  # scaling
        (np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.1, 0, 0, 1]]), "not rigid"),  # projective row
        (np.eye(3), "4x4"),
        (np.full((4, 4), np.nan), "NaN or inf"),
        (np.where(np.eye(4) > 0, np.inf, 0.0), "NaN or inf"),
    ],
)
def test_check_rigid_rejects_with_the_argument_name(bad, fragment):
    with pytest.raises(ValueError, match=fragment) as info:
        check_rigid(bad, name="my_transform")
    assert str(info.value).startswith("my_transform ")


def test_check_rigid_rejects_a_single_nan_among_good_numbers():
    t = np.eye(4)
    t[1, 3] = np.nan
    with pytest.raises(ValueError, match=r"root_transform contains NaN"):
        check_rigid(t, name="root_transform")
    assert not is_rigid(t)


@pytest.mark.parametrize("bad", [np.eye(3), np.eye(4)[:3], np.zeros(16), np.diag([1.0, 1.0, -1.0, 1.0])])
def test_is_rigid_is_false_not_an_error_for_bad_input(bad):
    assert is_rigid(bad) is False
