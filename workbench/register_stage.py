"""The ``register`` command: locally adaptive registration of the template to each scan (Rhee §4).

Outputs, per scan, in the study folder::

    registration/<id>/correspondence.mha   scan_to_template field on the scan grid (template position − voxel,
                                           mm; the convention of truth/<id>_correspondence.mha, usable by
                                           sitk.DisplacementFieldTransform)
    registration/<id>/template_to_scan.mha its inverse on the template grid (scan position − voxel, mm)
    registration/<id>/registered.nii.gz    the template resampled onto the scan grid through the field
    registration/<id>/log.json             settings, per-level and per-step log, similarity before/after,
                                           folding, accuracy against the truth when the study has one

``study.json`` names them under the scan's ``registration`` key.  Each
scan's folder is written in a staging folder and renamed into place, so an
interrupted run leaves no half-written registration.
"""

from __future__ import annotations

import secrets
import shutil
import time
from pathlib import Path

import numpy as np

from deformation.geometry import Volume
from deformation.skinning import stack_transforms
from registration.adaptive import AdaptiveSettings, register_adaptive
from registration.baselines import warp_template
from registration.initialise import invert_correspondence, vbd_initial_field
from registration.segmentation import segment_body
from validation.registration_measures import body_on_scan, registration_measures
from workbench import __version__
from workbench.deform_stage import _replace_dir, load_weights
from workbench.errors import InputFileError, OutputExistsError
from workbench.jsonio import read_json, write_json
from workbench.study import MANIFEST, Study, read_study
from workbench.volume_io import write_displacement, write_volume

__all__ = ["run_register_stage", "REGISTRATION_DIR", "INIT_MODES", "format_summary"]

REGISTRATION_DIR = "registration"
INIT_MODES = ("vbd", "none")


def _set_scan_entry(root: Path, scan_id: str, key: str, entry: dict) -> None:
    manifest = read_json(root / MANIFEST)
    for s in manifest["scans"]:
        if s["id"] == scan_id:
            s[key] = entry
    write_json(manifest, root / MANIFEST, overwrite=True)  # atomic replace


def _pose_for(study: Study, sid: str, pose_source: str, say):
    if pose_source in ("auto", "estimated") and study.has_pose(sid):
        return study.pose(sid), "estimated"
    if pose_source == "estimated":
        raise InputFileError(f"scan {sid!r} has no estimated pose; run `workbench pose {study.root}` first, or "
                             "pass --pose truth for a phantom.", study.root / MANIFEST)
    if study.has_truth(sid):
        if pose_source == "auto":
            say(f"{sid}: no estimated pose (`workbench pose`); VBD from the ground-truth pose")
        return study.truth_pose(sid), "truth"
    raise InputFileError(f"scan {sid!r} has neither an estimated pose nor a ground truth: run `workbench pose "
                         f"{study.root}` first, or register with --init none.", study.root / MANIFEST)


