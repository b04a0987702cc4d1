"""Compiled (numba) per-voxel kernels for the phantoms.

The phantom's anatomy and posing are *defined* by the NumPy code in
:mod:`.shapes`, :mod:`.anatomy` and :mod:`.posing`; this module evaluates the
very same functions point by point, fused and in parallel, because a
paper-size hand (255×255×90 voxels, 21 bones, ~10 Newton steps per voxel)
is far too slow with NumPy temporaries.  ``tests/validation`` checks that
both implementations agree to 1e-9 mm.

Shapes are flattened into three tables (see :func:`compile_shapes`):

* ``prims (P, 18)``: ``[type, params...]``; type 0 = round cone
  ``a(3) b(3) ra rb``, type 1 = ellipsoid ``centre(3) radii(3) rotation(9)``;
* ``groups (G, 2)`` with ``group_k (G,)``: a smooth union of prims
  ``[start, end)`` with blend width k;
* ``shapes (S, 2)`` with ``shape_k (S,)``: a smooth union of groups.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .shapes import Ellipsoid, RoundCone, SmoothUnion

__all__ = ["compile_shapes", "prim_row", "PRIM_WIDTH", "points"]


PRIM_WIDTH = 18


def points(a) -> np.ndarray:
    """``a`` as the kernels take arrays of points: C-contiguous float64 and read-only (a view, no copy, when it
    already is C-contiguous float64).  numba compiles a kernel once per argument type, and a writable and a
    read-only array are two types: one kind for every caller is one compilation on the first run, not two."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


# -- compiling shape objects into tables -------------------------------------------------
def prim_row(s) -> np.ndarray:
    row = np.zeros(PRIM_WIDTH)
    if isinstance(s, RoundCone):
        row[0] = 0
        row[1:4], row[4:7], row[7], row[8] = s.a, s.b, s.ra, s.rb
    elif isinstance(s, Ellipsoid):
        row[0] = 1
        row[1:4], row[4:7], row[7:16] = s.center, s.radii, np.asarray(s.rotation, float).reshape(-1)
    else:
        raise TypeError(f"not a primitive shape: {s!r}")
    return row


def compile_shapes(shapes) -> tuple:
    """Flatten a list of shapes (primitive, union of primitives, or union of those) into tables."""
    prims, groups, group_k, table, shape_k = [], [], [], [], []

    def add_group(parts, k):
        start = len(prims)
        prims.extend(prim_row(p) for p in parts)
        groups.append((start, len(prims)))
        group_k.append(k)

    for s in shapes:
        g0 = len(groups)
        if isinstance(s, SmoothUnion):
            if all(not isinstance(p, SmoothUnion) for p in s.parts):
                add_group(s.parts, s.k)
                k_out = 0.0
            else:
                for p in s.parts:
                    if isinstance(p, SmoothUnion):
                        if any(isinstance(q, SmoothUnion) for q in p.parts):
                            raise ValueError("shapes nest smooth unions at most two levels deep")
                        add_group(p.parts, p.k)
                    else:
                        add_group((p,), 0.0)
                k_out = s.k
        else:
            add_group((s,), 0.0)
            k_out = 0.0
        table.append((g0, len(groups)))
        shape_k.append(k_out)
    return (
        np.array(prims, float),
        np.array(groups, np.int64),
        np.array(group_k, float),
        np.array(table, np.int64),
        np.array(shape_k, float),
    )


