"""deformation.fields.interpolate.sample_spline against SciPy's map_coordinates (the convention it compiles)."""

import numpy as np
import pytest
from scipy import ndimage

from deformation.fields.interpolate import SERIAL_BELOW, sample_spline
from deformation.geometry import GridGeometry


def _grid(rng):
    direction = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # a rotated, anisotropic grid
    return GridGeometry((11, 9, 7), (0.8, 1.1, 2.0), (3.0, -2.0, 1.0), tuple(direction.reshape(-1)))


def _scipy(coeffs, g, points, order):
    """SciPy's value, NaN beyond half a voxel outside the grid (registration.rigid.Sampler's convention)."""
    idx = g.world_to_index(points)
    out = ndimage.map_coordinates(coeffs, idx[:, ::-1].T, order=order, mode="mirror", prefilter=False)
    out[np.any((idx < -0.5) | (idx > np.asarray(g.size) - 0.5), axis=1)] = np.nan
    return out


@pytest.mark.parametrize("order", [1, 3])
def test_matches_scipy_inside_at_the_edges_and_outside(order):
    rng = np.random.default_rng(0)
    g = _grid(rng)
    data = rng.random(g.array_shape)
    coeffs = ndimage.spline_filter(data, order=3, mode="mirror") if order == 3 else data
    # from a quarter of the grid before it to 15 % past it: outside, the half-voxel border, the mirrored stencil
    points = g.index_to_world(rng.uniform(-0.25, 1.15, size=(4000, 3)) * np.asarray(g.size))
    ref = _scipy(coeffs, g, points, order)
    got = sample_spline(coeffs, g.world_to_index_matrix, points, order=order)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    inside = ~np.isnan(ref)
    assert inside.sum() > 500 and (~inside).sum() > 500
    # the same sums in another order: a few ulps of values in [0, 1] (coefficients up to ~3)
    assert np.abs(got[inside] - ref[inside]).max() < 1e-13


def test_transforms_batch_equals_transformed_points_both_kernels():
    rng = np.random.default_rng(1)
    g = _grid(rng)
    coeffs = ndimage.spline_filter(rng.random(g.array_shape), order=3, mode="mirror")
    points = g.index_to_world(rng.uniform(0, 1, size=(300, 3)) * np.asarray(g.size))
    angles = rng.normal(scale=0.1, size=(3, 3))
    transforms = np.tile(np.eye(4), (3, 1, 1))
    for k, a in enumerate(angles):
        q, _ = np.linalg.qr(np.eye(3) + np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]]))
        transforms[k, :3, :3] = q * np.sign(np.diag(q))  # a rotation near the identity
        transforms[k, :3, 3] = rng.normal(size=3)
    small = sample_spline(coeffs, g.world_to_index_matrix, points, transforms=transforms)  # the serial kernel
    assert small.size < SERIAL_BELOW
    for k, t in enumerate(transforms):
        moved = points @ t[:3, :3].T + t[:3, 3]
        ref = _scipy(coeffs, g, moved, 3)
        assert np.array_equal(np.isnan(small[k]), np.isnan(ref))
        ok = ~np.isnan(ref)
        assert np.abs(small[k][ok] - ref[ok]).max() < 1e-12  # the transform's sums in another order too
    many = np.repeat(transforms, SERIAL_BELOW // len(points) + 1, axis=0)  # past SERIAL_BELOW: the threads
    big = sample_spline(coeffs, g.world_to_index_matrix, points, transforms=many)
    assert big.size >= SERIAL_BELOW
    assert np.array_equal(big[:: SERIAL_BELOW // len(points) + 1], small, equal_nan=True)  # the same bits


def test_order_must_be_1_or_3():
    with pytest.raises(ValueError, match="order must be 1"):
        sample_spline(np.zeros((2, 2, 2)), np.eye(4), np.zeros((1, 3)), order=2)
