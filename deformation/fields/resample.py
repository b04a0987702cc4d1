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
nearest (a serial, hence deterministic, splat), then from the candidates
``T_b⁻¹ y`` (each bone's inverse rigid transform, exact wherever tissue moves
with a bone).  Rows are independent: they run in parallel, deterministically.
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

from deformation.fields.interpolate import fill_value, flat_data, interp_scalar, output_dtype, sample_array
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
#: outside the template grid, or ``y`` lies in no template cell's forward bounding box (outside the forward
#: map's image, as where linear blending shrinks the air around a fist): the voxel gets the fill value.
OK, FOLDED, NOT_CONVERGED, OUTSIDE = 0, 1, 2, 3
STATUS_NAMES = {OK: "ok", FOLDED: "folded", NOT_CONVERGED: "not_converged", OUTSIDE: "outside"}


@nb.njit(cache=True, inline="always")
def _eval(fwd, x0, x1, x2, out, jac):
    """Trilinear F and its exact in-cell Jacobian at continuous template index (x0, x1, x2) = (i, j, k)."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    i0 = min(max(int(np.floor(x0)), 0), nx - 2)
    j0 = min(max(int(np.floor(x1)), 0), ny - 2)
    k0 = min(max(int(np.floor(x2)), 0), nz - 2)
    fx = x0 - i0
    fy = x1 - j0
    fz = x2 - k0
    for c in range(3):
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
        out[c] = b0 + (b1 - b0) * fz
        # derivatives along i, j, k
        dx00 = c100 - c000
        dx10 = c110 - c010
        dx01 = c101 - c001
        dx11 = c111 - c011
        d0 = dx00 + (dx10 - dx00) * fy
        d1 = dx01 + (dx11 - dx01) * fy
        jac[c, 0] = d0 + (d1 - d0) * fz
        e0 = a10 - a00
        e1 = a11 - a01
        jac[c, 1] = e0 + (e1 - e0) * fz
        jac[c, 2] = b1 - b0


@nb.njit(cache=True, inline="always")
def _det3(m):
    return (
        m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
        - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
        + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
    )


@nb.njit(cache=True, inline="always")
def _newton(fwd, y, x, tol, max_iter, max_step, f, jac):
    """Newton on F(x) = y from x (modified in place).  Returns (residual, det J at x)."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    lim0 = nx - 1.0
    lim1 = ny - 1.0
    lim2 = nz - 1.0
    res = np.inf
    det = 0.0
    pinned = 0
    for it in range(max_iter + 1):
        _eval(fwd, x[0], x[1], x[2], f, jac)
        r0 = y[0] - f[0]
        r1 = y[1] - f[1]
        r2 = y[2] - f[2]
        last = res
        res = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        det = _det3(jac)
        if res <= tol or it == max_iter or det == 0.0:
            break
        # stuck against the grid's edge without getting closer: the preimage is outside
        if _on_border(x, nx, ny, nz) and res > 0.5 * last:
            pinned += 1
            if pinned >= 2:
                break
        else:
            pinned = 0
        inv = 1.0 / det
        # δ = J⁻¹ r by the adjugate
        d0 = inv * (
            (jac[1, 1] * jac[2, 2] - jac[1, 2] * jac[2, 1]) * r0
            - (jac[0, 1] * jac[2, 2] - jac[0, 2] * jac[2, 1]) * r1
            + (jac[0, 1] * jac[1, 2] - jac[0, 2] * jac[1, 1]) * r2
        )
        d1 = inv * (
            -(jac[1, 0] * jac[2, 2] - jac[1, 2] * jac[2, 0]) * r0
            + (jac[0, 0] * jac[2, 2] - jac[0, 2] * jac[2, 0]) * r1
            - (jac[0, 0] * jac[1, 2] - jac[0, 2] * jac[1, 0]) * r2
        )
        d2 = inv * (
            (jac[1, 0] * jac[2, 1] - jac[1, 1] * jac[2, 0]) * r0
            - (jac[0, 0] * jac[2, 1] - jac[0, 1] * jac[2, 0]) * r1
            + (jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]) * r2
        )
        m = max(abs(d0), abs(d1), abs(d2))
        if m > max_step:
            sc = max_step / m
            d0 *= sc
            d1 *= sc
            d2 *= sc
        x[0] = min(max(x[0] + d0, 0.0), lim0)
        x[1] = min(max(x[1] + d1, 0.0), lim1)
        x[2] = min(max(x[2] + d2, 0.0), lim2)
    return res, det


