"""Bone frames from a label map: oriented bounding boxes (Rhee et al. 2011, §3.1).

"The oriented bounding box (OBB) of each bone of the template volume is
created from the principal axes of the covariance matrix of the bone voxels,
and the center of the OBB's base is taken as the origin of the bone's
coordinates."  The base is the box face nearest the parent bone (proximal),
so the frame's ``z`` axis points from the parent into the bone, along its
longest principal axis; ``x``/``y`` follow the other principal axes
(right-handed).  Everything is in world mm: voxel centres come from the label
map's geometry (spacing, origin and direction), never from array indices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deformation.geometry import Volume

__all__ = ["BoneFrame", "bone_frames"]


@dataclass
class BoneFrame:
    """A bone's OBB and frame: ``frame`` maps bone coordinates to template world (4x4)."""

    name: str
    label: int
    n_voxels: int
    centroid: np.ndarray
    axes: np.ndarray  # 3x3, columns x, y, z (z = longest axis, pointing away from the parent)
    half_extents: np.ndarray  # along x, y, z (mm), voxel centres ± half a voxel
    frame: np.ndarray


def bone_frames(labels: Volume, skeleton) -> dict[str, BoneFrame]:
    """OBB frames of every skeleton bone present in ``labels``.

    Raises ``ValueError`` naming the bone when its label has fewer than 4 voxels.
    """
    if labels.is_vector:
        raise ValueError("bone_frames needs a scalar label map")
    g = labels.geometry
    flat = labels.data.reshape(-1)
    centroids = {}
    raw = {}
    for b in skeleton.bones:
        idx = np.flatnonzero(flat == b.label)
        if idx.size < 4:
            raise ValueError(
                f"bone {b.name!r} (label {b.label}) has {idx.size} voxels in the label map; "
                "check the label ids in skeleton.json against the label map"
            )
        k, j, i = np.unravel_index(idx, g.array_shape)  # array order [z, y, x] → index (i, j, k)
        pts = g.index_to_world(np.column_stack([i, j, k]).astype(float))
        c = pts.mean(axis=0)
        w, v = np.linalg.eigh(np.cov((pts - c).T))
        axes = v[:, ::-1]  # descending variance: the longest axis first
        raw[b.name] = (pts, c, axes)
        centroids[b.name] = c
    out = {}
    voxel_half = 0.5 * np.abs(g.direction_matrix * np.asarray(g.spacing)).sum(axis=1)  # world half-voxel
    for b in skeleton.bones:
        pts, c, axes = raw[b.name]
        z = axes[:, 0]
        if b.parent is not None:
            if z @ (c - centroids[b.parent]) < 0:
                z = -z  # point away from the parent
        else:
            kids = [centroids[k.name] for k in skeleton.bones if k.parent == b.name]
            if kids and z @ (np.mean(kids, axis=0) - c) > 0:
                z = -z  # the root's base faces away from its children
        x = axes[:, 1]
        y = np.cross(z, x)
        r = np.column_stack([x, y, z])
        local = (pts - c) @ r
        lo, hi = local.min(axis=0), local.max(axis=0)
        # Voxel centres → voxel extents: the world half-voxel box projected on each OBB axis
        # (exact when the OBB is aligned with the grid, a slight over-estimate otherwise).
        pad = np.abs(r.T) @ voxel_half
        lo, hi = lo - pad, hi + pad
        centre_box = c + r @ ((lo + hi) / 2)
        half = (hi - lo) / 2
        origin = centre_box - r[:, 2] * half[2]  # centre of the base face (Rhee §3.1)
        frame = np.eye(4)
        frame[:3, :3] = r
        frame[:3, 3] = origin
        out[b.name] = BoneFrame(b.name, b.label, len(pts), c, r, half, frame)
    return out
