"""The ``model`` stage: the example-based volume deformation model (EVD, Rhee §5, Rhee Eq. 6–7).

For each training scan ``k``, the displacement of every template voxel in the
template frame after undoing VBD with the scan's pose (Rhee Eq. 7):
``d_k(v) = (Σ_b w_b(v) T_b,k)⁻¹ v̂_k − v``, where ``v̂_k`` is where voxel ``v``
lies in scan ``k``.

* ``source="registration"`` (the pipeline's): ``v̂_k`` from the register
  stage's inverse field (``template_to_scan``) and the pose stage's
  *estimated* poses — a model from the user's own scans, no truth needed;
* ``source="truth"`` (phantom protocols): the phantom's exact forward map
  and true poses.

Template voxels with no correspondence in a scan (they leave its field of
view, or the inverse did not converge there) keep VBD: ``d_k = 0``.  The
template's rest pose joins the examples with ``d = 0`` unless a training
scan is near rest (:mod:`deformation.models.evd`; ``evd.json``'s
``template_example``).

Outputs (``model/``): ``evd.json`` and ``evd_displacements.mha``
(3 components per training scan, mm, on the template grid); when every
registration wrote its expected error, ``evd_uncertainty.mha`` (one
component per training scan: the error of its ``d_k``, mm), from which
``workbench deform --uncertainty-out`` poses the model's expected error
(:mod:`deformation.models.evd`, "Uncertainty").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench import __version__
from workbench.stages.mechanism import Json, Stage, VectorImage

__all__ = ["ModelSettings", "STAGE", "SOURCES"]

SOURCES = ("registration", "truth")


@dataclass(frozen=True)
class ModelSettings:
    source: str = "registration"
    scans: tuple | None = None  #: training scans (None: all)

    def __post_init__(self):
        if self.source not in SOURCES:
            raise ValueError(f"--source must be one of {SOURCES}, got {self.source!r}")
        if self.scans is not None:
            object.__setattr__(self, "scans", tuple(str(v) for v in self.scans))


def _needs(s: ModelSettings):
    return ("weights", "register", "pose") if s.source == "registration" else ("weights",)


def _inputs(study, s: ModelSettings, scan):
    files = {"template": study.path(study.manifest["template"]), "skeleton": study.path(study.manifest["skeleton"])}
    if s.source == "truth":
        for sid in study.check_scan_ids(s.scans):
            t = study.truth_files(sid)
            if not t:
                from workbench.study import StudyError

                raise StudyError(
                    f"{study.manifest_path}: scan {sid!r} has no ground truth to build a model from; "
                    "use --source registration (after `workbench register`).",
                    study.manifest_path,
                )
            files[f"truth_pose/{sid}"] = t["pose"]
            files[f"truth/{sid}"] = t.get("template_to_scan") or t["correspondence"]
    return files


def _run(ctx) -> dict:
    from deformation.fields.resample import FOLDED, invert_scan_to_template
    from deformation.geometry import Volume
    from deformation.models.evd import ExampleVolumeDeformation, fill_unmatched
    from deformation.models.posespace import pose_vector
    from deformation.models.skinning import stack_transforms
    from validation.leave_one_out import registration_training_positions, registration_training_sigma

    study, s = ctx.study, ctx.settings
    ids = study.check_scan_ids(s.scans)
    weights, body = study.weights()
    sk = study.skeleton()
    g = study.template().geometry
    poses, fields, unmatched, sigmas = [], [], {}, []
    for k, sid in enumerate(ids):
        if s.source == "registration":
            pose, pos, found = registration_training_positions(study, sid, g, weights)
            sigmas.append(registration_training_sigma(study, sid, pos, found))  # its registration's σ, or None
            how = "the registration's inverse field and the estimated pose"
        else:
            pose = study.truth_pose(sid)
            if study.has_truth_template_to_scan(sid):  # the exact forward map (phantom studies)
                f = study.truth_template_to_scan(sid)
                g.check_same(f.geometry, names=("template", f"{sid} template_to_scan"))
                pos, found = f.data + g.world_coordinates(), np.ones(g.array_shape, bool)
                how = "the truth's exact template → scan map"
            else:
                truth = study.truth_correspondence(sid)
                # prefer scan voxels that came from the template's body (where the map is not one-to-one)
                ijk = np.rint(g.world_to_index((truth.data + truth.geometry.world_coordinates()).reshape(-1, 3)))
                ijk = np.clip(ijk.astype(np.int64), 0, np.asarray(g.size) - 1)
                prefer = body.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]].reshape(truth.geometry.array_shape).astype(bool)
                bm = invert_scan_to_template(
                    truth, g, transforms=stack_transforms(pose.transforms, sk.bone_names), prefer=prefer
                )
                pos, found = bm.template_positions(), bm.status <= FOLDED
                how = "inverting the truth's scan → template field"
            pos = fill_unmatched(g, weights, pose.transforms, pos, found)
        unmatched[sid] = int((~found).sum())
        poses.append(pose)
        fields.append(pos)
        ctx.report(k + 1, len(ids), f"{sid}: template → scan positions from {how}")
    # the scans' expected errors when every registration wrote one (the truth's maps are exact: none)
    scan_sigma = sigmas if sigmas and all(v is not None for v in sigmas) else None
    model = ExampleVolumeDeformation.from_correspondences(  # Rhee Eq. 7
        g, weights, sk, poses, fields, scan_sigma=scan_sigma
    )
    del fields
    disp = model.displacements[:, : len(ids)].reshape(g.array_shape + (3 * len(ids),))
    cv = model.cross_validation_variance()
    body_mask = body.data.reshape(-1) > 0
    uncertainty = {
        "file": "evd_uncertainty.mha" if scan_sigma is not None else None,
        "layout": "per voxel: each training scan's expected error sigma_k (mm, its registration's uncertainty.mha "
        "where the voxel lies in the scan, its largest where the registration did not find it)",
        # None without the scans' σ (a model from the truth's exact maps, or registrations that wrote none)
        "scans_median_mm": {
            sid: float(np.median(model.scan_sigma[body_mask, k]))
            if scan_sigma is not None and body_mask.any()
            else None
            for k, sid in enumerate(ids)
        },
        # the pose interpolation's error where the training poses explain nothing, cross-validated over the scans
        "interpolation_median_mm": float(np.sqrt(np.median(cv[body_mask]))) if body_mask.any() else None,
        "method": "deformation.models.evd (module docstring, 'Uncertainty'): sigma at a pose is "
        "sqrt(sum_k s_k^2 sigma_k^2 + (1 - gamma) v), v cross-validated by leaving each scan out",
    }
    doc = {
        "format": "avw-evd",
        "version": 1,
        "source": s.source,
        "scans": list(ids),
        "joint_order": [j.name for j in sk.joints],
        "pose_vectors": {sid: pose_vector(sk, p).tolist() for sid, p in zip(ids, poses)},
        "displacements": "evd_displacements.mha",
        "layout": "per voxel: (d_x, d_y, d_z) of each training scan in turn, mm, template frame (Rhee Eq. 7)",
        "poses": "estimated (pose stage)" if s.source == "registration" else "ground truth",
        "template_example": model.template_example,
        "template_example_is": "the template's rest pose as one more example with zero displacement "
        "(Kurihara's base pose S0), included unless a training scan is near rest "
        "(deformation.models.evd.wants_template_example)",
        "weights_sha256": weights.digest(),
        "unmatched_voxels": unmatched,
        "unmatched": "template voxels with no correspondence in that scan (outside its field of view, or the "
        "inverse not found): d_k = 0 there, i.e. VBD",
        "uncertainty": uncertainty,
        "workbench_version": __version__,
    }
    out = {"evd_displacements.mha": VectorImage(Volume(disp, g)), "evd.json": Json(doc)}
    if scan_sigma is not None:
        out["evd_uncertainty.mha"] = VectorImage(Volume(model.scan_sigma.reshape(g.array_shape + (len(ids),)), g))
    return out


STAGE = Stage(
    name="model",
    folder="model",
    per_scan=False,
    settings_type=ModelSettings,
    run=_run,
    needs=_needs,
    inputs=_inputs,
    uses=lambda study, s: s.scans,
    version=5,  # what each version changed: docs/measurements/workbench.md
)
