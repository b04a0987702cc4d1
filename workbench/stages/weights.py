"""The ``weights`` stage: skinning weights of every template voxel (the ``w`` of Rhee Eq. 2 and Kurihara Eq. 2–3).

``method="harmonic"``: the body (segmented from the template, :func:`registration.segmentation.segment_body`) is
meshed with the Kuhn tetrahedra of a lattice of its voxel centres (:func:`deformation.meshes.tetmesh.lattice_tetmesh`:
the mask's own resolution up to :data:`~deformation.meshes.tetmesh.MAX_LATTICE_VERTICES` vertices, or
``edge_length_mm``)
and each bone's weight solved as a harmonic function (:func:`deformation.models.harmonic.harmonic_voxel_weights`);
``"distance"``: inverse-distance weights (:func:`deformation.models.skinning.distance_voxel_weights`). The mesh is a
function of the body mask and the step, so a rerun gives the same bits.

A template of more than :data:`~workbench.stages.stage.WORKING_VOXELS` voxels (a CT the size of Kurihara's) gets
its weights and body mask on every f-th voxel along each axis (``grid_factor``; the weights are smooth; a bone
with no voxel left on that grid is one clear error naming ``--grid-factor``): deform, animate and the init stage's
VBD solve their maps on that grid and pull the full template (or blend the field) up to full resolution
(:class:`deformation.fields.resample.CoarseBackwardMap`); register after a VBD start, model and validate, which need
full-grid weights, say so.

Outputs (``skinning/``): ``body_mask.nii.gz``, ``weights.json`` with ``weights_index.mha`` and
``weights_value.mha`` (:mod:`workbench.io.weights`), and, for harmonic weights, ``tetmesh.vtu`` (with one point
array per bone, ``weight_<bone>``: open it in ParaView).
"""

from __future__ import annotations

from dataclasses import dataclass

from deformation.geometry import every_nth
from workbench import __version__
from workbench.errors import InputFileError
from workbench.stages.mechanism import Labels, Stage, TetMeshFile, WeightMap, working_factor, working_labels

__all__ = ["WeightsSettings", "STAGE", "WEIGHT_METHODS"]

WEIGHT_METHODS = ("harmonic", "distance")


@dataclass(frozen=True)
class WeightsSettings:
    method: str = "harmonic"
    #: the tet lattice's spacing in mm, rounded to whole voxels per axis (None: every voxel, coarser above
    #: MAX_LATTICE_VERTICES vertices)
    edge_length_mm: float | None = None
    grid_factor: int | None = None  #: weights on every f-th template voxel (None: 1 up to WORKING_VOXELS, else more)

    def __post_init__(self):
        if self.method not in WEIGHT_METHODS:
            raise ValueError(f"weights method must be one of {WEIGHT_METHODS}, got {self.method!r}")
        if self.edge_length_mm is not None and not self.edge_length_mm > 0:
            raise ValueError(f"--edge-length-mm must be positive, got {self.edge_length_mm}")
        if self.grid_factor is not None and not (isinstance(self.grid_factor, int) and self.grid_factor >= 1):
            raise ValueError(f"--grid-factor must be a whole number ≥ 1, got {self.grid_factor!r}")


def _inputs(study, s, scan):
    return {
        "template": study.path(study.manifest["template"]),
        "labels": study.template_labels_path(),
        "skeleton": study.path(study.manifest["skeleton"]),
    }


def _run(ctx) -> dict:
    from deformation.models.harmonic import harmonic_voxel_weights
    from deformation.models.skinning import distance_voxel_weights
    from registration.segmentation import segment_body
    from workbench.io.tetmeshes import weight_arrays

    study, s = ctx.study, ctx.settings
    sk = study.skeleton()
    bone_labels = {b: sk.label_of(b) for b in sk.bone_names}
    template, labels = study.template(), study.template_labels()
    f = working_factor(s.grid_factor, template.geometry)
    if f > 1:  # a big template: the weights (and body mask) on every f-th voxel; deform solves its maps there
        ctx.say(
            f"template of {template.geometry.n_voxels:,} voxels: weights on {every_nth(f)} voxel along each axis "
            f"({template.geometry.every(f).n_voxels:,} voxels; --grid-factor)"
        )
        template, labels = template.every(f), working_labels(study, labels, f)
    body = segment_body(template, labels=labels)
    out = {"body_mask.nii.gz": Labels(body)}
    info = {"method": s.method, "grid_factor": f}
    if s.method == "harmonic":
        # A bone that holds no lattice node (smaller than a step of several voxels, or where the body is too
        # thin for a mostly-body cube) fixes the vertex nearest to it instead: the discrete boundary condition
        # at the mesh's resolution.
        r = harmonic_voxel_weights(
            labels, bone_labels, body, edge_length_mm=s.edge_length_mm, progress=ctx.say, snap_missing=True
        )
        weights = r.weights
        info.update(r.info)
        out["tetmesh.vtu"] = TetMeshFile(r.mesh, weight_arrays(r.bones, r.vertex_weights))
    else:
        try:
            weights = distance_voxel_weights(labels, bone_labels)
        except ValueError as e:
            raise InputFileError(f"{study.template_labels_path()}: {e}", study.template_labels_path()) from e
    out["weights.json"] = WeightMap(weights, template.geometry, {**info, "workbench_version": __version__})
    return out


STAGE = Stage(
    name="weights",
    folder="skinning",
    per_scan=False,
    settings_type=WeightsSettings,
    run=_run,
    needs=lambda s: ("bones",),
    inputs=_inputs,
    version=3,  # what each version changed: docs/measurements/workbench.md
)
