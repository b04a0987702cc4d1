"""Volume blend deformation of voxel grids and example-based volume deformation (Rhee §3.2, §5).

* :func:`vbd_forward` — VBD, Rhee Eq. 2: every template grid point ``v``
  moves to ``(Σ_j w_j(v) T_j) v``.
* :class:`ExampleVolumeDeformation` — EVD, Rhee Eq. 6–7.  From registered
  correspondences (the position ``v̂_k`` of every template voxel in scan
  ``k``) the training displacement in the template frame is
  ``d_k = (Σ_j w_j T_j^k)⁻¹ v̂_k − v_0`` (Rhee Eq. 7); at a pose ``a`` the
  displacement ``d_a = Σ_k s_k(a) d_k`` is interpolated over pose space
  with normalised RBFs (Kurihara Eq. 12–14), and the posed position is
  ``v_a = E(v_0 + d_a)`` (Rhee Eq. 6), ``E`` being VBD with the weights of
  ``v_0``, so the training poses are reproduced exactly.

The template itself is an example (Kurihara's base pose ``S_0``, §4): at its
own pose every transform is the identity and Rhee Eq. 7 gives ``d = 0``.  It
joins the examples unless a training pose is close to rest
(:func:`wants_template_example`): two examples so close make the RBF matrix
of Kurihara Eq. 13 near-singular.  With ``weighting="wpsd"`` the pose weights
are per voxel, from the weighted pose distance of Kurihara Eq. 16
(:mod:`.posespace`), computed on the fly.  Measurements behind these choices:
``docs/measurements/deformation-and-validation.md``.

Beyond the examples' range the normalised RBF weights extrapolate (some ``s_k`` negative, some above one: a
bend past the most bent scan weighs it ~1.4 and the next −0.5), and so would ``d_a``, without a bound.  The
blended displacement at a voxel is therefore never longer than the longest example's there (its direction
kept): where the weights are a convex blend this changes nothing, and beyond the range no template voxel
travels further than the bones that drive it plus the largest correction any scan showed at it
(``|v_a − v_0| ≤ max_j |T_j v_0 − v_0| + max_k |d_k|``, as ``E`` blends rigid motions).  The cost, on the
phantoms' bends past their range, is in ``docs/measurements/deformation-and-validation.md``.

Uncertainty (issue R): a training scan's ``d_k`` carries its registration's expected error ``σ_k`` (the
register stage's ``uncertainty.mha`` at the voxel's place in the scan).  At a pose ``a`` the model's
displacement is ``Σ_k s_k d_k``, so independent errors give ``Σ_k s_k² σ_k²``; between and beyond the
training poses the interpolation errs too.  Its variance is cross-validated: each scan is predicted from the
others, and the residual less the scans' own errors, divided by the share of a Gaussian process's variance
the others leave unexplained at that pose (``1 − γ``, :meth:`~.posespace.PoseSpace.explained`, with the
Gaussians of Kurihara Eq. 13), is averaged over the scans; at ``a`` it counts ``(1 − γ(a))`` times.  So the
expected error is each scan's own at its training pose and grows away from them.  ``E`` blends rotations
(``|M d| ≤ |d|``), so the displacement's error bounds the posed position's.

Positions are ``(nz, ny, nx, 3)`` (:mod:`.resample` makes a posed volume); the
displacements are stored per voxel, ``(n_voxels, n_poses, 3)`` float32.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from deformation.geometry import GridGeometry
from deformation.models.posespace import (
    PoseSpace,
    chol_factor,
    chol_subst,
    dof_bones,
    per_bone_sq,
    query_kernel,
    rbf_width,
    weighted_sq,
)
from deformation.models.skinning import SkinningWeights, blend_point, stack_transforms

__all__ = [
    "vbd_forward",
    "forward_kernel",
    "fill_unmatched",
    "ExampleVolumeDeformation",
    "EVD_WEIGHTINGS",
    "template_pose",
    "wants_template_example",
    "with_template_example",
    "TEMPLATE_EXAMPLE_SEPARATION",
]

EVD_WEIGHTINGS = ("psd", "wpsd")


@nb.njit(cache=True, inline="always")
def _evd_point(a, i, j, k, v, disp, s, idx, val, t, cap_on, out):
    """Rhee Eq. 6 at grid point (i, j, k) = voxel v: E(v0 + Σ_p s_p d_p) with v0 = a·(i, j, k, 1), the blended
    displacement no longer than the longest example's at v (module docstring, "Beyond the examples' range")."""
    # Rhee Eq. 6's d_a = Σ_p s_p(a) d_p: the training displacements blended
    d0 = d1 = d2 = 0.0
    cap = 0.0  # the longest example displacement at v
    for p in range(disp.shape[1]):
        e0, e1, e2 = disp[v, p, 0], disp[v, p, 1], disp[v, p, 2]
        sp = s[p]
        d0 += sp * e0
        d1 += sp * e1
        d2 += sp * e2
        cap = max(cap, e0 * e0 + e1 * e1 + e2 * e2)
    n2 = d0 * d0 + d1 * d1 + d2 * d2
    # the pose weights extrapolate (some s_p < 0 or > 1): the length capped, the direction kept (a convex blend's
    # round-off, 1e-6 of the square, is left alone: the training poses keep their bits)
    if cap_on and n2 > cap * (1.0 + 1e-6):
        f = np.sqrt(cap / n2)
        d0 *= f
        d1 *= f
        d2 *= f
    # Rhee Eq. 6's v0 + d_a, v0 the template grid point in world mm
    p0 = a[0, 0] * i + a[0, 1] * j + a[0, 2] * k + a[0, 3] + d0
    p1 = a[1, 0] * i + a[1, 1] * j + a[1, 2] * k + a[1, 3] + d1
    p2 = a[2, 0] * i + a[2, 1] * j + a[2, 2] * k + a[2, 3] + d2
    o0, o1, o2 = blend_point(idx, val, v, t, p0, p1, p2)  # Rhee Eq. 6: va = E(v0 + d_a), E the VBD of Rhee Eq. 2
    out[k, j, i, 0] = o0
    out[k, j, i, 1] = o1
    out[k, j, i, 2] = o2