# -- scalar building blocks --------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def _smin(a, b, k):
    if k <= 0.0:
        return min(a, b)
    h = 0.5 + 0.5 * (b - a) / k
    h = min(max(h, 0.0), 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


@nb.njit(cache=True)
def _prim_sdf(pr, x, y, z):
    if pr[0] == 0.0:
        ax, ay, az = pr[1], pr[2], pr[3]
        bax, bay, baz = pr[4] - ax, pr[5] - ay, pr[6] - az
        pax, pay, paz = x - ax, y - ay, z - az
        t = (pax * bax + pay * bay + paz * baz) / (bax * bax + bay * bay + baz * baz)
        t = min(max(t, 0.0), 1.0)
        qx, qy, qz = pax - t * bax, pay - t * bay, paz - t * baz
        return math.sqrt(qx * qx + qy * qy + qz * qz) - (pr[7] + t * (pr[8] - pr[7]))
    dx, dy, dz = x - pr[1], y - pr[2], z - pr[3]
    k0 = 0.0
    k1 = 0.0
    rmin = min(pr[4], min(pr[5], pr[6]))
    for i in range(3):
        qi = dx * pr[7 + i] + dy * pr[10 + i] + dz * pr[13 + i]  # rotᵀ (p − c)
        r = pr[4 + i]
        k0 += (qi / r) ** 2
        k1 += (qi / (r * r)) ** 2
    k0 = math.sqrt(k0)
    k1 = math.sqrt(k1)
    if k1 > 0.0:
        return k0 * (k0 - 1.0) / k1
    return -rmin


@nb.njit(cache=True)
def _shape_sdf(prims, groups, group_k, table, shape_k, s, x, y, z):
    out = 0.0
    for g in range(table[s, 0], table[s, 1]):
        d = 0.0
        for i in range(groups[g, 0], groups[g, 1]):
            di = _prim_sdf(prims[i], x, y, z)
            d = di if i == groups[g, 0] else _smin(d, di, group_k[g])
        out = d if g == table[s, 0] else _smin(out, d, shape_k[s])
    return out


@nb.njit(cache=True, inline="always")
def _smoothstep(x):
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


@nb.njit(cache=True, inline="always")
def _bump(t):
    """Compactly supported C² bump: (1 − t²)³ on |t| < 1."""
    if abs(t) >= 1.0:
        return 0.0
    u = 1.0 - t * t
    return u * u * u


@nb.njit(cache=True)
def _weights(d, power, falloff, w):
    """Localised inverse-distance weights (one-hot inside bones) into ``w``; returns the min distance."""
    nbones = d.shape[0]
    n_in = 0
    dmin = d[0]
    for k in range(nbones):
        if d[k] <= 0.0:
            n_in += 1
        dmin = min(dmin, d[k])
    s = 0.0
    for k in range(nbones):
        if n_in > 0:
            w[k] = 1.0 if d[k] <= 0.0 else 0.0
        else:
            w[k] = d[k] ** (-power) * math.exp(-(d[k] - dmin) / falloff)
        s += w[k]
    for k in range(nbones):
        w[k] /= s
    return dmin


# -- the forward map ------------------------------------------------------------------------
@nb.njit(cache=True)
def _forward_point(x, y, z, tabs, params, out, jac, d, w):
    """F(p) for one template point; writes F into ``out`` and the 3x3 linear part into ``jac``."""
    prims, groups, group_k, table, shape_k = tabs
    t12, dq, sign, joints, mode, power, falloff, fade_mm, waves, resid_gain = params
    nbones = t12.shape[0]
    for k in range(nbones):
        d[k] = _shape_sdf(prims, groups, group_k, table, shape_k, k, x, y, z)
    dmin = _weights(d, power, falloff, w)
    if mode == 0:  # vbd: Rhee Eq. 2, F(v) = (Σ_k w_k T_k) v
        m = np.zeros(12)
        for k in range(nbones):
            if w[k] != 0.0:
                for i in range(12):
                    m[i] += w[k] * t12[k, i]
        for i in range(3):
            out[i] = m[4 * i] * x + m[4 * i + 1] * y + m[4 * i + 2] * z + m[4 * i + 3]
            for j in range(3):
                jac[i, j] = m[4 * i + j]
        return
    # soft: δ (bulge + skin slide), then dual quaternion blend
    px, py, pz = x, y, z
    fade = _smoothstep(dmin / fade_mm)
    if fade > 0.0:
        body = np.nan
        for j in range(joints.shape[0]):
            jt = joints[j]
            theta = jt[12]
            if theta == 0.0:
                continue
            radius = jt[13]
            ux, uy, uz = x - jt[0], y - jt[1], z - jt[2]
            lx = ux * jt[3] + uy * jt[6] + uz * jt[9]
            ly = ux * jt[4] + uy * jt[7] + uz * jt[10]
            lz = ux * jt[5] + uy * jt[8] + uz * jt[11]
            along = _bump(lz / (1.5 * radius)) * _bump(math.hypot(lx, ly) / (2.0 * radius))
            if along == 0.0:
                continue
            member = w[int(jt[14])] + w[int(jt[15])]
            if member == 0.0:
                continue
            s = 1.0 if theta > 0 else -1.0
            th = theta * math.pi / 180.0
            flexor = _smoothstep(-s * ly / (0.5 * radius))
            radial = min(math.hypot(lx, ly) / radius, 1.2)
            bulge = jt[16] * radius * abs(math.sin(th)) * along * flexor * radial * member * fade
            px += bulge * (-s * jt[4])
            py += bulge * (-s * jt[7])
            pz += bulge * (-s * jt[10])
            extensor = _smoothstep(s * ly / (0.5 * radius))
            if extensor > 0.0:
                if body != body:  # NaN: not computed yet
                    body = _shape_sdf(prims, groups, group_k, table, shape_k, nbones, x, y, z)
                skin = math.exp(-0.5 * (body / (0.15 * radius)) ** 2)
                slide = jt[17] * radius * abs(th) * along * extensor * skin * member * fade
                px -= slide * jt[5]
                py -= slide * jt[8]
                pz -= slide * jt[11]
            amp = resid_gain * radius * abs(math.sin(th)) * along * member * fade
            for q in range(waves.shape[1]):
                wv = waves[j, q]
                sq = amp * wv[7] * math.sin(wv[0] * x + wv[1] * y + wv[2] * z + wv[6])
                px += sq * wv[3]
                py += sq * wv[4]
                pz += sq * wv[5]
    piv = 0
    for k in range(nbones):
        if w[k] > w[piv]:
            piv = k
    b = np.zeros(8)
    for k in range(nbones):
        if w[k] != 0.0:
            sk = w[k] * sign[piv, k]
            for i in range(8):
                b[i] += sk * dq[k, i]
    nrm = math.sqrt(b[0] ** 2 + b[1] ** 2 + b[2] ** 2 + b[3] ** 2)
    qw, qx, qy, qz = b[0] / nrm, b[1] / nrm, b[2] / nrm, b[3] / nrm
    dw, dx, dy, dz = b[4] / nrm, b[5] / nrm, b[6] / nrm, b[7] / nrm
    # t = 2 qd conj(qr), vector part
    tx = 2.0 * (-dw * qx + dx * qw - dy * qz + dz * qy)
    ty = 2.0 * (-dw * qy + dx * qz + dy * qw - dz * qx)
    tz = 2.0 * (-dw * qz - dx * qy + dy * qx + dz * qw)
    jac[0, 0] = 1 - 2 * (qy * qy + qz * qz)
    jac[0, 1] = 2 * (qx * qy - qz * qw)
    jac[0, 2] = 2 * (qx * qz + qy * qw)
    jac[1, 0] = 2 * (qx * qy + qz * qw)
    jac[1, 1] = 1 - 2 * (qx * qx + qz * qz)
    jac[1, 2] = 2 * (qy * qz - qx * qw)
    jac[2, 0] = 2 * (qx * qz - qy * qw)
    jac[2, 1] = 2 * (qy * qz + qx * qw)
    jac[2, 2] = 1 - 2 * (qx * qx + qy * qy)
    out[0] = jac[0, 0] * px + jac[0, 1] * py + jac[0, 2] * pz + tx
    out[1] = jac[1, 0] * px + jac[1, 1] * py + jac[1, 2] * pz + ty
    out[2] = jac[2, 0] * px + jac[2, 1] * py + jac[2, 2] * pz + tz


@nb.njit(cache=True, parallel=True)
def forward_map(points, tabs, params):
    n = points.shape[0]
    nbones = params[0].shape[0]
    out = np.empty((n, 3))
    for i in nb.prange(n):
        d = np.empty(nbones)
        w = np.empty(nbones)
        jac = np.empty((3, 3))
        _forward_point(points[i, 0], points[i, 1], points[i, 2], tabs, params, out[i], jac, d, w)
    return out


@nb.njit(cache=True)
def _solve3(a, r, out):
    """out = a⁻¹ r by Cramer's rule; returns False when a is (near) singular."""
    det = (
        a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
        - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    )
    if abs(det) < 1e-12:
        return False
    for c in range(3):
        m = a.copy()
        for i in range(3):
            m[i, c] = r[i]
        out[c] = (
            m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
            - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
            + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
        ) / det
    return True


@nb.njit(cache=True, parallel=True)
def inverse_map(targets, guesses, use_guess, tabs, params, t_inv12, tol, max_iter, fd_jacobian):
    """Solve F(p) = x per point by damped Newton; returns (p, residual).

    Without a guess the start is the inverse blend with posed-bone weights
    (each bone's distance evaluated at ``T_k⁻¹ x``).
    """
    prims, groups, group_k, table, shape_k = tabs
    t12 = params[0]
    power = params[5]
    falloff = params[6]
    nbones = t12.shape[0]
    n = targets.shape[0]
    p_out = np.empty((n, 3))
    r_out = np.empty(n)
    for i in nb.prange(n):
        d = np.empty(nbones)
        w = np.empty(nbones)
        jac = np.empty((3, 3))
        f = np.empty(3)
        p = np.empty(3)
        dp = np.empty(3)
        r = np.empty(3)
        cand = np.empty(3)
        fc = np.empty(3)
        jc = np.empty((3, 3))
        x, y, z = targets[i, 0], targets[i, 1], targets[i, 2]
        if use_guess:
            p[:] = guesses[i]
        else:
            for k in range(nbones):
                xk = t_inv12[k, 0] * x + t_inv12[k, 1] * y + t_inv12[k, 2] * z + t_inv12[k, 3]
                yk = t_inv12[k, 4] * x + t_inv12[k, 5] * y + t_inv12[k, 6] * z + t_inv12[k, 7]
                zk = t_inv12[k, 8] * x + t_inv12[k, 9] * y + t_inv12[k, 10] * z + t_inv12[k, 11]
                d[k] = _shape_sdf(prims, groups, group_k, table, shape_k, k, xk, yk, zk)
            _weights(d, power, falloff, w)
            m = np.zeros((3, 3))
            rhs = np.empty(3)
            for a in range(3):
                acc = 0.0
                for k in range(nbones):
                    acc += w[k] * t12[k, 4 * a + 3]
                    for b in range(3):
                        m[a, b] += w[k] * t12[k, 4 * a + b]
                rhs[a] = (x, y, z)[a] - acc
            if not _solve3(m, rhs, p):
                p[0], p[1], p[2] = x, y, z
        _forward_point(p[0], p[1], p[2], tabs, params, f, jac, d, w)
        r[0], r[1], r[2] = x - f[0], y - f[1], z - f[2]
        rn = math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2)
        step = 1.0
        h = 1e-4
        use_fd = fd_jacobian
        for _ in range(max_iter):
            if rn <= tol:
                break
            if step < 1e-4:
                if use_fd:
                    break
                # The blended rotation is a poor Jacobian here (weights change fast):
                # switch to finite differences and start again with full steps.
                use_fd = True
                step = 1.0
            if use_fd:
                for c in range(3):
                    cand[:] = p
                    cand[c] += h
                    _forward_point(cand[0], cand[1], cand[2], tabs, params, fc, jc, d, w)
                    for a in range(3):
                        jac[a, c] = (fc[a] - f[a]) / h
            if not _solve3(jac, r, dp):
                dp[:] = r
            for a in range(3):
                cand[a] = p[a] + step * dp[a]
            _forward_point(cand[0], cand[1], cand[2], tabs, params, fc, jc, d, w)
            rc0, rc1, rc2 = x - fc[0], y - fc[1], z - fc[2]
            rcn = math.sqrt(rc0 * rc0 + rc1 * rc1 + rc2 * rc2)
            if rcn < rn:
                if rcn > 0.25 * rn:
                    use_fd = True  # linear convergence only: Newton with the true Jacobian is quadratic
                p[:] = cand
                f[:] = fc
                if not use_fd:
                    jac[:, :] = jc
                r[0], r[1], r[2] = rc0, rc1, rc2
                rn = rcn
                step = min(1.0, 2.0 * step)
            else:
                step *= 0.5
        p_out[i] = p
        r_out[i] = rn
    return p_out, r_out


