"""Kurihara's skeleton-driven surface model (Kurihara & Miyata 2004, §5): SSD, PSD and WPSD of a skin mesh.

From the base mesh ``S_0`` (the template's skin), its vertices' skinning
weights and the consistent meshes ``S^f_i`` of the measured poses (every one
with ``S_0``'s connectivity, :mod:`registration.surface_fit`):

* the training: each ``S^f_i`` taken back to the base pose by inverse SSD
  with its pose's bone transforms, ``v⁰_ij = (Σ_k w_jk L_ik)⁻¹ v_ij``
  (Kurihara Eq. 6, :func:`deformation.models.posespace.psd_training`);
* SSD: ``v = Σ_k w_k L_k v_0`` (Kurihara Eq. 2) of ``S_0`` itself;
* PSD: the base-pose samples morphed with one set of normalised RBF weights
  of the pose, ``u⁰_j = Σ_i s_i(a) v⁰_ij`` (Kurihara Eq. 7, 12–14), then SSD (Kurihara Eq. 8);
* WPSD: the same with per-vertex weights from the pose distance weighted by
  the vertex's skinning weights (Kurihara Eq. 16), so a finger's vertices interpolate
  over that finger's joints only.

``S_0`` is itself an example at the rest pose (Kurihara's "base pose": the
identity transforms take it to itself), unless a measured pose is near rest
(:func:`deformation.models.evd.wants_template_example`, the same rule as the volume
model's).
"""

from __future__ import annotations

import numpy as np

from deformation.meshes.mesh import SurfaceMesh
from deformation.models.evd import with_template_example
from deformation.models.posespace import PoseSpace, psd_training, skin, wpsd_deform
from deformation.models.skinning import SkinningWeights

__all__ = ["SurfaceModel", "SURFACE_METHODS"]

SURFACE_METHODS = ("ssd", "psd", "wpsd")


class SurfaceModel:
    """SSD / PSD / WPSD of a base mesh over example meshes (module docstring).

    ``base_samples`` ``(n_vertices, P, 3)``: each vertex's base-pose position in every example (the
    template's, when included, last: ``S_0``'s own vertices); ``space`` the examples' pose vectors.
    """

    def __init__(
        self,
        base: SurfaceMesh,
        weights: SkinningWeights,
        space: PoseSpace,
        base_samples,
        *,
        template_example: bool = False,
    ):
        b = np.ascontiguousarray(base_samples, dtype=np.float64)
        if weights.n_points != base.n_vertices:
            raise ValueError(f"{weights.n_points} skinning weights for a base mesh of {base.n_vertices} vertices")
        if b.shape != (base.n_vertices, space.n_poses, 3):
            raise ValueError(
                f"base samples must be (n_vertices, n_poses, 3) = {(base.n_vertices, space.n_poses, 3)}, got {b.shape}"
            )
        self.base = base
        self.weights = weights
        self.space = space
        self.base_samples = b
        self.template_example = bool(template_example)
        self._point_space = None

    @property
    def n_examples(self) -> int:
        return self.space.n_poses

    @classmethod
    def from_meshes(
        cls, base: SurfaceMesh, weights: SkinningWeights, skeleton, poses, meshes, *, template_example="auto"
    ) -> SurfaceModel:
        """The model from the measured poses (:class:`~deformation.kinematics.skeleton.Pose`, template → scan) and their
        consistent meshes (``S_0``'s connectivity), Kurihara Eq. 6."""
        poses, meshes = list(poses), list(meshes)
        if len(poses) != len(meshes) or not poses:
            raise ValueError(f"{len(poses)} poses and {len(meshes)} meshes: one consistent mesh per pose needed")
        for k, m in enumerate(meshes):
            if m.n_vertices != base.n_vertices or not np.array_equal(m.triangles, base.triangles):
                raise ValueError(
                    f"mesh {k} does not have the base mesh's connectivity ({m.n_vertices} vertices "
                    f"against {base.n_vertices}): fit it from the base mesh"
                )
        # Kurihara Eq. 6: each S^f_i back to the base pose by inverse SSD
        samples = psd_training([m.vertices for m in meshes], weights, [p.transforms for p in poses])
        vectors, template_example = with_template_example(skeleton, PoseSpace(skeleton, poses).train, template_example)
        samples = np.moveaxis(samples, 0, 1)  # (n, P, 3): per vertex, as the kernels read them
        if template_example:  # S0 at rest: the identity transforms take it to itself (Kurihara Eq. 6 gives S0)
            samples = np.concatenate([samples, np.asarray(base.vertices, float)[:, None]], axis=1)
        return cls(base, weights, PoseSpace(skeleton, vectors), samples, template_example=template_example)

    def deform(self, pose, method: str = "wpsd") -> SurfaceMesh:
        """The skin at ``pose`` (a :class:`~deformation.kinematics.skeleton.Pose`: bone transforms and joint angles) by
        ``method`` — "ssd" (Kurihara Eq. 2), "psd" (Kurihara Eq. 7–8 with Kurihara Eq. 12–15) or "wpsd"
        (Kurihara Eq. 16)."""
        if method not in SURFACE_METHODS:
            raise ValueError(f"method must be one of {SURFACE_METHODS}, got {method!r}")
        t = pose.transforms
        if method == "ssd":
            v = skin(self.base.vertices, self.weights, t)  # Kurihara Eq. 2 of S_0
        elif method == "psd":
            # Kurihara Eq. 7–8 with one set of s_i(a) (Kurihara Eq. 12–15)
            v = skin(self.base_samples, self.weights, t, self.space.weights(pose))
        else:
            if self._point_space is None:  # Φ⁻¹ per vertex folded with the samples, once (Kurihara: precomputed)
                self._point_space = self.space.point_space(self.weights)
                self._folded = self._point_space.fold(self.base_samples)
            # Kurihara Eq. 7–8 with per-vertex s_ji(a) from Kurihara Eq. 16's distances
            v = wpsd_deform(self.base_samples, self.weights, self._point_space, pose, t, folded=self._folded)
        return SurfaceMesh(v, self.base.triangles)
