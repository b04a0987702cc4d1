"""Resampling a forward-deformed volume onto a regular grid: the backward map.

VBD (Rhee Eq. 2) and EVD (Rhee Eq. 6) move *template* voxels forward: they
give ``F(v)``, the posed position of every template grid point ``v``.  A
posed volume on a regular grid needs the opposite, the template position
``F⁻¹(y)`` of every target voxel ``y``.

``F`` between grid points is the trilinear interpolation of the forward
positions.  For each target voxel :func:`backward_map` solves ``F(x) = y`` by
Newton's method on that map (its Jacobian is exact inside a cell), walking
along each row of the target grid: every solve starts from its neighbour's
answer moved by ``J⁻¹ Δy``.  The first voxel of a row, and any voxel where
that fails, starts from the template voxel whose forward position landed
nearest (the last in array order: a serial scatter, hence deterministic, run
beside the parallel passes), then from the candidates ``T_b⁻¹ y`` (each bone's
inverse rigid transform, exact wherever tissue moves with a bone).  Target
voxels farther than the tolerance from every template cell's image (the
bounding boxes of the cells' forward-mapped corners, cut by the planes of the
template box's faces; a cell torn apart across a fold counts only near its
corners) are outside without a solve.  Rows are independent: they
run in parallel, deterministically.
Rasterising the deformed cells as tetrahedra instead would invert a
piecewise-linear map (not the trilinear one the forward pass defines) and
write each voxel from whichever tetrahedron reaches it, racy in parallel.

Every target voxel gets a status (:data:`OK`, :data:`FOLDED`,
:data:`NOT_CONVERGED`, :data:`OUTSIDE`).  Label maps are resampled with
nearest neighbour, intensities trilinearly (:func:`resample_forward`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from deformation.fields.interpolate import fill_value, flat_data, interp_scalar, output_dtype
from deformation.geometry import SLAB_VOXELS, GridGeometry, Volume, every_nth, slabs

__all__ = [
    "BackwardMap",
    "backward_map",
    "backward_points",
    "upsample_backward_map",
    "CoarseBackwardMap",
    "resample_forward",
    "invert_scan_to_template",
    "backward_kernel",
    "OK",
    "FOLDED",
    "NOT_CONVERGED",
    "OUTSIDE",
    "STATUS_NAMES",
]

#: Status of a target voxel: ``OK`` converged, ``|F(x) − y| ≤ tol``; ``FOLDED`` converged but
#: ``det ∂F/∂x ≤ 0`` at the solution (several template points land on ``y``, one is returned);
#: ``NOT_CONVERGED`` no candidate converged (the best iterate is returned); ``OUTSIDE`` the preimage lies
#: outside the template grid, or ``y`` is farther than the tolerance from every template cell's (cut) forward
#: bounding box (outside the forward map's image, as where linear blending shrinks the air around a fist; a
#: cell torn apart across a fold counts only near its corners): the voxel gets the fill value.
OK, FOLDED, NOT_CONVERGED, OUTSIDE = 0, 1, 2, 3
STATUS_NAMES = {OK: "ok", FOLDED: "folded", NOT_CONVERGED: "not_converged", OUTSIDE: "outside"}


@nb.njit(cache=True, inline="always")
def _eval_c(fwd, k0, j0, i0, c, fx, fy, fz):
    """Component ``c`` of the trilinear F in the cell (i0, j0, k0) at fractions (fx, fy, fz), and its derivatives
    along i, j, k."""
    c000 = fwd[k0, j0, i0, c]
    c100 = fwd[k0, j0, i0 + 1, c]
    c010 = fwd[k0, j0 + 1, i0, c]
    c110 = fwd[k0, j0 + 1, i0 + 1, c]
    c001 = fwd[k0 + 1, j0, i0, c]
    c101 = fwd[k0 + 1, j0, i0 + 1, c]
    c011 = fwd[k0 + 1, j0 + 1, i0, c]
    c111 = fwd[k0 + 1, j0 + 1, i0 + 1, c]
    a00 = c000 + (c100 - c000) * fx
    a10 = c010 + (c110 - c010) * fx
    a01 = c001 + (c101 - c001) * fx
    a11 = c011 + (c111 - c011) * fx
    b0 = a00 + (a10 - a00) * fy
    b1 = a01 + (a11 - a01) * fy
    dx00 = c100 - c000
    dx10 = c110 - c010
    dx01 = c101 - c001
    dx11 = c111 - c011
    d0 = dx00 + (dx10 - dx00) * fy
    d1 = dx01 + (dx11 - dx01) * fy
    e0 = a10 - a00
    e1 = a11 - a01
    return b0 + (b1 - b0) * fz, d0 + (d1 - d0) * fz, e0 + (e1 - e0) * fz, b1 - b0


@nb.njit(cache=True, inline="always")
def _eval(fwd, x0, x1, x2):
    """Trilinear F and its exact in-cell Jacobian at continuous template index (x0, x1, x2) = (i, j, k):
    ``(F_x, F_y, F_z, ∂F_x/∂i, ∂F_x/∂j, ∂F_x/∂k, ∂F_y/∂i, …, ∂F_z/∂k)``."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    i0 = min(max(int(np.floor(x0)), 0), nx - 2)
    j0 = min(max(int(np.floor(x1)), 0), ny - 2)
    k0 = min(max(int(np.floor(x2)), 0), nz - 2)
    fx = x0 - i0
    fy = x1 - j0
    fz = x2 - k0
    f0, j00, j01, j02 = _eval_c(fwd, k0, j0, i0, 0, fx, fy, fz)
    f1, j10, j11, j12 = _eval_c(fwd, k0, j0, i0, 1, fx, fy, fz)
    f2, j20, j21, j22 = _eval_c(fwd, k0, j0, i0, 2, fx, fy, fz)
    return f0, f1, f2, j00, j01, j02, j10, j11, j12, j20, j21, j22


@nb.njit(cache=True, inline="always")
def _det3(j00, j01, j02, j10, j11, j12, j20, j21, j22):
    return j00 * (j11 * j22 - j12 * j21) - j01 * (j10 * j22 - j12 * j20) + j02 * (j10 * j21 - j11 * j20)


@nb.njit(cache=True, inline="always")
def _solve3(j00, j01, j02, j10, j11, j12, j20, j21, j22, inv, r0, r1, r2):
    """``J⁻¹ r`` by the adjugate, ``inv`` = 1 / det J."""
    d0 = inv * ((j11 * j22 - j12 * j21) * r0 - (j01 * j22 - j02 * j21) * r1 + (j01 * j12 - j02 * j11) * r2)
    d1 = inv * (-(j10 * j22 - j12 * j20) * r0 + (j00 * j22 - j02 * j20) * r1 - (j00 * j12 - j02 * j10) * r2)
    d2 = inv * ((j10 * j21 - j11 * j20) * r0 - (j00 * j21 - j01 * j20) * r1 + (j00 * j11 - j01 * j10) * r2)
    return d0, d1, d2


@nb.njit(cache=True, inline="always")
def _on_border(x0, x1, x2, nx, ny, nz):
    e = 1e-6
    return x0 <= e or x1 <= e or x2 <= e or x0 >= nx - 1 - e or x1 >= ny - 1 - e or x2 >= nz - 1 - e


@nb.njit(cache=True, inline="always")
def _prio_at(prio, x0, x1, x2):
    nz, ny, nx = prio.shape
    i = min(max(int(np.floor(x0 + 0.5)), 0), nx - 1)
    j = min(max(int(np.floor(x1 + 0.5)), 0), ny - 1)
    k = min(max(int(np.floor(x2 + 0.5)), 0), nz - 1)
    return prio[k, j, i]


