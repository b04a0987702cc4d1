"""Pose space: RBF pose weights, pose space deformation (PSD), weighted PSD (WPSD).

Kurihara & Miyata 2004 §5.  A *pose vector* ``a`` is the concatenation of
every joint's degrees of freedom in the skeleton's joint order (degrees; the
translations of a 6-DOF joint in mm); the root bone's world placement is not
part of it, since moving the whole body does not deform it.

Pose weights: ``f_i(a) = Σ_j c_ij φ(d(a, a_j))`` with ``f_i(a_j) = δ_ij``
(Kurihara Eq. 12–13), so ``C = Φ⁻¹``; then ``s_i = f_i / Σ_j f_j``
(Kurihara Eq. 14), which gives Kurihara Eq. 10–11.  The paper does not name ``φ``; we
use a Gaussian ``φ(d) = exp(−(d/σ)²)`` whose width ``σ`` is the mean
nearest-neighbour distance between the training poses in the same metric
(scale-free), and whose kernel matrix of distinct poses is positive definite.

Distances: PSD uses ``d(a, b) = √Σ_k (a_k − b_k)²`` (Kurihara Eq. 15); WPSD
uses per point ``j`` ``d_j(a, b) = √Σ_k u_jk (a_k − b_k)²`` (Kurihara Eq. 16)
with, as the paper did, ``u_jk`` the point's skinning weight of the bone that
DOF ``k`` moves.  A floor ``u_jk ≥ U_FLOOR`` makes a point wholly on the root
bone fall back to the global PSD weights.

PSD itself (Kurihara Eq. 6–8) is in :func:`psd_training` (the inverse SSD of
each sample, Kurihara Eq. 6) and :func:`psd_deform` (morph, Kurihara Eq. 7,
then SSD, Kurihara Eq. 8).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from deformation.models.skinning import SkinningWeights, blend_point, inverse_lbs, lbs, stack_transforms

__all__ = [
    "PoseSpace",
    "pose_vector",
    "pose_weights",
    "U_FLOOR",
    "psd_training",
    "psd_deform",
    "PointPoseSpace",
    "wpsd_deform",
    "skin",
    "dof_bones",
    "per_bone_sq",
    "chol_factor",
    "chol_subst",
    "query_kernel",
    "rbf_width",
    "weighted_sq",
]

#: Floor on the WPSD DOF weights ``u_jk`` (see the module docstring).
U_FLOOR = 1e-6


def pose_vector(skeleton, pose) -> np.ndarray:
    """The pose vector of a :class:`~deformation.kinematics.skeleton.Pose`: every joint's DOF values, joint order.

    Uses the pose's recorded joint angles when present, otherwise recovers
    them from the bone transforms (``Joint.angles_from_motion`` of the
    child's motion relative to its parent).
    """
    parts = []
    for j in skeleton.joints:
        ang = None if pose.joint_angles is None else pose.joint_angles.get(j.name)
        if ang is None:
            ang = j.angles_from_motion(skeleton.relative_motion(pose.transforms, j.name))
        ang = np.asarray(ang, dtype=float).reshape(-1)
        if ang.shape != (j.dof,):
            raise ValueError(f"joint {j.name!r} has {j.dof} DOF but the pose gives {ang.size} values")
        parts.append(ang)
    return np.concatenate(parts) if parts else np.zeros(0)


def dof_bones(skeleton, bones) -> np.ndarray:
    """For every pose-vector component, the index (in ``bones``) of the bone that DOF moves (the joint's child)."""
    bones = tuple(bones)
    out = []
    for j in skeleton.joints:
        if j.child not in bones:
            raise ValueError(
                f"joint {j.name!r} moves bone {j.child!r}, which the skinning weights do not have "
                f"(they cover {list(bones)})"
            )
        out += [bones.index(j.child)] * j.dof
    return np.asarray(out, dtype=np.int64)


def per_bone_sq(diff: np.ndarray, dof_bone: np.ndarray, n_bones: int) -> np.ndarray:
    """Squared pose-vector differences summed per bone (Kurihara Eq. 16's ``Σ_k u_jk (a_k − a_ik)²``, before
    the point's weights): ``out[b, ...] = Σ_{k: dof_bone[k] = b} diff[..., k]²``, shape ``(n_bones,) +
    diff.shape[:-1]``.  A joint's DOFs are adjacent in the pose vector, so each bone's are one run, all summed
    by one ``np.add.reduceat`` (13 µs for the hand's 66 DOFs; a Python loop over the DOFs took 70 µs, a
    sixth of WPSD's time on a 50k-vertex mesh)."""
    diff = np.asarray(diff, dtype=np.float64)
    out = np.zeros((n_bones,) + diff.shape[:-1])
    if not len(dof_bone):
        return out
    starts = np.flatnonzero(np.r_[True, dof_bone[1:] != dof_bone[:-1]])
    # Kurihara Eq. 16's (a_k − b_k)², summed over the DOFs k of each bone (u_jk is the same for all of them)
    runs = np.moveaxis(np.add.reduceat(diff * diff, starts, axis=-1), -1, 0)
    np.add.at(out, dof_bone[starts], runs)  # a bone's runs added up (one run each: its parent joint's DOFs)
    return out


def _nn_width(sq_pair: np.ndarray) -> float:
    """Mean nearest-neighbour distance from a matrix of squared pair distances (the Gaussian's σ)."""
    n = sq_pair.shape[0]
    if n < 2:
        return 1.0
    d = np.sqrt(np.maximum(sq_pair, 0.0)) + np.diag(np.full(n, np.inf))
    return float(np.mean(d.min(axis=1)))


def pose_weights(train: np.ndarray, query: np.ndarray, *, dof_weights=None) -> np.ndarray:
    """Normalised RBF weights ``s_i(a)`` of the training poses at ``query`` (Kurihara Eq. 12–14).

    ``train (P, n_dof)``, ``query (n_dof,)`` or ``(Q, n_dof)``; ``dof_weights
    (n_dof,)`` gives Kurihara Eq. 16's ``u_k`` for one point (default all one: Kurihara Eq. 15).
    Returns ``(P,)`` or ``(Q, P)``, each row summing to one.
    """
    train = np.atleast_2d(np.asarray(train, dtype=float))
    q = np.asarray(query, dtype=float)
    single = q.ndim == 1
    q = np.atleast_2d(q)
    u = np.ones(train.shape[1]) if dof_weights is None else np.asarray(dof_weights, dtype=float)
    if q.shape[1] != train.shape[1] or u.shape != (train.shape[1],):
        raise ValueError(f"query has {q.shape[1]} DOF, the training poses {train.shape[1]}, dof_weights {u.shape}")
    if train.shape[0] == 1:
        s = np.ones((q.shape[0], 1))
        return s[0] if single else s
    # Kurihara Eq. 15 squared (Kurihara Eq. 16 with dof_weights) between the training poses
    pair = ((train[:, None, :] - train[None, :, :]) ** 2 * u).sum(-1)
    sigma = _nn_width(pair)
    if sigma <= 0:
        raise ValueError("two training poses coincide (zero pose distance): Φ of Kurihara Eq. 13 is singular")
    phi = np.exp(-pair / sigma**2)  # Φ_ij = φ(d(a_i, a_j)) of Kurihara Eq. 13 at the examples (Kurihara Eq. 12)
    dq = ((q[:, None, :] - train[None, :, :]) ** 2 * u).sum(-1)  # Kurihara Eq. 15 squared: d(a, a_j)²
    try:
        # Kurihara Eq. 13: f_i(a) = Σ_j c_ij φ_j(a), C = Φ⁻¹ (Kurihara Eq. 12: f_i(a_j) = δ_ij); φ scaled by
        # exp(min dq / σ²), which Kurihara Eq. 14's normalisation cancels: far from every example, the φ
        # themselves underflow to 0 and s would be 0 / 0
        dq = dq - dq.min(axis=1, keepdims=True)
        f = np.linalg.solve(phi, np.exp(-dq / sigma**2).T).T
    except np.linalg.LinAlgError:
        raise ValueError(
            "Φ of Kurihara Eq. 13 is singular: two training poses coincide in this pose distance (drop one)"
        ) from None
    # Kurihara Eq. 14: s_i = f_i / Σ_j f_j, so Σ_i s_i = 1 (Kurihara Eq. 11) and s_i(a_j) = δ_ij (Kurihara Eq. 10)
    s = f / f.sum(axis=1, keepdims=True)
    return s[0] if single else s


class PoseSpace:
    """Training poses of a skeleton, and their normalised RBF weights at any pose (PSD, Kurihara Eq. 12–15)."""

    def __init__(self, skeleton, train_poses):
        self.skeleton = skeleton
        vecs = [p if isinstance(p, np.ndarray) else pose_vector(skeleton, p) for p in train_poses]
        self.train = np.asarray(np.stack(vecs), dtype=float)
        if self.train.ndim != 2 or self.train.shape[1] != skeleton.n_dof:
            raise ValueError(f"training pose vectors must have {skeleton.n_dof} values, got {self.train.shape}")
        d = np.sqrt(((self.train[:, None] - self.train[None]) ** 2).sum(-1)) + np.eye(len(self.train))
        if len(self.train) > 1 and d.min() < 1e-9:
            i, j = np.unravel_index(np.argmin(d), d.shape)
            raise ValueError(
                f"training poses {i} and {j} are identical: pose space interpolation needs distinct poses (drop one)"
            )

    @property
    def n_poses(self) -> int:
        return int(self.train.shape[0])

    def vector(self, pose) -> np.ndarray:
        return pose if isinstance(pose, np.ndarray) else pose_vector(self.skeleton, pose)

    def weights(self, pose) -> np.ndarray:
        """``s(a)`` over the training poses (Kurihara Eq. 14)."""
        return pose_weights(self.train, self.vector(pose))

    def explained(self, pose) -> float:
        """``φ(a)ᵀ Φ⁻¹ φ(a)`` in [0, 1], Φ and φ the Gaussians of Kurihara Eq. 13 (unscaled): the share of a unit
        Gaussian process's variance at ``a`` that the training poses explain — 1 at a training pose, falling to
        0 far from them (the process's posterior variance there is ``1 − explained``); 1 with one training pose
        at that pose, 0 elsewhere."""
        q = self.vector(pose)
        train = self.train
        if len(train) < 2:
            return float(np.sum((train[0] - q) ** 2) < 1e-18)
        pair = ((train[:, None, :] - train[None, :, :]) ** 2).sum(-1)
        sigma = _nn_width(pair)
        phi = np.exp(-((train - q[None]) ** 2).sum(-1) / sigma**2)
        return float(np.clip(phi @ np.linalg.solve(np.exp(-pair / sigma**2), phi), 0.0, 1.0))

    def point_space(self, weights: SkinningWeights) -> PointPoseSpace:
        """Per-point WPSD coefficients for points with these skinning weights (Kurihara Eq. 16)."""
        return PointPoseSpace(self, weights)


# -- per-point (WPSD) pose weights ------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def query_kernel(phi, n, inv):
    """φ_i = exp(−(d_i − min d) / σ²) in place from squared pose distances d (Kurihara Eq. 13's φ): the common
    factor exp(min d / σ²) cancels in Kurihara Eq. 14's normalisation, and without it a pose far from every example
    underflows every φ to 0 (s = 0 / 0)."""
    m = np.inf
    for i in range(n):
        if phi[i] < m:
            m = phi[i]
    for i in range(n):
        phi[i] = np.exp(-(phi[i] - m) * inv)  # Kurihara Eq. 13's φ(d(a, a_i)), scaled by exp(min d / σ²)


@nb.njit(cache=True, inline="always")
def chol_factor(a, n):
    """In-place lower Cholesky factor of the SPD matrix a (n×n).  False if a is not positive definite."""
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if s <= 0.0:
            return False
        a[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            t = a[i, j]
            for k in range(j):
                t -= a[i, k] * a[j, k]
            a[i, j] = t / a[j, j]
    return True


@nb.njit(cache=True, inline="always")
def chol_subst(a, b, n, work):
    """Solve L Lᵀ x = b with the factor from :func:`chol_factor`; b is overwritten by x."""
    for i in range(n):
        t = b[i]
        for k in range(i):
            t -= a[i, k] * work[k]
        work[i] = t / a[i, i]
    for i in range(n - 1, -1, -1):
        t = work[i]
        for k in range(i + 1, n):
            t -= a[k, i] * b[k]
        b[i] = t / a[i, i]


@nb.njit(cache=True, inline="always")
def weighted_sq(idx, val, j, per_bone, glob, out):
    """Kurihara Eq. 16 squared: ``out[r] = Σ_b u_jb per_bone[b, r]`` with ``u_jb = U_FLOOR + w_jb``.

    ``per_bone (n_bones, R)`` holds the squared DOF differences summed per bone (for the query pose,
    ``R = P``; for the training pairs, ``R = P²``) and ``glob (R,)`` their sum over bones, which carries
    the floor, so only the point's ≤ K influencing bones are visited.
    """
    for r in range(out.shape[0]):
        out[r] = U_FLOOR * glob[r]  # Kurihara Eq. 16's u_jk floored: U_FLOOR on every bone, not in the paper
    for m in range(idx.shape[1]):
        w = val[j, m]
        if w == 0.0:
            continue
        b = idx[j, m]
        for r in range(out.shape[0]):
            out[r] += w * per_bone[b, r]  # Kurihara Eq. 16 squared: Σ_k u_jk (a_k − b_k)², u_jk = w_jb


@nb.njit(cache=True, inline="always")
def rbf_width(pair, P):
    """The Gaussian's width ``σ``: the mean nearest-neighbour distance of ``P`` poses from their squared
    pairwise distances ``pair (P, P)`` (the module docstring's scale-free width)."""
    tot = 0.0
    for i in range(P):
        m = np.inf
        for l in range(P):
            if l != i and pair[i, l] < m:
                m = pair[i, l]
        tot += np.sqrt(max(m, 0.0))
    return tot / P


@nb.njit(cache=True, parallel=True)
def _wpsd_coefficients(idx, val, bone_pair, out_c, out_inv_sigma2):
    """Per point: C = Φ⁻¹ (P×P) and 1/σ² (Kurihara: "we can precompute coefficient c_ij for every vertex")."""
    n = idx.shape[0]
    n_bones, P = bone_pair.shape[0], bone_pair.shape[1]
    flat = bone_pair.reshape(n_bones, P * P)
    glob = flat.sum(axis=0)
    for j in nb.prange(n):
        pair_flat = np.empty(P * P)
        a = np.empty((P, P))
        col = np.empty(P)
        work = np.empty(P)
        weighted_sq(idx, val, j, flat, glob, pair_flat)
        pair = pair_flat.reshape(P, P)
        sig = rbf_width(pair, P)
        inv = 1.0 / (sig * sig)
        out_inv_sigma2[j] = inv
        for i in range(P):
            for l in range(P):
                a[i, l] = np.exp(
                    -pair[i, l] * inv
                )  # Φ_il = φ(d_j(a_i, a_l)), Kurihara Eq. 13 with Kurihara Eq. 16's d_j
        ok = chol_factor(a, P)
        for c in range(P):
            for i in range(P):
                col[i] = 1.0 if i == c else 0.0
            if ok:
                chol_subst(a, col, P, work)  # Kurihara Eq. 12: f_i(a_l) = δ_il gives C_j = Φ_j⁻¹, column c
            for i in range(P):
                out_c[j, i, c] = col[i] if ok else np.nan


class PointPoseSpace:
    """WPSD (Kurihara Eq. 16): per-point pose weights from per-point pose distances.

    ``u_jk`` is the point's skinning weight of the bone that DOF ``k`` moves
    (floored at :data:`U_FLOOR`).  The coefficient matrices ``C_j = Φ_j⁻¹``
    and the widths are precomputed per point, as Kurihara suggests, so an
    evaluation costs ``O(n_pose²)`` per point (:meth:`weights`).
    """

    def __init__(self, space: PoseSpace, weights: SkinningWeights):
        self.space = space
        self.weights_ = weights
        self.dof_bone = dof_bones(space.skeleton, weights.bones)
        # squared DOF differences summed per bone: bone_pair[b, i, l] = Σ_{k moves b} (a_ik − a_lk)²
        self.bone_pair = self._per_bone(space.train[:, None, :] - space.train[None, :, :])
        P = space.n_poses
        self.coef = np.empty((weights.n_points, P, P))
        self.inv_sigma2 = np.empty(weights.n_points)
        _wpsd_coefficients(weights.index, weights.value, self.bone_pair, self.coef, self.inv_sigma2)
        bad = ~np.isfinite(self.coef).all(axis=(1, 2))
        if bad.any():
            raise ValueError(
                f"{int(bad.sum())} points have a singular WPSD kernel matrix (Kurihara Eq. 16): two training "
                "poses coincide in those points' weighted pose distance"
            )

    def _per_bone(self, diff: np.ndarray) -> np.ndarray:
        return per_bone_sq(diff, self.dof_bone, self.weights_.n_bones)

    def fold(self, base_samples_per_point: np.ndarray) -> np.ndarray:
        """WPSD's per-point coefficients folded with the base-pose samples, ``(n, P, 4)``: ``[..., :3] = B_j =
        C_jᵀ base_j`` and ``[..., 3] = c_j = C_jᵀ 1``.  Kurihara Eq. 14 and 7 give ``u_j = Σ_i s_ji base_ji`` with
        ``s_j = C_j φ_j / Σ_i (C_j φ_j)_i``, which is ``Σ_l φ_jl B_jl / Σ_l φ_jl c_jl``: per evaluation 4P
        products a point instead of P² + 3P (Kurihara precomputes C_j; the samples are fixed too)."""
        base = np.asarray(base_samples_per_point, dtype=np.float64)
        P = self.space.n_poses
        if base.shape != (self.weights_.n_points, P, 3):
            raise ValueError(
                f"base samples must be (n_points, n_poses, 3) = {(self.weights_.n_points, P, 3)}, got {base.shape}"
            )
        out = np.empty((base.shape[0], P, 4))
        out[..., :3] = np.einsum("jil,jic->jlc", self.coef, base)  # B_j = C_jᵀ base_j (Kurihara Eq. 13 and 7)
        out[..., 3] = self.coef.sum(axis=1)  # c_j = C_jᵀ 1 (Kurihara Eq. 14's denominator)
        return out

    def weights(self, pose) -> np.ndarray:
        """``s_j(a)`` of every point: ``(n_points, n_poses)``, rows summing to one."""
        a = self.space.vector(pose)
        bone_q = self._per_bone((a[None, :] - self.space.train)[None])[:, 0]  # (n_bones, P)
        out = np.empty((self.weights_.n_points, self.space.n_poses))
        _wpsd_weights(self.weights_.index, self.weights_.value, bone_q, self.coef, self.inv_sigma2, out)
        return out


@nb.njit(cache=True, parallel=True)
def _wpsd_weights(idx, val, bone_q, coef, inv_sigma2, out):
    n = idx.shape[0]
    P = bone_q.shape[1]
    glob_q = bone_q.sum(axis=0)
    for j in nb.prange(n):
        phi = np.empty(P)
        weighted_sq(idx, val, j, bone_q, glob_q, phi)
        query_kernel(phi, P, inv_sigma2[j])
        tot = 0.0
        for i in range(P):
            f = 0.0
            for l in range(P):
                f += coef[j, i, l] * phi[l]  # Kurihara Eq. 13: f_i(a) = Σ_l c_il φ(d_j(a, a_l))
            out[j, i] = f
            tot += f
        for i in range(P):
            out[j, i] /= tot  # Kurihara Eq. 14: s_ji = f_i / Σ_l f_l


# -- PSD / WPSD of meshes (Kurihara Eq. 6–8) --------------------------------------------------------
def psd_training(samples, weights: SkinningWeights, sample_transforms) -> np.ndarray:
    """Every sample's vertices taken to the base pose by inverse SSD (Kurihara Eq. 6): ``(P, n, 3)``.

    ``samples`` is a sequence of ``(n, 3)`` vertex arrays in corresponding
    order (vertex ``j`` of every sample is the same skin point), and
    ``sample_transforms`` one set of bone transforms (template → sample) per
    sample.
    """
    # Kurihara Eq. 6: v⁰_ij = (Σ_k w_jk L_ik)⁻¹ v_ij for every sample i
    return np.stack([inverse_lbs(v, weights, t) for v, t in zip(samples, sample_transforms, strict=True)])


def psd_deform(base_samples: np.ndarray, weights: SkinningWeights, s: np.ndarray, transforms) -> np.ndarray:
    """PSD: morph the base-pose samples with ``s`` (Kurihara Eq. 7), then SSD with the pose's transforms
    (Kurihara Eq. 8).

    ``s`` is ``(P,)`` for PSD (the same weights for all vertices) or ``(n, P)``
    for WPSD (per-vertex weights from :meth:`PointPoseSpace.weights`).
    """
    s = np.asarray(s, dtype=float)
    if s.ndim == 1:
        u0 = np.tensordot(s, base_samples, axes=(0, 0))  # Kurihara Eq. 7: u⁰_j = Σ_i s_i v⁰_ij
    else:
        u0 = np.einsum("np,pnc->nc", s, base_samples)  # Kurihara Eq. 7 with WPSD's per-vertex s_ji
    # Kurihara Eq. 8: u_j = Σ_k w_jk L_k u⁰_j; L_k are the pose's own bone transforms, not Kurihara's joint angles
    # interpolated with s_i (the pose is given, so its transforms are known)
    return lbs(u0, weights, transforms)


@nb.njit(cache=True, parallel=True)
def _skin_kernel(base, s, per_point, idx, val, t, out):
    """out_j = (Σ_k w_jk T_k)(Σ_i s_ji base_ij): Kurihara Eq. 7 and 8 fused; base (n, P, 3)."""
    n, P = base.shape[0], base.shape[1]
    for j in nb.prange(n):
        u0 = 0.0
        u1 = 0.0
        u2 = 0.0
        for i in range(P):  # Kurihara Eq. 7: u⁰_j = Σ_i s_ji v⁰_ij (one example and s = 1: plain SSD's p_j)
            si = s[j, i] if per_point else s[0, i]
            u0 += si * base[j, i, 0]
            u1 += si * base[j, i, 1]
            u2 += si * base[j, i, 2]
        o0, o1, o2 = blend_point(idx, val, j, t, u0, u1, u2)  # Kurihara Eq. 8 (Kurihara Eq. 2 for plain SSD)
        out[j, 0] = o0
        out[j, 1] = o1
        out[j, 2] = o2


def skin(base_points: np.ndarray, weights: SkinningWeights, transforms, s=None) -> np.ndarray:
    """Compiled SSD / PSD / WPSD in one pass.

    ``base_points`` is ``(n, 3)`` (plain SSD, Kurihara Eq. 2) or ``(n, P, 3)`` base-pose
    samples laid out per point; ``s`` is ``(P,)`` (PSD) or ``(n, P)`` (WPSD).
    """
    t = stack_transforms(transforms, weights.bones)[:, :3, :]
    base = np.asarray(base_points, dtype=np.float64)
    if base.ndim == 2:
        if s is not None:
            raise ValueError("pose weights s only apply to (n, P, 3) base samples; (n, 3) points are plain SSD")
        base = base[:, None, :]
        s = np.ones((1, 1))
    elif s is None:
        raise ValueError("pose weights s are needed with (n, P, 3) base samples")
    s = np.atleast_2d(np.asarray(s, dtype=np.float64))
    if s.ndim != 2 or s.shape[0] not in (1, base.shape[0]):
        raise ValueError(f"pose weights must be (P,) or (n_points, P), got {s.shape}")
    if base.shape[0] != weights.n_points or s.shape[-1] != base.shape[1]:
        raise ValueError(
            f"base points {base.shape}, pose weights {s.shape} and {weights.n_points} weighted points do not agree"
        )
    out = np.empty((base.shape[0], 3))
    _skin_kernel(base, s, s.shape[0] == base.shape[0] and s.shape[0] > 1, weights.index, weights.value, t, out)
    return out


@nb.njit(cache=True, parallel=True)
def _wpsd_exponents(idx, val, inv_sigma2, bone_q, glob_q, arg):
    """Per point j, the exponents of Kurihara Eq. 13's φ with Kurihara Eq. 16's distances:
    ``arg[j, l] = −(d_jl − min_l d_jl) / σ_j²`` (:func:`query_kernel`'s shift against underflow), ``d_jl``
    as :func:`weighted_sq` sums it (``glob_q[l] = Σ_b bone_q[b, l]`` carries the U_FLOOR term, so only the
    point's ≤ K bones are visited), written in place (cheaper than a row view per point)."""
    n, P = arg.shape
    for j in nb.prange(n):
        for l in range(P):
            arg[j, l] = U_FLOOR * glob_q[l]
        for m in range(idx.shape[1]):
            w = val[j, m]
            if w == 0.0:
                continue
            b = idx[j, m]
            for l in range(P):
                arg[j, l] += w * bone_q[b, l]  # Kurihara Eq. 16 squared, as weighted_sq
        m = arg[j, 0]
        for l in range(1, P):
            m = min(m, arg[j, l])
        inv = inv_sigma2[j]
        for l in range(P):
            arg[j, l] = -(arg[j, l] - m) * inv  # the exponent of Kurihara Eq. 13's φ, shifted as in query_kernel


@nb.njit(cache=True, parallel=True)
def _wpsd_skin_kernel(folded, idx, val, t, phi, out):
    """WPSD's morph and skin per point j: u0 = Σ_l φ_jl B_jl / Σ_l φ_jl c_jl (Kurihara Eq. 14 and 7 through
    :meth:`PointPoseSpace.fold`), then SSD (Kurihara Eq. 8)."""
    n, P = folded.shape[0], folded.shape[1]
    for j in nb.prange(n):
        u0 = 0.0
        u1 = 0.0
        u2 = 0.0
        tot = 0.0
        for l in range(P):  # Kurihara Eq. 13, 14 and 7 folded: Σ_l φ_jl B_jl and Σ_l φ_jl c_jl
            p = phi[j, l]
            u0 += p * folded[j, l, 0]
            u1 += p * folded[j, l, 1]
            u2 += p * folded[j, l, 2]
            tot += p * folded[j, l, 3]
        # Kurihara Eq. 14's normalisation gives u⁰_j (Kurihara Eq. 7); then Kurihara Eq. 8: Σ_k w_jk L_k u⁰_j
        o0, o1, o2 = blend_point(idx, val, j, t, u0 / tot, u1 / tot, u2 / tot)
        out[j, 0] = o0
        out[j, 1] = o1
        out[j, 2] = o2


def wpsd_deform(
    base_samples_per_point: np.ndarray,
    weights: SkinningWeights,
    point_space: PointPoseSpace,
    pose,
    transforms,
    *,
    folded: np.ndarray | None = None,
) -> np.ndarray:
    """WPSD (Kurihara §5.2): per-vertex pose weights (Kurihara Eq. 16), morph (Kurihara Eq. 7), SSD
    (Kurihara Eq. 8).

    ``base_samples_per_point`` is ``(n, P, 3)``: each vertex's base-pose position in every sample
    (:func:`psd_training`, transposed).  Equal to ``skin(base, weights, transforms,
    point_space.weights(pose))`` up to rounding, without the ``(n, P)`` weights.  ``folded``:
    ``point_space.fold(base)``, made once for a mesh posed many times (made here when not given).
    The exponentials run in NumPy (vectorised, faster than one by one in a numba loop:
    docs/measurements/deformation-and-validation.md).
    """
    if point_space.weights_ is not weights:
        raise ValueError(
            "the point pose space was built for other skinning weights: build it with "
            "PoseSpace.point_space(weights) for these"
        )
    P = point_space.space.n_poses
    if folded is None:
        folded = point_space.fold(base_samples_per_point)
    elif folded.shape != (weights.n_points, P, 4):
        raise ValueError(
            f"folded samples must be (n_points, n_poses, 4) = {(weights.n_points, P, 4)} "
            f"(PointPoseSpace.fold), got {folded.shape}"
        )
    a = point_space.space.vector(pose)
    bone_q = np.ascontiguousarray(point_space._per_bone((a[None, :] - point_space.space.train)[None])[:, 0])
    t = stack_transforms(transforms, weights.bones)[:, :3, :]
    phi = np.empty((weights.n_points, P))
    _wpsd_exponents(weights.index, weights.value, point_space.inv_sigma2, bone_q, bone_q.sum(axis=0), phi)
    np.exp(phi, out=phi)  # Kurihara Eq. 13's φ(d_j(a, a_l))
    out = np.empty((weights.n_points, 3))
    _wpsd_skin_kernel(folded, weights.index, weights.value, np.ascontiguousarray(t), phi, out)
    return out