@nb.njit(cache=True, parallel=True)
def forward_kernel(a, nx, ny, nz, idx, val, t, disp, s, out, cap=True):
    """Rhee Eq. 6 on a grid: ``out[v] = (Σ_m w_m T_{b_m}) (v + Σ_p s_p disp[v, p])`` for every grid point ``v``.

    The compiled kernel behind :func:`vbd_forward` (no examples: ``disp`` of
    shape ``(n_voxels, 0, 3)``, Rhee Eq. 2) and
    :meth:`ExampleVolumeDeformation.forward`.  ``a`` is the grid's 3×4
    index → world matrix, ``(nx, ny, nz)`` its size; ``idx``, ``val`` the
    sparse skinning weights per voxel; ``t`` the bones' 3×4 transforms;
    ``s`` the pose weights of the examples; ``out`` ``(nz, ny, nx, 3)``; ``cap``: the blended displacement no
    longer than the longest example's (module docstring; False: Rhee Eq. 6 as written).
    """
    nxy = nx * ny
    for k in nb.prange(nz):
        for j in range(ny):
            for i in range(nx):
                v = k * nxy + j * nx + i
                _evd_point(a, i, j, k, v, disp, s, idx, val, t, cap, out)


@nb.njit(cache=True, parallel=True)
def _forward_kernel_wpsd(a, nx, ny, nz, idx, val, t, disp, bone_pair, bone_q, out, cap=True):
    """As :func:`forward_kernel` with per-voxel pose weights (Kurihara Eq. 16, 12–14), solved on the fly."""
    P = disp.shape[1]
    n_bones = bone_pair.shape[0]
    nxy = nx * ny
    flat = bone_pair.reshape(n_bones, P * P)
    glob_pair = flat.sum(axis=0)
    glob_q = bone_q.sum(axis=0)
    for k in nb.prange(nz):
        pair_flat = np.empty(P * P)
        phi = np.empty(P)
        work = np.empty(P)
        for j in range(ny):
            for i in range(nx):
                v = k * nxy + j * nx + i
                # Kurihara Eq. 16 (squared) per voxel: pose distances to the query and between the examples
                weighted_sq(idx, val, v, bone_q, glob_q, phi)
                weighted_sq(idx, val, v, flat, glob_pair, pair_flat)
                pair = pair_flat.reshape(P, P)
                sig = rbf_width(pair, P)  # Gaussian width: mean nearest-neighbour distance in this metric
                inv = 1.0 / (sig * sig) if sig > 0.0 else 0.0
                query_kernel(phi, P, inv)  # Kurihara Eq. 13's φ(d_j(a, a_l)) of the query, Gaussian
                for q in range(P):
                    for r in range(q + 1):  # Φ_ql = φ(d_j(a_q, a_l)): the matrix of Kurihara Eq. 12's conditions
                        e = np.exp(-pair[q, r] * inv)
                        pair[q, r] = e
                        pair[r, q] = e
                ok = chol_factor(pair, P)
                if ok:
                    chol_subst(pair, phi, P, work)  # Kurihara Eq. 12–13: f = Φ⁻¹ φ(a) (C = Φ⁻¹, Φ symmetric)
                    tot = 0.0
                    for q in range(P):
                        tot += phi[q]
                    for q in range(P):
                        phi[q] /= tot  # Kurihara Eq. 14: s_q = f_q / Σ_l f_l
                else:
                    for q in range(P):
                        phi[q] = 1.0 / P
                _evd_point(a, i, j, k, v, disp, phi, idx, val, t, cap, out)


