"""Skinning: sparse per-point bone weights, linear blend skinning and its inverse.

* :class:`SkinningWeights` — at most ``K`` (default 4) bone influences per
  point, non-negative and summing to one (Kurihara Eq. 3), laid out per point
  (``index (n, K)``, ``value (n, K)``) so that one pass over the points reads
  them contiguously.
* :func:`blend_matrices` — the blended matrix ``M(p) = Σ_k w_k(p) T_k`` of
  every point.
* :func:`lbs` — linear blend skinning of mesh vertices, Kurihara Eq. 2
  (``p' = Σ_k w_k L_k p``); the same map on voxel grid points is volume blend
  deformation, Rhee Eq. 2 (:func:`vbd_points`).
* :func:`inverse_lbs` — the per-point inverse where the correspondence is
  known (Kurihara Eq. 6, Rhee Eq. 7): ``p = (Σ_k w_k T_k)⁻¹ p'`` with the
  weights of the point's *template* position.

Transforms are 4×4 matrices mapping template world → posed world (mm), given
as an array ``(n_bones, 4, 4)`` in the order of ``SkinningWeights.bones``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

__all__ = [
    "SkinningWeights",
    "MAX_INFLUENCES",
    "blend_matrices",
    "lbs",
    "vbd_points",
    "inverse_lbs",
    "stack_transforms",
    "distance_weights",
    "distance_voxel_weights",
    "blend_point",
]

#: Influences kept per point (Kurihara's meshes and GPU skinning use four).
MAX_INFLUENCES = 4


#: rows per chunk of the dense → sparse weight steps (bounds their temporaries to a few tens of MB)
DENSE_CHUNK = 1 << 16


@dataclass(eq=False)
class SkinningWeights:
    """Sparse skinning weights of ``n`` points over the bones ``bones``.

    Parameters
    ----------
    bones : sequence of str
        Bone names; ``index`` refers to positions in this tuple.
    index : (n, K) integer array
        Bone index of each influence, strongest first.  Unused slots have
        value 0 and repeat the strongest bone's index (so a gather never goes
        out of range).
    value : (n, K) float array
        Weights, non-negative, each row summing to one (checked to 1e-5, then
        stored as float32).
    """

    bones: tuple
    index: np.ndarray
    value: np.ndarray

    def __post_init__(self):
        self.bones = tuple(str(b) for b in self.bones)
        index = np.asarray(self.index)
        value = np.asarray(self.value)
        if value.dtype != np.float32:
            value = value.astype(np.float64)
        if index.ndim != 2 or value.shape != index.shape:
            raise ValueError(f"index and value must both be (n, K); got {index.shape} and {value.shape}")
        if not np.issubdtype(index.dtype, np.integer):
            raise ValueError(f"index must be integers, got {index.dtype}")
        if index.size and (index.min() < 0 or index.max() >= len(self.bones)):
            raise ValueError(f"bone index out of range 0..{len(self.bones) - 1}: found {index.min()}..{index.max()}")
        if not np.all(np.isfinite(value)):
            raise ValueError("weights must be finite")
        if value.size and value.min() < -1e-6:
            raise ValueError(f"weights must be non-negative (Kurihara Eq. 3); minimum {value.min():.3g}")
        sums = value.sum(axis=1, dtype=np.float64) if value.shape[1] <= 8 else value.sum(axis=1)
        if value.size and np.max(np.abs(sums - 1.0)) > 1e-5:  # Kurihara Eq. 3: Σ_k w_jk = 1 per point
            worst = int(np.argmax(np.abs(sums - 1.0)))
            raise ValueError(
                f"weights must sum to one per point (Kurihara Eq. 3); point {worst} sums to {sums[worst]:.6f}"
            )
        self.index = np.ascontiguousarray(index, dtype=np.int16 if len(self.bones) > 255 else np.uint8)
        value = np.ascontiguousarray(value, dtype=np.float32)
        if value.size and value.min() < 0:
            value = np.clip(value, 0.0, None)
        self.value = value

    @property
    def n_points(self) -> int:
        return int(self.index.shape[0])

    @property
    def max_influences(self) -> int:
        return int(self.index.shape[1])

    @property
    def n_bones(self) -> int:
        return len(self.bones)

    def __repr__(self) -> str:
        return f"SkinningWeights({self.n_points} points, {self.n_bones} bones, ≤{self.max_influences} influences)"

    @classmethod
    def from_dense(cls, dense, bones, *, max_influences: int = MAX_INFLUENCES) -> SkinningWeights:
        """Keep the ``max_influences`` largest weights of each row of ``dense (n, n_bones)`` and renormalise.

        Negative entries (a harmonic solve's round-off) are clipped to zero
        first.  A row that is all zero is an error: the point has no bone.
        """
        dense = np.asarray(dense)
        bones = tuple(bones)
        if dense.ndim != 2 or dense.shape[1] != len(bones):
            raise ValueError(f"dense weights must be (n, {len(bones)}) for bones {bones}, got {dense.shape}")
        k = int(min(max_influences, len(bones)))
        if k < 1:
            raise ValueError("max_influences must be at least 1")
        n = dense.shape[0]
        idx_out = np.empty((n, k), dtype=np.intp)
        val_out = np.empty((n, k), dtype=np.float64)
        # rows in chunks: the sort's temporaries are (rows, n_bones) float64 and int64, several of them
        # (docs/measurements/deformation-and-validation.md); every row is independent
        for lo in range(0, n, DENSE_CHUNK):
            d = np.clip(np.asarray(dense[lo : lo + DENSE_CHUNK], dtype=np.float64), 0.0, None)
            if k < len(bones):
                idx = np.argpartition(-d, k - 1, axis=1)[:, :k]
            else:
                idx = np.broadcast_to(np.arange(len(bones)), d.shape).copy()
            val = np.take_along_axis(d, idx, axis=1)
            order = np.argsort(-val, axis=1, kind="stable")
            idx_out[lo : lo + DENSE_CHUNK] = np.take_along_axis(idx, order, axis=1)
            val_out[lo : lo + DENSE_CHUNK] = np.take_along_axis(val, order, axis=1)
        s = val_out.sum(axis=1)
        if np.any(s <= 0):
            raise ValueError(f"{int(np.sum(s <= 0))} point(s) have no positive weight on any bone")
        val_out /= s[:, None]  # Kurihara Eq. 3: Σ_k w_jk = 1 again over the kept influences
        idx_out = np.where(val_out > 0, idx_out, idx_out[:, :1])  # unused slots repeat the strongest bone
        return cls(bones, idx_out, val_out)

    @classmethod
    def one_hot(cls, bone_index, bones, *, max_influences: int = MAX_INFLUENCES) -> SkinningWeights:
        """Every point wholly on one bone (``bone_index (n,)``)."""
        bone_index = np.asarray(bone_index, dtype=np.int64).reshape(-1)
        k = int(min(max_influences, len(bones)))
        idx = np.repeat(bone_index[:, None], k, axis=1)
        val = np.zeros(idx.shape)
        val[:, 0] = 1.0
        return cls(bones, idx, val)

    def digest(self) -> str:
        """SHA-256 of the bones and arrays: a model built on these weights is valid only with them."""
        import hashlib

        h = hashlib.sha256()
        h.update("\n".join(self.bones).encode())
        h.update(np.ascontiguousarray(self.index).tobytes())
        h.update(np.ascontiguousarray(self.value).tobytes())
        return h.hexdigest()

    def dense(self) -> np.ndarray:
        """The weights as a dense ``(n, n_bones)`` float64 array."""
        out = np.zeros((self.n_points, self.n_bones))
        np.add.at(out, (np.arange(self.n_points)[:, None], self.index.astype(np.int64)), self.value)
        return out

    def take(self, rows) -> SkinningWeights:
        """The weights of a subset of the points (an index array or boolean mask)."""
        return SkinningWeights(self.bones, self.index[rows], self.value[rows])

    def reorder(self, bones) -> SkinningWeights:
        """The same weights expressed over another ordering (a superset) of bone names."""
        bones = tuple(bones)
        missing = [b for b in self.bones if b not in bones]
        if missing:
            raise ValueError(f"bones {missing} are not in the new bone list {bones}")
        lut = np.array([bones.index(b) for b in self.bones], dtype=np.int64)
        return SkinningWeights(bones, lut[self.index.astype(np.int64)], self.value)


@nb.njit(cache=True, inline="always")
def blend_point(idx, val, v, t, p0, p1, p2):
    """``(Σ_m w_m T_{b_m}) p`` for point ``v`` of sparse weights (compiled kernels' inner step, Rhee Eq. 2).

    ``t`` is ``(n_bones, 3, 4)``; returns the blended point as a tuple ``(x, y, z)``.
    """
    o0 = 0.0
    o1 = 0.0
    o2 = 0.0
    for m in range(idx.shape[1]):
        w = val[v, m]
        if w == 0.0:
            continue
        b = idx[v, m]
        # Rhee Eq. 2 (Kurihara Eq. 2): (Σ_m w_m T_{b_m}) p over the point's ≤ K bones, T 3×4
        o0 += w * (t[b, 0, 0] * p0 + t[b, 0, 1] * p1 + t[b, 0, 2] * p2 + t[b, 0, 3])
        o1 += w * (t[b, 1, 0] * p0 + t[b, 1, 1] * p1 + t[b, 1, 2] * p2 + t[b, 1, 3])
        o2 += w * (t[b, 2, 0] * p0 + t[b, 2, 1] * p1 + t[b, 2, 2] * p2 + t[b, 2, 3])
    return o0, o1, o2


def stack_transforms(transforms, bones) -> np.ndarray:
    """``(n_bones, 4, 4)`` float64 in the order of ``bones``: from a ``{bone: 4×4}`` mapping (or a Pose), or
    an ``(n_bones, 4, 4)`` array already in that order (its shape checked)."""
    if isinstance(transforms, np.ndarray) and transforms.ndim == 3:
        t = np.asarray(transforms, dtype=np.float64)
    else:
        try:
            t = np.stack([np.asarray(transforms[b], dtype=np.float64) for b in bones])
        except KeyError as e:
            raise ValueError(
                f"no transform for bone {e.args[0]!r}; the pose names "
                f"{sorted(getattr(transforms, 'transforms', transforms))}"
            ) from None
    if t.shape != (len(bones), 4, 4):
        raise ValueError(f"need one 4×4 transform per bone ({len(bones)}), got shape {t.shape}")
    return t


def blend_matrices(weights: SkinningWeights, transforms) -> np.ndarray:
    """``M_p = Σ_k w_pk T_k`` for every point: ``(n, 3, 4)`` (the last row of a blend is ``[0 0 0 1]``)."""
    t = stack_transforms(transforms, weights.bones)[:, :3, :]
    m = np.zeros((weights.n_points, 3, 4))
    for s in range(weights.max_influences):  # Σ_k w_k T_k of Rhee Eq. 2 / Kurihara Eq. 2, one influence slot at a time
        m += weights.value[:, s, None, None].astype(np.float64) * t[weights.index[:, s].astype(np.int64)]
    return m


def _points(points, weights: SkinningWeights) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (n, 3) world mm, got shape {p.shape}")
    if p.shape[0] != weights.n_points:
        raise ValueError(f"{p.shape[0]} points but weights for {weights.n_points}")
    return p


def lbs(points, weights: SkinningWeights, transforms) -> np.ndarray:
    """Linear blend skinning, Kurihara Eq. 2: ``p'_j = Σ_k w_jk L_k p_j`` (points ``(n, 3)`` mm)."""
    p = _points(points, weights)
    m = blend_matrices(weights, transforms)
    return np.einsum("nij,nj->ni", m[:, :, :3], p) + m[:, :, 3]  # Kurihara Eq. 2: (Σ_k w_jk L_k) p_j


def vbd_points(points, weights: SkinningWeights, transforms) -> np.ndarray:
    """Volume blend deformation of voxel grid points, Rhee Eq. 2 — the same map as :func:`lbs`."""
    return lbs(points, weights, transforms)  # Rhee Eq. 2: va = (Σ_j w_j T_j) vs, Kurihara Eq. 2 on grid points


def inverse_lbs(posed_points, weights: SkinningWeights, transforms) -> np.ndarray:
    """The inverse blend of points whose template weights are known (Kurihara Eq. 6, Rhee Eq. 7).

    ``p = (Σ_k w_k T_k)⁻¹ p'``.  The blended matrix of a point whose weights
    mix strongly different rotations can be near singular (the "candy
    wrapper" of linear blend skinning); such points are reported by a
    ``numpy.linalg.LinAlgError`` from the solve only when exactly
    singular, so callers that need a check should compare ``lbs`` of the
    result with the input.
    """
    q = _points(posed_points, weights)
    m = blend_matrices(weights, transforms)
    # Kurihara Eq. 6 / Rhee Eq. 7's inverse blend: p = (Σ_k w_k T_k)⁻¹ p', solved per point (no inverse formed)
    return np.linalg.solve(m[:, :, :3], (q - m[:, :, 3])[:, :, None])[:, :, 0]


def distance_weights(
    bone_distances, bones, *, power: float = 4.0, falloff_mm: float = 20.0, max_influences: int = MAX_INFLUENCES
) -> SkinningWeights:
    """A simple distance-based weighting, the fallback to harmonic weights and a comparison for them.

    ``w_k ∝ d_k^-p · exp(−d_k / λ)`` on the distances ``d_k ≥ 0`` (mm) from
    each point to each bone's surface (``bone_distances (n, n_bones)``; zero or
    negative inside a bone, where that bone takes the whole weight).  The
    exponential keeps far points on their nearest bones only (pure inverse
    distance weights blend all bones almost equally far away).  Computed
    relative to each point's nearest bone, so no power under- or overflows.
    """
    dist = np.asarray(bone_distances)
    if dist.ndim != 2 or dist.shape[1] != len(bones):
        raise ValueError(f"bone_distances must be (n, {len(bones)}), got {dist.shape}")
    if power <= 0 or falloff_mm <= 0:
        raise ValueError("power and falloff_mm must be positive")
    parts = []
    for lo in range(0, dist.shape[0], DENSE_CHUNK):  # rows in chunks: each step's temporaries are (rows, n_bones)
        d = np.asarray(dist[lo : lo + DENSE_CHUNK], dtype=np.float64)
        dmin = d.min(axis=1, keepdims=True)
        inside = dmin[:, 0] <= 0.0
        dpos = np.maximum(d, 1e-9)
        dmin_pos = np.maximum(dmin, 1e-9)
        w = (dmin_pos / dpos) ** power * np.exp(-(dpos - dmin_pos) / falloff_mm)
        if np.any(inside):
            w[inside] = (d[inside] <= dmin[inside]).astype(np.float64)
        parts.append(SkinningWeights.from_dense(w, bones, max_influences=max_influences))
    if len(parts) <= 1:
        return (
            parts[0]
            if parts
            else SkinningWeights.from_dense(np.zeros((0, len(bones))), bones, max_influences=max_influences)
        )
    return SkinningWeights(
        tuple(bones), np.concatenate([p.index for p in parts]), np.concatenate([p.value for p in parts])
    )


def distance_voxel_weights(labels, bone_labels: dict, **kwargs) -> SkinningWeights:
    """:func:`distance_weights` of every voxel of a label map (``Volume``), on the distance (mm) to each bone.

    The distances are Euclidean distance transforms with the grid's spacing;
    ``bone_labels`` is ``{bone: label id}`` in the column order wanted.
    Raises ``ValueError`` naming a bone without a voxel.
    """
    from scipy import ndimage

    lab = np.asarray(labels.data)
    g = labels.geometry
    sp = np.asarray(g.spacing)[::-1]  # array order (z, y, x)
    bones = tuple(bone_labels)
    dist = np.empty((g.n_voxels, len(bones)))
    for k, b in enumerate(bones):
        inside = lab == bone_labels[b]
        if not inside.any():
            raise ValueError(f"the label map has no voxel of bone {b!r} (label {bone_labels[b]})")
        dist[:, k] = np.where(inside, 0.0, ndimage.distance_transform_edt(~inside, sampling=sp)).ravel()
    return distance_weights(dist, bones, **kwargs)