@nb.njit(cache=True, inline="always")
def _newton(fwd, y0, y1, y2, x0, x1, x2, tol, max_iter, max_step):
    """Newton on F(x) = y from x.  Returns (residual, det J, x, J): the last iterate and the Jacobian there
    (9 entries, row-major)."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    lim0 = nx - 1.0
    lim1 = ny - 1.0
    lim2 = nz - 1.0
    res = np.inf
    det = 0.0
    pinned = 0
    j00 = j01 = j02 = j10 = j11 = j12 = j20 = j21 = j22 = 0.0
    for it in range(max_iter + 1):
        f0, f1, f2, j00, j01, j02, j10, j11, j12, j20, j21, j22 = _eval(fwd, x0, x1, x2)
        r0 = y0 - f0
        r1 = y1 - f1
        r2 = y2 - f2
        last = res
        res = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        det = _det3(j00, j01, j02, j10, j11, j12, j20, j21, j22)
        if res <= tol or it == max_iter or det == 0.0:
            break
        # stuck against the grid's edge without getting closer: the preimage is outside
        if _on_border(x0, x1, x2, nx, ny, nz) and res > 0.5 * last:
            pinned += 1
            if pinned >= 2:
                break
        else:
            pinned = 0
        d0, d1, d2 = _solve3(j00, j01, j02, j10, j11, j12, j20, j21, j22, 1.0 / det, r0, r1, r2)
        m = max(abs(d0), abs(d1), abs(d2))
        if m > max_step:
            sc = max_step / m
            d0 *= sc
            d1 *= sc
            d2 *= sc
        x0 = min(max(x0 + d0, 0.0), lim0)
        x1 = min(max(x1 + d1, 0.0), lim1)
        x2 = min(max(x2 + d2, 0.0), lim2)
    return res, det, x0, x1, x2, j00, j01, j02, j10, j11, j12, j20, j21, j22


@nb.njit(cache=True, inline="always")
def _mark8(a, b, c, mask):
    """Set the 8 voxels (a..a+1, b..b+1, c..c+1) of ``mask`` that lie in it."""
    tz, ty, tx = mask.shape
    for cc in range(max(c, 0), min(c + 2, tz)):
        for bb in range(max(b, 0), min(b + 2, ty)):
            for aa in range(max(a, 0), min(a + 2, tx)):
                mask[cc, bb, aa] = 1


@nb.njit(cache=True, inline="always")
def _face_corner(fwd, k, j, i, axis, s, u, v):
    """Forward position (world mm, float64) of the corner (s along ``axis``, u and v along the other two) of the
    template cell with lower corner (i, j, k)."""
    if axis == 0:
        kk, jj, ii = k + v, j + u, i + s
    elif axis == 1:
        kk, jj, ii = k + v, j + s, i + u
    else:
        kk, jj, ii = k + s, j + v, i + u
    return np.float64(fwd[kk, jj, ii, 0]), np.float64(fwd[kk, jj, ii, 1]), np.float64(fwd[kk, jj, ii, 2])


@nb.njit(cache=True)
def _face_plane(fwd, k, j, i, axis, side):
    """The plane bounding a template border cell (lower corner (i, j, k)) on its face ``axis`` (0 i, 1 j, 2 k) =
    ``side`` (0 or 1), the template box's face: unit normal ``n`` (pointing away from the cell's opposite face)
    and ``h`` = max over the cell's 8 forward-mapped corners of ``n · F`` (world mm).  The cell's image lies in
    its corners' convex hull, hence in ``n · y ≤ h``."""
    p00 = _face_corner(fwd, k, j, i, axis, side, 0, 0)
    p01 = _face_corner(fwd, k, j, i, axis, side, 0, 1)
    p10 = _face_corner(fwd, k, j, i, axis, side, 1, 0)
    p11 = _face_corner(fwd, k, j, i, axis, side, 1, 1)
    # normal: the cross product of the face's diagonals, turned away from the opposite face
    a0, a1, a2 = p11[0] - p00[0], p11[1] - p00[1], p11[2] - p00[2]
    b0, b1, b2 = p10[0] - p01[0], p10[1] - p01[1], p10[2] - p01[2]
    n0 = a1 * b2 - a2 * b1
    n1 = a2 * b0 - a0 * b2
    n2 = a0 * b1 - a1 * b0
    norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if not norm > 0.0:
        return 0.0, 0.0, 0.0, np.inf  # a degenerate face: no plane
    away = 0.0
    for u in range(2):
        for v in range(2):
            q = _face_corner(fwd, k, j, i, axis, 1 - side, u, v)
            away += n0 * q[0] + n1 * q[1] + n2 * q[2]
    if away > n0 * (p00[0] + p01[0] + p10[0] + p11[0]) + n1 * (p00[1] + p01[1] + p10[1] + p11[1]) + n2 * (
        p00[2] + p01[2] + p10[2] + p11[2]
    ):
        norm = -norm
    n0 /= norm
    n1 /= norm
    n2 /= norm
    h = -np.inf
    for dk in range(2):
        for dj in range(2):
            for di in range(2):
                h = max(
                    h,
                    n0 * fwd[k + dk, j + dj, i + di, 0]
                    + n1 * fwd[k + dk, j + dj, i + di, 1]
                    + n2 * fwd[k + dk, j + dj, i + di, 2],
                )
    return n0, n1, n2, h


@nb.njit(cache=True, inline="always")
def _mark_box(cover, tx, ty, tz, a0, a1, b0, b1, c0, c1):
    """Set ``cover`` (flat, a ``tx × ty × tz`` grid) over the target voxels a0..a1 × b0..b1 × c0..c1 (inclusive,
    clipped to the grid).  A box at most 2 voxels a side is written without a branch: 8 writes, the same voxel
    twice along an axis where the box is 1 voxel wide."""
    if a1 - a0 <= 1 and b1 - b0 <= 1 and c1 - c0 <= 1:
        da = a1 - a0
        db = (b1 - b0) * tx
        dc = (c1 - c0) * tx * ty
        base = (c0 * ty + b0) * tx + a0
        cover[base] = 1
        cover[base + da] = 1
        cover[base + db] = 1
        cover[base + db + da] = 1
        cover[base + dc] = 1
        cover[base + dc + da] = 1
        cover[base + dc + db] = 1
        cover[base + dc + db + da] = 1
    else:
        for c in range(c0, c1 + 1):
            for b in range(b0, b1 + 1):
                for a in range(a0, a1 + 1):
                    cover[(c * ty + b) * tx + a] = 1


@nb.njit(cache=True, inline="always")
def _mark8_flat(a, b, c, cover, tx, ty, tz):
    """:func:`_mark8` on a flat ``cover`` of a ``tx × ty × tz`` grid."""
    for cc in range(max(c, 0), min(c + 2, tz)):
        for bb in range(max(b, 0), min(b + 2, ty)):
            for aa in range(max(a, 0), min(a + 2, tx)):
                cover[(cc * ty + bb) * tx + aa] = 1


@nb.njit(cache=True)
def _mark_box_planes(cover, tx, ty, tz, a0, a1, b0, b1, c0, c1, tgt_a, planes, n_planes):
    """:func:`_mark_box` keeping only the voxels whose world position lies on the inner side of every plane
    ``planes[q, :3] · y ≤ planes[q, 3]``."""
    for c in range(c0, c1 + 1):
        for b in range(b0, b1 + 1):
            for a in range(a0, a1 + 1):
                y0 = tgt_a[0, 0] * a + tgt_a[0, 1] * b + tgt_a[0, 2] * c + tgt_a[0, 3]
                y1 = tgt_a[1, 0] * a + tgt_a[1, 1] * b + tgt_a[1, 2] * c + tgt_a[1, 3]
                y2 = tgt_a[2, 0] * a + tgt_a[2, 1] * b + tgt_a[2, 2] * c + tgt_a[2, 3]
                inside = True
                for q in range(n_planes):
                    if planes[q, 0] * y0 + planes[q, 1] * y1 + planes[q, 2] * y2 > planes[q, 3]:
                        inside = False
                if inside:
                    cover[(c * ty + b) * tx + a] = 1


@nb.njit(cache=True)
def _mark_prio_octants(ta, tb, i, j, k, prio, g0, g1, g2, tx, ty, tz, priocov, hp):
    """Mark in ``priocov`` the target voxels within the grown bounding box of the image of each octant of the cell
    (lower corner (i, j, k); ``ta``, ``tb`` the target indices of slabs k and k + 1) that belongs to a corner with
    ``prio`` set — the part of the cell whose nearest template voxel is preferred (as :func:`_prio_at` rounds).
    ``hp`` is scratch, (3, 3, 3, 3)."""
    # the trilinear target index at the cell's fractions {0, 1/2, 1}³, one axis at a time
    for q in range(3):
        for dk in range(2):
            t = ta if dk == 0 else tb
            for dj in range(2):
                u = np.float64(t[j + dj, i, q])
                v = np.float64(t[j + dj, i + 1, q])
                hp[2 * dk, 2 * dj, 0, q] = u
                hp[2 * dk, 2 * dj, 1, q] = 0.5 * (u + v)
                hp[2 * dk, 2 * dj, 2, q] = v
            for fi in range(3):
                hp[2 * dk, 1, fi, q] = 0.5 * (hp[2 * dk, 0, fi, q] + hp[2 * dk, 2, fi, q])
        for fj in range(3):
            for fi in range(3):
                hp[1, fj, fi, q] = 0.5 * (hp[0, fj, fi, q] + hp[2, fj, fi, q])
    for dk in range(2):
        for dj in range(2):
            for di in range(2):
                if prio[k + dk, j + dj, i + di] == 0:
                    continue
                lo0 = lo1 = lo2 = np.inf
                hi0 = hi1 = hi2 = -np.inf
                for ek in range(2):
                    for ej in range(2):
                        for ei in range(2):
                            v0 = hp[dk + ek, dj + ej, di + ei, 0]
                            v1 = hp[dk + ek, dj + ej, di + ei, 1]
                            v2 = hp[dk + ek, dj + ej, di + ei, 2]
                            lo0 = min(lo0, v0)
                            hi0 = max(hi0, v0)
                            lo1 = min(lo1, v1)
                            hi1 = max(hi1, v1)
                            lo2 = min(lo2, v2)
                            hi2 = max(hi2, v2)
                a0 = max(int(np.ceil(lo0 - g0)), 0)
                a1 = min(int(np.floor(hi0 + g0)), tx - 1)
                b0 = max(int(np.ceil(lo1 - g1)), 0)
                b1 = min(int(np.floor(hi1 + g1)), ty - 1)
                c0 = max(int(np.ceil(lo2 - g2)), 0)
                c1 = min(int(np.floor(hi2 + g2)), tz - 1)
                for c in range(c0, c1 + 1):
                    for b in range(b0, b1 + 1):
                        for a in range(a0, a1 + 1):
                            priocov[(c * ty + b) * tx + a] = 1