#: σ (template voxels) of the Gaussian that pools the cross-validated interpolation variance: each voxel has a few
#: residuals (one per scan), ~350 voxels pooled make its estimate ~19× less noisy
CV_POOL_VOXELS = 2.0

#: The template joins the examples when every training pose is at least this fraction of the training poses'
#: mean nearest-neighbour distance (the RBF width of :mod:`.posespace`) from the rest pose.
TEMPLATE_EXAMPLE_SEPARATION = 0.5


def template_pose(skeleton):
    """The template's own pose: the identity transform for every bone (Rhee Eq. 7 gives ``d = 0`` there)."""
    from deformation.kinematics.skeleton import Pose

    return Pose({b: np.eye(4) for b in skeleton.bone_names}, skeleton=getattr(skeleton, "name", None))


def wants_template_example(train_vectors, rest_vector) -> bool:
    """Whether the template's rest pose joins the EVD examples (module docstring): no training pose within
    :data:`TEMPLATE_EXAMPLE_SEPARATION` × the training poses' mean nearest-neighbour distance of it (with one
    training pose, any distance)."""
    train = np.atleast_2d(np.asarray(train_vectors, dtype=float))
    d_rest = np.sqrt(((train - np.asarray(rest_vector, float)[None]) ** 2).sum(-1))
    if len(train) < 2:
        return bool(d_rest.min() > 1e-9)
    pair = np.sqrt(((train[:, None] - train[None]) ** 2).sum(-1)) + np.diag(np.full(len(train), np.inf))
    return bool(d_rest.min() >= TEMPLATE_EXAMPLE_SEPARATION * float(pair.min(axis=1).mean()))


def with_template_example(skeleton, vectors, template_example="auto") -> tuple[list, bool]:
    """The examples' pose vectors, the template's rest pose appended when it joins them (``True``, ``False``, or
    ``"auto"``: :func:`wants_template_example`), and whether it did."""
    vectors = [np.asarray(v, float) for v in vectors]
    rest = PoseSpace(skeleton, [template_pose(skeleton)]).train[0]
    if template_example == "auto":
        template_example = wants_template_example(vectors, rest)
    elif not isinstance(template_example, bool):
        raise ValueError(f"template_example must be True, False or 'auto', got {template_example!r}")
    return vectors + [rest] if template_example else vectors, bool(template_example)


def _check_grid_weights(geometry: GridGeometry, weights: SkinningWeights) -> None:
    if weights.n_points != geometry.n_voxels:
        raise ValueError(
            f"voxel weights cover {weights.n_points} points but the grid {geometry.describe()} has "
            f"{geometry.n_voxels} voxels: compute the weights on this grid"
        )


