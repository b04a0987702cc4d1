"""deformation.filters.smooth: each convention against its reference (SciPy's kernel, SimpleITK's filter, σ in mm)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from deformation.filters import smooth
from deformation.geometry import GridGeometry, Volume


def test_scipy_gaussian_of_a_delta_is_the_sampled_normal_kernel():
    # far from the edges, a delta smoothed by σ = 2 voxels along one axis is the normalised sampled Gaussian
    # exp(−k² / 2σ²) cut at truncate·σ: the convention's kernel, checked against the closed form
    a = np.zeros((1, 1, 41))
    a[0, 0, 20] = 1.0
    out = smooth(a, [0.0, 0.0, 2.0], truncate=3.0)
    k = np.arange(-6, 7, dtype=float)
    ref = np.exp(-(k**2) / 8.0)
    np.testing.assert_allclose(out[0, 0, 14:27], ref / ref.sum(), rtol=1e-12, atol=1e-15)
    assert np.all(out[0, 0, :14] == 0) and np.all(out[0, 0, 27:] == 0)


def test_units_mode_and_identity():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((9, 11, 13)).astype(np.float32)
    spacing = np.array([2.0, 1.0, 0.5])  # mm along z, y, x
    # σ 1 mm is 0.5, 1 and 2 voxels along z, y, x
    np.testing.assert_array_equal(
        smooth(a, 1.0, units="mm", spacing=spacing, mode="nearest"),
        ndimage.gaussian_filter(a, [0.5, 1.0, 2.0], mode="nearest"),
    )
    assert smooth(a, 0.0) is a  # every σ 0: the array itself
    assert smooth(a, 1.0).dtype == np.float32 and smooth(a, 1.0, dtype=np.float64).dtype == np.float64
    with pytest.raises(ValueError):
        smooth(a, 1.0, units="mm")
    with pytest.raises(ValueError):
        smooth(a, [1.0, 0.0, 1.0], method="recursive")


def test_recursive_is_simpleitks_filter_and_volumes_keep_their_geometry():
    rng = np.random.default_rng(2)
    a = rng.standard_normal((10, 12, 14)).astype(np.float32)
    g = GridGeometry(size=(14, 12, 10), spacing=(0.5, 1.0, 2.0), origin=(1.0, 2.0, 3.0))
    img = sitk.GetImageFromArray(a)
    img.SetSpacing((0.5, 1.0, 2.0))
    ref = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(img, [1.5, 1.5, 1.5]))
    out = smooth(Volume(a, g), 1.5, units="mm", method="recursive")
    assert out.geometry == g
    np.testing.assert_array_equal(out.data, ref)
    # in voxels the spacing is 1: σ 1.5 voxels along every axis
    img.SetSpacing((1.0, 1.0, 1.0))
    ref_v = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(img, 1.5))
    np.testing.assert_array_equal(smooth(a, 1.5, method="recursive"), ref_v)
    # Deriche's recursive filter approximates the sampled Gaussian away from the edges
    inner = (slice(4, -4),) * 3
    big = rng.standard_normal((24, 24, 24)).astype(np.float32)
    np.testing.assert_allclose(smooth(big, 1.5, method="recursive")[inner], smooth(big, 1.5)[inner], rtol=0, atol=0.02)
