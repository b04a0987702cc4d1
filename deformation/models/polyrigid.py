"""A one-to-one articulated deformation: the bones' motions blended as a flow (log-Euclidean polyrigid).

VBD (Rhee Eq. 2) blends the bones' *matrices*; where two bones turn towards
each other (the crease of a flexed joint) the blend is many-to-one, and its
backward map must fold.  This module blends the bones' *velocities* instead
and integrates them (Arsigny et al.'s log-Euclidean polyrigid framework):

* every bone ``k`` moves from the template (``t = 0``) to the scan
  (``t = 1``) along ``M_k(t) = M_p(t) exp(t ℓ_k)``, ``ℓ_k = log(T_p⁻¹ T_k)``
  its motion relative to its parent ``p``, so joints stay articulated;
* the velocity of space is the blend of the bones' spatial velocities
  ``V_k(t) = Ṁ_k M_k⁻¹``: ``v(x, t) = Σ_k w_k(x, t) V_k(t) x̃``;
* the weights move with the bones: ``w_k(x, t)`` are the distance weights
  (:func:`deformation.models.skinning.distance_weights`) of ``D_k(M_k(t)⁻¹ x)``,
  ``D_k`` the template's signed distance map of bone ``k``.

Inside a bone its weight is one, so the bone moves rigidly; outside, the
weights are Lipschitz, so the flow is a diffeomorphism: the map and its
inverse are one-to-one, with no fold in the crease.  With weights fixed in
space (Arsigny's stationary polyrigid field) a bone moving through its
neighbours' weights would bend.  Reference: Arsigny V, Commowick O, Ayache N, Pennec X. A fast and log-Euclidean
polyaffine framework for locally linear registration. J Math Imaging Vis
33 (2009) 222–238. https://doi.org/10.1007/s10851-008-0135-9
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy.linalg import expm, logm

from deformation.geometry import GridGeometry, Volume

__all__ = ["PolyrigidFlow", "bone_distance_maps", "max_map_factor"]


def bone_distance_maps(labels: Volume, bone_labels: dict) -> np.ndarray:
    """Signed distance (mm, negative inside) to every bone, ``(n_bones, nz, ny, nx)`` float32, on the label grid.

    SimpleITK's signed Maurer distance with the grid's spacing; raises
    ``ValueError`` naming a bone without a voxel.
    """
    import SimpleITK as sitk

    lab = np.asarray(labels.data)
    out = np.empty((len(bone_labels),) + lab.shape, np.float32)
    for k, (bone, label) in enumerate(bone_labels.items()):
        inside = lab == label
        if not inside.any():
            raise ValueError(f"the label map has no voxel of bone {bone!r} (label {label})")
        img = sitk.GetImageFromArray(inside.astype(np.uint8))
        img.SetSpacing([float(s) for s in labels.geometry.spacing])  # distances only need the spacing
        d = sitk.SignedMaurerDistanceMap(img, insideIsPositive=False, squaredDistance=False, useImageSpacing=True)
        out[k] = sitk.GetArrayFromImage(d)
    return out


def _real_logm(m: np.ndarray) -> np.ndarray:
    out = logm(m)
    return np.real(out)


@dataclass
class PolyrigidFlow:
    """The flow of the blended bone velocities for one pose (see the module docstring).

    Parameters
    ----------
    transforms : ``(n_bones, 4, 4)`` template → scan, rigid
    parents : parent index per bone (``-1`` for a root), parents before children
    distance_maps : ``(n_bones, nz, ny, nx)`` signed distances on ``geometry`` (:func:`bone_distance_maps`)
    geometry : the template grid the distance maps live on
    power, falloff_mm : of the distance weights (:func:`deformation.models.skinning.distance_weights`)
    steps : RK4 steps from ``t = 0`` to ``1`` (``None``: enough that no step turns a bone by more than 2°)
    """

    transforms: np.ndarray
    parents: tuple
    distance_maps: np.ndarray
    geometry: GridGeometry
    power: float = 4.0
    falloff_mm: float = 20.0
    steps: int | None = None

    def __post_init__(self):
        t = np.asarray(self.transforms, float)
        n = len(t)
        if t.shape != (n, 4, 4) or len(self.parents) != n or self.distance_maps.shape[0] != n:
            raise ValueError(
                f"transforms {t.shape}, parents ({len(self.parents)}) and distance maps "
                f"({self.distance_maps.shape[0]}) must agree on the number of bones"
            )
        self.transforms = t
        rel = []
        for k, p in enumerate(self.parents):
            if p >= k and p != -1:
                raise ValueError("parents must come before their children")
            r = t[k] if p < 0 else np.linalg.solve(t[p], t[k])
            rel.append(_real_logm(r))  # ℓ_k
        self._rel = np.stack(rel)
        if self.steps is None:
            angle = max(np.linalg.norm([m[2, 1], m[0, 2], m[1, 0]]) for m in self._rel)
            self.steps = int(max(8, math.ceil(np.rad2deg(angle) / 2.0)))

    def _paths(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M_k(t)⁻¹ (T, n, 3, 4), V_k(t) (T, n, 3, 4))`` at ``times``."""
        n = len(self.transforms)
        minv = np.empty((len(times), n, 3, 4))
        vel = np.empty((len(times), n, 3, 4))
        for i, t in enumerate(times):
            m = np.empty((n, 4, 4))
            v = np.empty((n, 4, 4))
            for k, p in enumerate(self.parents):
                e = expm(t * self._rel[k])
                if p < 0:
                    m[k], v[k] = e, self._rel[k]
                else:
                    m[k] = m[p] @ e
                    v[k] = v[p] + m[p] @ self._rel[k] @ np.linalg.inv(m[p])  # V_k = V_p + M_p ℓ_k M_p⁻¹
            minv[i] = np.linalg.inv(m)[:, :3, :]
            vel[i] = v[:, :3, :]
        return minv, vel

    def _integrator(self, backward: bool):
        """``points (n, 3) → their images``, the bones' paths and the maps prepared once for many calls."""
        n = self.steps
        times = np.linspace(0.0, 1.0, 2 * n + 1)  # RK4 stage times: t_i, t_i + h/2, t_i + h
        minv, vel = self._paths(times)
        maps = np.ascontiguousarray(self.distance_maps, dtype=np.float32)
        w2i = np.asarray(self.geometry.world_to_index_matrix, dtype=np.float64)
        # M_k(t)⁻¹ followed by the template grid's world → index, one 3x4 map per stage time and bone
        to_index = np.ascontiguousarray(w2i[:3, :3] @ minv)
        to_index[..., 3] += w2i[:3, 3]
        scale = np.ascontiguousarray(self.geometry.spacing, dtype=np.float64)  # mm per index step along i, j, k
        power, falloff = float(self.power), float(self.falloff_mm)
        return lambda points: _flow(
            np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3),
            to_index,
            vel,
            maps,
            scale,
            n,
            backward,
            power,
            falloff,
        )

    def _integrate(self, points: np.ndarray, backward: bool) -> np.ndarray:
        return self._integrator(backward)(points)

    def forward(self, points) -> np.ndarray:
        """Template points ``(n, 3)`` → scan (integrate ``t = 0 → 1``)."""
        return self._integrate(points, False)

    def backward(self, points) -> np.ndarray:
        """Scan points ``(n, 3)`` → template (integrate ``t = 1 → 0``): the exact inverse of :meth:`forward`."""
        return self._integrate(points, True)

    def scan_to_template(self, scan_geometry: GridGeometry, *, factor: int = 1, progress=None) -> Volume:
        """The backward map as a ``scan_to_template`` displacement field on ``scan_geometry`` (float32, mm).

        ``factor`` f > 1 (a big scan): see ``_field``.  ``progress(done, total)`` is called as voxels are
        finished."""
        return self._field(scan_geometry, True, factor, progress)

    def template_to_scan(self, *, factor: int = 1, progress=None) -> Volume:
        """The forward map as a displacement field on the template grid (float32, mm); ``factor`` and
        ``progress`` as :meth:`scan_to_template`."""
        return self._field(self.geometry, False, factor, progress)

    def _field(self, grid: GridGeometry, backward: bool, factor: int, progress) -> Volume:
        """The map on ``grid``, a slab of planes at a time (each voxel is integrated on its own: the same bits
        as integrating the whole grid at once).  ``progress(done, total)``: voxels made (with a factor, the
        coarse ones integrated, then every fine one).

        With ``factor`` f > 1 the flow is integrated on every f-th voxel of ``grid`` and blended up
        (:class:`deformation.fields.resample.CoarseBackwardMap`: trilinear in a cell whose 8 corners' images lie
        within a few coarse voxels of each other, exact where the map is affine, as inside a bone); the voxels
        of the other cells (where curled fingers touch and the map jumps) and those past the last coarse voxel
        (which a blend would extrapolate) are integrated exactly.  The map has kinks (the distance weights
        change where a voxel's nearest bone does), so the blend is an approximation, and not one-to-one by
        construction: where a blended cell meets an integrated one their values differ by the blend's error
        (time, deviation and folds against the exact map: docs/measurements/deformation-and-validation.md).
        """
        from deformation import geometry as geometry_module
        from deformation.fields.resample import OK, BackwardMap, CoarseBackwardMap

        f = int(factor)
        if f < 1:
            raise ValueError(f"the map factor must be a whole number ≥ 1, got {factor!r}")
        if f > 1 and min(grid.every(f).size) < 2:
            raise ValueError(
                f"a map factor of {f} leaves {grid.every(f).size} voxels of this "
                f"{grid.size}-voxel grid: at most {max_map_factor(grid)} here"
            )
        run = self._integrator(backward)
        out = np.empty(grid.array_shape + (3,), dtype=np.float32)

        def integrate(g: GridGeometry, into: np.ndarray, done: int, total: int, displacement: bool) -> int:
            nx, ny, nz = g.size
            for k0, k1 in geometry_module.slabs(nz, nx * ny, geometry_module.SLAB_VOXELS):  # tests make it small
                x = g.world_coordinates(z_slice=slice(k0, k1))
                into[k0:k1] = run(x).reshape(x.shape) - x if displacement else run(x).reshape(x.shape)
                done += x.shape[0] * nx * ny
                if progress is not None:
                    progress(done, total)
            return done

        if f == 1:
            integrate(grid, out, 0, grid.n_voxels, True)
            return Volume(out, grid)
        coarse, frame = grid.every(f), self.geometry.every(f)  # images as indices of the template's grid
        nx, ny, nz = grid.size
        last = [f * (n - 1) for n in coarse.size]  # the last coarse voxel along x, y, z: fine index
        img = np.empty(coarse.array_shape + (3,))  # the coarse voxels' images (world mm)
        total = coarse.n_voxels + grid.n_voxels  # the coarse voxels integrated, then every fine one made
        done = integrate(coarse, img, 0, total, False)
        idx = frame.world_to_index(img).astype(np.float32)
        del img
        bm = CoarseBackwardMap(
            BackwardMap(
                frame, coarse, idx, np.zeros(coarse.array_shape, np.float32), np.full(coarse.array_shape, OK, np.uint8)
            ),
            f,
            self.geometry,
            grid,
        )
        del idx

        def exact_here(k0, k1):
            jump = bm.unblended(k0, k1)
            jump[np.arange(k0, k1) > last[2]] = True  # past the last coarse voxel: no extrapolation
            jump[:, np.arange(ny) > last[1]] = True
            jump[:, :, np.arange(nx) > last[0]] = True
            return jump

        for k0, k1 in geometry_module.slabs(nz, nx * ny, geometry_module.SLAB_VOXELS):
            x = grid.world_coordinates(z_slice=slice(k0, k1))
            pos = self.geometry.index_to_world(bm.rows(k0, k1).template_index)
            jump = exact_here(k0, k1)
            if jump.any():
                pos[jump] = run(x[jump])
            out[k0:k1] = pos - x
            done += (k1 - k0) * nx * ny
            if progress is not None:
                progress(done, total)
        return Volume(out, grid)


