"""The ``validate`` stage: each scan's results against its ground truth (Rhee §6.1, Tables 2–4).

The only stage that reads the truth.  Per scan with truth
(:mod:`validation.registration_measures`, :mod:`validation.pose_measures`):

* the rows ``source`` / ``initialised`` / ``registered``: MED over the scan's
  body voxels (mm), marker MED (mm), SSD, CC, MI (nats, 32 bins), fraction of
  folded body voxels (det ≤ 0);
* the estimated pose's errors per bone and joint, when the pose stage ran.

Scans without truth have nothing to validate (recorded as skipped).
Outputs (``validation/<scan>/``): ``measures.json`` (the rows, each
marker's error, the pose errors), ``error_mm.nii.gz`` (the registered
correspondence's error ``|recovered − true|`` template position at every
scan voxel, mm; 0 outside the body) and ``body.nii.gz`` (the scan's body
voxels the measures are taken over) — the report stage draws them, so that
no other stage reads the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

from workbench.stages.mechanism import Image, Json, Labels, Stage

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
    import numpy as np

    from deformation.geometry import Volume
    from registration.rigid import bone_regions
    from validation.pose_measures import pose_errors
    from validation.registration_measures import body_on_scan, error_map, marker_errors, validation_rows

    study, s, sid = ctx.study, ctx.settings, ctx.scan
    template = study.template()
    _, body = study.weights()
    truth = study.truth_correspondence(sid)
    field = study.registration_correspondence(sid)
    markers = study.truth_markers(sid)
    rows = validation_rows(
        study.scan(sid),
        template,
        truth=truth,
        template_body=body,
        markers=markers,
        registered=study.registered(sid),
        field=field,
        initial=study.init_field(sid),
    )
    body_scan = body_on_scan(truth, body)
    doc = {
        "format": "avw-validation",
        "version": 1,
        "scan": sid,
        "rows": rows,
        "markers": [
            {"name": m.get("name", f"m{i}"), "error_mm": float(e)}
            for i, (m, e) in enumerate(zip(markers, marker_errors(field, markers)))
        ],
        "measures": {
            "med_mm": "mean |recovered − true| template position over the scan's body voxels (mm)",
            "marker_med_mm": "the same at the skin markers",
            "ssd": "mean squared intensity difference, scan vs template resampled through the field",
            "cc": "Pearson correlation",
            "mi": "mutual information, nats, 32 bins",
            "folded_fraction": "fraction of the scan's body voxels with Jacobian determinant ≤ 0",
        },
    }
    if s.pose and study.has_pose(sid):
        centroids = {
            k: r.centroid for k, r in bone_regions(template, study.template_labels(), study.skeleton()).items()
        }
        doc["pose"] = pose_errors(study.pose(sid), study.truth_pose(sid), centroids)
    g = truth.geometry
    err = error_map(field, truth, body_scan)
    sigma = study.registration_uncertainty(sid)
    if sigma is not None:  # the dense registration's expected error against the true one (issue R's calibration)
        from validation.registration_measures import uncertainty_calibration

        doc["uncertainty"] = uncertainty_calibration(err, sigma.data, body_scan)
    from workbench.stages.pose import finite

    # a measure with nothing to measure (no markers) is written as null
    return {
        "measures.json": Json(finite(doc)),
        "error_mm.nii.gz": Image(Volume(err, g)),
        "body.nii.gz": Labels(Volume(body_scan.astype(np.uint8), g)),
    }


STAGE = Stage(
    name="validate",
    folder="validation",
    per_scan=True,
    settings_type=ValidateSettings,
    run=_run,
    needs=lambda s: ("register", "weights"),
    inputs=_inputs,
    applies=_applies,
    version=3,  # what each version changed: docs/measurements/workbench.md
)
