"""The ``pose`` stage of a study: bone transforms, joint centres and angles written into the study.

Outputs, in the study folder (written to a staging folder and renamed into
place, so an interrupted run leaves nothing half-written)::

    poses/<scan>_pose.json          estimated pose, the same schema as truth/<scan>_pose.json
    poses/skeleton_estimated.json   the skeleton with the estimated joint centres
    poses/bone_frames.json          each bone's OBB frame in the template (Rhee §3.1)
    poses/pose_vectors.json         each scan's joint angles, concatenated in the skeleton's joint order
    poses/joints.json               per joint: centre, hinge axis, Eq. 1 residuals, conditioning
    poses/fits.json                 per scan and bone: status, metric before/after, iterations, time
    poses/report.txt / report.json  summary tables; accuracy against the truth when the study has it
    poses/template_labels.nii.gz    only when the bones were segmented from seeds (+ segmentation.json)

``study.json`` then names each scan's estimate under ``scans[i]["pose"]`` and
the stage under ``stages["pose"]``.
"""

from __future__ import annotations

import os
import secrets
import shutil
import time
from pathlib import Path

import numpy as np

from workbench import __version__
from workbench.errors import InputFileError, OutputExistsError
from workbench.jsonio import read_json, write_json
from workbench.study import MANIFEST, Study, read_study
from workbench.volume_io import write_labels

__all__ = ["run_pose_stage", "read_initial_poses", "read_seeds"]

STAGE_DIR = "poses"


def read_seeds(path, skeleton) -> dict[str, np.ndarray]:
    """Read a seeds file; every skeleton bone needs at least one point."""
    from registration.segmentation import SEEDS_FORMAT

    d = read_json(path)
    if d.get("format") != SEEDS_FORMAT:
        raise InputFileError(f"{path}: not a seeds file ('format' is {d.get('format')!r}, expected "
                             f"{SEEDS_FORMAT!r}); see `workbench pose --help` for the schema.", path)
    seeds = d.get("seeds")
    if not isinstance(seeds, dict):
        raise InputFileError(f"{path}: 'seeds' must map bone names to lists of [x, y, z] points (mm).", path)
    unknown = sorted(set(seeds) - set(skeleton.bone_names))
    if unknown:
        raise InputFileError(f"{path}: unknown bones {unknown}; the skeleton has {skeleton.bone_names}.", path)
    missing = [b for b in skeleton.bone_names if b not in seeds]
    if missing:
        raise InputFileError(f"{path}: no seed for bones {missing}; give at least one point inside each bone.", path)
    out = {}
    for b, pts in seeds.items():
        a = np.asarray(pts, dtype=float)
        if a.ndim == 1:
            a = a[None]
        if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0 or not np.all(np.isfinite(a)):
            raise InputFileError(f"{path}: seeds of {b!r} must be a list of [x, y, z] points in mm, got {pts!r}.",
                                 path)
        out[b] = a
    return out