def max_map_factor(grid: GridGeometry) -> int:
    """The largest map factor whose coarse grid keeps at least 2 voxels along every axis (a cell to blend)."""
    return max(1, (min(grid.size) - 1))


@nb.njit(cache=True, inline="always")
def _sdf(maps, k, ri, rj, rk, scale):
    """Bone ``k``'s distance at the continuous template index (ri, rj, rk): trilinear in its map, plus the way to
    the grid outside it.

    A point beyond the template grid (a bone turned far, its inverse motion carrying the point out) takes the
    map's value at the nearest grid point plus its distance to that point, in mm (``scale``: the grid's spacing
    along i, j, k): an upper bound of the true distance (the bone lies inside the grid), continuous, and never the
    small edge value alone — clamping alone would let a fingertip turned into a fist claim the palm's tissue (the
    phantom hand's strongest curl).
    """
    nz, ny, nx = maps.shape[1], maps.shape[2], maps.shape[3]
    ci = min(max(ri, 0.0), nx - 1.0)
    cj = min(max(rj, 0.0), ny - 1.0)
    ck = min(max(rk, 0.0), nz - 1.0)
    i0, j0, k0 = min(int(ci), nx - 2), min(int(cj), ny - 2), min(int(ck), nz - 2)
    ti, tj, tk = ci - i0, cj - j0, ck - k0
    c00 = maps[k, k0, j0, i0] * (1 - ti) + maps[k, k0, j0, i0 + 1] * ti
    c01 = maps[k, k0, j0 + 1, i0] * (1 - ti) + maps[k, k0, j0 + 1, i0 + 1] * ti
    c10 = maps[k, k0 + 1, j0, i0] * (1 - ti) + maps[k, k0 + 1, j0, i0 + 1] * ti
    c11 = maps[k, k0 + 1, j0 + 1, i0] * (1 - ti) + maps[k, k0 + 1, j0 + 1, i0 + 1] * ti
    d = (c00 * (1 - tj) + c01 * tj) * (1 - tk) + (c10 * (1 - tj) + c11 * tj) * tk
    if ri != ci or rj != cj or rk != ck:
        d += math.sqrt(((ri - ci) * scale[0]) ** 2 + ((rj - cj) * scale[1]) ** 2 + ((rk - ck) * scale[2]) ** 2)
    return d


