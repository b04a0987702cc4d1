"""Dense displacement fields: positions, composition, inversion, Jacobians, SimpleITK transforms.

A *displacement field* is a :class:`~deformation.geometry.Volume` whose data
are ``(nz, ny, nx, 3)`` displacements in world mm with components ``(x, y, z)``
(the array-order convention of :mod:`deformation.geometry`).  A field ``u`` on
a grid ``G`` represents the map

    U(x) = x + u(x)        for the voxel centres x of G,

and, between voxel centres, the trilinear interpolant of ``u`` (the same as
``sitk.DisplacementFieldTransform`` with its default linear interpolator).
**Outside** the grid — beyond the voxel-centre box grown by half a voxel, see
:mod:`deformation.fields.interpolate` — the displacement is zero: ``U`` is the
identity there, again as in ITK.

Directions are stated in names.  A ``scan_to_template`` field lives on the
scan grid and gives, for each scan voxel ``x``, the template position it came
from minus ``x``; its map sends scan space to template space.  Its inverse,
``template_to_scan``, lives on the template grid.  Composition reads right to
left like maps: ``compose(outer, inner)`` is ``O ∘ I``.

All per-voxel work is numba-compiled and parallel.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import SimpleITK as sitk

from deformation.fields.interpolate import (
    SERIAL_BELOW,
    interp_vector,
    native_order,
    sample_displaced_array,
    serial_twin,
    to_index,
)
from deformation.filters import smooth
from deformation.geometry import GeometryMismatchError, GridGeometry, Volume, from_every, slabs

__all__ = [
    "positions",
    "from_positions",
    "identity_field",
    "compose",
    "invert",
    "jacobian_determinant",
    "jacobian_determinant_components",
    "folding_statistics",
    "unfold",
    "to_sitk_transform",
    "from_sitk_transform",
    "from_transform",
]


# -- compiled kernels -----------------------------------------------------------------------
@nb.njit(cache=True, parallel=True)
def _add_grid(i2w, arr, sign, out):
    """``out[k, j, i] = arr[k, j, i] + sign * x(i, j, k)`` with x the world voxel centre."""
    nz, ny, nx = arr.shape[0], arr.shape[1], arr.shape[2]
    for r in nb.prange(nz * ny):
        k = r // ny
        j = r - k * ny
        for i in range(nx):
            for c in range(3):
                x = i2w[c, 0] * i + i2w[c, 1] * j + i2w[c, 2] * k + i2w[c, 3]
                out[k, j, i, c] = np.float64(arr[k, j, i, c]) + sign * x


@nb.njit(cache=True, parallel=True)
def _invert_step(f, nx, ny, nz, w2i_u, i2w_y, v, v_new, resid, done, tol):
    """One fixed-point step for the inverse of U(x) = x + u(x) on a grid of points y; returns the
    number of voxels not yet converged.

    ``f (nvox, 3)`` is u flattened, on a grid of size (nx, ny, nz) with world → index ``w2i_u``.
    For every voxel y not ``done``: ``s = u(y + v(y))`` (trilinear, zero outside u's grid) and
    ``resid(y) = |U(y + v) - y| = |v + s|``; if ``resid ≤ tol`` the voxel is frozen (``done``,
    ``v_new = v``), otherwise ``v_new(y) = -s``.  Frozen voxels keep ``v`` and their residual.
    """
    tz, ty, tx = v.shape[0], v.shape[1], v.shape[2]
    vn = v_new.reshape((tz * ty * tx, 3))
    n_active = 0
    for r in nb.prange(tz * ty):
        k = r // ty
        j = r - k * ty
        for i in range(tx):
            v0 = v[k, j, i, 0]
            v1 = v[k, j, i, 1]
            v2 = v[k, j, i, 2]
            row = r * tx + i
            if done[k, j, i]:
                vn[row, 0] = v0
                vn[row, 1] = v1
                vn[row, 2] = v2
                continue
            ci, cj, ck = to_index(
                w2i_u,
                i2w_y[0, 0] * i + i2w_y[0, 1] * j + i2w_y[0, 2] * k + i2w_y[0, 3] + v0,
                i2w_y[1, 0] * i + i2w_y[1, 1] * j + i2w_y[1, 2] * k + i2w_y[1, 3] + v1,
                i2w_y[2, 0] * i + i2w_y[2, 1] * j + i2w_y[2, 2] * k + i2w_y[2, 3] + v2,
            )
            interp_vector(f, nx, ny, nz, ci, cj, ck, 1, 0.0, vn, row)  # vn[row] = s (scratch)
            s0 = vn[row, 0]
            s1 = vn[row, 1]
            s2 = vn[row, 2]
            d0 = v0 + s0
            d1 = v1 + s1
            d2 = v2 + s2
            res = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            resid[k, j, i] = res
            if res <= tol:
                done[k, j, i] = 1
                vn[row, 0] = v0
                vn[row, 1] = v1
                vn[row, 2] = v2
            else:
                n_active += 1
                vn[row, 0] = -s0
                vn[row, 1] = -s1
                vn[row, 2] = -s2
    return n_active


@nb.njit(cache=True, inline="always")
def _stencil(idx, n):
    """The two samples of a first derivative at ``idx`` on an axis of ``n`` voxels and the factor per unit
    index: central differences inside (½), one-sided first differences on the two boundary planes (1), none
    on a single plane (0) — the one rule of :func:`_diff` and :func:`_diff_zyx`."""
    lo = max(idx - 1, 0)
    hi = min(idx + 1, n - 1)
    return lo, hi, (1.0 / (hi - lo) if hi > lo else 0.0)


@nb.njit(cache=True)
def _diff(u, k, j, i, a, axis, n):
    """Derivative of component a along index axis ``axis`` (0=i, 1=j, 2=k) per unit index of a
    (nz, ny, nx, 3) field (:func:`_stencil`)."""
    if axis == 0:
        lo, hi, f = _stencil(i, n)
        return f * (u[k, j, hi, a] - u[k, j, lo, a])
    if axis == 1:
        lo, hi, f = _stencil(j, n)
        return f * (u[k, hi, i, a] - u[k, lo, i, a])
    lo, hi, f = _stencil(k, n)
    return f * (u[hi, j, i, a] - u[lo, j, i, a])


@nb.njit(cache=True)
def _det_at(u, m, k, j, i):
    """det(I + G @ m) at voxel (k, j, i); G[a, axis] = ∂u_a/∂index_axis, m = (direction·diag(spacing))⁻¹."""
    nz, ny, nx = u.shape[0], u.shape[1], u.shape[2]
    j00 = j01 = j02 = j10 = j11 = j12 = j20 = j21 = j22 = 0.0
    for a in range(3):
        gi = np.float64(_diff(u, k, j, i, a, 0, nx))
        gj = np.float64(_diff(u, k, j, i, a, 1, ny))
        gk = np.float64(_diff(u, k, j, i, a, 2, nz))
        r0 = gi * m[0, 0] + gj * m[1, 0] + gk * m[2, 0]
        r1 = gi * m[0, 1] + gj * m[1, 1] + gk * m[2, 1]
        r2 = gi * m[0, 2] + gj * m[1, 2] + gk * m[2, 2]
        if a == 0:
            j00, j01, j02 = r0 + 1.0, r1, r2
        elif a == 1:
            j10, j11, j12 = r0, r1 + 1.0, r2
        else:
            j20, j21, j22 = r0, r1, r2 + 1.0
    return j00 * (j11 * j22 - j12 * j21) - j01 * (j10 * j22 - j12 * j20) + j02 * (j10 * j21 - j11 * j20)


@nb.njit(parallel=True, cache=True)
def _jacobian_det(u, m, out):
    """det(I + G @ m) per voxel (:func:`_det_at`)."""
    nz, ny, nx = u.shape[0], u.shape[1], u.shape[2]
    for r in nb.prange(nz * ny):
        k = r // ny
        j = r - k * ny
        for i in range(nx):
            out[k, j, i] = _det_at(u, m, k, j, i)


@nb.njit(cache=True)
def _restore_towards(u, u0, cand, mask, m, min_det, fractions):
    """Move each candidate voxel of ``u`` (rows (k, j, i) of ``cand``, in that order, in place) back towards
    ``u0`` by the largest of ``fractions`` that keeps ``det ≥ min_det`` at it and at its six face neighbours
    that lie in ``mask`` (the only determinants its value enters, by central or one-sided differences).  One
    pass, sequential (the result does not depend on threads); returns how many voxels moved."""
    nz, ny, nx = u.shape[0], u.shape[1], u.shape[2]
    moved = 0
    old = np.empty(3)
    for c in range(cand.shape[0]):
        k, j, i = cand[c, 0], cand[c, 1], cand[c, 2]
        for a in range(3):
            old[a] = u[k, j, i, a]
        for f in fractions:
            for a in range(3):
                u[k, j, i, a] = old[a] + f * (u0[k, j, i, a] - old[a])
            ok = True
            for d in range(7):
                kk, jj, ii = k, j, i
                if d == 1:
                    kk -= 1
                elif d == 2:
                    kk += 1
                elif d == 3:
                    jj -= 1
                elif d == 4:
                    jj += 1
                elif d == 5:
                    ii -= 1
                elif d == 6:
                    ii += 1
                if kk < 0 or jj < 0 or ii < 0 or kk >= nz or jj >= ny or ii >= nx or not mask[kk, jj, ii]:
                    continue
                if _det_at(u, m, kk, jj, ii) < min_det:
                    ok = False
                    break
            if ok:
                moved += 1
                break
            for a in range(3):
                u[k, j, i, a] = old[a]
    return moved


@nb.njit(cache=True, inline="always")
def _diff_zyx(u, a, k, j, i, axis, n):
    """∂u[a]/∂(array axis ``axis``) per unit index of a (3, nz, ny, nx) field (:func:`_stencil`)."""
    if axis == 0:
        lo, hi, f = _stencil(k, n)
        return f * (u[a, hi, j, i] - u[a, lo, j, i])
    if axis == 1:
        lo, hi, f = _stencil(j, n)
        return f * (u[a, k, hi, i] - u[a, k, lo, i])
    lo, hi, f = _stencil(i, n)
    return f * (u[a, k, j, hi] - u[a, k, j, lo])


@nb.njit(parallel=True, cache=True)
def _jacobian_det_zyx(u, inv_sp, out):
    """det(I + ∂u/∂x) per voxel of a (3, nz, ny, nx) field ``u`` whose component a lies along array axis a, on
    an axis-aligned grid (``inv_sp``: 1 / spacing per array axis), to the bit :func:`_jacobian_det`'s value of
    the same field stacked (x, y, z)."""
    nz, ny, nx = u.shape[1], u.shape[2], u.shape[3]
    for r in nb.prange(nz * ny):
        k = r // ny
        j = r - k * ny
        for i in range(nx):
            # g_ab = ∂u_a/∂x_b (+1 on the diagonal), a, b in array-axis order (z, y, x)
            g00 = np.float64(_diff_zyx(u, 0, k, j, i, 0, nz)) * inv_sp[0] + 1.0
            g01 = np.float64(_diff_zyx(u, 0, k, j, i, 1, ny)) * inv_sp[1]
            g02 = np.float64(_diff_zyx(u, 0, k, j, i, 2, nx)) * inv_sp[2]
            g10 = np.float64(_diff_zyx(u, 1, k, j, i, 0, nz)) * inv_sp[0]
            g11 = np.float64(_diff_zyx(u, 1, k, j, i, 1, ny)) * inv_sp[1] + 1.0
            g12 = np.float64(_diff_zyx(u, 1, k, j, i, 2, nx)) * inv_sp[2]
            g20 = np.float64(_diff_zyx(u, 2, k, j, i, 0, nz)) * inv_sp[0]
            g21 = np.float64(_diff_zyx(u, 2, k, j, i, 1, ny)) * inv_sp[1]
            g22 = np.float64(_diff_zyx(u, 2, k, j, i, 2, nx)) * inv_sp[2] + 1.0
            # expanded as _det_at expands the (x, y, z) matrix (its entry [a][b] is g[2-a][2-b]): the same bits
            out[k, j, i] = g22 * (g11 * g00 - g10 * g01) - g21 * (g12 * g00 - g10 * g02) + g20 * (g12 * g01 - g11 * g02)


# -- helpers --------------------------------------------------------------------------------
_jacobian_det_serial = serial_twin(_jacobian_det)  # small crops: no thread team
_jacobian_det_zyx_serial = serial_twin(_jacobian_det_zyx)  # the same, components along array axes


def _update_jacobian_det(u, m, det, box) -> None:
    """Recompute ``det`` (``_jacobian_det`` of ``u``) after ``u`` changed inside ``box`` (a tuple of slices):
    the values within one voxel of the box, computed on a crop two voxels wider whose own border planes
    (one-sided differences) are used only where they are the grid's."""
    shape = det.shape
    crop = tuple(slice(max(b.start - 2, 0), min(b.stop + 2, n)) for b, n in zip(box, shape))
    sub = np.ascontiguousarray(u[crop])
    d = np.empty(sub.shape[:3])
    _jacobian_det_serial(sub, m, d)
    inner = tuple(
        slice(0 if c.start == 0 else 1, (c.stop - c.start) if c.stop == n else (c.stop - c.start - 1))
        for c, n in zip(crop, shape)
    )
    det[tuple(slice(c.start + i.start, c.start + i.stop) for c, i in zip(crop, inner))] = d[inner]


def _check_field(field: Volume, name: str = "field") -> np.ndarray:
    if not isinstance(field, Volume):
        raise TypeError(f"{name} must be a Volume (data plus grid geometry), got {type(field).__name__}")
    d = field.data
    if d.ndim != 4 or d.shape[3] != 3:
        raise ValueError(f"{name} must have data (nz, ny, nx, 3) (displacements x, y, z in mm), got {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"{name} must hold floating-point displacements, got dtype {d.dtype}")
    d = native_order(np.ascontiguousarray(d))
    return d if d.dtype in (np.float32, np.float64) else d.astype(np.float64)  # e.g. float16


def _grid_array(values, geometry: GridGeometry, name: str, trailing=(3,)) -> np.ndarray:
    """Array data of ``values`` (a Volume on ``geometry``, or an array of its shape)."""
    if isinstance(values, Volume):
        values.geometry.check_same(
            geometry, names=(name, "grid"), remedy=f"give {name} on the grid it is used on (resample it first)"
        )
        values = values.data
    arr = np.asarray(values)
    if arr.shape != geometry.array_shape + tuple(trailing):
        raise GeometryMismatchError(
            f"{name} shape {arr.shape} does not match the grid {geometry.describe()} "
            f"(expected {geometry.array_shape + tuple(trailing)})"
        )
    return arr


# -- positions --------------------------------------------------------------------------------
def positions(field: Volume) -> np.ndarray:
    """World positions ``x + u(x)`` (mm, float64, ``(nz, ny, nx, 3)``) of every voxel centre x of the field's grid.

    For a ``scan_to_template`` field these are the template positions of the
    scan voxels.
    """
    u = _check_field(field)
    out = np.empty(u.shape, dtype=np.float64)
    _add_grid(np.ascontiguousarray(field.geometry.index_to_world_matrix), u, 1.0, out)
    return out


def from_positions(positions, geometry: GridGeometry) -> Volume:
    """The field ``u(x) = positions[x] - x`` on ``geometry`` (inverse of :func:`positions`; float64).

    ``positions`` ``(nz, ny, nx, 3)`` gives, for each voxel centre x of
    ``geometry``, the world point (mm) it maps to.
    """
    p = native_order(np.ascontiguousarray(_grid_array(positions, geometry, "positions")))
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    out = np.empty(p.shape, dtype=np.float64)
    _add_grid(np.ascontiguousarray(geometry.index_to_world_matrix), p, -1.0, out)
    return Volume(out, geometry)


def identity_field(geometry: GridGeometry) -> Volume:
    """The zero displacement field (identity map) on ``geometry``."""
    return Volume(np.zeros(geometry.array_shape + (3,)), geometry)


# -- composition ------------------------------------------------------------------------------
def compose(outer: Volume, inner: Volume) -> Volume:
    """The field of ``O ∘ I`` on ``inner``'s grid: ``(O∘I)(x) = I(x) + o(I(x))``.

    That is ``w(x) = i(x) + o(x + i(x))``, with ``i`` and ``o`` the two fields.

    ``inner`` (a field on grid G_I) is applied first, then ``outer`` (on its
    own grid G_O).  E.g. ``compose(template_to_atlas, scan_to_template)`` is a
    ``scan_to_atlas`` field on the scan grid.  ``o`` is sampled trilinearly at
    the points ``I(x)``; within G_O's half-voxel border the edge displacement
    is extended, and where ``I(x)`` lies beyond it the outer displacement is
    taken as zero — ``O`` is the identity outside its grid, as
    ``sitk.DisplacementFieldTransform`` does — so there ``w(x) = i(x)``.
    Fields are composed, never added.  The result's dtype is the common dtype
    of the two fields.
    """
    o = _check_field(outer, "outer")
    i = _check_field(inner, "inner")
    s = sample_displaced_array(o, outer.geometry.world_to_index_matrix, inner.geometry, i, order=1, fill=0.0)
    return Volume(np.add(i, s, dtype=np.result_type(o.dtype, i.dtype)), inner.geometry)


# -- inversion --------------------------------------------------------------------------------
def invert(
    field: Volume,
    *,
    geometry: GridGeometry | None = None,
    initial=None,
    max_iter: int = 100,
    tol_mm: float = 1e-3,
    stall_iter: int | None = 10,
) -> tuple[Volume, np.ndarray]:
    """Invert the map ``U(x) = x + u(x)``: a field ``v`` on ``geometry`` with ``U(y + v(y)) ≈ y``.

    If ``field`` is ``scan_to_template`` (on the scan grid) then, with
    ``geometry`` the template grid, the result is ``template_to_scan``.

    Fixed-point iteration ``v(y) ← -u(y + v(y))`` (u trilinear, zero outside
    its grid), starting from ``initial`` (a field on ``geometry``, or an array;
    zero by default).  A voxel whose residual reaches ``tol_mm`` is frozen
    (later steps skip it), so the cost falls as voxels converge.  The
    iteration stops when every voxel has converged, or after ``max_iter``
    updates, or when the number of unconverged voxels has not decreased for
    ``stall_iter`` consecutive updates (such voxels do not converge: see
    below; ``None`` disables this rule).  The iteration contracts where ``U``
    does, with rate ``|∇u|``: for ``|∇u| ≤ 0.5`` the error at least halves per
    step.

    Returns ``(v, residual_mm)`` with ``residual_mm (nz, ny, nx) = |U(y + v(y)) - y|``
    of the returned ``v`` (the same trilinear ``U``).  A large residual flags
    where ``U`` is not invertible (folds) or where the inverse would need
    points outside ``u``'s grid (there ``U`` is the identity, so no ``y`` inside
    can be reached from outside).

    Our own kernel rather than SimpleITK's inverse filters: it is undamped (it
    converges in fewer iterations), can invert onto another grid, starts from a
    guess and returns the residual (the measurements:
    docs/measurements/library-choices.md).
    """
    u = _check_field(field)
    geo = field.geometry if geometry is None else geometry
    if max_iter < 0:
        raise ValueError(f"max_iter must be ≥ 0, got {max_iter}")
    if initial is None:
        v = np.zeros(geo.array_shape + (3,), dtype=np.float64)
    else:
        v = np.array(_grid_array(initial, geo, "initial"), dtype=np.float64, order="C", copy=True)
    v_new = np.empty_like(v)
    resid = np.empty(geo.array_shape, dtype=np.float64)
    done = np.zeros(geo.array_shape, dtype=np.uint8)
    nx, ny, nz = field.geometry.size
    f = np.ascontiguousarray(u, dtype=np.float64).reshape(nx * ny * nz, 3)
    w2i = np.ascontiguousarray(field.geometry.world_to_index_matrix)
    i2w = np.ascontiguousarray(geo.index_to_world_matrix)
    best, stalled = None, 0
    for it in range(max_iter + 1):
        # resid is the residual of v; v_new is the next iterate (= v where converged and frozen)
        n_active = _invert_step(f, nx, ny, nz, w2i, i2w, v, v_new, resid, done, float(tol_mm))
        if n_active == 0 or it == max_iter:
            break
        if stall_iter is not None:
            if best is None or n_active < best:
                best, stalled = n_active, 0
            else:
                stalled += 1
                if stalled >= stall_iter:
                    break
        v, v_new = v_new, v
    return Volume(v, geo), resid


# -- Jacobian and folding ---------------------------------------------------------------------
def jacobian_determinant(field: Volume) -> np.ndarray:
    """``det ∂U/∂x`` of ``U(x) = x + u(x)`` at every voxel (``(nz, ny, nx)``, float64).

    Derivatives are taken along the index axes by central differences
    (one-sided first differences on the boundary planes, so an affine map is
    exact everywhere), then converted to world mm with the full geometry:
    ``∂u/∂x = (∂u/∂ijk) (direction · diag(spacing))⁻¹``.

    Compared with ``sitk.DisplacementFieldJacobianDeterminant`` (ITK 5.4):
    that filter divides by the spacing but **ignores the direction** and uses
    zero-flux boundaries (half the derivative on the boundary planes).  It
    agrees with this function in the interior when the direction is the
    identity, or when it is given the displacement components expressed in the
    index-axis frame (``direction.T @ u``) — both are tested.
    """
    u = _check_field(field)
    m = np.ascontiguousarray(np.linalg.inv(field.geometry.index_to_world_matrix[:3, :3]))
    out = np.empty(field.geometry.array_shape, dtype=np.float64)
    (_jacobian_det_serial if out.size < SERIAL_BELOW else _jacobian_det)(u, m, out)
    return out


def jacobian_determinant_components(u: np.ndarray, spacing_zyx) -> np.ndarray:
    """:func:`jacobian_determinant` of a displacement held as its components along the array axes.

    ``u`` is ``(3, nz, ny, nx)`` in mm, ``u[0]`` along array axis 0 (z, index
    k), on an axis-aligned grid of spacing ``spacing_zyx`` (per array axis) —
    the layout of the dense registration's working fields
    (:mod:`registration.dense`), read in place rather than stacked into a
    Volume (a copy of the field at every step).  The same values, to the bit.
    """
    u = np.ascontiguousarray(u)
    if u.ndim != 4 or u.shape[0] != 3:
        raise ValueError(f"u must be (3, nz, ny, nx), got {u.shape}")
    out = np.empty(u.shape[1:], dtype=np.float64)
    (_jacobian_det_zyx_serial if out.size < SERIAL_BELOW else _jacobian_det_zyx)(
        u, 1.0 / np.asarray(spacing_zyx, dtype=np.float64), out
    )
    return out


def folding_statistics(field: Volume, mask=None) -> dict:
    """Statistics of the Jacobian determinant of ``U`` over ``mask`` (all voxels by default).

    ``mask`` is a boolean ``(nz, ny, nx)`` array or a Volume on the field's
    grid.  Returns ``dict(n_voxels, n_folded, fraction_folded, min_det,
    max_det, p01, p99)``: a voxel is folded where ``det ≤ 0``; ``p01`` and
    ``p99`` are the 1st and 99th percentiles (NumPy's linear method).  With an
    empty mask the counts are 0 and the other values NaN.
    """
    det = jacobian_determinant(field)
    if mask is not None:
        m = _grid_array(mask, field.geometry, "mask", trailing=())
        det = det[np.asarray(m, dtype=bool)]
    else:
        det = det.reshape(-1)
    n = int(det.size)
    if n == 0:
        nan = float("nan")
        return dict(n_voxels=0, n_folded=0, fraction_folded=nan, min_det=nan, max_det=nan, p01=nan, p99=nan)
    n_folded = int(np.count_nonzero(det <= 0))
    p01, p99 = np.percentile(det, [1.0, 99.0])
    return dict(
        n_voxels=n,
        n_folded=n_folded,
        fraction_folded=n_folded / n,
        min_det=float(det.min()),
        max_det=float(det.max()),
        p01=float(p01),
        p99=float(p99),
    )


RESTORE_FRACTIONS = (1.0, 0.75, 0.5, 0.25)  #: how far back towards the input a repaired voxel may go, tried in turn
UNFOLD_PAD = 8  #: voxels beyond the smoothing's reach that unfold's crop adds around the folds at first
RESTORE_PASSES = 10  #: at most this many restoring passes (each pass moves fewer voxels; they stop when none moves)


def unfold(
    field: Volume,
    *,
    min_det: float = 0.05,
    sigma: float = 1.0,
    margin: int = 1,
    max_iterations: int = 200,
    mask=None,
    frozen=None,
    restore: bool = True,
) -> tuple[Volume, dict]:
    """Remove folds from ``field`` by smoothing it locally where ``det ∂U/∂x < min_det``.

    Each iteration replaces the displacement on the voxels whose determinant
    is below ``min_det``, grown by ``margin`` voxels, with its Gaussian-smoothed
    value (``sigma`` in voxels, per component, ``mode='nearest'``); elsewhere
    the field is untouched.  Smoothing pulls ``∂u`` towards its local mean,
    which in practice raises the determinant of a thin fold, so the folded
    patch shrinks; the margin grows by one voxel every 20 iterations without
    progress, so a fold wider than the kernel is still reached.  There is no
    guarantee of success: ``n_folded_after`` says what is left.  This is the usual repair of a non-invertible
    initial field (e.g. the backward map of linear-blend VBD, Rhee Eq. 2, in
    the crease of a flexed joint, where the forward blend is not one-to-one):
    it changes the field only in and next to the folded voxels.  Folds
    farther apart than the smoothing's reach (2·4σ + ``margin`` + ``UNFOLD_PAD``
    voxels) are repaired one cluster after the other, each on a crop of the
    grid around it (bit for bit the whole grid's repair of the folds in that
    crop: another cluster's folds inside it are repaired with it), so a
    200 M-voxel field costs its folds' neighbourhood plus one copy;
    ``iterations`` is the most any crop took.

    ``mask`` (optional bool array or Volume on the grid) restricts the voxels
    whose determinant is checked (e.g. the body); all voxels by default.
    ``frozen`` (optional bool array or Volume on the grid) marks voxels whose
    displacement is never changed (e.g. bones held rigid); folds are then
    removed from the voxels around them.

    ``restore`` (default) then gives back what the smoothing changed and the
    unfolding did not need: the smoothing replaces every voxel of a region,
    but a fold is undone by a few of them.  Each changed voxel, in turn, goes
    back towards its input value by the largest of
    ``RESTORE_FRACTIONS`` that keeps ``det ≥ min_det`` at it and its six
    face neighbours (the only determinants it enters) wherever ``mask`` is,
    the largest changes first; passes repeat until one moves nothing (at most
    ``RESTORE_PASSES``).
    No determinant of the mask drops below ``min_det`` by it, so it never
    adds a fold, and it may finish a repair the smoothing left incomplete
    (what the passes change: docs/measurements/library-choices.md).
    Returns the new field (``field`` is not modified) and ``dict(iterations,
    n_folded_before, n_folded_after, n_changed, n_restored, max_change_mm)``
    (``n_changed``: voxels that differ from the input in the end,
    ``n_restored``: of the smoothed ones, those that went back all the way);
    folded counts are of ``det ≤ 0`` over the mask.
    """
    if not min_det > 0:
        raise ValueError(f"unfold: min_det must be > 0, got {min_det}")
    if not sigma > 0:
        raise ValueError(f"unfold: sigma must be > 0 (voxels), got {sigma}")
    u0 = _check_field(field)
    g = field.geometry
    m = None if mask is None else np.asarray(_grid_array(mask, g, "mask", trailing=()), dtype=bool)
    fz = None if frozen is None else np.asarray(_grid_array(frozen, g, "frozen", trailing=()), dtype=bool)
    m_inv = np.ascontiguousarray(np.linalg.inv(g.index_to_world_matrix[:3, :3]))
    shape = g.array_shape
    # The repair works fold by fold, each on a crop of the grid around it: a grid may hold 200 M voxels with
    # folds in a few creases, and a whole-grid repair holds a float64 copy, its determinants and the input to
    # restore from (the memory: docs/measurements/deformation-and-validation.md).
    # Folds closer than ``pad`` voxels are one cluster; each cluster's crop is repaired as the whole grid would be
    # with only the folds in the crop (it is widened until the repair keeps off the crop's faces, where a
    # determinant would be one-sided and a Gaussian box clipped), and the clusters one after the other.
    low, n_before = _low_dets(u0, m_inv, float(min_det), m)
    out = u0.copy()
    smoothed = np.zeros(shape, dtype=bool)
    pad0 = max(1, 2 * int(math.ceil(4.0 * sigma)) + int(margin) + UNFOLD_PAD)
    iterations = 0
    for box in _clusters(low, pad0):
        pad = pad0
        while True:
            crop = tuple(slice(max(b.start - pad, 0), min(b.stop + pad, n)) for b, n in zip(box, shape))
            inner = np.zeros(tuple(c.stop - c.start for c in crop), dtype=bool)  # the crop less its own faces
            inner[tuple(slice(0 if c.start == 0 else 1, None if c.stop == n else -1) for c, n in zip(crop, shape))] = (
                True
            )
            u, info, touched, changed = _unfold_crop(
                out[crop],
                m_inv,
                inner if m is None else inner & m[crop],
                None if fz is None else fz[crop],
                min_det,
                sigma,
                margin,
                max_iterations,
                restore,
            )
            # nothing low left (an earlier cluster's crop held this one and repaired it), or the repair kept off
            # the crop's faces that are not the grid's: done; else a wider crop
            if info.pop("n_low") == 0 or all(
                (c.start == 0 or t.start >= 1) and (c.stop == n or t.stop <= c.stop - c.start - 1)
                for c, t, n in zip(crop, touched, shape)
            ):
                break
            pad *= 2
        out[crop] = u.astype(out.dtype, copy=False)
        smoothed[crop] |= changed
        iterations = max(iterations, info["iterations"])
    n_after, n_changed, max_change = _unfold_summary(out, u0, m_inv, m)
    return Volume(out, g), dict(
        iterations=iterations,
        n_folded_before=n_before,
        n_folded_after=n_after,
        n_changed=n_changed,
        n_restored=int(np.count_nonzero(smoothed)) - n_changed,
        max_change_mm=max_change,
    )


def _slab_dets(u, m_inv):
    """``(k0, k1, det)``: :func:`_jacobian_det` of the whole field in float64, made a slab of planes ``k0:k1``
    at a time (each from the slab and a plane of its neighbours on both sides: the same bits)."""
    nz = u.shape[0]
    for k0, k1 in slabs(nz, u.shape[1] * u.shape[2]):
        a0, a1 = max(k0 - 1, 0), min(k1 + 1, nz)
        det = np.empty((a1 - a0,) + u.shape[1:3])
        _jacobian_det(np.asarray(u[a0:a1], dtype=np.float64), m_inv, det)
        yield k0, k1, det[k0 - a0 : k1 - a0]


def _low_dets(u, m_inv, min_det, mask):
    """Where ``det ∂U/∂x < min_det`` within ``mask`` (bool, 1 B a voxel), and how many voxels fold there
    (``det ≤ 0``)."""
    low = np.zeros(u.shape[:3], dtype=bool)
    n_folded = 0
    for k0, k1, det in _slab_dets(u, m_inv):
        m = None if mask is None else mask[k0:k1]
        low[k0:k1] = det < min_det if m is None else (det < min_det) & m
        n_folded += int(np.count_nonzero(det <= 0 if m is None else (det <= 0) & m))
    return low, n_folded


def _clusters(low, gap):
    """Bounding boxes (slices) of the groups of ``low`` voxels: voxels in blocks of ``gap``³ that touch (26
    neighbours) are one group, so voxels of different groups are at least ``gap`` apart; in the order of
    their first block (z, y, x)."""
    from scipy import ndimage as ndi

    pooled = low
    for ax in range(3):
        pooled = np.logical_or.reduceat(pooled, np.arange(0, low.shape[ax], gap), axis=ax)
    lab, _ = ndi.label(pooled, structure=np.ones((3, 3, 3), dtype=bool))
    boxes = []
    for k, blocks in enumerate(ndi.find_objects(lab), start=1):
        fine = tuple(slice(b.start * gap, min(b.stop * gap, n)) for b, n in zip(blocks, low.shape))
        sub = low[fine] & from_every(lab[blocks] == k, gap, low[fine].shape)
        hit = [np.flatnonzero(np.any(sub, axis=tuple(a for a in range(3) if a != ax))) for ax in range(3)]
        boxes.append(tuple(slice(f.start + int(h[0]), f.start + int(h[-1]) + 1) for f, h in zip(fine, hit)))
    return boxes


def _unfold_summary(out, u0, m_inv, mask):
    """After the repair: folded voxels (``det ≤ 0`` within ``mask``), voxels changed, largest change (mm)."""
    n_after = 0
    for k0, k1, det in _slab_dets(out, m_inv):
        n_after += int(np.count_nonzero(det <= 0 if mask is None else (det <= 0) & mask[k0:k1]))
    n_changed, max_change = 0, 0.0
    for k0, k1 in slabs(out.shape[0], out.shape[1] * out.shape[2]):
        d = np.linalg.norm(np.asarray(out[k0:k1], np.float64) - np.asarray(u0[k0:k1], np.float64), axis=-1)
        n_changed += int(np.count_nonzero(d > 0))
        max_change = max(max_change, float(d.max()))
    return n_after, n_changed, max_change


def _unfold_crop(u0, m_inv, m, fz, min_det, sigma, margin, max_iterations, restore):
    """:func:`unfold` on a crop of the grid (``u0``, its mask ``m`` and ``frozen`` ``fz``, arrays of the crop):
    the repaired crop (float64), the summary (with ``n_low``, the voxels below ``min_det`` at the start), the
    box (slices) that holds every voxel it read or wrote, and the voxels it smoothed (bool)."""
    from scipy import ndimage as ndi

    u = np.array(u0, dtype=np.float64)
    det = np.empty(u.shape[:3], dtype=np.float64)
    _jacobian_det(u, m_inv, det)
    shape = np.asarray(u.shape[:3])

    def grown_box(where, by, within=None):
        """Bounding box of ``where`` (looked for inside the box ``within``, the whole grid by default) grown
        by ``by`` voxels, clipped to the grid."""
        off = [0, 0, 0] if within is None else [w.start for w in within]
        sub = where if within is None else where[within]
        box = []
        for ax, n in enumerate(shape):
            hit = np.flatnonzero(np.any(sub, axis=tuple(a for a in range(3) if a != ax)))
            box.append(slice(max(int(hit[0]) + off[ax] - by, 0), min(int(hit[-1]) + off[ax] + by + 1, int(n))))
        return tuple(box)

    def low(box=(slice(None),) * 3):
        bad = det[box] < min_det
        return bad if m is None else bad & m[box]

    def union(a, b):
        return tuple(slice(min(x.start, y.start), max(x.stop, y.stop)) for x, y in zip(a, b))

    def grow_box(box, by):
        """``box`` grown by ``by`` voxels, clipped to the grid."""
        return tuple(slice(max(b.start - by, 0), min(b.stop + by, int(n))) for b, n in zip(box, shape))

    def rel(a, b):
        """The box ``a`` in the coordinates of the box ``b`` that holds it."""
        return tuple(slice(x.start - y.start, x.stop - y.start) for x, y in zip(a, b))

    bad = low()
    n_before = int(np.count_nonzero((det <= 0) if m is None else (det <= 0) & m))
    changed = np.zeros(u.shape[:3], dtype=bool)
    grow, best, stall, it = int(margin), int(np.count_nonzero(bad)), 0, 0
    n_low = best
    # every array operation of the loop works on boxes around the folds: ``hull`` holds every voxel that is
    # or has been low (the determinant changes only next to what was smoothed), so the loop costs the folds'
    # neighbourhood, not the grid
    hull = grown_box(bad, 0) if best else None
    touched = hull if best else (slice(0, 0),) * 3
    n_bad = best
    while n_bad and it < max_iterations:
        it += 1
        rbox = grow_box(grown_box(bad, 0, hull), grow + 1)  # the region (the folds dilated) lies inside it
        touched = union(touched, rbox)  # read, even when the frozen voxels leave nothing to smooth
        region = ndi.binary_dilation(bad[rbox], iterations=grow) if grow > 0 else bad[rbox].copy()
        if fz is not None:
            region &= ~fz[rbox]
            if not region.any():
                stall, grow = 0, grow + 1
                if grow > 50:
                    break
                continue
        # smooth only the region's bounding box grown by the kernel's reach (truncate=4σ): the values on
        # the region are those of smoothing the whole grid, at the cost of the folds' neighbourhood only
        reach = int(math.ceil(4.0 * sigma))
        rb = grown_box(region, 0)  # the region's own box, in rbox's coordinates, then the grid's
        rb = tuple(slice(r.start + o.start, r.stop + o.start) for r, o in zip(rb, rbox))
        box = grow_box(rb, reach)
        sub = u[box]
        sm = np.stack([smooth(sub[..., c], sigma, mode="nearest", truncate=4.0) for c in range(3)], axis=-1)
        full = np.zeros(sub.shape[:3], dtype=bool)  # the region, on the smoothing box
        full[rel(rb, box)] = region[rel(rb, rbox)]
        sub[full] = sm[full]
        changed[box] |= full
        _update_jacobian_det(u, m_inv, det, rb)  # reads u two voxels around rb
        touched = union(touched, union(box, grow_box(rb, 2)))
        ub = grow_box(rb, 1)
        bad[ub] = low(ub)
        hull = union(hull, ub)
        n_bad = int(np.count_nonzero(bad[hull]))
        if n_bad < best:
            best, stall = n_bad, 0
        else:
            stall += 1
            if stall >= 20:
                grow, stall = grow + 1, 0
    n_smoothed = int(np.count_nonzero(changed))
    if restore and n_smoothed:
        u_in = np.asarray(u0, dtype=np.float64)
        check = np.ones(u.shape[:3], dtype=bool) if m is None else m  # the changed voxels lie in the smoothed
        # regions, so what this reads (their neighbours' determinants) lies within two voxels of them: in touched
        fractions = np.asarray(RESTORE_FRACTIONS, dtype=np.float64)
        for _ in range(RESTORE_PASSES):
            change = np.linalg.norm(u - u_in, axis=-1)
            cand = np.argwhere(change > 0)
            if not len(cand):
                break
            order = np.argsort(-change[tuple(cand.T)], kind="stable")  # the largest change first
            if not _restore_towards(
                u, u_in, np.ascontiguousarray(cand[order]), check, m_inv, float(min_det), fractions
            ):
                break
        _jacobian_det(u, m_inv, det)
    n_after = int(np.count_nonzero((det <= 0) if m is None else (det <= 0) & m))
    diff = np.linalg.norm(u - u0, axis=-1)
    n_changed = int(np.count_nonzero(diff > 0))
    info = dict(
        iterations=it,
        n_folded_before=n_before,
        n_folded_after=n_after,
        n_changed=n_changed,
        n_restored=n_smoothed - n_changed,
        max_change_mm=float(diff.max()) if diff.size else 0.0,
        n_low=n_low,
    )
    return u, info, touched, changed


# -- SimpleITK transforms -----------------------------------------------------------------------
def to_sitk_transform(field: Volume) -> sitk.DisplacementFieldTransform:
    """A ``sitk.DisplacementFieldTransform`` whose ``TransformPoint(x)`` is ``U(x) = x + u(x)``.

    The field is copied into a float64 vector image with the field's geometry
    (ITK's transforms need double).  Constructing the transform *consumes* that
    image (SimpleITK empties the image passed to the constructor), which is why
    it is a private copy here; ``field`` is not modified.  The transform
    interpolates linearly and is the identity outside the grid, as :func:`compose`.
    """
    u = _check_field(field)
    img = sitk.GetImageFromArray(np.asarray(u, dtype=np.float64), isVector=True)
    field.geometry.apply_to_sitk(img)
    return sitk.DisplacementFieldTransform(img)


def from_transform(transform: sitk.Transform, geometry: GridGeometry) -> Volume:
    """The displacement field ``T(x) - x`` of any SimpleITK transform on the voxel centres of ``geometry``.

    E.g. an ``Euler3DTransform`` mapping template → scan world gives a
    ``template_to_scan`` field on the template grid.  Uses
    ``sitk.TransformToDisplacementField`` (float64).
    """
    img = sitk.TransformToDisplacementField(
        transform,
        sitk.sitkVectorFloat64,
        list(geometry.size),
        list(geometry.origin),
        list(geometry.spacing),
        list(geometry.direction),
    )
    return Volume(sitk.GetArrayFromImage(img), geometry)


def from_sitk_transform(transform: sitk.Transform, geometry: GridGeometry | None = None) -> Volume:
    """The field of a ``sitk.DisplacementFieldTransform`` (or any transform) sampled on ``geometry``.

    With ``geometry=None`` the transform must be a ``DisplacementFieldTransform``
    and its own field is returned on its own grid (an exact copy).  Otherwise
    ``T(x) - x`` is evaluated at the voxel centres of ``geometry`` (the
    transform's interpolator, linear by default; identity outside its grid).
    """
    if geometry is None:
        if not isinstance(transform, sitk.DisplacementFieldTransform):
            raise TypeError(
                "from_sitk_transform without a geometry needs a sitk.DisplacementFieldTransform "
                f"(got {type(transform).__name__}); pass the grid to sample it on"
            )
        return Volume.from_sitk(transform.GetDisplacementField())
    return from_transform(transform, geometry)
