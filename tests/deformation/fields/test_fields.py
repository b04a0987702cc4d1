"""Sampling (deformation.fields.interpolate) and displacement fields (deformation.fields.displacement).

Every geometric test uses anisotropic spacing and a non-identity direction
matrix, so a swapped axis, a forgotten spacing or a transposed direction
cannot hide.  SimpleITK is the reference for the sampling conventions.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from deformation.fields import displacement as F
from deformation.fields.interpolate import sample, sample_array, sample_displaced_array, warp
from deformation.geometry import GeometryMismatchError, GridGeometry, Volume

SIZE = (23, 19, 15)  # (nx, ny, nz): all different
SPACING = (0.8, 1.1, 1.7)
ORIGIN = (-12.5, 30.25, 7.0)
DIRECTION = Rotation.from_euler("ZYX", [30.0, -20.0, 50.0], degrees=True).as_matrix()
# float32 has a 24-bit significand: one ulp of a value in [0, 1) is at most 2**-24.  Both we and
# ITK interpolate in float64 and round once to float32, so they may differ by one such ulp.
F32_ULP_BELOW_1 = 2.0**-23  # (a generous 2 ulp)
# World coordinates here are < 100 mm: float64 round-off of a handful of affine operations on them
# is ~1e-13 mm; 1e-9 mm leaves ample room and is still far below anything physical.
ROUNDOFF_MM = 1e-9


def _geom(size=SIZE, spacing=SPACING, origin=ORIGIN, direction=DIRECTION) -> GridGeometry:
    return GridGeometry(size, spacing, origin, np.asarray(direction).reshape(-1))


def _centre(g: GridGeometry) -> np.ndarray:
    return g.index_to_world((np.asarray(g.size) - 1) / 2.0)


def _other_geom(g: GridGeometry, *, offset_mm=(3.0, -2.5, 4.0)) -> GridGeometry:
    """A differently placed, rotated, anisotropic grid overlapping ``g`` partly (some voxels outside)."""
    d2 = Rotation.from_euler("XYZ", [-35.0, 15.0, 70.0], degrees=True).as_matrix()
    size2, sp2 = np.array([21, 24, 17]), np.array([0.9, 0.75, 1.3])
    origin2 = _centre(g) + np.asarray(offset_mm) - d2 @ (sp2 * (size2 - 1) / 2.0)
    return GridGeometry(tuple(size2), tuple(sp2), tuple(origin2), d2.reshape(-1))


def _sitk_reference(g: GridGeometry) -> sitk.Image:
    img = sitk.Image(list(g.size), sitk.sitkFloat32)
    g.apply_to_sitk(img)
    return img


def _affine_sitk():
    """A sitk.AffineTransform and the same map as (matrix, centre, translation)."""
    m = Rotation.from_euler("ZXY", [12.0, -7.0, 9.0], degrees=True).as_matrix() @ np.diag([1.05, 0.93, 1.1])
    c, t = np.array([-5.0, 40.0, 15.0]), np.array([0.7, -1.2, 0.4])
    tx = sitk.AffineTransform(m.reshape(-1).tolist(), t.tolist(), c.tolist())
    return tx, (m, c, t)


def _apply_affine(p, mct):
    m, c, t = mct
    return (p - c) @ m.T + c + t


def _sinusoid(p, modes):
    """u(p) = Σ a sin(k·p + φ) over modes (a, k, φ); p (..., 3) world mm."""
    out = np.zeros(np.shape(p))
    for a, k, ph in modes:
        out += np.asarray(a) * np.sin(p @ np.asarray(k) + ph)[..., None]
    return out


def _lipschitz(modes) -> float:
    """An upper bound of |∇u| (operator norm) of a sum of sinusoidal modes: Σ |a| |k|."""
    return float(sum(np.linalg.norm(a) * np.linalg.norm(k) for a, k, _ in modes))


def _trilinear_error_bound(modes, g: GridGeometry) -> float:
    """Bound on |u - trilinear(u)| (Euclidean norm) for sinusoidal modes on grid ``g``.

    Tensor-product linear interpolation is a max-norm contraction applied axis by axis, so
    its error is at most Σ_m h_m²/8 · max|∂²u/∂s_m²| with s_m the world arc length along index
    axis m (direction column d_m, spacing h_m).  For a mode a·sin(k·p + φ) that second
    derivative is bounded by |a| (k·d_m)².
    """
    d, h = g.direction_matrix, np.asarray(g.spacing)
    return float(sum(np.linalg.norm(a) * np.sum(h**2 * (np.asarray(k) @ d) ** 2) / 8.0 for a, k, _ in modes))


def _field(g: GridGeometry, fn) -> Volume:
    """The displacement field of the analytic map ``fn`` (world points → world points) on ``g``."""
    x = g.world_coordinates()
    return Volume(fn(x) - x, g)


def _interior(g: GridGeometry, margin_mm: float) -> np.ndarray:
    """Voxels whose ball of radius ``margin_mm`` lies inside the voxel-centre box of ``g``."""
    ijk = g.world_to_index(g.world_coordinates())
    m = margin_mm / np.asarray(g.spacing)
    return np.all((ijk >= m) & (ijk <= np.asarray(g.size) - 1 - m), axis=-1)


# ===================================================================================== sampling
@pytest.fixture(scope="module")
def geom() -> GridGeometry:
    return _geom()


def test_direction_is_a_proper_rotation_with_no_zero_entries():
    assert np.linalg.det(DIRECTION) == pytest.approx(1.0, abs=1e-14)
    assert np.all(np.abs(DIRECTION) > 0.05)


@pytest.mark.parametrize("use_affine", [False, True])
def test_trilinear_sample_matches_sitk_resample(geom, use_affine):
    rng = np.random.default_rng(1)
    vol = Volume(rng.random(geom.array_shape, dtype=np.float32), geom)
    out_geom = _other_geom(geom)
    pts = out_geom.world_coordinates()
    tx = sitk.Transform(3, sitk.sitkIdentity)
    if use_affine:
        tx, mct = _affine_sitk()
        pts = _apply_affine(pts, mct)
    fill = -7.0
    ref = sitk.GetArrayFromImage(sitk.Resample(vol.to_sitk(), _sitk_reference(out_geom), tx, sitk.sitkLinear, fill))
    ours = sample(vol, pts, order=1, fill=fill)
    assert ours.dtype == np.float32 and ours.shape == out_geom.array_shape
    outside = ours == fill
    assert 0.1 < outside.mean() < 0.9  # the comparison covers inside, border and outside points
    np.testing.assert_array_equal(outside, ref == fill)
    # both interpolate in float64 and round once to float32 (values in [0, 1)): ≤ 1 ulp apart
    np.testing.assert_allclose(ours, ref, rtol=0, atol=F32_ULP_BELOW_1)


def test_trilinear_sample_of_a_vector_volume_matches_sitk_and_per_component(geom):
    rng = np.random.default_rng(2)
    vol = Volume(rng.random(geom.array_shape + (3,), dtype=np.float32), geom)
    out_geom = _other_geom(geom, offset_mm=(-2.0, 1.0, -3.0))
    tx, mct = _affine_sitk()
    pts = _apply_affine(out_geom.world_coordinates(), mct)
    ref = sitk.GetArrayFromImage(sitk.Resample(vol.to_sitk(), _sitk_reference(out_geom), tx, sitk.sitkLinear, 0.0))
    ours = sample(vol, pts)
    assert ours.shape == out_geom.array_shape + (3,)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=F32_ULP_BELOW_1)  # as in the scalar test
    for c in range(3):  # the vector kernel is the scalar kernel per component, bit for bit
        np.testing.assert_array_equal(ours[..., c], sample(Volume(vol.data[..., c], geom), pts))


@pytest.mark.parametrize("dtype", [np.uint8, np.int16])
def test_nearest_matches_sitk_and_preserves_labels(geom, dtype):
    rng = np.random.default_rng(3)
    labels = np.kron(rng.integers(1, 6, size=(5, 5, 6)), np.ones((3, 4, 4), dtype=int))[:15, :19, :23]
    vol = Volume(labels.astype(dtype), geom)
    out_geom = _other_geom(geom)
    tx, mct = _affine_sitk()
    pts = _apply_affine(out_geom.world_coordinates(), mct)
    ref = sitk.GetArrayFromImage(
        sitk.Resample(vol.to_sitk(), _sitk_reference(out_geom), tx, sitk.sitkNearestNeighbor, 99)
    )
    ours = sample(vol, pts, order=0, fill=99)
    assert ours.dtype == dtype
    np.testing.assert_array_equal(ours, ref)  # nearest neighbour copies values: exact
    assert set(np.unique(ours)) <= set(np.unique(labels)) | {99}
    # at voxel centres nearest neighbour returns every label unchanged
    np.testing.assert_array_equal(sample(vol, geom.world_coordinates(), order=0), vol.data)


def test_nearest_rejects_a_fill_the_dtype_cannot_hold(geom):
    vol = Volume(np.zeros(geom.array_shape, dtype=np.uint8), geom)
    with pytest.raises(ValueError, match="not representable"):
        sample(vol, np.zeros((2, 3)), order=0, fill=-1)


@pytest.mark.parametrize("order, interp", [(1, sitk.sitkLinear), (0, sitk.sitkNearestNeighbor)])
def test_half_voxel_border_is_edge_clamped_and_beyond_is_fill_like_sitk(geom, order, interp):
    rng = np.random.default_rng(4)
    vol = Volume(rng.random(geom.array_shape, dtype=np.float32) + 1.0, geom)  # values in [1, 2): never fill
    nx = geom.size[0]
    # a line of points along the i axis through voxel row (j, k) = (3, 2), index -1.05 ... nx + 0.05
    m = int(round((nx + 1.1) / 0.1)) + 1
    line = GridGeometry(
        (m, 1, 1),
        (0.1 * SPACING[0], SPACING[1], SPACING[2]),
        tuple(geom.index_to_world([-1.05, 3.0, 2.0])),
        geom.direction,
    )
    i = -1.05 + 0.1 * np.arange(m)
    ref = sitk.GetArrayFromImage(sitk.Resample(vol.to_sitk(), _sitk_reference(line), sitk.Transform(), interp, 0.0))
    ours = sample(vol, line.world_coordinates(), order=order, fill=0.0)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=2 * F32_ULP_BELOW_1)  # values in [1, 2): 1 ulp = 2**-23
    ours = ours.reshape(-1)
    row = vol.data[2, 3, :]
    assert np.all(ours[i < -0.5] == 0.0) and np.all(ours[i > nx - 0.5] == 0.0)
    np.testing.assert_array_equal(ours[(i > -0.5) & (i < 0.0)], row[0])  # clamped to the edge voxel
    np.testing.assert_array_equal(ours[(i > nx - 1) & (i < nx - 0.5)], row[-1])


def test_trilinear_is_exact_for_linear_functions(geom):
    rng = np.random.default_rng(5)
    c, d = np.array([0.7, -1.3, 0.4]), 2.5
    x = geom.world_coordinates()
    vol = Volume(x @ c + d, geom)
    ijk = rng.uniform(0.0, np.asarray(geom.size) - 1.0, size=(4000, 3))  # inside the voxel-centre box
    pts = geom.index_to_world(ijk)
    # trilinear interpolation reproduces functions linear in the index, and a linear function of the
    # world point is one; values ~50: float64 round-off ~1e-13
    np.testing.assert_allclose(sample(vol, pts), pts @ c + d, rtol=0, atol=ROUNDOFF_MM)
    # float32 points are used as they are (converted exactly to float64), so exactness holds at the
    # rounded point
    p32 = pts.astype(np.float32)
    np.testing.assert_allclose(sample(vol, p32), p32.astype(np.float64) @ c + d, rtol=0, atol=ROUNDOFF_MM)
    # vector volumes, components x, y, z in the trailing axis; and shapes (..., 3) → (..., c)
    cv = rng.normal(size=(3, 3))
    vvol = Volume(x @ cv.T, geom)
    got = sample(vvol, pts.reshape(40, 100, 3))
    assert got.shape == (40, 100, 3)
    np.testing.assert_allclose(got.reshape(-1, 3), pts @ cv.T, rtol=0, atol=ROUNDOFF_MM)
    # integer data are interpolated to float64
    ivol = Volume(np.round(10 * (x @ c)).astype(np.int32), geom)
    assert sample(ivol, pts).dtype == np.float64


def test_sample_array_warp_and_displaced_sampling_agree(geom):
    rng = np.random.default_rng(6)
    vol = Volume(rng.random(geom.array_shape), geom)
    out_geom = _other_geom(geom)
    disp = rng.normal(scale=0.8, size=out_geom.array_shape + (3,))
    pos = out_geom.world_coordinates() + disp
    expected = sample(vol, pos, fill=-1.0)
    np.testing.assert_array_equal(sample_array(vol.data, geom.world_to_index_matrix, pos, 1, -1.0), expected)
    w = warp(vol, pos, out_geom, fill=-1.0)
    assert w.geometry == out_geom
    np.testing.assert_array_equal(w.data, expected)
    # the fused kernel forms x + disp itself: the same points up to one float64 rounding, and
    # the interpolated values (gradients ≤ 1/voxel of data in [0,1)) differ by ~1e-15
    fused = sample_displaced_array(vol.data, geom.world_to_index_matrix, out_geom, disp, 1, -1.0)
    np.testing.assert_allclose(fused, expected, rtol=0, atol=1e-12)
    # warp through a displacement volume is the fused kernel, converted to the dtype asked for
    wd = warp(vol, displacement=Volume(disp, out_geom), fill=-1.0, dtype=np.float32)
    assert wd.geometry == out_geom and wd.data.dtype == np.float32
    np.testing.assert_array_equal(wd.data, fused.astype(np.float32))
    with pytest.raises(GeometryMismatchError):
        warp(vol, pos[:-1], out_geom)
    with pytest.raises(ValueError):
        warp(vol, pos, out_geom, displacement=Volume(disp, out_geom))


# ================================================================================ fields: basics
def test_positions_and_from_positions_round_trip(geom):
    rng = np.random.default_rng(7)
    u = Volume(rng.normal(size=geom.array_shape + (3,)), geom)
    p = F.positions(u)
    np.testing.assert_allclose(p, geom.world_coordinates() + u.data, rtol=0, atol=ROUNDOFF_MM)
    back = F.from_positions(p, geom)
    assert back.geometry == geom
    np.testing.assert_allclose(back.data, u.data, rtol=0, atol=ROUNDOFF_MM)
    with pytest.raises(GeometryMismatchError):
        F.from_positions(p[:, :-1], geom)


# =========================================================================== fields: composition
def test_compose_matches_the_analytic_composition(geom):
    # inner map B: a rotation by ~9° about an off-centre point (pushes part of the grid outside A's grid)
    rb = Rotation.from_rotvec(np.deg2rad(9.0) * np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5]))
    cb = _centre(geom) + np.array([6.0, -4.0, 5.0])

    def b_map(p):
        return (p - cb) @ rb.as_matrix().T + cb

    # outer map A: another rotation about another centre plus a small sinusoidal warp, on another grid
    ra = Rotation.from_euler("XYZ", [5.0, -8.0, 4.0], degrees=True).as_matrix()
    ca = _centre(geom) - np.array([3.0, 2.0, 1.0])
    modes = [(np.array([0.6, -0.4, 0.5]), np.array([0.25, -0.18, 0.12]), 0.4)]

    def a_map(p):
        return (p - ca) @ ra.T + ca + _sinusoid(p, modes)

    ga = _other_geom(geom, offset_mm=(1.0, 0.5, -1.0))
    a, b = _field(ga, a_map), _field(geom, b_map)
    w = F.compose(a, b)
    assert w.geometry == geom
    x = geom.world_coordinates()
    bx = b_map(x)
    inside = ga.contains_world(bx)  # B(x) inside A's voxel-centre box: interpolation, not clamping
    assert 0.2 < inside.mean() < 0.95
    err = np.linalg.norm(w.data - (a_map(bx) - x), axis=-1)[inside]
    # the rotation part of a is linear (interpolated exactly); the sinusoid's trilinear error is bounded
    bound = _trilinear_error_bound(modes, ga) + ROUNDOFF_MM
    assert err.max() <= bound
    # compose, do not add: the sum of the two fields at x is wrong by far more than that bound
    added = sample(a, x, fill=0.0) + b.data
    assert np.linalg.norm(added - (a_map(bx) - x), axis=-1)[inside].max() > 10 * bound
    # where B(x) leaves A's grid (beyond its half-voxel border), A is the identity: w = b exactly
    ijk = ga.world_to_index(bx)
    beyond = np.any((ijk < -0.5 - 1e-6) | (ijk > np.asarray(ga.size) - 0.5 + 1e-6), axis=-1)
    assert beyond.any()
    np.testing.assert_array_equal(w.data[beyond], b.data[beyond])


def test_compose_follows_sitk_composite_transform_order(geom):
    # sitk.CompositeTransform([T1, T2]) applies T2 first: T1(T2(x)); compose(outer=T1, inner=T2) must agree.
    c = _centre(geom)
    t1 = sitk.Euler3DTransform(c.tolist(), 0.10, -0.05, 0.20, (1.0, -0.5, 0.3))
    t2 = sitk.Euler3DTransform((c + [2.0, 1.0, -3.0]).tolist(), -0.15, 0.10, 0.05, (-0.4, 0.8, 0.2))
    g1 = _other_geom(geom)
    w = F.compose(F.from_transform(t1, g1), F.from_transform(t2, geom))
    truth = F.from_transform(sitk.CompositeTransform([t1, t2]), geom)
    inside = g1.contains_world(F.positions(F.from_transform(t2, geom)))
    assert inside.mean() > 0.3
    # rigid fields are linear, so trilinear interpolation is exact: only float64 round-off remains
    np.testing.assert_allclose(w.data[inside], truth.data[inside], rtol=0, atol=ROUNDOFF_MM)


# ============================================================================= fields: inversion
# A shear-like sinusoid u(x) = a sin(k·x + φ) with a ⟂ k has the closed-form inverse
# v(y) = -a sin(k·y + φ): k·(y + v) = k·y because k·a = 0.
A_PERP = np.array([1.2, 0.9, -0.6])
K_PERP = np.cross(A_PERP, [0.2, -0.7, 0.4])
K_PERP *= 0.4 / (np.linalg.norm(A_PERP) * np.linalg.norm(K_PERP))  # |∇u| = |a||k| = 0.4
PERP_MODES = [(A_PERP, K_PERP, 0.7)]


def test_invert_matches_the_closed_form_inverse(geom):
    u = _field(geom, lambda p: p + _sinusoid(p, PERP_MODES))
    v, resid = F.invert(u, tol_mm=1e-9)
    assert v.geometry == geom and resid.shape == geom.array_shape
    y = geom.world_coordinates()
    v_true = -_sinusoid(y, PERP_MODES)
    # only where the preimage y + v lies inside u's grid with its interpolation stencil (|v| ≤ |a|)
    inner = _interior(geom, np.linalg.norm(A_PERP) + max(SPACING))
    assert inner.sum() > 200
    # |v - v*| ≤ (ε + residual) / (1 - L): ε the trilinear error of u, L = |∇u| the Lipschitz constant
    lip, eps = _lipschitz(PERP_MODES), _trilinear_error_bound(PERP_MODES, geom)
    err = np.linalg.norm(v.data - v_true, axis=-1)
    assert np.all(err[inner] <= (eps + resid[inner]) / (1 - lip) + ROUNDOFF_MM)
    assert resid[inner].max() <= 1e-9  # the iteration converged there (rate 0.4 per step)
    assert err[inner].max() > 1e-4  # ... to the interpolated problem: the bound is not vacuous


def test_invert_matches_a_numerical_analytic_inverse_of_a_general_field(geom):
    modes = [
        (np.array([0.9, -0.5, 0.7]), np.array([0.18, 0.11, -0.14]), 0.3),
        (np.array([-0.4, 0.6, 0.3]), np.array([-0.07, 0.15, 0.12]), 1.9),
    ]
    lip = _lipschitz(modes)
    assert lip < 0.5
    u = _field(geom, lambda p: p + _sinusoid(p, modes))
    v, resid = F.invert(u, tol_mm=1e-9)
    y = geom.world_coordinates()
    v_star = np.zeros_like(y)
    for _ in range(80):  # the analytic map's inverse: the same contraction, no interpolation; 0.5**80 ≈ 1e-24
        v_star = -_sinusoid(y + v_star, modes)
    inner = _interior(geom, sum(np.linalg.norm(a) for a, _, _ in modes) + max(SPACING))
    assert inner.sum() > 100
    eps = _trilinear_error_bound(modes, geom)
    err = np.linalg.norm(v.data - v_star, axis=-1)
    assert np.all(err[inner] <= (eps + resid[inner]) / (1 - lip) + ROUNDOFF_MM)


def test_compose_with_the_inverse_is_the_identity(geom):
    u = _field(geom, lambda p: p + _sinusoid(p, PERP_MODES))
    v, resid = F.invert(u, tol_mm=1e-9)
    # U ∘ V: |u(y + v) + v| is by definition the returned residual (the same trilinear U)
    uv = F.compose(u, v)
    np.testing.assert_allclose(np.linalg.norm(uv.data, axis=-1), resid, rtol=0, atol=ROUNDOFF_MM)
    # V ∘ U: v sampled between nodes.  v* = -a sin(k·y + φ) has the same trilinear error bound ε as u,
    # and v's nodal error is ≤ (ε + residual)/(1 - L) (previous test) where its stencil is interior.
    vu = F.compose(v, u)
    lip, eps = _lipschitz(PERP_MODES), _trilinear_error_bound(PERP_MODES, geom)
    inner = _interior(geom, 2 * np.linalg.norm(A_PERP) + 2 * max(SPACING))
    assert inner.sum() > 50
    nodal = (eps + resid[_interior(geom, np.linalg.norm(A_PERP) + max(SPACING))].max()) / (1 - lip)
    assert np.linalg.norm(vu.data, axis=-1)[inner].max() <= eps + nodal + ROUNDOFF_MM


def test_invert_onto_another_grid_and_from_an_initial_guess(geom):
    u = _field(geom, lambda p: p + _sinusoid(p, PERP_MODES))
    g2 = _other_geom(geom, offset_mm=(0.0, 0.0, 0.0))
    v, resid = F.invert(u, geometry=g2, tol_mm=1e-9)
    assert v.geometry == g2
    y = g2.world_coordinates()
    # y inside u's grid by more than |a| + one voxel: the preimage is reachable
    ok = geom.contains_world(y, margin_voxels=-(np.linalg.norm(A_PERP) / min(SPACING) + 1.0))
    assert ok.sum() > 100
    assert resid[ok].max() <= 1e-9
    # starting from the answer, zero updates return it with its residual
    v0, r0 = F.invert(u, geometry=g2, initial=v, max_iter=0)
    np.testing.assert_array_equal(v0.data, v.data)
    np.testing.assert_allclose(r0, resid, rtol=0, atol=1e-15)
    with pytest.raises(GeometryMismatchError):
        F.invert(u, geometry=g2, initial=F.identity_field(geom))


# ============================================================================= fields: Jacobians
@pytest.mark.parametrize("kind", ["affine", "rotation", "reflection"])
def test_jacobian_determinant_of_affine_maps_is_exact(geom, kind):
    r = Rotation.from_euler("ZYX", [25.0, 10.0, -40.0], degrees=True).as_matrix()
    if kind == "affine":
        a = r @ np.array([[1.3, 0.2, 0.0], [0.0, 0.8, -0.1], [0.0, 0.0, 1.1]])
    elif kind == "rotation":
        a = r
    else:
        a = r @ np.diag([1.0, -1.0, 1.0])  # a mirror: orientation reversed everywhere
    t = np.array([3.0, -1.0, 2.0])
    u = _field(geom, lambda p: p @ a.T + t)
    det = F.jacobian_determinant(u)
    # central (and, on the boundary planes, one-sided) differences of a linear field are exact; the
    # displacements are ~50 mm, so round-off is ~1e-14 mm per ~1 mm step
    np.testing.assert_allclose(det, np.linalg.det(a), rtol=0, atol=1e-12)
    stats = F.folding_statistics(u)
    assert stats["n_voxels"] == geom.n_voxels
    assert stats["n_folded"] == (geom.n_voxels if kind == "reflection" else 0)


def test_jacobian_determinant_of_components_along_array_axes_is_the_grids():
    # the dense registration's layout (3, nz, ny, nx), component a along array axis a, on an anisotropic
    # axis-aligned grid, boundary planes included; a random field folds in places, so both signs are tested
    rng = np.random.default_rng(3)
    sp_zyx = np.array([2.5, 1.25, 0.8])
    u = rng.normal(scale=0.6, size=(3, 7, 9, 11)).astype(np.float32)
    g = GridGeometry(size=(11, 9, 7), spacing=tuple(sp_zyx[::-1]))
    ref = F.jacobian_determinant(Volume(np.stack([u[2], u[1], u[0]], axis=-1), g))
    got = F.jacobian_determinant_components(u, sp_zyx)
    assert (ref <= 0).any() and (ref > 0).any()
    # the same differences, scaled and expanded in the same order: the same bits (the dense registration's
    # step halving compares them with a threshold, so a last-bit difference could change its result)
    np.testing.assert_array_equal(got, ref)


def test_jacobian_determinant_agrees_with_sitk_filter_in_the_interior():
    modes = [(np.array([0.9, -0.5, 0.7]), np.array([0.18, 0.11, -0.14]), 0.3)]
    inner = (slice(1, -1),) * 3  # sitk uses zero-flux boundaries: compare off the boundary planes
    # (a) identity direction: the filter is used as it is
    g0 = _geom(direction=np.eye(3))
    u0 = _field(g0, lambda p: p + _sinusoid(p, modes))
    ref0 = sitk.GetArrayFromImage(sitk.DisplacementFieldJacobianDeterminant(u0.to_sitk(), True))
    # both: central differences over the same voxels in float64 → round-off only
    np.testing.assert_allclose(F.jacobian_determinant(u0)[inner], ref0[inner], rtol=0, atol=1e-12)
    # (b) the filter ignores the direction; given the components in the index-axis frame (Dᵀu) it
    # agrees with ours, because det(I + Dᵀ G S⁻¹) = det(I + G S⁻¹ Dᵀ)
    g = _geom()
    u = _field(g, lambda p: p + _sinusoid(p, modes))
    ours = F.jacobian_determinant(u)
    rotated = Volume(u.data @ g.direction_matrix, g)  # row-vector form of Dᵀ u
    ref = sitk.GetArrayFromImage(sitk.DisplacementFieldJacobianDeterminant(rotated.to_sitk(), True))
    np.testing.assert_allclose(ours[inner], ref[inner], rtol=0, atol=1e-12)
    naive = sitk.GetArrayFromImage(sitk.DisplacementFieldJacobianDeterminant(u.to_sitk(), True))
    assert np.abs(naive - ours)[inner].max() > 1e-2  # the pitfall the docstring warns about


def test_folding_statistics_count_the_folds_of_a_map_built_to_fold(geom):
    # u(p) = e·A sin(ω e·p): det ∂U/∂x = 1 + Aω cos(ω e·p); with Aω = 2 it folds where cos(ω e·p) ≤ -1/2
    e = np.array([0.6, -0.3, 0.74])
    e /= np.linalg.norm(e)
    omega = 2 * np.pi / 14.0
    amp = 2.0 / omega
    x = geom.world_coordinates()
    u = Volume(e * (amp * np.sin(omega * (x @ e)))[..., None], geom)
    det_exact = 1.0 + amp * omega * np.cos(omega * (x @ e))
    # central differences along index axis m (world step h_m d_m) err by ≤ h_m²/6 · A (ω e·d_m)³;
    # det = 1 + Σ_m (e·d_m) D_m, so |det - det_exact| ≤ δ off the boundary planes
    ed = e @ geom.direction_matrix
    delta = float(np.sum(np.abs(ed) * np.asarray(SPACING) ** 2 / 6.0 * amp * np.abs(omega * ed) ** 3))
    det = F.jacobian_determinant(u)
    interior = np.zeros(geom.array_shape, dtype=bool)
    interior[1:-1, 1:-1, 1:-1] = True
    assert np.abs(det - det_exact)[interior].max() <= delta
    # voxels whose sign the discretisation cannot change
    mask = interior & (np.abs(det_exact) > delta)
    stats = F.folding_statistics(u, mask=mask)
    expected = int(np.count_nonzero(det_exact[mask] <= 0))
    assert 0.1 * mask.sum() < expected < 0.6 * mask.sum()
    assert stats["n_voxels"] == int(mask.sum())
    assert stats["n_folded"] == expected
    assert stats["fraction_folded"] == pytest.approx(expected / mask.sum(), rel=1e-15)
    assert stats["min_det"] <= stats["p01"] <= stats["p99"] <= stats["max_det"]
    assert -1.0 - delta <= stats["min_det"] < 0.0 and 1.0 < stats["max_det"] <= 3.0 + delta
    # a mask given as a Volume on the field's grid is the same; on another grid it is refused
    assert F.folding_statistics(u, mask=Volume(mask, geom)) == stats
    with pytest.raises(GeometryMismatchError):
        F.folding_statistics(u, mask=Volume(mask, _geom(spacing=(1.0, 1.0, 1.0))))


# ========================================================================= fields: SimpleITK
def test_to_sitk_transform_maps_voxel_centres_to_x_plus_u_and_off_grid_like_sample(geom):
    rng = np.random.default_rng(8)
    u = _field(geom, lambda p: p + _sinusoid(p, PERP_MODES) + 0.3)
    before = u.data.copy()
    tx = F.to_sitk_transform(u)
    np.testing.assert_array_equal(u.data, before)  # the transform consumed a private copy
    x = geom.world_coordinates().reshape(-1, 3)
    pick = rng.choice(len(x), size=300, replace=False)
    got = np.array([tx.TransformPoint(p) for p in x[pick].tolist()])
    np.testing.assert_allclose(got, x[pick] + u.data.reshape(-1, 3)[pick], rtol=0, atol=ROUNDOFF_MM)
    # between voxel centres, and beyond the grid, the transform is our trilinear U (identity outside)
    ijk = rng.uniform(-2.0, np.asarray(geom.size) + 1.0, size=(500, 3))
    p = geom.index_to_world(ijk)
    got = np.array([tx.TransformPoint(q) for q in p.tolist()])
    outside = ~geom.contains_world(p, margin_voxels=0.5)
    assert 0.05 < outside.mean() < 0.9
    # displacements differ by float64 round-off only (the same linear interpolation)
    np.testing.assert_allclose(got, p + sample(u, p, fill=0.0), rtol=0, atol=ROUNDOFF_MM)


def test_from_sitk_transform_round_trips_and_resamples(geom):
    u = _field(geom, lambda p: p + _sinusoid(p, PERP_MODES))
    tx = F.to_sitk_transform(u)
    back = F.from_sitk_transform(tx)
    assert back.geometry.is_close(geom)
    np.testing.assert_array_equal(back.data, u.data)  # the same float64 numbers
    g2 = _other_geom(geom)
    on_g2 = F.from_sitk_transform(tx, g2)
    assert on_g2.geometry == g2
    expected = sample(u, g2.world_coordinates(), fill=0.0)
    np.testing.assert_allclose(on_g2.data, expected, rtol=0, atol=ROUNDOFF_MM)  # as in the previous test
    with pytest.raises(TypeError):
        F.from_sitk_transform(sitk.Euler3DTransform())


def test_from_transform_of_an_euler_transform_is_the_transform_applied(geom):
    c = _centre(geom) + np.array([2.0, -3.0, 1.0])
    angles, t = (0.2, -0.35, 0.5), np.array([1.5, -2.0, 0.75])
    tx = sitk.Euler3DTransform(c.tolist(), *angles, t.tolist())
    f = F.from_transform(tx, geom)
    assert f.geometry == geom and f.data.dtype == np.float64
    r = np.asarray(tx.GetMatrix()).reshape(3, 3)
    x = geom.world_coordinates()
    np.testing.assert_allclose(f.data, (x - c) @ r.T + c + t - x, rtol=0, atol=ROUNDOFF_MM)
    pts = x.reshape(-1, 3)[::37]
    got = np.array([tx.TransformPoint(p) for p in pts.tolist()])
    np.testing.assert_allclose(F.positions(f).reshape(-1, 3)[::37], got, rtol=0, atol=ROUNDOFF_MM)
    # a rigid map: Jacobian determinant 1 (round-off only)
    np.testing.assert_allclose(F.jacobian_determinant(f), 1.0, rtol=0, atol=1e-12)


def _bump_fold(g: GridGeometry, amplitude_per_width: float) -> tuple[Volume, np.ndarray]:
    """u = A·g(p) along e, g a Gaussian of width w about the grid centre: ∂(e·u)/∂(e·p) reaches
    -A/(w√e) on the axis, so the map folds when A/w > √e ≈ 1.65 and only within ~2w of the centre."""
    e = np.array([0.6, -0.3, 0.74])
    e /= np.linalg.norm(e)
    w = 2.0  # mm
    p = g.world_coordinates() - _centre(g)
    r2 = np.einsum("...i,...i->...", p, p)
    u = e * (amplitude_per_width * w * np.exp(-r2 / (2 * w * w)))[..., None]
    return Volume(u.astype(np.float32), g), np.sqrt(r2)


def test_unfold_removes_a_planted_fold_and_leaves_the_rest_of_the_field_alone():
    g = _geom(size=(26, 22, 16))
    field, r = _bump_fold(g, 2.5)
    before = F.folding_statistics(field)
    assert before["n_folded"] > 0  # the planted fold (A/w = 2.5 > 1.65)
    original = field.data.copy()
    out, info = F.unfold(field)
    assert np.array_equal(field.data, original)  # input untouched
    assert info["n_folded_before"] == before["n_folded"]
    after = F.folding_statistics(out)
    assert after["n_folded"] == info["n_folded_after"] == 0
    assert after["min_det"] >= 0.05  # the requested floor (min_det default)
    # the repair is local: the bump is < 1e-6 of its peak beyond 5.5 w = 11 mm, where nothing may change
    far = r > 11.0
    assert far.sum() > 0.4 * far.size
    assert np.array_equal(out.data[far], original[far])
    assert 0 < info["n_changed"] <= far.size - far.sum()
    assert out.geometry == field.geometry and out.data.dtype == field.data.dtype


def test_unfold_leaves_frozen_voxels_alone_and_repairs_around_them():
    # a bone held rigid on one side of a fold: its voxels keep their displacement to the bit, and the fold is
    # still removed (by the free voxels on the other side)
    from scipy import ndimage

    g = _geom(size=(26, 22, 16))
    field, r = _bump_fold(g, 2.5)
    bad = F.jacobian_determinant(field) <= 0
    free, _ = F.unfold(field, restore=False)  # the voxels the smoothing replaces, beside the fold too
    touched = np.any(free.data != field.data, axis=-1)
    below = np.indices(bad.shape)[0] < int(np.median(np.nonzero(bad)[0]))
    frozen = touched & ~ndimage.binary_dilation(bad, iterations=1) & below  # beside the fold, on one side
    assert frozen.sum() >= 5
    out, info = F.unfold(field, frozen=frozen)
    assert not np.array_equal(out.data, field.data)
    assert np.array_equal(out.data[frozen], field.data[frozen])
    assert info["n_folded_after"] == 0 == F.folding_statistics(out)["n_folded"]


def test_unfold_restore_gives_back_what_the_fold_did_not_need_and_adds_no_fold():
    # the smoothing replaces whole patches; the restoring passes move each replaced voxel back to its input value
    # as far as det ≥ min_det allows at the voxels it enters.  On the planted fold (7 folded voxels): the same
    # complete repair, with fewer voxels changed and a smaller total change
    g = _geom(size=(26, 22, 16))
    field, r = _bump_fold(g, 2.5)
    plain, info0 = F.unfold(field, restore=False)
    out, info = F.unfold(field)
    assert info0["n_folded_after"] == info["n_folded_after"] == 0
    assert F.folding_statistics(out)["min_det"] >= 0.05  # the floor holds after the restoring passes
    d0 = np.linalg.norm(plain.data - field.data, axis=-1)
    d = np.linalg.norm(out.data - field.data, axis=-1)
    assert info["n_changed"] == np.count_nonzero(d) < np.count_nonzero(d0) == info0["n_changed"]
    assert info["n_restored"] == info0["n_changed"] - info["n_changed"] > 0
    assert d.sum() < 0.5 * d0.sum()  # measured: 5 of 48 voxels stay changed, 4 % of the total change


def test_unfold_keeps_a_one_to_one_field_and_checks_its_arguments():
    g = _geom(size=(20, 18, 12))
    field, _ = _bump_fold(g, 1.0)  # A/w = 1 < 1.65: det ≥ 1 - 1/√e ≈ 0.39 everywhere
    out, info = F.unfold(field)
    assert info["iterations"] == 0 and info["n_changed"] == 0
    assert np.array_equal(out.data, field.data)
    with pytest.raises(ValueError, match="min_det"):
        F.unfold(field, min_det=0.0)
    with pytest.raises(ValueError, match="sigma"):
        F.unfold(field, sigma=-1.0)


def test_small_inputs_take_the_serial_kernels_with_the_same_result(geom, monkeypatch):
    # below SERIAL_BELOW points the interpolation and the Jacobian run serially: same arithmetic per point,
    # so a large call and the same points sampled in small chunks must agree bit for bit
    from deformation.fields.interpolate import SERIAL_BELOW

    rng = np.random.default_rng(4)
    data = rng.normal(size=geom.array_shape).astype(np.float32)
    vec = rng.normal(size=geom.array_shape + (3,)).astype(np.float32)
    lo, hi = geom.index_to_world(np.zeros(3)), geom.index_to_world(np.asarray(geom.size) - 1.0)
    pts = rng.uniform(np.minimum(lo, hi) - 2, np.maximum(lo, hi) + 2, (SERIAL_BELOW + 1000, 3))
    for arr in (data, vec):
        big = sample_array(arr, geom.world_to_index_matrix, pts)
        chunks = np.concatenate(
            [sample_array(arr, geom.world_to_index_matrix, pts[i : i + 5000]) for i in range(0, pts.shape[0], 5000)]
        )
        assert np.array_equal(big, chunks)
    field = Volume(0.3 * vec, geom)
    det = F.jacobian_determinant(field)  # geom has fewer voxels than SERIAL_BELOW: the serial kernel
    assert det.size < SERIAL_BELOW
    # the components-along-array-axes twin (the dense registration's layout), serial below the threshold
    u = np.ascontiguousarray(np.moveaxis(0.3 * vec[..., ::-1], -1, 0))  # (3, nz, ny, nx), u[0] along z
    sp = np.array([1.5, 1.2, 0.9])
    small = F.jacobian_determinant_components(u, sp)
    monkeypatch.setattr(F, "SERIAL_BELOW", 0)  # now every input takes the parallel kernels
    assert np.array_equal(det, F.jacobian_determinant(field))
    assert small.size < SERIAL_BELOW and np.array_equal(small, F.jacobian_determinant_components(u, sp))


def test_unfold_near_the_grid_edge_tracks_the_determinant_of_the_whole_grid():
    # unfold recomputes det on crops around what it changed; a fold cut by the grid's edge exercises the crops'
    # border planes, which must fall back to the grid's one-sided differences: the count it reports must be a
    # full recomputation's
    g = _geom(size=(26, 22, 16))
    field, _ = _bump_fold(g, 2.5)
    shifted = Volume(np.ascontiguousarray(np.roll(field.data, (6, 9, 11), axis=(0, 1, 2))), g)  # fold at a corner
    before = F.folding_statistics(shifted)
    assert before["n_folded"] > 0
    # a complete repair and a partial one (without the restoring passes, which finish this fold's repair)
    for kw in ({}, {"max_iterations": 1, "restore": False}):
        out, info = F.unfold(shifted, **kw)
        assert info["n_folded_before"] == before["n_folded"]
        assert F.folding_statistics(out)["n_folded"] == info["n_folded_after"]
    assert info["n_folded_after"] > 0  # one iteration is not enough: the partial case is really partial


def test_unfold_fold_by_fold_on_crops_equals_the_repair_of_the_whole_grid(monkeypatch):
    # unfold repairs each cluster of folds on a crop around it (a big grid's copies would not fit in memory): a
    # cluster's repair must be the bits of the same repair run on the whole grid (a mask, frozen voxels, two
    # folds close enough to be one cluster, a partial repair), and two clusters far apart the whole-grid repair
    # of one, then of the other; also when the first crop is too tight (one voxel around the folds: the repair
    # reaches its faces and the crop is widened)
    def whole(field, mask=None, frozen=None, max_iterations=200, restore=True):
        m_inv = np.ascontiguousarray(np.linalg.inv(field.geometry.index_to_world_matrix[:3, :3]))
        u, info, _, _ = F._unfold_crop(field.data, m_inv, mask, frozen, 0.05, 1.0, 1, max_iterations, restore)
        info.pop("n_low")
        return u.astype(np.float32), info

    g = _geom(size=(60, 44, 30))
    one, r = _bump_fold(g, 2.5)
    close = Volume(one.data + np.roll(one.data, (9, 14, 20), axis=(0, 1, 2)), g)  # one cluster of two folds
    g2 = _geom(size=(90, 44, 30))
    far_one, _ = _bump_fold(g2, 2.5)
    far = Volume(far_one.data + np.roll(far_one.data, 40, axis=2), g2)  # folds at x ≈ 46 and 86: two clusters
    left = np.broadcast_to(np.arange(90) < 65, g2.array_shape)
    for pad in (F.UNFOLD_PAD, -8):  # -8: a first pad of 2·4σ + margin - 8 = 1 voxel
        monkeypatch.setattr(F, "UNFOLD_PAD", pad)
        for field, kw in (
            (one, {}),
            (one, {"frozen": (r > 3.0) & (r < 3.6)}),
            (close, {}),
            (close, {"mask": r < 25.0}),
            (close, {"restore": False, "max_iterations": 3}),
        ):
            out, info = F.unfold(field, **kw)
            u, ref = whole(field, **kw)
            assert info["n_folded_before"] > 0
            # the change is measured on the field as written (float32), the whole-grid repair's before rounding
            assert info.pop("max_change_mm") == pytest.approx(ref.pop("max_change_mm"), rel=1e-6)
            assert info == ref
            assert np.array_equal(out.data, u)
        out, info = F.unfold(far)
        u1, i1 = whole(far, mask=left)
        u2, i2 = whole(Volume(u1, g2), mask=~left)
        assert i1["n_folded_before"] > 0 and i2["n_folded_before"] > 0
        assert np.array_equal(out.data, u2)
        assert info["n_folded_before"] == i1["n_folded_before"] + i2["n_folded_before"]
        assert info["n_folded_after"] == F.folding_statistics(out)["n_folded"] == 0


def test_unfold_crops_stay_local_around_nested_clusters_and_frozen_blocks(monkeypatch):
    # a U of folds with a second cluster inside it: the U's crop repairs both, and the inner cluster's crop then
    # finds nothing low and is taken as it is (it was widened to the whole grid before).  Folds inside a frozen
    # block wider than the first crop: the repair reads the block's voxels and must be widened until it finds
    # free ones, as on the whole grid (it stopped at the crop before)
    e = np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74])
    g = GridGeometry((100, 100, 24), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), np.eye(3).reshape(-1))
    p = g.world_coordinates()
    centres = (
        [(10, y, 12) for y in range(10, 90, 8)]
        + [(x, 10, 12) for x in range(18, 80, 8)]
        + [(76, y, 12) for y in range(18, 90, 8)]
        + [(42, 50, 12)]
    )
    u = sum(np.exp(-np.sum((p - np.asarray(c, float)) ** 2, axis=-1) / 8.0)[..., None] for c in centres) * 5.0 * e
    nested = Volume(u.astype(np.float32), g)
    low, _ = F._low_dets(nested.data, np.eye(3), 0.05, None)
    assert len(F._clusters(low, 17)) == 2
    shapes = []
    crop = F._unfold_crop
    monkeypatch.setattr(F, "_unfold_crop", lambda u0, *a: shapes.append(u0.shape[:3]) or crop(u0, *a))
    out, info = F.unfold(nested)
    assert info["n_folded_before"] > 0 == info["n_folded_after"] == F.folding_statistics(out)["n_folded"]
    # the U's crop spans the grid; the inner cluster's is its first, unwidened (it grew to the whole grid before)
    assert len(shapes) == 2 and np.prod(shapes[1]) < 0.2 * np.prod(g.array_shape), shapes
    monkeypatch.setattr(F, "_unfold_crop", crop)

    g = GridGeometry((70, 70, 70), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), np.eye(3).reshape(-1))
    r2 = np.sum((g.world_coordinates() - 35.0) ** 2, axis=-1)
    field = Volume((5.0 * e * np.exp(-r2 / 8.0)[..., None]).astype(np.float32), g)
    frozen = np.max(np.abs(np.indices(g.array_shape) - 35), axis=0) <= 20  # half-width 20 > the first pad, 17
    out, info = F.unfold(field, frozen=frozen, max_iterations=60, restore=False)
    u, ref, _, _ = F._unfold_crop(field.data, np.eye(3), None, frozen, 0.05, 1.0, 1, 60, False)
    assert info["n_changed"] == ref["n_changed"] > 0
    assert np.array_equal(out.data, u.astype(np.float32))


def test_sample_shifted_is_scipy_map_coordinates_with_edge_extension():
    # the index-space sampler of the dense registration: trilinear and nearest, scalar and stacked, shifts
    # reaching beyond the grid (edge values continue, scipy's mode="nearest"); both compute in float64 from
    # float32 data, so they agree to the float32 rounding of the result (observed: bit for bit)
    from scipy import ndimage

    from deformation.fields.interpolate import sample_shifted

    rng = np.random.default_rng(11)
    a = rng.random((9, 12, 14)).astype(np.float32)
    shift = (rng.standard_normal((3,) + a.shape) * 4.0).astype(np.float32)  # mm; many points leave the grid
    sp = np.array([2.0, 1.5, 1.2])
    grid = np.indices(a.shape, dtype=np.float64)
    coords = [grid[i] + shift[i] / sp[i] for i in range(3)]
    for order in (0, 1):
        ref = ndimage.map_coordinates(a, coords, order=order, mode="nearest")
        got = sample_shifted(a, shift, 1.0 / sp, order=order)
        assert got.dtype == np.float32 and got.shape == a.shape
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)
    both = sample_shifted(np.stack([a, 3.0 * a]), shift, 1.0 / sp)
    np.testing.assert_allclose(both[1], 3.0 * both[0], rtol=1e-6)
    with pytest.raises(ValueError, match="shift"):
        sample_shifted(a, shift[:, :-1], 1.0 / sp)


def test_the_cropped_determinant_update_matches_a_full_recomputation():
    # unfold's incremental det: after u changes inside a box, the values within one voxel of it are recomputed
    # on a crop; boxes in the middle, at faces and at a corner, on a field rough enough that one-sided and
    # central differences differ — every value must be the full grid's, bit for bit
    from deformation.fields.displacement import _update_jacobian_det

    g = _geom(size=(14, 12, 10))
    rng = np.random.default_rng(5)
    u = rng.normal(size=g.array_shape + (3,))
    m = np.ascontiguousarray(np.linalg.inv(g.index_to_world_matrix[:3, :3]))
    for box in (
        (slice(3, 6), slice(4, 7), slice(5, 9)),
        (slice(0, 2), slice(0, 3), slice(0, 4)),
        (slice(1, 3), slice(2, 4), slice(1, 2)),  # crops clipped at 0 that must refresh det[0]
        (slice(7, 10), slice(9, 12), slice(11, 14)),
        (slice(0, 10), slice(5, 6), slice(13, 14)),
    ):
        det = F.jacobian_determinant(Volume(u, g))
        v = u.copy()
        v[box] += rng.normal(size=v[box].shape)
        _update_jacobian_det(v, m, det, box)
        assert np.array_equal(det, F.jacobian_determinant(Volume(v, g)))


def test_serial_twins_have_cache_entries_of_their_own():
    # numba names a function's on-disk cache entry by its qualified name and first line: a serial twin compiled
    # from the parallel kernel's own Python function shared its entry, and whichever compiled first was loaded
    # for both (measured: the "serial" Jacobian on a 20-voxel crop took the parallel kernel's 7 ms on a busy
    # machine, against 0.08 ms).  Each twin must be serial and cached apart from its kernel.
    from deformation.fields import displacement as F
    from deformation.fields import interpolate as I

    for kernel, twin in (
        (F._jacobian_det, F._jacobian_det_serial),
        (F._jacobian_det_zyx, F._jacobian_det_zyx_serial),
        (I._sample_points_scalar, I._sample_points_scalar_serial),
        (I._sample_points_vector, I._sample_points_vector_serial),
    ):
        assert kernel.targetoptions.get("parallel") and not twin.targetoptions.get("parallel")
        assert twin.py_func.__qualname__ != kernel.py_func.__qualname__  # what numba names the cache entry by