# -- soft-tissue structure (soft_tissue.py defines it in NumPy) -------------------------------------
_OFFSET = 1 << 20
_JITTER = 0.9


@nb.njit(cache=True, inline="always")
def _mix64(z):
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@nb.njit(cache=True)
def _uniform(i, j, k, key, channel):
    h = _mix64(key)
    h = _mix64(h ^ np.uint64(i + _OFFSET))
    h = _mix64(h ^ np.uint64(j + _OFFSET))
    h = _mix64(h ^ np.uint64(k + _OFFSET))
    h = _mix64(h ^ np.uint64(channel))
    return np.float64(h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@nb.njit(cache=True)
def _site(i, j, k, key, cell):
    return (
        (i + 0.5 + _JITTER * (_uniform(i, j, k, key, 0) - 0.5)) * cell,
        (j + 0.5 + _JITTER * (_uniform(i, j, k, key, 1) - 0.5)) * cell,
        (k + 0.5 + _JITTER * (_uniform(i, j, k, key, 2) - 0.5)) * cell,
    )


@nb.njit(cache=True, inline="always")
def _site_at(i, j, k, key, cell, table, first):
    """A lattice cell's site: from the table (SoftTissue.site_tables) when it covers the cell, else hashed."""
    a, b, c = i - first[0], j - first[1], k - first[2]
    if (0 <= a < table.shape[0]) and (0 <= b < table.shape[1]) and (0 <= c < table.shape[2]):
        return table[a, b, c, 0], table[a, b, c, 1], table[a, b, c, 2]
    return _site(i, j, k, key, cell)


@nb.njit(cache=True)
def _cell(x, y, z, cell, key, table, first, sites, d2s):
    """Distance to the boundary of the jittered-lattice Voronoi cell containing (x, y, z), and its value.

    ``sites (125, 3)`` and ``d2s (125,)`` are the caller's scratch space (one allocation per point, not per call).
    """
    bi, bj, bk = int(math.floor(x / cell)), int(math.floor(y / cell)), int(math.floor(z / cell))
    best = np.inf
    nearest = 0
    ni = nj = nk = 0
    q = 0
    for di in range(-2, 3):
        for dj in range(-2, 3):
            for dk in range(-2, 3):
                sx, sy, sz = _site_at(bi + di, bj + dj, bk + dk, key, cell, table, first)
                sites[q, 0], sites[q, 1], sites[q, 2] = sx, sy, sz
                d2 = (sx - x) ** 2 + (sy - y) ** 2 + (sz - z) ** 2
                d2s[q] = d2
                if d2 < best:
                    best, nearest, ni, nj, nk = d2, q, bi + di, bj + dj, bk + dk
                q += 1
    bound = np.inf
    s1x, s1y, s1z = sites[nearest, 0], sites[nearest, 1], sites[nearest, 2]
    for q in range(125):
        gap = math.sqrt((sites[q, 0] - s1x) ** 2 + (sites[q, 1] - s1y) ** 2 + (sites[q, 2] - s1z) ** 2)
        if gap > 0.0:
            bound = min(bound, (d2s[q] - best) / (2.0 * gap))
    a, b, c = ni - first[0], nj - first[1], nk - first[2]
    if (0 <= a < table.shape[0]) and (0 <= b < table.shape[1]) and (0 <= c < table.shape[2]):
        return bound, table[a, b, c, 3]
    return bound, _uniform(ni, nj, nk, key, 3)


@nb.njit(cache=True, inline="always")
def _box(s, half, edge):
    return 0.5 * (math.tanh((s + half) / edge) - math.tanh((s - half) / edge))


# -- appearance ----------------------------------------------------------------------------------
@nb.njit(cache=True, parallel=True)
def intensity_map(
    points,
    tabs,
    nbones,
    contrast,
    edge,
    layers,
    wavevectors,
    phases,
    amplitudes,
    tex_amp,
    scan_points,
    bone_frames,
    tissue,
    keys,
    tubes,
    tube_info,
    sites,
):
    """Noise-free intensity at template points (see :meth:`Anatomy.intensity`).

    ``bone_frames`` ``(nbones, 3, 4)``, when not empty, maps ``scan_points``
    into each bone's template frame, where that bone's distance is taken.
    ``tissue`` (empty: none) holds :meth:`SoftTissue.params`, ``keys`` its two
    lattice keys, ``tubes``/``tube_info`` its round cones and (kind, radius), ``sites`` its
    :meth:`SoftTissue.site_tables`.
    Structure is skipped where its layer's weight is below 1e-15 (it would
    change the intensity by less than 1e-11).
    """
    prims, groups, group_k, table, shape_k = tabs
    air, skin_i, fat, muscle, cortex, marrow, tendon, vessel = contrast
    skin_mm, fat_mm, cortex_mm = layers
    n = points.shape[0]
    rigid = bone_frames.shape[0] > 0
    structured = tissue.shape[0] > 0
    out = np.empty(n)
    for i in nb.prange(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        b = _shape_sdf(prims, groups, group_k, table, shape_k, nbones, x, y, z)
        db = np.inf
        sx = sy = sz = 0.0
        if rigid:
            sx, sy, sz = scan_points[i, 0], scan_points[i, 1], scan_points[i, 2]
        for k in range(nbones):
            if rigid:
                m = bone_frames[k]
                qx = m[0, 0] * sx + m[0, 1] * sy + m[0, 2] * sz + m[0, 3]
                qy = m[1, 0] * sx + m[1, 1] * sy + m[1, 2] * sz + m[1, 3]
                qz = m[2, 0] * sx + m[2, 1] * sy + m[2, 2] * sz + m[2, 3]
                db = min(db, _shape_sdf(prims, groups, group_k, table, shape_k, k, qx, qy, qz))
            else:
                db = min(db, _shape_sdf(prims, groups, group_k, table, shape_k, k, x, y, z))
        tex = 0.0
        for q in range(phases.shape[0]):
            tex += amplitudes[q] * math.cos(
                wavevectors[q, 0] * x + wavevectors[q, 1] * y + wavevectors[q, 2] * z + phases[q]
            )
        tex *= tex_amp
        val = muscle * (1.0 + tex)
        fat_v = fat * (1.0 + tex)
        in_body = 0.5 * (1.0 - math.tanh(b / edge))
        muscle_w = 0.5 * (1.0 - math.tanh((b + skin_mm + fat_mm) / edge))
        if structured and in_body > 1e-15:
            scratch = np.empty((125, 3))
            d2s = np.empty(125)
            if muscle_w > 1e-15:
                sm, um = _cell(x, y, z, tissue[0], keys[0], sites[0], sites[1], scratch, d2s)
                val = val * (1.0 + tissue[4] * (2.0 * um - 1.0))
                val += (fat_v - val) * _box(sm, tissue[2], edge)
            if muscle_w < 1.0 - 1e-15:
                sf, uf = _cell(x, y, z, tissue[1], keys[1], sites[2], sites[3], scratch, d2s)
                fat_v = fat_v * (1.0 + tissue[5] * (2.0 * uf - 1.0))
                fat_v += (skin_i - fat_v) * _box(sf, tissue[3], edge)
        val += (fat_v - val) * (1.0 - muscle_w)
        if structured and in_body > 1e-15:
            for kind in range(2):
                frac = 0.0
                for t in range(tubes.shape[0]):
                    if tube_info[t, 0] == kind:
                        d = _prim_sdf(tubes[t], x, y, z)
                        if d < 14.0 * edge:  # beyond, the blurred tube is below e^-28 (< 1e-9 of intensity)
                            r = tube_info[t, 1]
                            frac = max(frac, 0.5 * (math.tanh((d + 2.0 * r) / edge) - math.tanh(d / edge)))
                val += ((tendon if kind == 0 else vessel) - val) * frac
        val += (skin_i - val) * (1.0 - 0.5 * (1.0 - math.tanh((b + skin_mm) / edge)))
        val += (cortex - val) * 0.5 * (1.0 - math.tanh(db / edge))
        val += (marrow * (1.0 + tex) - val) * 0.5 * (1.0 - math.tanh((db + cortex_mm) / edge))
        out[i] = air + (val - air) * in_body
    return out


@nb.njit(cache=True, parallel=True)
def distances_map(points, tabs, nshapes):
    """Signed distance to every shape ``(n, nshapes)`` (bones first, then the body)."""
    prims, groups, group_k, table, shape_k = tabs
    n = points.shape[0]
    out = np.empty((n, nshapes))
    for i in nb.prange(n):
        for s in range(nshapes):
            out[i, s] = _shape_sdf(prims, groups, group_k, table, shape_k, s, points[i, 0], points[i, 1], points[i, 2])
    return out
