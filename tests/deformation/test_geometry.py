"""Grid geometry: index ↔ world in ITK's convention (deformation.geometry)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from deformation.geometry import GeometryMismatchError, GridGeometry, Volume

SIZE = (7, 5, 4)  # (nx, ny, nz): all different, so a swapped axis cannot hide
SPACING = (0.7, 1.3, 2.1)
ORIGIN = (-12.5, 30.25, 7.0)
# A proper rotation with no zero entries: every index axis feeds every world axis.
DIRECTION = Rotation.from_euler("ZYX", [30.0, -20.0, 50.0], degrees=True).as_matrix()
# World coordinates are ~30 mm: float64 rounding of the affine map is ~1e-14 mm.
ATOL_MM = 1e-12


@pytest.fixture
def geom() -> GridGeometry:
    return GridGeometry(SIZE, SPACING, ORIGIN, DIRECTION.reshape(-1))


def _sitk_image(g: GridGeometry) -> sitk.Image:
    img = sitk.Image(list(g.size), sitk.sitkFloat32)
    img.SetSpacing(g.spacing)
    img.SetOrigin(g.origin)
    img.SetDirection(g.direction)
    return img


def test_direction_is_a_proper_rotation():
    assert np.linalg.det(DIRECTION) == pytest.approx(1.0, abs=1e-14)
    assert np.all(np.abs(DIRECTION) > 0.05)


def test_shapes_and_derived_quantities(geom):
    assert geom.size == (7, 5, 4)
    assert geom.array_shape == (4, 5, 7)
    assert geom.n_voxels == 140
    assert geom.extent_mm == pytest.approx((4.9, 6.5, 8.4), abs=1e-12)
    np.testing.assert_array_equal(geom.direction_matrix, DIRECTION)


def test_index_to_world_is_origin_plus_direction_times_scaled_index(geom):
    rng = np.random.default_rng(400)
    ijk = rng.uniform(-1.0, 8.0, size=(50, 3))
    expected = np.array(ORIGIN) + (DIRECTION @ (np.array(SPACING) * ijk).T).T
    np.testing.assert_allclose(geom.index_to_world(ijk), expected, rtol=0, atol=ATOL_MM)
    # Explicit: index (1, 0, 0) sits one x-spacing along the first direction column.
    np.testing.assert_allclose(
        geom.index_to_world([1, 0, 0]), np.array(ORIGIN) + 0.7 * DIRECTION[:, 0], rtol=0, atol=ATOL_MM
    )
    np.testing.assert_allclose(
        geom.index_to_world([0, 0, 1]), np.array(ORIGIN) + 2.1 * DIRECTION[:, 2], rtol=0, atol=ATOL_MM
    )
    np.testing.assert_array_equal(geom.index_to_world([0, 0, 0]), ORIGIN)


def test_index_world_round_trip(geom):
    rng = np.random.default_rng(401)
    ijk = rng.uniform(-2.0, 9.0, size=(4, 25, 3))
    back = geom.world_to_index(geom.index_to_world(ijk))
    assert back.shape == ijk.shape
    np.testing.assert_allclose(back, ijk, rtol=0, atol=1e-12)
    world = rng.uniform(-50.0, 50.0, size=(100, 3))
    np.testing.assert_allclose(geom.index_to_world(geom.world_to_index(world)), world, rtol=0, atol=ATOL_MM)
    np.testing.assert_allclose(geom.world_to_index_matrix @ geom.index_to_world_matrix, np.eye(4), rtol=0, atol=1e-14)


def test_agrees_with_simpleitk(geom):
    img = _sitk_image(geom)
    rng = np.random.default_rng(402)
    for ijk in rng.uniform(-1.0, 8.0, size=(30, 3)):
        itk_point = img.TransformContinuousIndexToPhysicalPoint(ijk.tolist())
        np.testing.assert_allclose(geom.index_to_world(ijk), itk_point, rtol=0, atol=ATOL_MM)
        itk_index = img.TransformPhysicalPointToContinuousIndex(itk_point)
        np.testing.assert_allclose(geom.world_to_index(itk_point), itk_index, rtol=0, atol=1e-12)
    for idx in [(0, 0, 0), (6, 4, 3), (3, 1, 2)]:
        np.testing.assert_allclose(
            geom.index_to_world(idx), img.TransformIndexToPhysicalPoint(idx), rtol=0, atol=ATOL_MM
        )
    assert GridGeometry.from_sitk(img) == geom


def test_world_coordinates_layout(geom):
    xyz = geom.world_coordinates()
    assert xyz.shape == (4, 5, 7, 3) and xyz.dtype == np.float64
    for k in range(4):
        for j in range(5):
            for i in range(7):
                np.testing.assert_allclose(xyz[k, j, i], geom.index_to_world((i, j, k)), rtol=0, atol=ATOL_MM)
    # Same numbers in one vectorised check, through SimpleITK's array layout ([z, y, x]).
    k, j, i = np.indices(geom.array_shape)
    np.testing.assert_allclose(xyz, geom.index_to_world(np.stack([i, j, k], axis=-1)), rtol=0, atol=ATOL_MM)


def test_world_coordinates_z_slice_and_dtype(geom):
    full = geom.world_coordinates()
    np.testing.assert_array_equal(geom.world_coordinates(z_slice=slice(1, 3)), full[1:3])
    np.testing.assert_array_equal(geom.world_coordinates(z_slice=slice(3, None)), full[3:])
    np.testing.assert_array_equal(geom.world_coordinates(z_slice=slice(None, None, 2)), full[::2])
    assert geom.world_coordinates(z_slice=slice(4, 4)).shape == (0, 5, 7, 3)
    f32 = geom.world_coordinates(dtype=np.float32)
    assert f32.dtype == np.float32
    # float32 carries ~7 significant digits of ~40 mm coordinates.
    np.testing.assert_allclose(f32, full, rtol=0, atol=1e-5)


def test_contains_world(geom):
    inside = geom.index_to_world([[0, 0, 0], [6, 4, 3], [3.2, 2.5, 1.1]])
    outside = geom.index_to_world([[-0.5, 0, 0], [6.5, 4, 3], [3, 2, 3.2]])
    assert geom.contains_world(inside).all()
    assert not geom.contains_world(outside).any()
    assert geom.contains_world(outside, margin_voxels=0.6).all()


def test_volume_sitk_round_trip(geom):
    rng = np.random.default_rng(403)
    data = rng.normal(size=geom.array_shape).astype(np.float32)
    vol = Volume(data, geom)
    img = vol.to_sitk()
    assert img.GetSize() == geom.size
    np.testing.assert_allclose(img.GetSpacing(), SPACING, rtol=0, atol=0)
    np.testing.assert_allclose(img.GetOrigin(), ORIGIN, rtol=0, atol=0)
    np.testing.assert_allclose(img.GetDirection(), DIRECTION.reshape(-1), rtol=0, atol=0)
    # Voxel [k, j, i] of the array is ITK pixel (i, j, k).
    assert img.GetPixel(6, 4, 3) == data[3, 4, 6]
    assert img.GetPixel(1, 2, 0) == data[0, 2, 1]
    back = Volume.from_sitk(img)
    assert back.geometry == geom
    assert back.data.dtype == np.float32
    np.testing.assert_array_equal(back.data, data)


def test_vector_volume_sitk_round_trip(geom):
    rng = np.random.default_rng(404)
    field = rng.normal(size=geom.array_shape + (3,))
    vol = Volume(field, geom)
    assert vol.is_vector and vol.n_components == 3
    img = vol.to_sitk()
    assert img.GetNumberOfComponentsPerPixel() == 3 and img.GetSize() == geom.size
    np.testing.assert_allclose(img.GetPixel(5, 1, 2), field[2, 1, 5], rtol=0, atol=0)
    back = Volume.from_sitk(img)
    assert back.geometry == geom
    np.testing.assert_array_equal(back.data, field)


def test_volume_rejects_a_mismatched_array(geom):
    with pytest.raises(GeometryMismatchError, match=r"expected leading shape \(nz, ny, nx\) = \(4, 5, 7\)"):
        Volume(np.zeros((7, 5, 4)), geom)
    with pytest.raises(ValueError, match="3-D or 4-D"):
        Volume(np.zeros((4, 5, 7, 3, 2)), geom)


def test_dict_round_trip(geom):
    assert GridGeometry.from_dict(geom.to_dict()) == geom
    assert GridGeometry.from_dict({"size": [2, 3, 4], "spacing": [1, 1, 1]}) == GridGeometry((2, 3, 4), (1, 1, 1))


def test_check_same_passes_for_equal_grids(geom):
    geom.check_same(GridGeometry(SIZE, SPACING, ORIGIN, DIRECTION.reshape(-1)))
    # Below the tolerances (1e-6 relative spacing, 1e-4 mm origin): still the same grid.
    geom.check_same(
        GridGeometry(SIZE, (0.7 * (1 + 1e-9), 1.3, 2.1), (ORIGIN[0] + 1e-6, *ORIGIN[1:]), DIRECTION.reshape(-1))
    )


def test_check_same_prints_both_geometries(geom):
    other = GridGeometry(SIZE, (0.7, 1.3, 2.5), ORIGIN, DIRECTION.reshape(-1))
    with pytest.raises(GeometryMismatchError) as info:
        geom.check_same(other, names=("image", "labels"))
    msg = str(info.value)
    assert f"image: {geom.describe()}" in msg
    assert f"labels: {other.describe()}" in msg
    assert "spacing=(0.7, 1.3, 2.1)" in msg and "spacing=(0.7, 1.3, 2.5)" in msg
    assert "Remedy: resample" in msg
    with pytest.raises(GeometryMismatchError, match="Remedy: regenerate the phantom."):
        geom.check_same(other, remedy="regenerate the phantom")


@pytest.mark.parametrize(
    "change",
    [
        {"size": (7, 5, 5)},
        {"origin": (-12.5, 30.25, 7.001)},
        {"direction": np.eye(3).reshape(-1)},
    ],
)
def test_check_same_sees_every_field(geom, change):
    args = {"size": SIZE, "spacing": SPACING, "origin": ORIGIN, "direction": DIRECTION.reshape(-1)}
    args.update(change)
    with pytest.raises(GeometryMismatchError, match="grid geometries differ"):
        geom.check_same(GridGeometry(**args))


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"size": (0, 5, 4)}, "size must be 3 positive integers"),
        ({"size": (7, 5)}, "size must be 3 positive integers"),
        ({"spacing": (0.7, 0.0, 2.1)}, "spacing must be positive"),
        ({"spacing": (0.7, 1.3)}, "spacing must have 3 components"),
        ({"origin": (0.0, np.nan, 0.0)}, "origin must be finite"),
        ({"direction": np.diag([1.0, 2.0, 1.0]).reshape(-1)}, "direction must be orthonormal"),
        ({"direction": np.eye(2).reshape(-1)}, "direction must be a 3x3 matrix"),
    ],
)
def test_grid_geometry_rejects_bad_fields(kwargs, fragment):
    args = {"size": SIZE, "spacing": SPACING}
    args.update(kwargs)
    with pytest.raises(ValueError, match=fragment):
        GridGeometry(**args)


def test_apply_to_sitk_refuses_another_size(geom):
    img = sitk.Image([7, 5, 3], sitk.sitkUInt8)
    with pytest.raises(GeometryMismatchError, match="differs from grid size"):
        geom.apply_to_sitk(img)


def test_volume_crop_keeps_voxels_in_place(geom):
    rng = np.random.default_rng(3)
    vol = Volume(rng.normal(size=geom.array_shape), geom)
    sub = vol.crop((1, 2, 1), (4, 5, 3))  # the grid is 7×5×4 (x, y, z), rotated and anisotropic
    assert sub.geometry.size == (3, 3, 2)
    # Every voxel of the crop is at the same world position, with the same value, as in the original.
    ijk = np.array([[i, j, k] for i in range(3) for j in range(3) for k in range(2)], float)
    np.testing.assert_allclose(sub.geometry.index_to_world(ijk), geom.index_to_world(ijk + [1, 2, 1]), atol=1e-9)
    for i, j, k in ijk.astype(int):
        assert sub.data[k, j, i] == vol.data[k + 1, j + 2, i + 1]
    assert vol.crop((-5, 0, 0), (2, 99, 99)).geometry.size == (2,) + tuple(geom.size[1:])  # clipped
    with pytest.raises(ValueError, match="empty crop"):
        vol.crop((2, 0, 0), (2, 1, 1))


def test_every_fth_voxel_of_a_volume_and_the_factor_within_a_budget():
    """Volume.every: labels as they are at voxels 0, f, 2f, … (same world positions); intensities smoothed first
    (σ = f/2 voxels): a constant stays constant and a one-voxel checkerboard, which plain sampling would alias
    to a constant 0, is averaged towards its mean 0.5.  factor_within: the smallest factor under a budget."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("xyz", [10.0, -20.0, 35.0], degrees=True).as_matrix()
    g = GridGeometry((9, 8, 7), (1.5, 0.7, 2.2), (10.0, -3.0, 4.0), tuple(rot.ravel()))
    lab = Volume(np.arange(g.n_voxels, dtype=np.int32).reshape(g.array_shape), g)
    c = lab.every(2)
    assert c.geometry.is_close(g.every(2)) and c.data.shape == (4, 4, 5)
    np.testing.assert_array_equal(c.data, lab.data[::2, ::2, ::2])
    np.testing.assert_allclose(c.geometry.index_to_world([[1.0, 2.0, 3.0]]), g.index_to_world([[2.0, 4.0, 6.0]]))
    assert lab.every(1) is lab
    flat = Volume(np.full(g.array_shape, 7.0), g).every(2, smooth=True)
    np.testing.assert_allclose(flat.data, 7.0, rtol=1e-5)
    k, j, i = np.indices((40, 40, 40))
    checker = Volume(((i + j + k) % 2).astype(np.float32), GridGeometry((40, 40, 40), (1.0, 1.0, 1.0)))
    assert np.all(checker.data[::2, ::2, ::2] == 0)  # plain sampling: every kept voxel is even
    s = checker.every(2, smooth=True).data[3:-3, 3:-3, 3:-3]  # away from the border
    assert np.abs(s - 0.5).max() < 0.1, np.abs(s - 0.5).max()
    assert g.factor_of(g.every(3)) == 3 and g.factor_of(g) == 1
    assert g.factor_of(g.every(2).crop((0, 0, 0), (2, 2, 2))) is None  # coarse, but not every 2nd voxel of g
    big = GridGeometry((512, 512, 750), (0.468, 0.468, 0.3))
    assert big.factor_within(32_000_000) == 2 and big.factor_within(big.n_voxels) == 1
    assert big.every(2).n_voxels <= 32_000_000 < big.every(1).n_voxels


def test_from_every_gives_each_voxel_the_coarse_voxel_at_or_before_it_and_slabs_cover_the_planes():
    from deformation.geometry import from_every, slabs

    g = GridGeometry((7, 5, 4), (1.0, 2.0, 3.0), (0.0, 0.0, 0.0), np.eye(3).reshape(-1))  # odd sizes
    for f in (1, 2, 3):
        coarse = np.arange(g.every(f).n_voxels).reshape(g.every(f).array_shape)
        up = from_every(coarse, f, g.array_shape)
        k, j, i = np.indices(g.array_shape)
        assert up.shape == g.array_shape and np.array_equal(up, coarse[k // f, j // f, i // f])
    for n, plane, voxels in ((10, 7, 20), (3, 100, 1), (5, 1, 1000)):
        got = list(slabs(n, plane, voxels))
        assert got[0][0] == 0 and got[-1][1] == n and all(a[1] == b[0] for a, b in zip(got, got[1:]))
        assert all(k1 - k0 == max(1, voxels // plane) for k0, k1 in got[:-1])