def run_register_stage(folder, *, scan_ids=None, init: str = "vbd", pose_source: str = "auto",
                       settings: AdaptiveSettings | None = None, overwrite: bool = False, progress=None,
                       step_progress=None, unfold_init: bool = False) -> list[dict]:
    """Register the template to each scan (all by default) and write ``registration/<id>/``.

    ``init``: ``"vbd"`` (Rhee §3.3: the template moved by VBD to the scan's
    pose — the estimated pose, or the truth's when there is none and
    ``pose_source`` is ``"auto"``) or ``"none"``.  With ``"vbd"`` the
    template's bone labels become zero-displacement control points (Rhee
    §4.3) unless ``settings.fix_bones`` is off.  ``unfold_init`` repairs the
    folds of the VBD field in the crease of a flexed joint first
    (:func:`registration.initialise.vbd_initial_field`): a one-to-one result
    at some cost in accuracy.  Returns one summary dict per
    scan (also written into its ``log.json``).
    """
    if init not in INIT_MODES:
        raise ValueError(f"init must be one of {INIT_MODES}, got {init!r}")
    if unfold_init and init != "vbd":
        raise ValueError("unfold_init repairs the VBD initialisation: it needs init='vbd' (--init vbd)")
    if pose_source not in ("auto", "estimated", "truth"):
        raise ValueError(f"pose_source must be 'auto', 'estimated' or 'truth', got {pose_source!r}")
    say = progress or (lambda line: None)
    settings = settings or AdaptiveSettings()
    study = read_study(folder)
    root = study.root
    ids = list(scan_ids or study.scan_ids)
    for sid in ids:
        study._scan_entry(sid)  # unknown ids: a clear error before any work
    existing = [sid for sid in ids if (root / REGISTRATION_DIR / sid / "log.json").exists()]
    if existing and not overwrite:
        raise OutputExistsError(root / REGISTRATION_DIR / existing[0],
                                f"{root / REGISTRATION_DIR}: scans {existing} are registered already; pass --force "
                                "to register them again.")
    template = study.template()
    g_t = template.geometry
    weights = body_t = rigid = None
    if init == "vbd":
        weights, body_t = load_weights(study)
        if settings.fix_bones and study.has_template_labels:
            rigid = study.template_labels()
    if body_t is None:
        body_t = segment_body(template, labels=study.template_labels() if study.has_template_labels else None)
    out = []
    for n, sid in enumerate(ids):
        t0 = time.perf_counter()
        scan = study.scan(sid)
        say(f"[{n + 1}/{len(ids)}] {sid}: {scan.geometry.describe()}")
        initial, transforms, init_info = None, None, {"init": init}
        if init == "vbd":
            pose, source = _pose_for(study, sid, pose_source, say)
            transforms = stack_transforms(pose.transforms, weights.bones)
            initial, bm = vbd_initial_field(g_t, scan.geometry, weights, transforms, body=body_t.data,
                                            unfold=unfold_init)
            init_info.update({"pose": source, "backward_map": bm})
            say(f"{sid}: VBD initialisation ({source} pose): {time.perf_counter() - t0:.1f} s")
        result = register_adaptive(scan, template, initial=initial, rigid_mask=rigid, settings=settings,
                                   progress=step_progress)
        inverse, inv_info = invert_correspondence(result.correspondence, g_t,
                                                  transforms=transforms)
        summary = {"scan": sid, "seconds": round(time.perf_counter() - t0, 2),
                   "registration_seconds": round(result.seconds, 2), "control_points": result.control_points,
                   "steps": len(result.steps), "evaluations": result.evaluations, **init_info,
                   "inverse": inv_info, "folding": result.folding,
                   "similarity_before": result.similarity_before, "similarity_after": result.similarity_after}
        if study.has_truth(sid):
            truth = study.truth_correspondence(sid)
            body = body_on_scan(truth, body_t)
            markers = study.truth_markers(sid)
            zero = Volume(np.zeros(truth.data.shape, np.float32), truth.geometry)
            rows = {"source": registration_measures(scan, warp_template(template, zero), zero, truth=truth,
                                                    body=body, markers=markers)}
            if initial is not None:
                rows["initialised"] = registration_measures(scan, warp_template(template, initial), initial,
                                                            truth=truth, body=body, markers=markers)
            rows["registered"] = registration_measures(scan, result.registered, result.correspondence,
                                                       truth=truth, body=body, markers=markers)
            summary["validation"] = rows
        _write_scan(root, sid, result, inverse, summary)
        out.append(summary)
        say(f"{sid}: done in {summary['seconds']:.1f} s, {result.control_points} control points")
    return out


def _write_scan(root: Path, sid: str, result, inverse: Volume, summary: dict) -> None:
    final = root / REGISTRATION_DIR / sid
    final.parent.mkdir(exist_ok=True)
    staging = final.parent / f".{sid}.partial-{secrets.token_hex(4)}"
    staging.mkdir()
    try:
        write_displacement(result.correspondence, staging / "correspondence.mha")
        write_displacement(inverse, staging / "template_to_scan.mha")
        write_volume(result.registered, staging / "registered.nii.gz")
        write_json({"format": "avw-registration", "version": 1, "method": "locally adaptive (Rhee §4, Alg. 1)",
                    "direction": "correspondence: scan_to_template on the scan grid (template position − "
                                 "voxel, mm); template_to_scan: its inverse on the template grid",
                    "summary": summary, "log": result.log(), "workbench_version": __version__},
                   staging / "log.json")
        _replace_dir(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    rel = f"{REGISTRATION_DIR}/{sid}"
    _set_scan_entry(root, sid, "registration", {
        "correspondence": f"{rel}/correspondence.mha", "template_to_scan": f"{rel}/template_to_scan.mha",
        "registered": f"{rel}/registered.nii.gz", "log": f"{rel}/log.json", "method": "adaptive",
        "init": summary.get("init"), "control_points": summary["control_points"],
        "folded_fraction": summary["folding"]["fraction_folded"], "seconds": summary["seconds"],
        "seed": result.settings.seed, "workbench_version": __version__})


def format_summary(summaries: list[dict]) -> str:
    """The end-of-run table: one row per scan and stage (source / initialised / registered)."""
    lines = ["| scan | volume | MED mm | marker MED mm | SSD | CC | MI | folded | control pts | s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for s in summaries:
        rows = s.get("validation")
        if rows is None:
            b, a = s["similarity_before"], s["similarity_after"]
            rows = {"before": {**b, "med_mm": float("nan"), "marker_med_mm": float("nan"),
                               "folded_fraction": float("nan")},
                    "registered": {**a, "med_mm": float("nan"), "marker_med_mm": float("nan"),
                                   "folded_fraction": s["folding"]["fraction_folded"]}}
        for name, r in rows.items():
            last = name == "registered"
            lines.append(f"| {s['scan']} | {name} | {r['med_mm']:.2f} | {r['marker_med_mm']:.2f} | {r['ssd']:.1f} | "
                         f"{r['cc']:.3f} | {r['mi']:.3f} | {r['folded_fraction']:.4f} | "
                         f"{s['control_points'] if last else ''} | {s['seconds'] if last else ''} |")
    return "\n".join(lines)