@nb.njit(cache=True, inline="always")
def _on_border(x, nx, ny, nz):
    e = 1e-6
    return x[0] <= e or x[1] <= e or x[2] <= e or x[0] >= nx - 1 - e or x[1] >= ny - 1 - e or x[2] >= nz - 1 - e


@nb.njit(cache=True, inline="always")
def _prio_at(prio, x):
    nz, ny, nx = prio.shape
    i = min(max(int(np.floor(x[0] + 0.5)), 0), nx - 1)
    j = min(max(int(np.floor(x[1] + 0.5)), 0), ny - 1)
    k = min(max(int(np.floor(x[2] + 0.5)), 0), nz - 1)
    return prio[k, j, i]


@nb.njit(cache=True, parallel=True)
def _target_index(fwd, tgt_w, out):
    """Continuous target index of every template voxel's forward position (float32)."""
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    for k in nb.prange(nz):
        for j in range(ny):
            for i in range(nx):
                p0 = fwd[k, j, i, 0]
                p1 = fwd[k, j, i, 1]
                p2 = fwd[k, j, i, 2]
                for q in range(3):
                    out[k, j, i, q] = tgt_w[q, 0] * p0 + tgt_w[q, 1] * p1 + tgt_w[q, 2] * p2 + tgt_w[q, 3]


@nb.njit(cache=True, parallel=True)
def _splat(tidx, prio, use_prio, occ):
    """Mark the 8 target voxels around the forward position of every template voxel (with ``prio`` set).

    Marking the cell's 8 corners (not only the nearest voxel) leaves no hole where the forward map
    stretches space by less than 2×.  The race between threads is benign (every writer writes 1).
    """
    nz, ny, nx = tidx.shape[0], tidx.shape[1], tidx.shape[2]
    tz, ty, tx = occ.shape
    for k in nb.prange(nz):
        for j in range(ny):
            for i in range(nx):
                if use_prio and prio[k, j, i] == 0:
                    continue
                a = int(np.floor(tidx[k, j, i, 0]))
                b = int(np.floor(tidx[k, j, i, 1]))
                c = int(np.floor(tidx[k, j, i, 2]))
                for dc in range(2):
                    cc = c + dc
                    if cc < 0 or cc >= tz:
                        continue
                    for db in range(2):
                        bb = b + db
                        if bb < 0 or bb >= ty:
                            continue
                        for da in range(2):
                            aa = a + da
                            if 0 <= aa < tx:
                                occ[cc, bb, aa] = 1


@nb.njit(cache=True, parallel=True)
def _cover_cells(tidx, max_extent, cover):
    """Mark every target voxel inside the bounding box of each template cell's 8 forward-mapped corners.

    A superset of the image of the trilinear forward map (each cell's image lies in its corners'
    convex hull), so a voxel left unmarked has no preimage.  Cells wider than ``max_extent`` voxels
    (torn apart across a fold) are skipped; :func:`_splat` marks their corners' voxels.
    """
    nz, ny, nx = tidx.shape[0], tidx.shape[1], tidx.shape[2]
    tz, ty, tx = cover.shape
    for k in nb.prange(nz - 1):
        for j in range(ny - 1):
            for i in range(nx - 1):
                lo0 = hi0 = tidx[k, j, i, 0]
                lo1 = hi1 = tidx[k, j, i, 1]
                lo2 = hi2 = tidx[k, j, i, 2]
                for dk in range(2):
                    for dj in range(2):
                        for di in range(2):
                            v0 = tidx[k + dk, j + dj, i + di, 0]
                            v1 = tidx[k + dk, j + dj, i + di, 1]
                            v2 = tidx[k + dk, j + dj, i + di, 2]
                            lo0 = min(lo0, v0)
                            hi0 = max(hi0, v0)
                            lo1 = min(lo1, v1)
                            hi1 = max(hi1, v1)
                            lo2 = min(lo2, v2)
                            hi2 = max(hi2, v2)
                a0 = max(int(np.ceil(lo0)), 0)
                a1 = min(int(np.floor(hi0)), tx - 1)
                b0 = max(int(np.ceil(lo1)), 0)
                b1 = min(int(np.floor(hi1)), ty - 1)
                c0 = max(int(np.ceil(lo2)), 0)
                c1 = min(int(np.floor(hi2)), tz - 1)
                if a1 - a0 > max_extent or b1 - b0 > max_extent or c1 - c0 > max_extent:
                    continue
                for cc in range(c0, c1 + 1):
                    for bb in range(b0, b1 + 1):
                        for aa in range(a0, a1 + 1):
                            cover[cc, bb, aa] = 1