def _finite(obj):
    """Non-finite floats (a metric never computed for a bone out of view) → None, so JSON can hold them."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)) and not np.isfinite(obj):
        return None
    return obj


def read_initial_poses(path, study: Study, skeleton) -> dict[str, np.ndarray]:
    """Root-bone initial transforms per scan from a JSON file.

    Either an ``avw-pose`` file (its root transform is used for every scan) or
    ``{"format": "avw-initial-poses", "version": 1, "scans": {"<id>": [[4x4]], ...}}``.
    """
    from deformation.skeleton import Pose
    from deformation.transforms import check_rigid

    d = read_json(path)
    try:
        if d.get("format") == "avw-pose":
            t = Pose.from_dict(d).transforms.get(skeleton.root)
            if t is None:
                raise InputFileError(f"{path}: the pose has no transform for the root bone {skeleton.root!r}.", path)
            return {sid: t for sid in study.scan_ids}
        if d.get("format") == "avw-initial-poses":
            scans = d.get("scans", {})
            unknown = sorted(set(scans) - set(study.scan_ids))
            if unknown:
                raise InputFileError(f"{path}: unknown scans {unknown}; the study has {study.scan_ids}.", path)
            return {sid: check_rigid(np.asarray(t, float), name=f"initial pose of {sid}") for sid, t in scans.items()}
    except ValueError as e:
        raise InputFileError(f"{path}: {e}", path) from e
    raise InputFileError(f"{path}: expected an 'avw-pose' file or {{'format': 'avw-initial-poses', 'version': 1, "
                         "'scans': {scan id: 4x4 root transform}}.", path)


def run_pose_stage(folder, *, method: str = "intensity", seeds=None, segment: bool = False,
                   modality: str | None = None, threshold: float | None = None, init: str = "identity",
                   scan_ids=None, metric: str = "ncc", interpolation: int = 3, prior_deg: float | None = 2.0,
                   min_ncc: float = 0.5, bias_correction: bool | None = None, margin_mm: float | None = None,
                   max_joint_gap_mm: float | None = 10.0, outlier_factor: float | None = 4.0,
                   overwrite: bool = False,
                   progress=None) -> dict:
    """Estimate poses for a study and write them into it; returns the report dictionary.

    Parameters
    ----------
    method : "intensity" (Rhee Eq. 1) or "surface" (Kurihara §3 ICP)
    seeds, segment : a seeds file; with ``segment`` (or when the study has no
        label map) the template bones are segmented from it (see
        :mod:`registration.segmentation`)
    init : "identity", "moments", or the path of an initial-pose file
    progress : callable(line: str), optional
    """
    from registration.bone_frames import bone_frames
    from registration.pose import estimate_poses
    from registration.report import accuracy, format_accuracy, format_fits
    from registration.rigid import bone_regions
    from registration.segmentation import segment_bones

    study = read_study(folder)
    root = study.root
    say = progress or (lambda line: None)
    out_dir = root / STAGE_DIR
    if out_dir.exists() and not overwrite:
        raise OutputExistsError(out_dir, f"{out_dir} exists (an earlier `workbench pose`); pass --force to replace it.")
    skeleton = study.skeleton()
    template = study.template()
    seg_report = None
    if segment or seeds is not None:
        if seeds is None:
            raise InputFileError("segmenting needs a seeds file (one world point in mm inside each bone).", root)
        sd = read_seeds(seeds, skeleton)
        from registration.segmentation import guess_modality

        modality = modality or guess_modality(template)
        if threshold is not None and modality != "ct":
            raise InputFileError(f"--threshold applies to CT segmentation, but the template segments as "
                                 f"{modality.upper()}; pass --modality ct if it is a CT.", root)
        kw = {} if threshold is None else {"threshold": threshold}
        labels, seg_report = segment_bones(template, skeleton, sd, modality=modality, **kw)
        for w in seg_report.warnings:
            say(f"segmentation: {w}")
        empty = [b for b, n in seg_report.voxels.items() if n == 0]
        if empty:
            raise InputFileError(f"segmentation found no voxels for bones {empty}: "
                                 + " ".join(seg_report.warnings) + " — or give the study a label map.", Path(seeds))
    elif not study.has_template_labels:
        raise InputFileError(f"{root}: the study has no bone label map; pass --seeds FILE to segment the template's "
                             "bones (see `workbench pose --help` for the seeds schema).", root)
    else:
        labels = study.template_labels()
    ids = list(scan_ids) if scan_ids else study.scan_ids
    unknown = [sid for sid in ids if sid not in study.scan_ids]
    if unknown:
        raise InputFileError(f"no scan {unknown} in this study; its scans are {study.scan_ids}.", root / MANIFEST)
    if init in ("identity", "moments"):
        root_init = None if init == "identity" else "moments"
    else:
        root_init = read_initial_poses(init, study, skeleton)
    scans = {sid: (lambda sid=sid: study.scan(sid)) for sid in ids}

    def cb(sid, si, n_scans, bone, done, total, fit):
        say(f"[scan {si + 1}/{n_scans} {sid}] bone {done}/{total} {bone:<18} {fit.status:<14} "
            f"ncc {fit.ncc:.3f}  {fit.seconds:.1f} s")

    t0 = time.perf_counter()
    result = estimate_poses(template, labels, scans, skeleton, method=method, root_init=root_init, metric=metric,
                            interpolation=interpolation, prior_deg=prior_deg, min_ncc=min_ncc,
                            bias_correction=bias_correction, margin_mm=margin_mm,
                            max_joint_gap_mm=max_joint_gap_mm, outlier_factor=outlier_factor, progress=cb)
    total = time.perf_counter() - t0
    centroids = {k: r.centroid for k, r in bone_regions(template, labels, skeleton).items()}
    report = {"method": method, "metric": metric, "interpolation": "cubic B-spline" if interpolation == 3 else "linear",
              "prior_deg": prior_deg, "bias_correction": bias_correction, "margin_mm": margin_mm,
              "max_joint_gap_mm": max_joint_gap_mm, "outlier_factor": outlier_factor, "init": init if init in ("identity", "moments") else str(init),
              "seconds_total": round(total, 2), "seconds_per_scan": {s.scan_id: round(s.seconds, 2) for s in result.scans},
              "failures": result.failures(), "eq1_rms_mm": result.overall_rms_mm(),
              "eq1_base_pose_counted": False}
    text = [f"workbench pose — {study.manifest.get('name', root.name)} — method {method}", "", format_fits(result)]
    truth = {sid: study.truth_pose(sid) for sid in ids if study.has_truth(sid)}
    if truth:
        acc = accuracy(result, truth, skeleton, centroids)
        report["accuracy"] = acc
        text += ["", "accuracy against the phantom's ground truth:", format_accuracy(acc)]
    report["text"] = "\n".join(text)
    report = _finite(report)

    stage = root / f".{STAGE_DIR}.partial-{secrets.token_hex(4)}"
    stage.mkdir()
    try:
        for s in result.scans:
            write_json(s.pose.to_dict(), stage / f"{s.scan_id}_pose.json")
        write_json(result.skeleton.to_dict(), stage / "skeleton_estimated.json")
        frames = bone_frames(labels, skeleton)
        write_json({"format": "avw-bone-frames", "version": 1, "units": "mm",
                    "convention": "Rhee §3.1: principal axes of the bone's voxels; z the longest, pointing away "
                                  "from the parent; origin at the centre of the box's base; frame maps bone "
                                  "coordinates to template world",
                    "bones": {b: {"frame": f.frame.tolist(), "half_extents_mm": f.half_extents.tolist(),
                                  "centroid": f.centroid.tolist(), "voxels": f.n_voxels}
                              for b, f in frames.items()}}, stage / "bone_frames.json")
        order = [j.name for j in skeleton.joints]
        write_json({"format": "avw-pose-vectors", "version": 1, "joint_order": order,
                    "dof": [j.dof for j in skeleton.joints],
                    "units": "degrees (6-DOF joints: three angles, then mm)",
                    "missing": "null: a joint with a bone flagged in that scan (see fits.json)",
                    "scans": {s.scan_id: [v for j in order
                                          for v in (np.asarray(s.pose.joint_angles[j]).tolist()
                                                    if j in s.pose.joint_angles
                                                    else [None] * skeleton.joint(j).dof)]
                              for s in result.scans}}, stage / "pose_vectors.json")
        write_json(_finite({"format": "avw-joints", "version": 1, "method": method, "units": "mm",
                            "eq1_rms_mm": result.overall_rms_mm(), "eq1_base_pose_counted": False,
                            "joints": result.joints_dict()}), stage / "joints.json")
        write_json(_finite({"format": "avw-fits", "version": 1, "method": method,
                            "scans": {s.scan_id: {"seconds": s.seconds,
                                                  "bones": {b: f.to_dict() for b, f in s.fits.items()}}
                                      for s in result.scans}}), stage / "fits.json")
        write_json(report, stage / "report.json")
        (stage / "report.txt").write_text(report["text"] + "\n", encoding="utf-8")
        if seg_report is not None:
            write_labels(labels, stage / "template_labels.nii.gz")
            write_json(seg_report.to_dict(), stage / "segmentation.json")
        manifest = dict(study.manifest)
        manifest["scans"] = [dict(s) for s in manifest["scans"]]
        for s in manifest["scans"]:
            if s["id"] in ids:
                s["pose"] = f"{STAGE_DIR}/{s['id']}_pose.json"
            elif out_dir.exists():
                s.pop("pose", None)  # the old stage folder goes away
        stages = dict(manifest.get("stages") or {})
        stages["pose"] = {"method": method, "folder": STAGE_DIR, "joints": f"{STAGE_DIR}/joints.json",
                          "fits": f"{STAGE_DIR}/fits.json", "report": f"{STAGE_DIR}/report.json",
                          "skeleton": f"{STAGE_DIR}/skeleton_estimated.json",
                          "labels": f"{STAGE_DIR}/template_labels.nii.gz" if seg_report is not None else None,
                          "scans": ids, "failures": len(result.failures()), "workbench_version": __version__}
        manifest["stages"] = stages
        old = None
        if out_dir.exists():
            old = root / f".{STAGE_DIR}.old-{secrets.token_hex(4)}"
            os.replace(out_dir, old)
        try:
            os.replace(stage, out_dir)
            write_json(manifest, root / MANIFEST, overwrite=True)  # atomic replace
        except BaseException:
            if out_dir.exists():
                shutil.rmtree(out_dir, ignore_errors=True)
            if old is not None:
                os.replace(old, out_dir)  # the study is as it was
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return report