def vbd_forward(geometry: GridGeometry, weights: SkinningWeights, transforms) -> np.ndarray:
    """VBD (Rhee Eq. 2): the posed world position of every template voxel, ``(nz, ny, nx, 3)`` float32.

    ``weights`` are per voxel in array order (``[z, y, x]`` flattened) and
    ``transforms`` the bones' template → posed 4×4 matrices (a mapping or a
    ``(n_bones, 4, 4)`` array in ``weights.bones`` order).
    """
    _check_grid_weights(geometry, weights)
    t = np.ascontiguousarray(stack_transforms(transforms, weights.bones)[:, :3, :])
    out = np.empty(geometry.array_shape + (3,), dtype=np.float32)
    nx, ny, nz = geometry.size
    disp = np.zeros((weights.n_points, 0, 3), dtype=np.float32)
    forward_kernel(  # Rhee Eq. 2: Rhee Eq. 6's kernel with no examples (d_a = 0), so va = (Σ_j w_j T_j) v0
        np.ascontiguousarray(geometry.index_to_world_matrix[:3]),
        nx,
        ny,
        nz,
        weights.index,
        weights.value,
        t,
        disp,
        np.zeros(0),
        out,
    )
    return out


def fill_unmatched(geometry: GridGeometry, weights: SkinningWeights, transforms, positions, found) -> np.ndarray:
    """``positions`` ``(nz, ny, nx, 3)`` of template voxels in a scan, VBD (Rhee Eq. 2) where ``found`` is false.

    Voxels with no correspondence in a scan (outside its field of view, or an
    inverse not found) then contribute ``d_k = 0`` to EVD (Rhee Eq. 7).
    """
    pos = np.array(positions, dtype=np.float64)
    miss = ~np.asarray(found, bool)
    if miss.any():
        pos[miss] = vbd_forward(geometry, weights, transforms)[miss]
    return pos