@nb.njit(cache=True)
def _scatter_guess(tidx, prio, use_prio, guess):
    """For each target voxel, a template voxel whose forward position is nearest to it (a Newton start).

    Serial and in increasing template order (the last writer wins), so the result is deterministic;
    with ``prio`` a second pass lets preferred (body) voxels overwrite the others.
    """
    nz, ny, nx = tidx.shape[0], tidx.shape[1], tidx.shape[2]
    tz, ty, tx = guess.shape
    for rep in range(2 if use_prio else 1):
        for k in range(nz):
            for j in range(ny):
                for i in range(nx):
                    if rep == 1 and prio[k, j, i] == 0:
                        continue
                    a = int(np.floor(tidx[k, j, i, 0] + 0.5))
                    b = int(np.floor(tidx[k, j, i, 1] + 0.5))
                    c = int(np.floor(tidx[k, j, i, 2] + 0.5))
                    if 0 <= a < tx and 0 <= b < ty and 0 <= c < tz:
                        guess[c, b, a] = (k * ny + j) * nx + i


@nb.njit(cache=True, inline="always")
def _cand_point(cands, c, u0, u1, u2, nx, ny, nz, xb):
    """Candidate ``c`` applied to (u0, u1, u2) (a target index or a world point), clamped into the grid."""
    for q in range(3):
        xb[q] = cands[c, q, 0] * u0 + cands[c, q, 1] * u1 + cands[c, q, 2] * u2 + cands[c, q, 3]
    xb[0] = min(max(xb[0], 0.0), nx - 1.0)
    xb[1] = min(max(xb[1], 0.0), ny - 1.0)
    xb[2] = min(max(xb[2], 0.0), nz - 1.0)


@nb.njit(cache=True)
def _restart(fwd, cands, u0, u1, u2, y, tol, max_iter, max_step, n_try, prio, need_prio, x, f, jac, xb, cres):
    """Newton from the ``n_try`` candidates of smallest residual ``|F(x_c) − y|``, best first.

    Keeps the best result in ``x``; returns (residual, det).  With ``need_prio`` only a converged
    solution where ``prio`` is set is accepted (and ``x`` is left alone if there is none).
    """
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    nc = cands.shape[0]
    for c in range(nc):
        _cand_point(cands, c, u0, u1, u2, nx, ny, nz, xb)
        _eval(fwd, xb[0], xb[1], xb[2], f, jac)
        cres[c] = (f[0] - y[0]) ** 2 + (f[1] - y[1]) ** 2 + (f[2] - y[2]) ** 2
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
        _cand_point(cands, c, u0, u1, u2, nx, ny, nz, xb)
        r2, d2 = _newton(fwd, y, xb, tol, max_iter, max_step, f, jac)
        if need_prio:
            if r2 <= tol and _prio_at(prio, xb) != 0:
                x[0] = xb[0]
                x[1] = xb[1]
                x[2] = xb[2]
                return r2, d2
            continue
        if r2 < best:
            best = r2
            bdet = d2
            x[0] = xb[0]
            x[1] = xb[1]
            x[2] = xb[2]
        if r2 <= tol:
            break
    return best, bdet