@nb.njit(cache=True)
def _scatter_guess(fwd, tgt_w, prio, use_prio, tshape, guess):
    """For each target voxel (flat ``guess``, initialised to -1), a template voxel whose forward position rounds to
    it (a Newton start): serial and in template order, the last writer winning, so deterministic; with ``use_prio``
    a second pass lets the preferred (``prio``) voxels overwrite the others."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    tz, ty, tx = tshape
    for rep in range(2 if use_prio else 1):
        for k in range(nz):
            for j in range(ny):
                for i in range(nx):
                    if rep == 1 and prio[k, j, i] == 0:
                        continue
                    p0 = fwd[k, j, i, 0]
                    p1 = fwd[k, j, i, 1]
                    p2 = fwd[k, j, i, 2]
                    # the target index in float32, as the cover sees it
                    a = int(
                        np.floor(np.float32(tgt_w[0, 0] * p0 + tgt_w[0, 1] * p1 + tgt_w[0, 2] * p2 + tgt_w[0, 3]) + 0.5)
                    )
                    b = int(
                        np.floor(np.float32(tgt_w[1, 0] * p0 + tgt_w[1, 1] * p1 + tgt_w[1, 2] * p2 + tgt_w[1, 3]) + 0.5)
                    )
                    c = int(
                        np.floor(np.float32(tgt_w[2, 0] * p0 + tgt_w[2, 1] * p1 + tgt_w[2, 2] * p2 + tgt_w[2, 3]) + 0.5)
                    )
                    if 0 <= a < tx and 0 <= b < ty and 0 <= c < tz:
                        guess[(c * ty + b) * tx + a] = (k * ny + j) * nx + i


@nb.njit(cache=True)
def _target_slab(fwd, tgt_w, k, t):
    """Continuous target index (float32) of the forward position of every template voxel of slab ``k``."""
    for j in range(fwd.shape[1]):
        for i in range(fwd.shape[2]):
            p0 = fwd[k, j, i, 0]
            p1 = fwd[k, j, i, 1]
            p2 = fwd[k, j, i, 2]
            for q in range(3):
                t[j, i, q] = tgt_w[q, 0] * p0 + tgt_w[q, 1] * p1 + tgt_w[q, 2] * p2 + tgt_w[q, 3]


@nb.njit(cache=True)
def _cover_slabs(fwd, tgt_w, tgt_a, prio, use_prio, max_extent, tol, k_lo, k_hi, tshape, cover, occ, priocov):
    """:func:`_landing`'s ``cover``, ``occ`` and ``priocov`` from the template slabs ``k_lo ≤ k < k_hi`` (cells
    with their lower corner there)."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    tz, ty, tx = tshape
    # tol in target index units along each axis (|Δ index_a| ≤ |row a of world → index| · |Δ world|), with a
    # margin for the float32 rounding of the target indices (half an ulp, |index| · 2⁻²⁴, where a bound can still
    # fall inside the grid: |index| up to the grid's size plus the margin)
    eps = 1e-4 + 2.0**-22 * (max(tx, ty, tz) + 2)
    g0 = tol * np.sqrt(tgt_w[0, 0] ** 2 + tgt_w[0, 1] ** 2 + tgt_w[0, 2] ** 2) + eps
    g1 = tol * np.sqrt(tgt_w[1, 0] ** 2 + tgt_w[1, 1] ** 2 + tgt_w[1, 2] ** 2) + eps
    g2 = tol * np.sqrt(tgt_w[2, 0] ** 2 + tgt_w[2, 1] ** 2 + tgt_w[2, 2] ** 2) + eps
    ts = np.empty((2, ny, nx, 3), dtype=np.float32)  # the target indices of slabs k and k + 1
    col = np.empty((6, nx), dtype=np.float32)  # bounds of the 4 voxels (j, j + 1) × (k, k + 1) at each i
    pcol = np.zeros(nx, dtype=np.int64)  # how many of them are preferred
    planes = np.empty((6, 4))
    hp = np.empty((3, 3, 3, 3))
    _target_slab(fwd, tgt_w, k_lo, ts[k_lo % 2])
    for k in range(k_lo, k_hi):
        ta = ts[k % 2]
        tb = ts[(k + 1) % 2]
        if k < nz - 1:
            _target_slab(fwd, tgt_w, k + 1, tb)
        if use_prio:
            for j in range(ny):
                for i in range(nx):
                    if prio[k, j, i] != 0:
                        _mark8(int(np.floor(ta[j, i, 0])), int(np.floor(ta[j, i, 1])), int(np.floor(ta[j, i, 2])), occ)
        if k == nz - 1:
            continue
        for j in range(ny - 1):
            for i in range(nx):
                for q in range(3):
                    u = ta[j, i, q]
                    v = ta[j + 1, i, q]
                    w = tb[j, i, q]
                    z = tb[j + 1, i, q]
                    lo = u if u < v else v
                    lo = lo if lo < w else w
                    lo = lo if lo < z else z
                    hi = u if u > v else v
                    hi = hi if hi > w else w
                    hi = hi if hi > z else z
                    col[q, i] = lo
                    col[3 + q, i] = hi
                if use_prio:
                    pcol[i] = (
                        (prio[k, j, i] != 0)
                        + (prio[k, j + 1, i] != 0)
                        + (prio[k + 1, j, i] != 0)
                        + (prio[k + 1, j + 1, i] != 0)
                    )
            border_jk = j == 0 or k == 0 or j == ny - 2 or k == nz - 2
            for i in range(nx - 1):
                # the cell whose lower corner is (i, j, k): its corners' bounding box, grown by tol
                lo0 = min(col[0, i], col[0, i + 1])
                lo1 = min(col[1, i], col[1, i + 1])
                lo2 = min(col[2, i], col[2, i + 1])
                hi0 = max(col[3, i], col[3, i + 1])
                hi1 = max(col[4, i], col[4, i + 1])
                hi2 = max(col[5, i], col[5, i + 1])
                a0 = max(int(np.ceil(lo0 - g0)), 0)
                a1 = min(int(np.floor(hi0 + g0)), tx - 1)
                b0 = max(int(np.ceil(lo1 - g1)), 0)
                b1 = min(int(np.floor(hi1 + g1)), ty - 1)
                c0 = max(int(np.ceil(lo2 - g2)), 0)
                c1 = min(int(np.floor(hi2 + g2)), tz - 1)
                if a1 < a0 or b1 < b0 or c1 < c0:
                    continue
                if a1 - a0 > max_extent or b1 - b0 > max_extent or c1 - c0 > max_extent:
                    for dj in range(2):
                        for di in range(2):
                            for t in (ta, tb):
                                v = t[j + dj, i + di]
                                _mark8_flat(
                                    int(np.floor(v[0])), int(np.floor(v[1])), int(np.floor(v[2])), cover, tx, ty, tz
                                )
                    if use_prio and pcol[i] + pcol[i + 1] > 0:
                        # a preferred preimage may lie anywhere in the torn cell: its whole grown box may restart
                        for c in range(c0, c1 + 1):
                            for b in range(b0, b1 + 1):
                                for a in range(a0, a1 + 1):
                                    priocov[(c * ty + b) * tx + a] = 1
                    continue
                if border_jk or i == 0 or i == nx - 2:
                    n_planes = 0
                    for axis in range(3):
                        at = i if axis == 0 else (j if axis == 1 else k)
                        last = (nx if axis == 0 else (ny if axis == 1 else nz)) - 2
                        for side in range(2):
                            if at == (last if side else 0):
                                n0, n1, n2, h = _face_plane(fwd, k, j, i, axis, side)
                                planes[n_planes, 0] = n0
                                planes[n_planes, 1] = n1
                                planes[n_planes, 2] = n2
                                planes[n_planes, 3] = h + tol * (1.0 + 1e-9) + 1e-9 * abs(h)  # float64 rounding
                                n_planes += 1
                    _mark_box_planes(cover, tx, ty, tz, a0, a1, b0, b1, c0, c1, tgt_a, planes, n_planes)
                else:
                    _mark_box(cover, tx, ty, tz, a0, a1, b0, b1, c0, c1)
                if use_prio:
                    n_prio = pcol[i] + pcol[i + 1]
                    if n_prio == 8:
                        _mark_box(priocov, tx, ty, tz, a0, a1, b0, b1, c0, c1)
                    elif n_prio:
                        _mark_prio_octants(ta, tb, i, j, k, prio, g0, g1, g2, tx, ty, tz, priocov, hp)