class ExampleVolumeDeformation:
    """EVD (Rhee §5, Rhee Eq. 6–7): training displacements over pose space, a posed volume at any pose.

    Parameters
    ----------
    geometry : GridGeometry
        The template grid.
    weights : SkinningWeights
        Per-voxel skinning weights on that grid (array order).
    space : PoseSpace
        The training poses' pose vectors (same order as ``displacements``).
    displacements : (n_voxels, n_poses, 3) float32
        ``d_k`` of Rhee Eq. 7 per voxel (world mm, template frame).
    template_example : bool
        The last example is the template's rest pose with ``d = 0`` (module docstring); ``n_scans`` then
        counts the others.
    scan_sigma : (n_voxels, n_scans) float32, optional
        The expected error (mm) of each training scan's ``d_k`` at every voxel (its registration's σ where the
        voxel lies in the scan); with it, and without it from the cross-validation alone,
        :meth:`expected_error` gives a posed volume's uncertainty (module docstring, "Uncertainty").
    """

    def __init__(
        self,
        geometry: GridGeometry,
        weights: SkinningWeights,
        space: PoseSpace,
        displacements,
        *,
        template_example: bool = False,
        scan_sigma=None,
    ):
        _check_grid_weights(geometry, weights)
        d = np.ascontiguousarray(displacements, dtype=np.float32)
        if d.shape != (geometry.n_voxels, space.n_poses, 3):
            raise ValueError(
                f"displacements must be (n_voxels, n_poses, 3) = {(geometry.n_voxels, space.n_poses, 3)}, got {d.shape}"
            )
        self.geometry = geometry
        self.weights = weights
        self.space = space
        self.displacements = d
        self.template_example = bool(template_example)
        if self.template_example and np.any(d[:, -1]):
            raise ValueError("the template's example (the last) must have zero displacement (Rhee Eq. 7 at rest)")
        self._dof_bone = dof_bones(space.skeleton, weights.bones)
        self.scan_sigma = None
        if scan_sigma is not None:
            sig = np.ascontiguousarray(scan_sigma, dtype=np.float32)
            if sig.shape != (geometry.n_voxels, self.n_scans):
                raise ValueError(
                    f"scan_sigma must be (n_voxels, n_scans) = {(geometry.n_voxels, self.n_scans)}, got {sig.shape}"
                )
            if not np.all(np.isfinite(sig)) or sig.min() < 0:
                raise ValueError("scan_sigma must be finite and ≥ 0 (mm)")
            self.scan_sigma = sig
        self._cv_var = None  # the cross-validated interpolation variance (mm²), made on first use

    @property
    def n_scans(self) -> int:
        """The training scans' examples (the template's, when included, not counted)."""
        return self.space.n_poses - int(self.template_example)

    @classmethod
    def from_examples(
        cls,
        geometry: GridGeometry,
        weights: SkinningWeights,
        skeleton,
        vectors,
        displacements,
        *,
        template_example="auto",
        scan_sigma=None,
    ) -> ExampleVolumeDeformation:
        """The model from the training scans' pose vectors ``(P, n_dof)`` and displacements ``(n_voxels, P, 3)``
        (Rhee Eq. 7), the template's rest pose with ``d = 0`` added as an example when ``template_example``
        is True, or "auto" and :func:`wants_template_example`; ``scan_sigma`` ``(n_voxels, P)``: the class's."""
        vectors, template_example = with_template_example(skeleton, vectors, template_example)
        d = np.asarray(displacements, dtype=np.float32)
        if template_example:
            d = np.concatenate([d, np.zeros(d.shape[:1] + (1, 3), np.float32)], axis=1)
        return cls(
            geometry,
            weights,
            PoseSpace(skeleton, vectors),
            d,
            template_example=template_example,
            scan_sigma=scan_sigma,
        )

    @classmethod
    def from_correspondences(
        cls,
        geometry: GridGeometry,
        weights: SkinningWeights,
        skeleton,
        poses,
        template_to_scan,
        *,
        template_example="auto",
        scan_sigma=None,
        progress=None,
    ) -> ExampleVolumeDeformation:
        """Build the model from each training scan's pose and template → scan positions (Rhee Eq. 7).

        ``poses`` are :class:`~deformation.kinematics.skeleton.Pose` objects (bone
        transforms template → scan) and ``template_to_scan`` the matching
        ``(nz, ny, nx, 3)`` arrays: the world position in scan ``k`` of every
        template voxel (ground truth, or a registration's inverse field).
        ``template_example``: see :meth:`from_examples`; ``scan_sigma``: one ``(nz, ny, nx)`` array per scan,
        the expected error (mm) of its positions (the class's ``scan_sigma``).
        """
        poses = list(poses)
        fields = list(template_to_scan)
        if len(poses) != len(fields):
            raise ValueError(f"{len(poses)} poses but {len(fields)} correspondence fields")
        _check_grid_weights(geometry, weights)
        n = geometry.n_voxels
        sig = None
        if scan_sigma is not None:  # checked before the work
            sig = [np.asarray(a, np.float32).reshape(-1) for a in scan_sigma]
            if len(sig) != len(poses) or any(a.shape[0] != n for a in sig):
                raise ValueError(f"scan_sigma needs one array of {n} voxels per scan ({len(poses)})")
            sig = np.stack(sig, axis=1)
        space = PoseSpace(skeleton, poses)  # distinct poses, checked before the work
        vectors, with_template = with_template_example(skeleton, space.train, template_example)
        n = geometry.n_voxels
        # room for the template's example (d = 0, the last) from the start: appending it would copy the model
        d = np.zeros((n, len(poses) + int(with_template), 3), dtype=np.float32)
        grid = geometry.world_coordinates().reshape(-1, 3)
        for k, (pose, pos) in enumerate(zip(poses, fields)):
            pos = np.asarray(pos).reshape(-1, 3)  # read blockwise below: no float64 copy of the whole field
            if pos.shape[0] != n:
                raise ValueError(f"correspondence {k} has {pos.shape[0]} points, the template grid {n} voxels")
            t = stack_transforms(pose.transforms, weights.bones)
            # Rhee Eq. 7: d_k = (Σ_j w_j T_j^k)⁻¹ v̂_k − v0, blockwise to bound memory
            for lo in range(0, n, 1 << 20):
                hi = min(n, lo + (1 << 20))
                m = np.zeros((hi - lo, 3, 4))
                for s in range(weights.max_influences):
                    m += weights.value[lo:hi, s, None, None] * t[weights.index[lo:hi, s].astype(np.int64), :3, :]
                rhs = np.asarray(pos[lo:hi], dtype=np.float64) - m[:, :, 3]
                try:
                    # Rhee Eq. 7's inverse VBD, v̂_k = pos, v0 = grid (solved, no inverse formed)
                    d[lo:hi, k] = np.linalg.solve(m[:, :, :3], rhs[:, :, None])[:, :, 0] - grid[lo:hi]
                except np.linalg.LinAlgError:
                    n_sing = int(np.sum(np.abs(np.linalg.det(m[:, :, :3])) < 1e-12))
                    raise ValueError(
                        f"correspondence {k}: the blended matrix (Σ w T) of {n_sing} voxel(s) is "
                        "singular, so VBD cannot be undone there (Rhee Eq. 7); the pose's "
                        "transforms or the weights are degenerate"
                    ) from None
            if progress is not None:
                progress(k + 1, len(poses))
        return cls(geometry, weights, PoseSpace(skeleton, vectors), d, template_example=with_template, scan_sigma=sig)

    def pose_weights(self, pose) -> np.ndarray:
        return self.space.weights(pose)

    def _blend(self, lo, hi, s, keep) -> np.ndarray:
        """``Σ_p s_p d_p`` over the examples ``keep`` for voxels ``lo:hi``, capped at their longest (float64)."""
        d = self.displacements[lo:hi][:, keep].astype(np.float64)
        out = np.einsum("npc,p->nc", d, s)
        cap = (d**2).sum(-1).max(axis=1) if d.shape[1] else np.zeros(hi - lo)
        n2 = (out**2).sum(-1)
        f = np.ones_like(n2)
        over = n2 > cap * (1.0 + 1e-6)  # as the forward kernel: the length capped, the direction kept
        f[over] = np.sqrt(cap[over] / n2[over])
        return out * f[:, None]

    def cross_validation_variance(self) -> np.ndarray:
        """The pose interpolation's variance (mm²) per voxel, from leaving each scan out (module docstring,
        "Uncertainty"): ``mean_k (r_k² − σ_k² − Σ_j s_j² σ_j²) / (1 − γ_k)``, ``r_k`` the residual of ``d_k``
        predicted from the other examples at scan k's pose, ``σ`` the scans' expected errors (0 without
        ``scan_sigma``) and ``γ_k`` the share the others explain there
        (:meth:`~deformation.models.posespace.PoseSpace.explained`), pooled over a Gaussian of
        ``CV_POOL_VOXELS`` and clipped at 0 (``1 − γ_k`` floored at 0.05: a pose the others explain almost
        wholly would divide its residual by almost nothing).  ``(n_voxels,)`` float32; zeros with one example
        (one scan at rest: nothing to leave out)."""
        if self._cv_var is not None:
            return self._cv_var
        n, P, ns = self.geometry.n_voxels, self.space.n_poses, self.n_scans
        total = np.zeros(n)
        if P < 2 or ns < 1:
            self._cv_var = total.astype(np.float32)
            return self._cv_var
        sig2 = None if self.scan_sigma is None else self.scan_sigma.astype(np.float64) ** 2
        for k in range(ns):
            keep = [p for p in range(P) if p != k]
            others = PoseSpace(self.space.skeleton, self.space.train[keep])
            s = others.weights(self.space.train[k])  # Kurihara Eq. 14 at scan k's pose, from the others
            share = max(1.0 - others.explained(self.space.train[k]), 0.05)  # the unexplained share, floored
            s_scans = np.array([s[i] if keep[i] < ns else 0.0 for i in range(len(keep))])  # the template's σ: 0
            for lo in range(0, n, 1 << 18):
                hi = min(n, lo + (1 << 18))
                r2 = ((self.displacements[lo:hi, k].astype(np.float64) - self._blend(lo, hi, s, keep)) ** 2).sum(-1)
                if sig2 is not None:  # the scans' own errors are in the residual: the interpolation's is the rest
                    sc = [p for p in keep if p < ns]
                    r2 -= sig2[lo:hi, k] + sig2[lo:hi][:, sc] @ (s_scans[: len(sc)] ** 2)
                total[lo:hi] += r2 / share
        # each voxel's mean of a few residuals, less their expected noise, is itself noisy (and the division by a
        # small unexplained share amplifies it): pooled over a Gaussian of CV_POOL_VOXELS before the clip at 0
        from scipy import ndimage

        pooled = ndimage.gaussian_filter(
            (total / ns).reshape(self.geometry.array_shape), CV_POOL_VOXELS, mode="nearest"
        )
        self._cv_var = np.maximum(pooled.reshape(-1), 0.0).astype(np.float32)
        return self._cv_var

    def expected_error(self, pose) -> np.ndarray:
        """The posed volume's expected error (mm) at every template voxel, ``(nz, ny, nx)`` float32 (module
        docstring, "Uncertainty"): ``√(Σ_k s_k² σ_k² + (1 − γ(a)) v)``, the scans' errors blended by the pose
        weights of Kurihara Eq. 14 and the cross-validated interpolation variance ``v`` where the training
        poses do not explain the pose (``γ``, :meth:`~deformation.models.posespace.PoseSpace.explained`: 1 at a
        training pose)."""
        s = self.space.weights(pose)
        var = np.float32(1.0 - self.space.explained(pose)) * self.cross_validation_variance()
        if self.scan_sigma is not None:  # float32 throughout: no float64 copy of the (n_voxels, n_scans) σ
            s2 = (s[: self.n_scans] ** 2).astype(np.float32)
            for lo in range(0, len(var), 1 << 20):
                hi = min(len(var), lo + (1 << 20))
                var[lo:hi] += np.square(self.scan_sigma[lo:hi]) @ s2
        return np.sqrt(var).reshape(self.geometry.array_shape)

    def forward(self, pose, transforms=None, *, weighting: str = "psd", cap: bool = True) -> np.ndarray:
        """The posed position of every template voxel at ``pose`` (Rhee Eq. 6), ``(nz, ny, nx, 3)`` float32.

        ``pose`` is a :class:`~deformation.kinematics.skeleton.Pose` (or a pose vector
        together with ``transforms``); ``weighting`` is ``"psd"`` (one set of
        normalised RBF weights for every voxel, Rhee's choice) or ``"wpsd"``
        (per-voxel weights, Kurihara Eq. 16); ``cap`` False leaves the blended displacement uncapped beyond the
        examples' range (Rhee Eq. 6 as written; module docstring).
        """
        if weighting not in EVD_WEIGHTINGS:
            raise ValueError(f"weighting must be one of {EVD_WEIGHTINGS}, got {weighting!r}")
        if transforms is None:
            if isinstance(pose, np.ndarray):
                raise ValueError("give the bone transforms with a bare pose vector")
            transforms = pose.transforms
        t = np.ascontiguousarray(stack_transforms(transforms, self.weights.bones)[:, :3, :])
        g = self.geometry
        nx, ny, nz = g.size
        a = np.ascontiguousarray(g.index_to_world_matrix[:3])
        out = np.empty(g.array_shape + (3,), dtype=np.float32)
        if weighting == "psd":
            s = np.ascontiguousarray(self.space.weights(pose), dtype=np.float64)  # Kurihara Eq. 12–15: s_k(a)
            # Rhee Eq. 6: va = E(v0 + Σ_k s_k(a) d_k) for every template voxel
            forward_kernel(
                a, nx, ny, nz, self.weights.index, self.weights.value, t, self.displacements, s, out, bool(cap)
            )
        else:
            vec = self.space.vector(pose)
            train = self.space.train
            bone_pair = per_bone_sq(train[:, None, :] - train[None, :, :], self._dof_bone, self.weights.n_bones)
            bone_q = per_bone_sq(vec[None, :] - train, self._dof_bone, self.weights.n_bones)
            # Rhee Eq. 6 with WPSD's per-voxel s_k (Kurihara Eq. 16 in place of Kurihara Eq. 15)
            _forward_kernel_wpsd(
                a,
                nx,
                ny,
                nz,
                self.weights.index,
                self.weights.value,
                t,
                self.displacements,
                bone_pair,
                bone_q,
                out,
                bool(cap),
            )
        return out