@nb.njit(cache=True, parallel=True)
def backward_kernel(
    fwd, tgt_a, cands, tol, max_iter, max_step, n_restarts, prio, occ, cover, guess, out_x, out_res, out_status
):
    """For every target voxel (rows in parallel) solve F(x) = y; x in template continuous index (i, j, k).

    The compiled kernel of :func:`backward_map` (which prepares its arguments).

    Each solve starts from the previous voxel's answer in the row, moved by the local inverse
    Jacobian times the step to this voxel (one Newton evaluation usually suffices); the first voxel
    of a row, and any voxel where that fails, starts from the template voxel that landed nearest
    (``guess``, ``_scatter_guess``), then from the candidates (``_restart``).  ``prio``
    (template grid, uint8) and ``occ`` (target grid) implement the preference for body preimages:
    where ``occ`` is set and the solution found lies where ``prio`` is 0, the candidates are
    tried for a converged solution with ``prio`` 1.  Target voxels that no template voxel reaches
    (``cover`` 0) are outside the forward map's image: no solve there.
    """
    nz, ny, nx = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    tz, ty, tx = out_x.shape[0], out_x.shape[1], out_x.shape[2]
    nc = cands.shape[0]
    use_prio = prio.shape[0] == fwd.shape[0]
    for row in nb.prange(tz * ty):
        kk = row // ty
        jj = row % ty
        y = np.empty(3)
        x = np.empty(3)
        xb = np.empty(3)
        f = np.empty(3)
        jac = np.empty((3, 3))
        xr = np.empty(3)
        cres = np.empty(nc)
        jl = np.empty((3, 3))
        have = False
        for ii in range(tx):
            for c in range(3):
                y[c] = tgt_a[c, 0] * ii + tgt_a[c, 1] * jj + tgt_a[c, 2] * kk + tgt_a[c, 3]
            if cover[kk, jj, ii] == 0:
                # no template voxel lands in the cells around y: no preimage (the fill value)
                _cand_point(cands, 0, ii, jj, kk, nx, ny, nz, xb)
                out_x[kk, jj, ii, 0] = xb[0]
                out_x[kk, jj, ii, 1] = xb[1]
                out_x[kk, jj, ii, 2] = xb[2]
                out_res[kk, jj, ii] = np.inf
                out_status[kk, jj, ii] = 3
                have = False
                continue
            occupied = (not use_prio) or occ[kk, jj, ii] != 0
            res = np.inf
            det = 0.0
            if have:
                # predictor: x += J⁻¹ Δy with J at the previous solution and Δy the step along the row
                dj = _det3(jl)
                if dj != 0.0:
                    inv = 1.0 / dj
                    r0 = tgt_a[0, 0]
                    r1 = tgt_a[1, 0]
                    r2 = tgt_a[2, 0]
                    x[0] += inv * (
                        (jl[1, 1] * jl[2, 2] - jl[1, 2] * jl[2, 1]) * r0
                        - (jl[0, 1] * jl[2, 2] - jl[0, 2] * jl[2, 1]) * r1
                        + (jl[0, 1] * jl[1, 2] - jl[0, 2] * jl[1, 1]) * r2
                    )
                    x[1] += inv * (
                        -(jl[1, 0] * jl[2, 2] - jl[1, 2] * jl[2, 0]) * r0
                        + (jl[0, 0] * jl[2, 2] - jl[0, 2] * jl[2, 0]) * r1
                        - (jl[0, 0] * jl[1, 2] - jl[0, 2] * jl[1, 0]) * r2
                    )
                    x[2] += inv * (
                        (jl[1, 0] * jl[2, 1] - jl[1, 1] * jl[2, 0]) * r0
                        - (jl[0, 0] * jl[2, 1] - jl[0, 1] * jl[2, 0]) * r1
                        + (jl[0, 0] * jl[1, 1] - jl[0, 1] * jl[1, 0]) * r2
                    )
                    x[0] = min(max(x[0], 0.0), nx - 1.0)
                    x[1] = min(max(x[1], 0.0), ny - 1.0)
                    x[2] = min(max(x[2], 0.0), nz - 1.0)
                res, det = _newton(fwd, y, x, tol, max_iter, max_step, f, jac)
            if res > tol and guess[kk, jj, ii] >= 0:
                g = guess[kk, jj, ii]
                xr[0] = g % nx
                xr[1] = (g // nx) % ny
                xr[2] = g // (nx * ny)
                r2, d2 = _newton(fwd, y, xr, tol, max_iter, max_step, f, jac)
                if r2 < res:
                    x[0] = xr[0]
                    x[1] = xr[1]
                    x[2] = xr[2]
                    res = r2
                    det = d2
            if res > tol:
                # far from the posed body one restart is enough: whatever is found there is air
                r2, d2 = _restart(
                    fwd,
                    cands,
                    ii,
                    jj,
                    kk,
                    y,
                    tol,
                    max_iter,
                    max_step,
                    n_restarts if occupied else 1,
                    prio,
                    False,
                    xr,
                    f,
                    jac,
                    xb,
                    cres,
                )
                if r2 < res:
                    x[0] = xr[0]
                    x[1] = xr[1]
                    x[2] = xr[2]
                    res = r2
                    det = d2
            if use_prio and occ[kk, jj, ii] != 0 and res <= tol and _prio_at(prio, x) == 0:
                r2, d2 = _restart(
                    fwd, cands, ii, jj, kk, y, tol, max_iter, max_step, n_restarts, prio, True, x, f, jac, xb, cres
                )
                if r2 <= tol:
                    res = r2
                    det = d2
            out_x[kk, jj, ii, 0] = x[0]
            out_x[kk, jj, ii, 1] = x[1]
            out_x[kk, jj, ii, 2] = x[2]
            out_res[kk, jj, ii] = res
            if res <= tol:
                out_status[kk, jj, ii] = 0 if det > 0.0 else 1
                have = True
                for q in range(3):  # _newton stopped right after evaluating at x: jac is J(x)
                    for r in range(3):
                        jl[q, r] = jac[q, r]
            elif _on_border(x, nx, ny, nz):
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
        y = np.empty(3)
        x = np.zeros(3)
        xb = np.empty(3)
        f = np.empty(3)
        jac = np.empty((3, 3))
        cres = np.empty(nc)
        for c in range(3):
            y[c] = pts[n, c]
        best, bdet = _restart(
            fwd, cands, y[0], y[1], y[2], y, tol, max_iter, max_step, n_restarts, no_prio, False, x, f, jac, xb, cres
        )
        for q in range(3):
            out_x[n, q] = x[q]
        out_res[n] = best
        if best <= tol:
            out_status[n] = 0 if bdet > 0.0 else 1
        else:
            out_status[n] = 3 if _on_border(x, nx, ny, nz) else 2


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
        one from the candidates: tissue, not air, fills the posed body.
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
    tidx = np.empty(fwd.shape, dtype=np.float32)
    _target_index(fwd, tgt_w, tidx)
    if prefer is not None:
        prio = np.ascontiguousarray(prefer, dtype=np.uint8)
        if prio.shape != template_geometry.array_shape:
            raise ValueError(
                f"prefer must be a mask on the template grid {template_geometry.array_shape}, got {prio.shape}"
            )
        occ = np.zeros(shape, dtype=np.uint8)
        _splat(tidx, prio, True, occ)
    else:
        prio = np.zeros((1, 1, 1), dtype=np.uint8)
        occ = np.zeros((1, 1, 1), dtype=np.uint8)
    cover = np.zeros(shape, dtype=np.uint8)
    _splat(tidx, prio, False, cover)
    # a cell torn wider than this (across a fold) is skipped; scaled by the resolution ratio so that an
    # upsampling target (fine grid) still sees its undeformed cells
    ratio = max(template_geometry.spacing) / min(target.spacing)
    _cover_cells(tidx, int(np.ceil(16 * max(1.0, ratio))), cover)
    guess = np.full(shape, -1, dtype=np.int64)
    _scatter_guess(tidx, prio, prefer is not None, guess)
    del tidx
    backward_kernel(
        fwd, tgt_a, cands, tol, int(max_iter), 2.0, int(n_restarts), prio, occ, cover, guess, out_x, out_res, out_status
    )
    _orient_status(out_status, template_geometry)
    return BackwardMap(template_geometry, target, out_x, out_res, out_status)


@nb.njit(cache=True, parallel=True)
def _guess_kernel(fwd, pts, guesses, tol, max_iter, max_step, out_x, out_res, out_status):
    """Newton from explicit guesses (template index) for each world point; keeps the best."""
    for n in nb.prange(pts.shape[0]):
        y = np.empty(3)
        xb = np.empty(3)
        f = np.empty(3)
        jac = np.empty((3, 3))
        for c in range(3):
            y[c] = pts[n, c]
        best = out_res[n]
        bdet = 1.0
        improved = False
        for g in range(guesses.shape[1]):
            for q in range(3):
                xb[q] = guesses[n, g, q]
            r2, d2 = _newton(fwd, y, xb, tol, max_iter, max_step, f, jac)
            if r2 < best:
                best = r2
                bdet = d2
                improved = True
                for q in range(3):
                    out_x[n, q] = xb[q]
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


def _pull(src: np.ndarray, bmap: BackwardMap, labels: bool, fill) -> np.ndarray:
    # template_index is a continuous index inside the grid: sample with an identity "world → index" map
    out = sample_array(src, np.eye(4), bmap.template_index, order=0 if labels else 1, fill=fill)
    out[bmap.status == OUTSIDE] = fill
    return out


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