@nb.njit(cache=True, parallel=True)
def _landing(fwd, tgt_w, tgt_a, prio, use_prio, max_extent, tol, n_chunks, tshape, cover, occ, priocov, guess):
    """Where the template voxels land on the target grid (``tshape``): the arrays the solver starts from.

    * ``cover`` (flat): every target voxel within ``tol`` (mm) of a template cell's
      forward image — a superset of the trilinear forward map's image, so a voxel left unmarked has no preimage,
      and every voxel whose Newton solve can converge (``|F(x) − y| ≤ tol``) is marked, except inside the
      image of a torn cell (below).  A cell's image lies in
      its 8 forward-mapped corners' convex hull: the cell marks the voxels of that hull's bounding box grown by
      ``tol``, and a cell on the template box's border only those on the inner side (within ``tol``) of the
      plane of each border face (``_face_plane``), which keeps the posed box's outside unmarked.  A cell wider
      than ``max_extent`` voxels (torn apart across a fold) marks the 8 target voxels around each of its corners
      instead, and, with ``use_prio`` and a preferred corner, its whole grown box in ``priocov``.
    * ``occ`` (with ``use_prio``): the 8 target voxels around the forward position of every template voxel with
      ``prio`` set.
    * ``priocov`` (with ``use_prio``; flat): every target voxel within ``tol`` of the image of the
      template points whose nearest voxel has ``prio`` set (the octants of the cells' preferred corners,
      ``_mark_prio_octants``): outside it no preferred preimage can converge.
    * ``guess`` (flat, -1 where no template voxel lands): :func:`_scatter_guess`.

    Task 0 is the serial guess; tasks 1 … ``n_chunks`` cut the template's slabs into runs for the rest, every
    write of which is a 1: the result does not depend on the number of tasks nor on the order they run in.
    """
    nz = fwd.shape[0]
    for task in nb.prange(n_chunks + 1):
        if task == 0:
            _scatter_guess(fwd, tgt_w, prio, use_prio, tshape, guess)
        else:
            chunk = task - 1
            _cover_slabs(
                fwd,
                tgt_w,
                tgt_a,
                prio,
                use_prio,
                max_extent,
                tol,
                chunk * nz // n_chunks,
                (chunk + 1) * nz // n_chunks,
                tshape,
                cover,
                occ,
                priocov,
            )


@nb.njit(cache=True, inline="always")
def _cand_point(cands, c, u0, u1, u2, nx, ny, nz):
    """Candidate ``c`` applied to (u0, u1, u2) (a target index or a world point), clamped into the grid."""
    x0 = cands[c, 0, 0] * u0 + cands[c, 0, 1] * u1 + cands[c, 0, 2] * u2 + cands[c, 0, 3]
    x1 = cands[c, 1, 0] * u0 + cands[c, 1, 1] * u1 + cands[c, 1, 2] * u2 + cands[c, 1, 3]
    x2 = cands[c, 2, 0] * u0 + cands[c, 2, 1] * u1 + cands[c, 2, 2] * u2 + cands[c, 2, 3]
    return min(max(x0, 0.0), nx - 1.0), min(max(x1, 0.0), ny - 1.0), min(max(x2, 0.0), nz - 1.0)


@nb.njit(cache=True)
def _restart(fwd, cands, u0, u1, u2, y0, y1, y2, tol, max_iter, max_step, n_try, prio, need_prio, x0, x1, x2, cres):
    """Newton from the ``n_try`` candidates of smallest residual ``|F(x_c) − y|``, best first.

    Returns (residual, det, x, J): the best result (``x`` as given if none is kept) and the Jacobian of the
    last evaluation.  With ``need_prio`` only a converged solution where ``prio`` is set is kept (residual
    ``inf`` if there is none).
    """
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    nc = cands.shape[0]
    j00 = j01 = j02 = j10 = j11 = j12 = j20 = j21 = j22 = 0.0
    for c in range(nc):
        b0, b1, b2 = _cand_point(cands, c, u0, u1, u2, nx, ny, nz)
        f0, f1, f2, j00, j01, j02, j10, j11, j12, j20, j21, j22 = _eval(fwd, b0, b1, b2)
        cres[c] = (f0 - y0) ** 2 + (f1 - y1) ** 2 + (f2 - y2) ** 2
    best = np.inf
    bdet = 0.0
    for _ in range(min(n_try, nc)):
        c = 0
        for q in range(1, nc):
            if cres[q] < cres[c]:
                c = q
        if cres[c] == np.inf:
            break
        cres[c] = np.inf  # used
        b0, b1, b2 = _cand_point(cands, c, u0, u1, u2, nx, ny, nz)
        r2, d2, b0, b1, b2, j00, j01, j02, j10, j11, j12, j20, j21, j22 = _newton(
            fwd, y0, y1, y2, b0, b1, b2, tol, max_iter, max_step
        )
        if need_prio:
            if r2 <= tol and _prio_at(prio, b0, b1, b2) != 0:
                return r2, d2, b0, b1, b2, j00, j01, j02, j10, j11, j12, j20, j21, j22
            continue
        if r2 < best:
            best = r2
            bdet = d2
            x0 = b0
            x1 = b1
            x2 = b2
        if r2 <= tol:
            break
    return best, bdet, x0, x1, x2, j00, j01, j02, j10, j11, j12, j20, j21, j22


