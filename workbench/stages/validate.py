"""The ``validate`` stage: each scan's results against its ground truth (Rhee §6.1, Tables 2–4).

The only stage that reads the truth.  Per scan with truth
(:mod:`validation.registration_measures`, :mod:`validation.pose_measures`):

* the rows ``source`` / ``initialised`` / ``registered``: MED over the scan's
  body voxels (mm), marker MED (mm), SSD, CC, MI (nats, 32 bins), fraction of
  folded body voxels (det ≤ 0);
* the estimated pose's errors per bone and joint, when the pose stage ran.

Scans without truth have nothing to validate (recorded as skipped).
Outputs (``validation/<scan>/measures.json``).
"""

from __future__ import annotations

from dataclasses import dataclass

from workbench.stages.mechanism import Json, Stage

__all__ = ["ValidateSettings", "STAGE"]


@dataclass(frozen=True)
class ValidateSettings:
    pose: bool = True  #: also the pose errors (when the pose stage ran)


def _applies(study, s, scan):
    return None if study.has_truth(scan) else "no ground truth"


def _inputs(study, s, scan):
    files = {"template": study.path(study.manifest["template"]), "scan": study.scan_path(scan)}
    files.update({f"truth/{k}": p for k, p in study.truth_files(scan).items()})
    if s.pose and study.has_pose(scan):
        files["pose"] = study.output("pose", f"{scan}_pose.json")
    return files


def _run(ctx) -> dict:
    from registration.rigid import bone_regions
    from validation.pose_measures import pose_errors
    from validation.registration_measures import validation_rows

    study, s, sid = ctx.study, ctx.settings, ctx.scan
    template = study.template()
    _, body = study.weights()
    rows = validation_rows(study.scan(sid), template, truth=study.truth_correspondence(sid), template_body=body,
                           markers=study.truth_markers(sid), registered=study.registered(sid),
                           field=study.registration_correspondence(sid), initial=study.init_field(sid))
    doc = {"format": "avw-validation", "version": 1, "scan": sid, "rows": rows,
           "measures": {"med_mm": "mean |recovered − true| template position over the scan's body voxels (mm)",
                        "marker_med_mm": "the same at the skin markers",
                        "ssd": "mean squared intensity difference, scan vs template resampled through the field",
                        "cc": "Pearson correlation", "mi": "mutual information, nats, 32 bins",
                        "folded_fraction": "fraction of the scan's body voxels with Jacobian determinant ≤ 0"}}
    if s.pose and study.has_pose(sid):
        centroids = {k: r.centroid for k, r in bone_regions(template, study.template_labels(),
                                                            study.skeleton()).items()}
        doc["pose"] = pose_errors(study.pose(sid), study.truth_pose(sid), centroids)
    return {"measures.json": Json(doc)}


STAGE = Stage(name="validate", folder="validation", per_scan=True, settings_type=ValidateSettings, run=_run,
              needs=lambda s: ("register", "weights"), inputs=_inputs, applies=_applies)