@nb.njit(cache=True)
def _velocity(x, y, z, s, to_index, vel, maps, scale, power, falloff, d, w, out):
    """The flow's velocity at world (x, y, z) and RK4 stage time ``s``: the bones' spatial velocities ``vel[s]``
    blended by the distance weights (:func:`deformation.models.skinning.distance_weights`) of each bone's distance
    at its template position ``M_k(t)⁻¹ x`` (``to_index[s, k]``: that map composed with the template grid's
    world → index)."""
    nb_ = to_index.shape[1]
    dmin = np.inf
    kmin = 0
    for k in range(nb_):
        m = to_index[s, k]
        ri = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]
        rj = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]
        rk = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]
        d[k] = _sdf(maps, k, ri, rj, rk, scale)
        if d[k] < dmin:
            dmin, kmin = d[k], k
    if dmin <= 0.0:  # inside a bone: its weight is one (distance_weights)
        for k in range(nb_):
            w[k] = 0.0
        w[kmin] = 1.0
    else:
        tot = 0.0
        for k in range(nb_):
            r = dmin / d[k]
            if power == 4.0:  # the default power: two products instead of pow()
                r *= r
                r *= r
            else:
                r = r**power
            w[k] = r * math.exp(-(d[k] - dmin) / falloff)
            tot += w[k]
        for k in range(nb_):
            w[k] /= tot
    out[0] = out[1] = out[2] = 0.0
    for k in range(nb_):
        if w[k] != 0.0:
            v = vel[s, k]
            for a in range(3):
                out[a] += w[k] * (v[a, 0] * x + v[a, 1] * y + v[a, 2] * z + v[a, 3])