@nb.njit(cache=True, parallel=True)
def backward_kernel(
    fwd, tgt_a, cands, tol, max_iter, max_step, n_restarts, prio, occ, priocov, cover, guess, out_x, out_res, out_status
):
    """For every target voxel (rows in parallel) solve F(x) = y; x in template continuous index (i, j, k).

    The compiled kernel of :func:`backward_map` (which prepares its arguments).

    Each solve starts from the previous voxel's answer in the row, moved by the local inverse
    Jacobian times the step to this voxel (one Newton evaluation usually suffices); the first voxel
    of a row, and any voxel where that fails, starts from the template voxel that landed nearest
    (``guess``, flat template indices from ``_landing``), then from the candidates (``_restart``).  ``prio``
    (template grid, uint8) and ``occ`` (target grid) implement the preference for body preimages:
    where ``occ`` is set and the solution found lies where ``prio`` is 0, the candidates are
    tried for a converged solution with ``prio`` 1 — unless ``priocov`` says none can converge there.
    Target voxels no template cell's image comes within ``tol`` of (``cover`` 0) are outside the
    forward map's image: no solve there.
    """
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    tz, ty, tx = out_x.shape[0], out_x.shape[1], out_x.shape[2]
    nc = cands.shape[0]
    use_prio = prio.shape[0] == fwd.shape[0]
    s0 = tgt_a[0, 0]  # the step Δy along a row
    s1 = tgt_a[1, 0]
    s2 = tgt_a[2, 0]
    for row in nb.prange(tz * ty):
        kk = row // ty
        jj = row % ty
        cres = np.empty(nc)
        have = False
        x0 = x1 = x2 = 0.0
        # J at the previous voxel's solution (the predictor's), and at the last evaluation
        l00 = l01 = l02 = l10 = l11 = l12 = l20 = l21 = l22 = 0.0
        ldet = 0.0
        j00 = j01 = j02 = j10 = j11 = j12 = j20 = j21 = j22 = 0.0
        for ii in range(tx):
            y0 = tgt_a[0, 0] * ii + tgt_a[0, 1] * jj + tgt_a[0, 2] * kk + tgt_a[0, 3]
            y1 = tgt_a[1, 0] * ii + tgt_a[1, 1] * jj + tgt_a[1, 2] * kk + tgt_a[1, 3]
            y2 = tgt_a[2, 0] * ii + tgt_a[2, 1] * jj + tgt_a[2, 2] * kk + tgt_a[2, 3]
            if cover[kk, jj, ii] == 0:
                # no cell's image comes within tol of y: no preimage (the fill value)
                b0, b1, b2 = _cand_point(cands, 0, ii, jj, kk, nx, ny, nz)
                out_x[kk, jj, ii, 0] = b0
                out_x[kk, jj, ii, 1] = b1
                out_x[kk, jj, ii, 2] = b2
                out_res[kk, jj, ii] = np.inf
                out_status[kk, jj, ii] = 3
                have = False
                continue
            occupied = (not use_prio) or occ[kk, jj, ii] != 0
            res = np.inf
            det = 0.0
            if have:
                # predictor: x += J⁻¹ Δy with J at the previous solution and Δy the step along the row
                dj = ldet  # det J at the previous solution
                if dj != 0.0:
                    d0, d1, d2 = _solve3(l00, l01, l02, l10, l11, l12, l20, l21, l22, 1.0 / dj, s0, s1, s2)
                    x0 += d0
                    x1 += d1
                    x2 += d2
                    x0 = min(max(x0, 0.0), nx - 1.0)
                    x1 = min(max(x1, 0.0), ny - 1.0)
                    x2 = min(max(x2, 0.0), nz - 1.0)
                res, det, x0, x1, x2, j00, j01, j02, j10, j11, j12, j20, j21, j22 = _newton(
                    fwd, y0, y1, y2, x0, x1, x2, tol, max_iter, max_step
                )
            if res > tol and guess[kk, jj, ii] >= 0:
                g = guess[kk, jj, ii]
                r2, d2, b0, b1, b2, j00, j01, j02, j10, j11, j12, j20, j21, j22 = _newton(
                    fwd,
                    y0,
                    y1,
                    y2,
                    float(g % nx),
                    float((g // nx) % ny),
                    float(g // (nx * ny)),
                    tol,
                    max_iter,
                    max_step,
                )
                if r2 < res:
                    x0 = b0
                    x1 = b1
                    x2 = b2
                    res = r2
                    det = d2
            if res > tol:
                # far from the posed body one restart is enough: whatever is found there is air
                r2, d2, b0, b1, b2, j00, j01, j02, j10, j11, j12, j20, j21, j22 = _restart(
                    fwd,
                    cands,
                    ii,
                    jj,
                    kk,
                    y0,
                    y1,
                    y2,
                    tol,
                    max_iter,
                    max_step,
                    n_restarts if occupied else 1,
                    prio,
                    False,
                    x0,
                    x1,
                    x2,
                    cres,
                )
                if r2 < res:
                    x0 = b0
                    x1 = b1
                    x2 = b2
                    res = r2
                    det = d2
            if (
                use_prio
                and occ[kk, jj, ii] != 0
                and priocov[kk, jj, ii] != 0
                and res <= tol
                and _prio_at(prio, x0, x1, x2) == 0
            ):
                r2, d2, b0, b1, b2, m00, m01, m02, m10, m11, m12, m20, m21, m22 = _restart(
                    fwd,
                    cands,
                    ii,
                    jj,
                    kk,
                    y0,
                    y1,
                    y2,
                    tol,
                    max_iter,
                    max_step,
                    n_restarts,
                    prio,
                    True,
                    x0,
                    x1,
                    x2,
                    cres,
                )
                if r2 <= tol:  # else x and its Jacobian stay
                    x0 = b0
                    x1 = b1
                    x2 = b2
                    res = r2
                    det = d2
                    j00, j01, j02, j10, j11, j12, j20, j21, j22 = m00, m01, m02, m10, m11, m12, m20, m21, m22
            out_x[kk, jj, ii, 0] = x0
            out_x[kk, jj, ii, 1] = x1
            out_x[kk, jj, ii, 2] = x2
            out_res[kk, jj, ii] = res
            if res <= tol:
                out_status[kk, jj, ii] = 0 if det > 0.0 else 1
                have = True
                # J(x): every solve above stops right after evaluating at its answer
                l00, l01, l02, l10, l11, l12, l20, l21, l22 = j00, j01, j02, j10, j11, j12, j20, j21, j22
                ldet = det
            elif _on_border(x0, x1, x2, nx, ny, nz):
                out_status[kk, jj, ii] = 3
                have = False
            else:
                out_status[kk, jj, ii] = 2
                have = False


@nb.njit(cache=True, parallel=True)
def _points_kernel(fwd, pts, cands, tol, max_iter, max_step, n_restarts, out_x, out_res, out_status):
    """As :func:`backward_kernel` for arbitrary world points (candidates map world → template index)."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    nc = cands.shape[0]
    no_prio = np.zeros((1, 1, 1), dtype=np.uint8)
    for n in nb.prange(pts.shape[0]):
        cres = np.empty(nc)
        y0 = np.float64(pts[n, 0])
        y1 = np.float64(pts[n, 1])
        y2 = np.float64(pts[n, 2])
        best, bdet, x0, x1, x2, _, _, _, _, _, _, _, _, _ = _restart(
            fwd,
            cands,
            y0,
            y1,
            y2,
            y0,
            y1,
            y2,
            tol,
            max_iter,
            max_step,
            n_restarts,
            no_prio,
            False,
            0.0,
            0.0,
            0.0,
            cres,
        )
        out_x[n, 0] = x0
        out_x[n, 1] = x1
        out_x[n, 2] = x2
        out_res[n] = best
        if best <= tol:
            out_status[n] = 0 if bdet > 0.0 else 1
        else:
            out_status[n] = 3 if _on_border(x0, x1, x2, nx, ny, nz) else 2


@dataclass
class BackwardMap:
    """Template position of every target voxel, and how well it was found.

    ``template_index`` is the continuous template index ``(i, j, k)`` per
    target voxel ``(nz, ny, nx, 3)``; ``residual_mm`` is ``|F(x) − y|``;
    ``status`` holds :data:`OK`, :data:`FOLDED`, :data:`NOT_CONVERGED` or
    :data:`OUTSIDE`.
    """

    template_geometry: GridGeometry
    target_geometry: GridGeometry
    template_index: np.ndarray
    residual_mm: np.ndarray
    status: np.ndarray

    def template_positions(self) -> np.ndarray:
        """World (mm) template position of every target voxel, ``(nz, ny, nx, 3)``."""
        return self.template_geometry.index_to_world(self.template_index)

    def scan_to_template(self) -> Volume:
        """The backward map as a displacement field on the target grid (template position − voxel, mm).

        The convention of the phantoms' truth correspondence, usable by
        ``sitk.DisplacementFieldTransform``.  Voxels ``OUTSIDE`` the template
        keep their (clamped) best position.
        """
        pos = self.template_positions()
        return Volume((pos - self.target_geometry.world_coordinates()).astype(np.float32), self.target_geometry)

    def summary(self) -> dict:
        n = int(self.status.size)
        out = {f"n_{name}": int(np.sum(self.status == code)) for code, name in STATUS_NAMES.items()}
        out["n_voxels"] = n
        good = self.status <= FOLDED
        out["max_residual_mm"] = float(self.residual_mm[good].max()) if good.any() else 0.0
        out["fraction_folded"] = out["n_folded"] / n if n else 0.0
        return out


def _orient_status(status: np.ndarray, template: GridGeometry) -> None:
    """The kernels test ``det ∂F/∂(i, j, k) > 0`` in *index* space; a template grid whose direction is a
    reflection flips that sign, so OK and FOLDED swap back here (in place)."""
    if np.linalg.det(template.direction_matrix) < 0:
        ok, folded = status == OK, status == FOLDED
        status[ok] = FOLDED
        status[folded] = OK


def _check_solver_args(max_iter, n_restarts, tol_voxels) -> None:
    if int(max_iter) < 1 or int(n_restarts) < 1:
        raise ValueError(f"max_iter and n_restarts must be at least 1, got {max_iter} and {n_restarts}")
    if not tol_voxels > 0:
        raise ValueError(f"tol_voxels must be positive, got {tol_voxels}")


def _candidates(template: GridGeometry, target: GridGeometry, transforms) -> np.ndarray:
    """Matrices target index → template index for the inverse of each transform (plus the identity)."""
    w = template.world_to_index_matrix
    a = target.index_to_world_matrix
    mats = [np.eye(4)]
    if transforms is not None:
        for t in np.asarray(transforms, dtype=np.float64).reshape(-1, 4, 4):
            mats.append(np.linalg.inv(t))
    out = np.stack([(w @ m @ a)[:3] for m in mats])
    # drop duplicates (e.g. several bones that have not moved)
    _, keep = np.unique(np.round(out, 9).reshape(len(out), -1), axis=0, return_index=True)
    return np.ascontiguousarray(out[np.sort(keep)])


def backward_map(
    forward_positions,
    template_geometry: GridGeometry,
    target_geometry: GridGeometry | None = None,
    *,
    transforms=None,
    prefer=None,
    tol_voxels: float = 1e-2,
    max_iter: int = 12,
    n_restarts: int = 4,
) -> BackwardMap:
    """Invert a forward map given by the posed positions of every template voxel.

    Parameters
    ----------
    forward_positions : (nz, ny, nx, 3) array
        World (mm) position that each template voxel moves to.
    template_geometry, target_geometry : GridGeometry
        The template's grid, and the grid to resample onto (default: the
        template's).
    transforms : (n, 4, 4), optional
        The bones' template → target transforms: their inverses seed the
        Newton solves (see the module docstring).  Without them only the
        identity is tried, which suffices for small deformations.
    prefer : (nz, ny, nx) bool array on the template grid, optional
        Where the forward map is not one-to-one (linear blends fold, and far
        air swept by a large rotation can land on the posed body), several
        template points map to one target voxel.  With ``prefer`` (e.g. the
        template's body mask), a target voxel reached by a preferred voxel
        (its forward position splatted to the 8 surrounding target voxels)
        takes a preferred preimage when Newton finds
        one from the candidates: tissue, not air, fills the posed body.  The
        candidates are tried only where a preferred part of a cell's image
        comes within the tolerance (``priocov``).
    tol_voxels : float
        Convergence tolerance on ``|F(x) − y|``, in units of the smallest
        template spacing.
    """
    fwd = np.ascontiguousarray(forward_positions, dtype=np.float32)
    if fwd.shape != template_geometry.array_shape + (3,):
        raise ValueError(
            f"forward_positions must be {template_geometry.array_shape + (3,)} (the template grid "
            f"{template_geometry.describe()}, components x, y, z), got {fwd.shape}"
        )
    if min(template_geometry.size) < 2:
        raise ValueError("the template grid needs at least 2 voxels along each axis")
    _check_solver_args(max_iter, n_restarts, tol_voxels)
    target = template_geometry if target_geometry is None else target_geometry
    cands = _candidates(template_geometry, target, transforms)
    tol = float(tol_voxels) * min(template_geometry.spacing)
    shape = target.array_shape
    out_x = np.empty(shape + (3,), dtype=np.float32)
    out_res = np.empty(shape, dtype=np.float32)
    out_status = np.empty(shape, dtype=np.uint8)
    tgt_a = np.ascontiguousarray(target.index_to_world_matrix[:3])
    tgt_w = np.ascontiguousarray(target.world_to_index_matrix[:3])
    if prefer is not None:
        prio = np.ascontiguousarray(prefer)
        # a bool or uint8 mask is not copied
        prio = prio.view(np.uint8) if prio.dtype == np.bool_ else prio.astype(np.uint8, copy=False)
        if prio.shape != template_geometry.array_shape:
            raise ValueError(
                f"prefer must be a mask on the template grid {template_geometry.array_shape}, got {prio.shape}"
            )
        occ = np.zeros(shape, dtype=np.uint8)
        priocov = np.zeros(shape, dtype=np.uint8)
    else:
        prio = np.zeros((1, 1, 1), dtype=np.uint8)
        occ = np.zeros((1, 1, 1), dtype=np.uint8)
        priocov = np.zeros((1, 1, 1), dtype=np.uint8)
    cover = np.zeros(shape, dtype=np.uint8)
    # a template voxel's flat index (int32 when it fits: half the memory traffic)
    guess = np.full(shape, -1, dtype=np.int32 if template_geometry.n_voxels < 2**31 else np.int64)
    # tasks of uneven cost (the serial guess, runs of slabs): threads take one at a time
    chunk = nb.set_parallel_chunksize(1)
    try:
        _landing(
            fwd,
            tgt_w,
            tgt_a,
            prio,
            prefer is not None,
            _max_extent(template_geometry, target),
            tol,
            min(fwd.shape[0], 4 * nb.get_num_threads()),
            shape,
            cover.reshape(-1),
            occ,
            priocov.reshape(-1),
            guess.reshape(-1),
        )
    finally:
        nb.set_parallel_chunksize(chunk)
    # rows cost unevenly (the body is not spread evenly over the grid): threads take 8 rows at a time
    chunk = nb.set_parallel_chunksize(8)
    try:
        backward_kernel(
            fwd,
            tgt_a,
            cands,
            tol,
            int(max_iter),
            2.0,
            int(n_restarts),
            prio,
            occ,
            priocov,
            cover,
            guess,
            out_x,
            out_res,
            out_status,
        )
    finally:
        nb.set_parallel_chunksize(chunk)
    _orient_status(out_status, template_geometry)
    return BackwardMap(template_geometry, target, out_x, out_res, out_status)


def _max_extent(template: GridGeometry, target: GridGeometry) -> int:
    """The widest cell image (target voxels a side) :func:`_landing` covers whole: a cell torn wider (across a
    fold) marks only the voxels around its corners.  Scaled by the resolution ratio, so that an upsampling target
    (a fine grid) still covers the undeformed cells whole."""
    return int(np.ceil(16 * max(1.0, max(template.spacing) / min(target.spacing))))


@nb.njit(cache=True, parallel=True)
def _guess_kernel(fwd, pts, guesses, tol, max_iter, max_step, out_x, out_res, out_status):
    """Newton from explicit guesses (template index) for each world point; keeps the best."""
    for n in nb.prange(pts.shape[0]):
        y0 = np.float64(pts[n, 0])
        y1 = np.float64(pts[n, 1])
        y2 = np.float64(pts[n, 2])
        best = out_res[n]
        bdet = 1.0
        improved = False
        for g in range(guesses.shape[1]):
            r2, d2, b0, b1, b2, _, _, _, _, _, _, _, _, _ = _newton(
                fwd, y0, y1, y2, guesses[n, g, 0], guesses[n, g, 1], guesses[n, g, 2], tol, max_iter, max_step
            )
            if r2 < best:
                best = r2
                bdet = d2
                improved = True
                out_x[n, 0] = b0
                out_x[n, 1] = b1
                out_x[n, 2] = b2
            if r2 <= tol:
                break
        if improved:
            out_res[n] = best
            if best <= tol:
                out_status[n] = 0 if bdet > 0.0 else 1


def _nearest_restarts(fwd, geometry: GridGeometry, x, res, status, pts_world, tol, max_iter, k: int = 8, prefer=None):
    """Retry NOT_CONVERGED points from the template voxels whose forward positions are nearest (cKDTree).

    With ``prefer`` only the preferred template voxels' positions are searched (a smaller tree).
    """
    from scipy.spatial import cKDTree

    bad = np.nonzero(status == NOT_CONVERGED)[0]
    if not bad.size:
        return
    flat = fwd.reshape(-1, 3)
    ids = np.arange(len(flat)) if prefer is None else np.nonzero(np.asarray(prefer).reshape(-1))[0]
    if not ids.size:
        return
    tree = cKDTree(flat[ids])
    _, nn = tree.query(pts_world[bad], k=min(k, len(ids)), workers=-1)
    nn = ids[np.asarray(nn).reshape(len(bad), -1)]
    nz, ny, nx = geometry.array_shape
    kk, jj, ii = np.unravel_index(nn, (nz, ny, nx))
    guesses = np.ascontiguousarray(np.stack([ii, jj, kk], -1).astype(np.float64))
    bx = np.ascontiguousarray(x[bad])
    br = np.ascontiguousarray(res[bad])
    bs = np.ascontiguousarray(status[bad])
    _guess_kernel(fwd, np.ascontiguousarray(pts_world[bad]), guesses, tol, max_iter, 2.0, bx, br, bs)
    x[bad], res[bad], status[bad] = bx, br, bs


def backward_points(
    forward_positions,
    template_geometry: GridGeometry,
    points,
    *,
    transforms=None,
    tol_voxels: float = 1e-2,
    max_iter: int = 12,
    n_restarts: int = 4,
):
    """Invert the forward map at arbitrary world points ``(n, 3)``.

    Returns ``(template world positions (n, 3), residual_mm (n,), status (n,))``;
    see :func:`backward_map` for the parameters and the status codes.
    """
    fwd = np.ascontiguousarray(forward_positions, dtype=np.float32)
    if fwd.shape != template_geometry.array_shape + (3,):
        raise ValueError(f"forward_positions must be {template_geometry.array_shape + (3,)}, got {fwd.shape}")
    if min(template_geometry.size) < 2:
        raise ValueError("the template grid needs at least 2 voxels along each axis")
    _check_solver_args(max_iter, n_restarts, tol_voxels)
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    world = GridGeometry((1, 1, 1), (1.0, 1.0, 1.0))  # candidates act on world points: identity "grid"
    cands = _candidates(template_geometry, world, transforms)
    tol = float(tol_voxels) * min(template_geometry.spacing)
    x = np.zeros((len(pts), 3))
    res = np.empty(len(pts), dtype=np.float32)
    status = np.empty(len(pts), dtype=np.uint8)
    _points_kernel(fwd, pts, cands, tol, int(max_iter), 2.0, int(n_restarts), x, res, status)
    _nearest_restarts(fwd, template_geometry, x, res, status, pts, tol, int(max_iter))
    _orient_status(status, template_geometry)
    return template_geometry.index_to_world(x), res, status


#: the largest spread of the 8 coarse neighbours' preimages (per template axis, in the coarse target's largest
#: voxel sides) that is blended: a smooth map's neighbours lie about one voxel apart (√3 when turned); farther,
#: the inverse jumps there
MAX_SPREAD = 2.5


@nb.njit(cache=True, parallel=True)
def _blendable_cells(cx, cst, sp, limit_mm, ok):
    """``ok[c]`` for each coarse cell (lower corner ``c``): its 8 corners all converged (ok or folded) and their
    preimages lie within ``limit_mm`` of each other along every template axis (``sp``: the coarse template's
    spacing, so uneven spacings compare in mm) — else the inverse jumps inside it (curled fingers meeting, a
    fold's two sheets) and a blend would land between the sheets."""
    tz, ty, tx = cst.shape
    cz, cy, cx_ = ok.shape
    for kp in nb.prange(cz):
        kc = np.int64(kp)  # one integer type in the corner tuples below
        k1 = min(kc + 1, tz - 1)
        for jc in range(cy):
            j1 = min(jc + 1, ty - 1)
            for ic in range(cx_):
                i1 = min(ic + 1, tx - 1)
                good = True
                for kk in (kc, k1):
                    for jj in (jc, j1):
                        for ii in (ic, i1):
                            if cst[kk, jj, ii] > 1:
                                good = False
                if good:
                    for c in range(3):
                        lo = cx[kc, jc, ic, c]
                        hi = lo
                        for kk in (kc, k1):
                            for jj in (jc, j1):
                                for ii in (ic, i1):
                                    v = cx[kk, jj, ii, c]
                                    lo = min(lo, v)
                                    hi = max(hi, v)
                        if (hi - lo) * sp[c] > limit_mm:
                            good = False
                ok[kc, jc, ic] = good


@nb.njit(cache=True, inline="always")
def _coarse_axis(i, f, n, cells):
    """Fine index ``i`` along an axis of ``n`` coarse voxels (``cells`` blending cells): the cell's lower
    corner, the blend weight (past 1 beyond the last coarse voxel: linear extrapolation), the upper corner,
    and the nearest coarse voxel."""
    x = i / f
    lo = min(int(x), cells - 1)
    w = x - lo if n > 1 else 0.0
    return lo, w, min(lo + 1, n - 1), min(int(x + 0.5), n - 1)


@nb.njit(cache=True, inline="always")
def _blend(cx, ok, f, k0, wz, k1, kn, j0, wy, j1, jn, i0, wx, i1, inn, c):
    """Component ``c`` of a fine voxel's template index (float32, as stored): f × the trilinear blend of the
    coarse template indices of its cell where the cell is blendable (``_blendable_cells``), else f × its
    nearest coarse voxel's."""
    if ok[k0, j0, i0]:
        a00 = cx[k0, j0, i0, c] + (cx[k0, j0, i1, c] - cx[k0, j0, i0, c]) * wx
        a10 = cx[k0, j1, i0, c] + (cx[k0, j1, i1, c] - cx[k0, j1, i0, c]) * wx
        a01 = cx[k1, j0, i0, c] + (cx[k1, j0, i1, c] - cx[k1, j0, i0, c]) * wx
        a11 = cx[k1, j1, i0, c] + (cx[k1, j1, i1, c] - cx[k1, j1, i0, c]) * wx
        b0 = a00 + (a10 - a00) * wy
        b1 = a01 + (a11 - a01) * wy
        return np.float32(f * (b0 + (b1 - b0) * wz))
    return np.float32(f * cx[kn, jn, inn, c])


@nb.njit(cache=True, parallel=True)
def _upsample_kernel(cx, cres, cst, ok, f, k_start, out_x, out_res, out_st):
    """Fine target voxel (i, j, k) ↔ coarse (i/f, j/f, k/f): the template index of :func:`_blend`, the largest
    residual of the cell's corners (the nearest one's where it is not blendable), the nearest one's status.
    Fine voxels past the last coarse one (a size not 1 + a multiple of f) extrapolate linearly from the last
    cell.  The outputs hold the fine slices ``k_start ≤ k < k_start + len(out)`` (a slab, or all)."""
    tz, ty, tx = cst.shape
    cz, cy, cx_ = ok.shape
    nz, ny, nx = out_st.shape
    for k in nb.prange(nz):
        k0, wz, k1, kn = _coarse_axis(np.int64(k_start + k), f, tz, cz)
        for j in range(ny):
            j0, wy, j1, jn = _coarse_axis(j, f, ty, cy)
            for i in range(nx):
                i0, wx, i1, inn = _coarse_axis(i, f, tx, cx_)
                for c in range(3):
                    out_x[k, j, i, c] = _blend(cx, ok, f, k0, wz, k1, kn, j0, wy, j1, jn, i0, wx, i1, inn, c)
                if ok[k0, j0, i0]:
                    r = 0.0
                    for kk in (k0, k1):
                        for jj in (j0, j1):
                            for ii in (i0, i1):
                                r = max(r, cres[kk, jj, ii])
                    out_res[k, j, i] = r
                else:
                    out_res[k, j, i] = cres[kn, jn, inn]
                out_st[k, j, i] = cst[kn, jn, inn]


@nb.njit(cache=True, parallel=True)
def _pull_kernel(cx, cst, ok, f, src, nx, ny, nz, order, fill, out):
    """``out`` (the fine target grid) = the template ``src`` (flat, ``nx × ny × nz``) sampled at each fine voxel's
    :func:`_blend` index, ``fill`` where the nearest coarse voxel is OUTSIDE: what sampling the fine map of
    :func:`_upsample_kernel` gives (the same arithmetic), without writing that map."""
    tz, ty, tx = cst.shape
    cz, cy, cx_ = ok.shape
    oz, oy, ox = out.shape
    for k in nb.prange(oz):
        k0, wz, k1, kn = _coarse_axis(np.int64(k), f, tz, cz)
        for j in range(oy):
            j0, wy, j1, jn = _coarse_axis(j, f, ty, cy)
            for i in range(ox):
                i0, wx, i1, inn = _coarse_axis(i, f, tx, cx_)
                if cst[kn, jn, inn] == OUTSIDE:
                    out[k, j, i] = fill
                else:
                    a = _blend(cx, ok, f, k0, wz, k1, kn, j0, wy, j1, jn, i0, wx, i1, inn, 0)
                    b = _blend(cx, ok, f, k0, wz, k1, kn, j0, wy, j1, jn, i0, wx, i1, inn, 1)
                    c = _blend(cx, ok, f, k0, wz, k1, kn, j0, wy, j1, jn, i0, wx, i1, inn, 2)
                    out[k, j, i] = interp_scalar(
                        src, nx, ny, nz, np.float64(a), np.float64(b), np.float64(c), order, fill
                    )


class CoarseBackwardMap:
    """A backward map solved on every ``factor``-th voxel of the grids, blended up to the fine grids on demand.

    ``coarse`` maps ``target.every(factor)`` to ``template.every(factor)``
    (:meth:`~deformation.geometry.GridGeometry.every`); each fine target voxel gets the trilinear
    blend of its 8 coarse neighbours' template positions where all of them
    converged (ok or folded) and lie within ``MAX_SPREAD`` coarse voxel
    sides of each other, else its nearest coarse voxel's position and status.
    ``residual_mm`` is the coarse solves' (the largest of the 8), and so is
    ``summary()["max_residual_mm"]``: the blend's own error is not measured —
    exact where the map is affine (a bone's rigid motion), second order in the
    coarse spacing elsewhere.
    Solving 1/factor³ of the voxels makes the inverse that much cheaper in
    time and memory (``workbench deform --map-factor``); :meth:`pull` never
    makes the fine map (17 bytes a voxel), so a Kurihara-size CT (197 M
    voxels) is posed without its 3.3 GiB.
    """

    def __init__(
        self,
        coarse: BackwardMap,
        factor: int,
        template_geometry: GridGeometry,
        target_geometry: GridGeometry | None = None,
    ):
        f = int(factor)
        target = template_geometry if target_geometry is None else target_geometry
        if not (
            coarse.template_geometry.is_close(template_geometry.every(f))
            and coarse.target_geometry.is_close(target.every(f))
        ):
            raise ValueError(f"the coarse map's grids are not {every_nth(f)} voxel of the template and target grids")
        self.coarse, self.factor = coarse, f
        self.template_geometry, self.target_geometry = template_geometry, target
        self._cx = np.ascontiguousarray(coarse.template_index, dtype=np.float32)
        self._cres = np.ascontiguousarray(coarse.residual_mm, dtype=np.float32)
        self._ok = np.empty(tuple(max(n - 1, 1) for n in coarse.status.shape), dtype=np.bool_)
        # the spread limit in mm: MAX_SPREAD of the coarse target's largest voxel side
        limit_mm = MAX_SPREAD * float(max(coarse.target_geometry.spacing))
        _blendable_cells(
            self._cx, coarse.status, np.asarray(coarse.template_geometry.spacing, dtype=np.float64), limit_mm, self._ok
        )

    def rows(self, k0: int, k1: int) -> BackwardMap:
        """The fine backward map of the target's slices ``k0 ≤ k < k1`` (a slab of the target grid)."""
        g = self.target_geometry
        nx, ny, nz = g.size
        if not 0 <= k0 < k1 <= nz:
            raise ValueError(f"slices {k0}..{k1} outside the target's {nz}")
        shape = (k1 - k0, ny, nx)
        out_x = np.empty(shape + (3,), dtype=np.float32)
        out_res = np.empty(shape, dtype=np.float32)
        out_st = np.empty(shape, dtype=np.uint8)
        _upsample_kernel(self._cx, self._cres, self.coarse.status, self._ok, self.factor, k0, out_x, out_res, out_st)
        sub = g if (k0, k1) == (0, nz) else g.crop((0, 0, k0), (nx, ny, k1))
        return BackwardMap(self.template_geometry, sub, out_x, out_res, out_st)

    def unblended(self, k0: int, k1: int) -> np.ndarray:
        """Fine target voxels of the slices ``k0 ≤ k < k1`` whose cell is not blendable (its corners'
        preimages spread or one did not converge: ``_blendable_cells``), which :meth:`rows` gives their
        nearest coarse voxel's position: bool ``(k1 − k0, ny, nx)``."""
        nx, ny, _ = self.target_geometry.size
        cz, cy, cx = self._ok.shape
        f = self.factor
        # the cell of a fine voxel, as _coarse_axis finds it
        kz, ky, kx = (np.minimum(np.arange(a, b) // f, n - 1) for a, b, n in ((k0, k1, cz), (0, ny, cy), (0, nx, cx)))
        return ~self._ok[np.ix_(kz, ky, kx)]

    def full(self) -> BackwardMap:
        """The fine backward map of the whole target grid (17 bytes a voxel)."""
        return self.rows(0, self.target_geometry.size[2])

    def scan_to_template(self) -> Volume:
        """:meth:`BackwardMap.scan_to_template` of the fine map, made a slab of
        :data:`~deformation.geometry.SLAB_VOXELS` at a time (12 bytes a fine voxel held, not the 17 of the fine map
        and the 24 of its world coordinates)."""
        g = self.target_geometry
        nx, ny, nz = g.size
        out = np.empty(g.array_shape + (3,), dtype=np.float32)
        for k0, k1 in slabs(nz, nx * ny, SLAB_VOXELS):  # the module's name: tests make it small
            pos = self.template_geometry.index_to_world(self.rows(k0, k1).template_index)
            out[k0:k1] = pos - g.world_coordinates(z_slice=slice(k0, k1))  # the full grid's coordinates: same bits
        return Volume(out, g)

    def summary(self) -> dict:
        """``BackwardMap.summary()`` of the coarse solves (counts of coarse voxels), with the factor."""
        return {**self.coarse.summary(), "map_factor": self.factor}

    def pull(self, volume: Volume, *, labels: bool = False, fill=0.0) -> Volume:
        """:func:`resample_forward` through the fine map without making it (one kernel blends each fine voxel's
        index and samples there: the same voxels as ``resample_forward(self.full(), volume)``, bit for bit,
        holding only the output)."""
        src = _source(self, volume, labels)
        order = 0 if labels else 1
        odt = output_dtype(src.dtype, order)
        flat, (nx, ny, nz), _ = flat_data(src)
        out = np.empty(self.target_geometry.array_shape, dtype=np.uint8 if odt == np.bool_ else odt)
        _pull_kernel(
            self._cx, self.coarse.status, self._ok, self.factor, flat, nx, ny, nz, order, fill_value(fill, odt), out
        )
        return Volume(out.view(np.bool_) if odt == np.bool_ else out, self.target_geometry)


def upsample_backward_map(
    coarse: BackwardMap, factor: int, template_geometry: GridGeometry, target_geometry: GridGeometry | None = None
) -> BackwardMap:
    """The fine backward map of a coarse one, all at once (:class:`CoarseBackwardMap` says how)."""
    return CoarseBackwardMap(coarse, factor, template_geometry, target_geometry).full()


def _source(bmap, volume: Volume, labels: bool) -> np.ndarray:
    """The template's voxels to pull through ``bmap`` (checked against its template grid; float32 intensities)."""
    if not volume.geometry.is_close(bmap.template_geometry):
        bmap.template_geometry.check_same(volume.geometry, names=("backward map's template", "volume"))
    if volume.is_vector:
        raise ValueError("resample_forward takes scalar volumes (resample each component separately)")
    src = np.asarray(volume.data)
    return src if labels else src.astype(np.float32, copy=False)


@nb.njit(cache=True, parallel=True)
def _pull_exact_kernel(x, status, src, nx, ny, nz, order, fill, out):
    """``out`` = the template ``src`` (flat, ``nx × ny × nz``) sampled at each target voxel's template index ``x``
    (nearest or trilinear, :func:`~deformation.fields.interpolate.interp_scalar`), ``fill`` where the voxel is
    OUTSIDE (no sample taken there)."""
    tz, ty, tx = status.shape
    for row in nb.prange(tz * ty):
        k = row // ty
        j = row - k * ty
        for i in range(tx):
            if status[k, j, i] == OUTSIDE:
                out[k, j, i] = fill
            else:
                out[k, j, i] = interp_scalar(
                    src,
                    nx,
                    ny,
                    nz,
                    np.float64(x[k, j, i, 0]),
                    np.float64(x[k, j, i, 1]),
                    np.float64(x[k, j, i, 2]),
                    order,
                    fill,
                )


def _pull(src: np.ndarray, bmap: BackwardMap, labels: bool, fill) -> np.ndarray:
    """``src`` sampled at ``bmap``'s template indices (what ``sample_array`` with the identity map gives, bit for
    bit), ``fill`` where the target voxel is OUTSIDE."""
    order = 0 if labels else 1
    odt = output_dtype(src.dtype, order)
    flat, (nx, ny, nz), _ = flat_data(src)
    out = np.empty(bmap.status.shape, dtype=np.uint8 if odt == np.bool_ else odt)
    x = np.ascontiguousarray(bmap.template_index)
    status = np.ascontiguousarray(bmap.status)
    _pull_exact_kernel(x, status, flat, nx, ny, nz, order, fill_value(fill, odt), out)
    return out.view(np.bool_) if odt == np.bool_ else out


def resample_forward(bmap: BackwardMap, volume: Volume, *, labels: bool = False, fill=0.0) -> Volume:
    """The template ``volume`` pulled onto the target grid through ``bmap`` (trilinear; nearest for labels)."""
    return Volume(_pull(_source(bmap, volume, labels), bmap, labels, fill), bmap.target_geometry)


def invert_scan_to_template(
    field: Volume,
    template_geometry: GridGeometry,
    *,
    transforms=None,
    prefer=None,
    forward=None,
    tol_mm: float | None = None,
) -> BackwardMap:
    """Invert a ``scan_to_template`` field: where every *template* voxel lies in the scan (the one inversion).

    ``field`` on the scan grid maps each scan voxel ``x`` to ``φ(x) = x +
    field(x)`` in the template.  The result's :meth:`BackwardMap.scan_to_template`
    is the ``template_to_scan`` field (scan position − template voxel, mm) on
    ``template_geometry``, and its ``status`` says where it was found
    (:data:`OK`, :data:`FOLDED`), where the inverse did not hold
    (:data:`NOT_CONVERGED`) and where the template voxel leaves the scan's
    field of view (:data:`OUTSIDE`).  EVD (Rhee Eq. 7) needs these
    template → scan positions.

    Two routes:

    * ``forward`` given — the registration started from an articulated map
      whose *forward* map ``F`` (template voxel → scan position, ``(nz, ny,
      nx, 3)`` on the template grid, e.g. VBD, Rhee Eq. 2) is known, and its
      steps were composed on the right, ``φ = F⁻¹ ∘ U`` (Rhee Algorithm 1,
      :mod:`registration.adaptive`).  Then ``U = F ∘ φ`` is a forward
      evaluation (no inversion), a near-identity one-to-one map of scan space
      (each step was guarded against folding), inverted by the fixed-point
      iteration of :func:`deformation.fields.displacement.invert`, and ``φ⁻¹ = U⁻¹ ∘ F``.
      The articulated part is inverted exactly by its own forward map; only
      the registration's small correction is inverted numerically.  Inverting
      ``φ`` as a whole instead is many-to-one wherever the start's backward
      map filled air with tissue (between the fingers), and picks the wrong
      sheet there.  A template voxel whose result does not map back to it
      within ``tol_mm`` (default: half the template's largest spacing; folds
      of ``F`` in a flexed crease) is marked :data:`NOT_CONVERGED`.
    * otherwise — ``φ`` itself is inverted by the Newton :func:`backward_map`
      onto ``template_geometry`` (a ground-truth field, or a registration
      without an articulated start); ``transforms`` (``(n, 4, 4)`` template
      → scan, e.g. the bones') seed the solves with their inverses, so large
      articulated motions converge, and ``prefer`` (a bool array on the
      *scan* grid) marks the scan voxels to prefer where several map to one
      template voxel.
    """
    g = field.geometry
    if forward is None:
        fwd = (np.asarray(field.data, np.float64) + g.world_coordinates()).astype(np.float32)
        inv = None if transforms is None else np.stack([np.linalg.inv(t) for t in np.asarray(transforms, float)])
        return backward_map(
            fwd, g, template_geometry, transforms=inv, prefer=None if prefer is None else np.asarray(prefer, bool)
        )
    from deformation.fields.displacement import invert
    from deformation.fields.interpolate import sample, sample_displaced_array

    f = np.asarray(forward, np.float64)
    if f.shape != template_geometry.array_shape + (3,):
        raise ValueError(
            f"forward must be (nz, ny, nx, 3) = {template_geometry.array_shape + (3,)} on the template "
            f"grid, got {f.shape}"
        )
    phi = np.asarray(field.data, np.float64)
    # U = F ∘ φ on the scan grid (F trilinear between template voxels; undefined where φ leaves the template grid)
    ux = sample_displaced_array(f, template_geometry.world_to_index_matrix, g, phi, 1, np.nan)
    u = ux - g.world_coordinates()
    u[~np.isfinite(u).all(axis=-1)] = 0.0  # outside the template: the identity
    w, _ = invert(Volume(u, g))
    pos = f + sample(w, f.reshape(-1, 3), order=1, fill=0.0).reshape(f.shape)  # φ⁻¹(v) = U⁻¹(F(v))
    back = pos + sample(field, pos.reshape(-1, 3), order=1, fill=0.0).reshape(f.shape)
    resid = np.linalg.norm(back - template_geometry.world_coordinates(), axis=-1)
    tol = 0.5 * max(template_geometry.spacing) if tol_mm is None else float(tol_mm)
    status = np.where(resid <= tol, OK, NOT_CONVERGED).astype(np.uint8)
    inside = g.contains_world(pos.reshape(-1, 3)).reshape(template_geometry.array_shape)
    status[~inside] = OUTSIDE
    return BackwardMap(g, template_geometry, g.world_to_index(pos.reshape(-1, 3)).reshape(f.shape), resid, status)