@nb.njit(cache=True, parallel=True)
def _flow(points, to_index, vel, maps, scale, n_steps, backward, power, falloff):
    n = points.shape[0]
    nb_ = to_index.shape[1]
    out = np.empty((n, 3))
    h = 1.0 / n_steps
    block = 256  # points per task: its work arrays made once (each point's result is its own: any block size)
    for b in nb.prange((n + block - 1) // block):
        d = np.empty(nb_)
        w = np.empty(nb_)
        k1 = np.empty(3)
        k2 = np.empty(3)
        k3 = np.empty(3)
        k4 = np.empty(3)
        for i in range(b * block, min(n, (b + 1) * block)):
            _flow_point(
                points, i, to_index, vel, maps, scale, n_steps, backward, power, falloff, h, d, w, k1, k2, k3, k4, out
            )
    return out


@nb.njit(cache=True)
def _flow_point(points, i, to_index, vel, maps, scale, n_steps, backward, power, falloff, h, d, w, k1, k2, k3, k4, out):
    """RK4 of point ``i`` from t = 0 to 1 (or back), into ``out[i]``."""
    x, y, z = points[i, 0], points[i, 1], points[i, 2]
    for step in range(n_steps):
        if backward:  # t from 1 to 0: dx/dt = v, stepping with −h
            s0 = 2 * (n_steps - step)
            sg = -h
            sm, s1 = s0 - 1, s0 - 2
        else:
            s0 = 2 * step
            sg = h
            sm, s1 = s0 + 1, s0 + 2
        _velocity(x, y, z, s0, to_index, vel, maps, scale, power, falloff, d, w, k1)
        _velocity(
            x + 0.5 * sg * k1[0],
            y + 0.5 * sg * k1[1],
            z + 0.5 * sg * k1[2],
            sm,
            to_index,
            vel,
            maps,
            scale,
            power,
            falloff,
            d,
            w,
            k2,
        )
        _velocity(
            x + 0.5 * sg * k2[0],
            y + 0.5 * sg * k2[1],
            z + 0.5 * sg * k2[2],
            sm,
            to_index,
            vel,
            maps,
            scale,
            power,
            falloff,
            d,
            w,
            k3,
        )
        _velocity(
            x + sg * k3[0], y + sg * k3[1], z + sg * k3[2], s1, to_index, vel, maps, scale, power, falloff, d, w, k4
        )
        x += sg / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        y += sg / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        z += sg / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
    out[i, 0], out[i, 1], out[i, 2] = x, y, z
