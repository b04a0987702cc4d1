"""The ``pose`` stage: bone transforms, joint centres and joint angles of every scan (Rhee §3.1, Kurihara §3).

Every bone of every scan is registered root first, then down the skeleton
(:func:`registration.pose.estimate_poses`: Rhee Eq. 1 by intensity, or
Kurihara's ICP of bone surfaces), then each joint's centre of rotation from
all scans (Kurihara Eq. 1, closed form) and each scan's joint angles.  The
stage covers all scans at once: Kurihara Eq. 1 pools them.

Outputs (``poses/``)::

    <scan>_pose.json          estimated pose, the same schema as truth/<scan>_pose.json
    skeleton_estimated.json   the skeleton with the estimated joint centres
    pose_vectors.json         each scan's joint angles, concatenated in the skeleton's joint order
    joints.json               per joint: centre, hinge axis, Kurihara Eq. 1 residuals, conditioning
    fits.json                 per scan and bone: status, metric before/after, iterations
    report.json / report.txt  the summary tables

The ground truth is not read here; the validate stage compares the poses with it.  The times (the
stage's, each scan's and each bone's fit) are in the stage's ``study.json`` entry, ``timings``: the files
hold none, so the same inputs and settings give the same bytes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deformation.geometry import every_nth
from workbench.io.inputs import read_initial_poses
from workbench.io.volumes import read_image_geometry
from workbench.stages.mechanism import Json, Stage, Text, working_factor, working_labels

__all__ = ["PoseSettings", "STAGE", "finite", "LOCAL_VOXELS"]

#: the working template's voxels between which the scans' bones are registered in several processes of this
#: machine: below, a process's start (a few seconds of imports) costs more than a scan's bones; above, each
#: process would hold a big template's regions and scan — one scan after the other then
LOCAL_VOXELS = (300_000, 16_000_000)


@dataclass(frozen=True)
class PoseSettings:
    method: str = "intensity"  #: "intensity" (Rhee Eq. 1) or "surface" (Kurihara §3 ICP)
    init: str = "identity"  #: root start: "identity", "moments", or an initial-pose file
    metric: str = "ncc"
    interpolation: int = 3  #: 3 cubic B-spline, 1 linear (the papers')
    prior_deg: float | None = 2.0
    min_ncc: float = 0.5
    bias_correction: bool | None = None  #: None: N4 for MRI-like images
    margin_mm: float | None = None
    max_joint_gap_mm: float | None = 10.0
    outlier_factor: float | None = 4.0
    scans: tuple | None = None  #: only these scans (None: all; Kurihara Eq. 1 pools the scans estimated)
    grid_factor: int | None = None  #: bones registered on every f-th voxel (None: 1 up to WORKING_VOXELS, else more)

    def __post_init__(self):
        if self.scans is not None:
            object.__setattr__(self, "scans", tuple(str(v) for v in self.scans))
        if self.method not in ("intensity", "surface"):
            raise ValueError(f"--method must be 'intensity' or 'surface', got {self.method!r}")
        if self.grid_factor is not None and not (isinstance(self.grid_factor, int) and self.grid_factor >= 1):
            raise ValueError(f"--grid-factor must be a whole number ≥ 1, got {self.grid_factor!r}")
        if self.metric not in ("ncc", "ssd"):
            raise ValueError(f"--metric must be 'ncc' or 'ssd', got {self.metric!r}")
        if self.interpolation not in (1, 3):
            raise ValueError(f"interpolation must be 1 (linear) or 3 (B-spline), got {self.interpolation!r}")
        if self.prior_deg is not None and self.prior_deg < 0:
            raise ValueError(f"--prior-deg must be ≥ 0, got {self.prior_deg}")
        if self.prior_deg == 0:  # 0 turns the prior off, as on the command line (--prior-deg 0)
            object.__setattr__(self, "prior_deg", None)
        if self.max_joint_gap_mm is not None and self.max_joint_gap_mm < 0:
            raise ValueError(f"--max-joint-gap-mm must be ≥ 0 (0 switches the check off), got {self.max_joint_gap_mm}")
        if self.outlier_factor is not None and (self.outlier_factor < 0 or 0 < self.outlier_factor <= 1):
            raise ValueError(
                f"--outlier-factor must be 0 (off) or above 1 (a multiple of the joint's median miss), "
                f"got {self.outlier_factor}"
            )


def finite(obj):
    """Non-finite floats (a metric never computed for a bone out of view) → None, so JSON can hold them."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)) and not np.isfinite(obj):
        return None
    return obj


def _inputs(study, s: PoseSettings, scan):
    files = {
        "template": study.path(study.manifest["template"]),
        "skeleton": study.path(study.manifest["skeleton"]),
        "labels": study.template_labels_path(),
    }
    files.update({f"scan/{sid}": study.scan_path(sid) for sid in study.check_scan_ids(s.scans)})
    if s.init not in ("identity", "moments"):
        files["init"] = Path(s.init)
    return files


def _require_bones_in_view(study, ids) -> None:
    """Before any work, with every bone started where the template has it (``--init identity``): each scan's
    field of view holds at least one bone's centre (the bones stage's ``bone_frames.json``), else one clear error
    naming the scan — no bone of it could be placed."""
    from deformation.geometry import GridGeometry
    from workbench.io.jsonio import read_json
    from workbench.study import StudyError

    frames = read_json(study.output("bones", "bone_frames.json"))["bones"]
    centres = np.array([f["centroid"] for f in frames.values()], dtype=np.float64)
    for sid in ids:
        path = study.scan_path(sid)
        g: GridGeometry = read_image_geometry(path)
        if not g.contains_world(centres).any():
            lo, hi = _world_box(g)
            raise StudyError(
                f"{path}: no bone of the template lies in this scan's field of view (scan {sid!r} spans "
                f"{_box_text(lo, hi)} mm; the template's bones lie within {_box_text(centres.min(0), centres.max(0))} "
                "mm), so no bone could be placed: the pose stage starts every bone where the template has it. "
                "Check the scan's origin and direction (its header), or start the root bone with --init moments "
                "or an initial-pose file.",
                path,
            )


def _world_box(g) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array(
        [[i, j, k] for i in (0, g.size[0] - 1) for j in (0, g.size[1] - 1) for k in (0, g.size[2] - 1)],
        dtype=np.float64,
    )
    w = g.index_to_world(corners)
    return w.min(0), w.max(0)


def _box_text(lo, hi) -> str:
    def mm(v) -> str:
        t = f"{v:.0f}"
        return "0" if t == "-0" else t

    return " x ".join(f"[{mm(a)}, {mm(b)}]" for a, b in zip(lo, hi))


def _require_placed(study, result) -> None:
    """A scan of which no bone could be placed (every fit flagged) is one clear error naming the scan: every
    later stage would start from nothing."""
    from collections import Counter

    from workbench.study import StudyError

    for r in result.scans:
        if r.fits and not any(f.ok for f in r.fits.values()):
            why = ", ".join(f"{n} {status}" for status, n in Counter(f.status for f in r.fits.values()).items())
            path = study.scan_path(r.scan_id)
            raise StudyError(
                f"{path}: no bone of scan {r.scan_id!r} could be placed ({why}; fits.json is not written)."
                " Check that the scan shows the template's body part, its header's origin and "
                "direction, or give the root bone a start (--init moments or an initial-pose file).",
                path,
            )


def _fit_arguments(s: PoseSettings, root_init) -> dict:
    """The arguments of :func:`registration.pose.pose_scans` / ``estimate_poses`` the settings give."""
    return dict(
        method=s.method,
        root_init=root_init,
        metric=s.metric,
        interpolation=s.interpolation,
        prior_deg=s.prior_deg,
        min_ncc=s.min_ncc,
        bias_correction=s.bias_correction,
        margin_mm=s.margin_mm,
        max_joint_gap_mm=s.max_joint_gap_mm,
    )


def _working(study, f: int):
    """The template, its labels and a scan reader on the grid the bones are registered on: every ``f``-th voxel
    (intensities smoothed first, :meth:`Volume.every`); the transforms found there are in world mm, as any."""
    return (
        study.template().every(f, smooth=True),
        working_labels(study, study.template_labels(), f),
        lambda sid: study.scan(sid).every(f, smooth=True),
    )


def _scan_task(shared, sid: str):
    """One scan's bones in a task (:mod:`workbench.scale`): the study's folder and the template's regions in,
    the fits out."""
    from registration.pose import pose_scans
    from workbench.study import read_study

    root, f, kwargs, prepared = shared
    study = read_study(root)
    scan = study.scan(sid).every(f, smooth=True)  # as _working's reader
    return pose_scans(None, None, {sid: scan}, study.skeleton(), prepared=prepared, **kwargs)[0]


def _run(ctx) -> dict:
    from registration.pose import estimate_poses, template_regions
    from registration.report import format_fits
    from workbench.scale import local_processes

    study, s = ctx.study, ctx.settings
    skeleton = study.skeleton()
    grid = read_image_geometry(study.path(study.manifest["template"]))
    f = working_factor(s.grid_factor, grid)
    template, labels, read_scan = _working(study, f)
    if f > 1:
        ctx.say(
            f"template of {grid.n_voxels:,} voxels: bones registered on {every_nth(f)} voxel "
            f"along each axis ({template.geometry.n_voxels:,} voxels; --grid-factor)"
        )
    ids = study.check_scan_ids(s.scans)
    if s.init in ("identity", "moments"):
        root_init = None if s.init == "identity" else "moments"
    else:
        root_init = read_initial_poses(s.init, ids, skeleton)
    for sid in ids:  # every scan read once before any work: a corrupt one (NaN voxels) is said at once, not
        study.scan(sid)  # after minutes of work on the scans before it (docs/measurements/workbench.md)
    if root_init is None:
        _require_bones_in_view(study, ids)
    scans = {sid: (lambda sid=sid: read_scan(sid)) for sid in ids}
    n_bones = len(skeleton.bones)

    def cb(sid, si, n_scans, bone, done, total, fit):
        ctx.report(
            si * n_bones + done,
            n_scans * n_bones,
            f"{sid} bone {done}/{total} {bone:<18} {fit.status:<14} ncc {fit.ncc:.3f}  {fit.seconds:.1f} s",
        )

    t0 = time.perf_counter()
    kwargs = _fit_arguments(s, root_init)
    # the template's side once (N4, the bone regions), shared by every scan's task
    prepared = template_regions(template, labels, skeleton, bias_correction=s.bias_correction, margin_mm=s.margin_mm)
    fit_kwargs = {k: v for k, v in kwargs.items() if k not in ("bias_correction", "margin_mm")}
    distributed = ctx.runner is not None and ctx.runner.distributed
    # each scan's bones as a task (a Dask task on a cluster; else, with several scans, one of a few processes of
    # this machine: most of a bone's registration runs on one core); Kurihara Eq. 1 pools them here
    lo, hi = LOCAL_VOXELS
    processes = 1 if distributed or not lo <= template.geometry.n_voxels <= hi else local_processes()
    per_scan = None
    if len(ids) > 1 and (distributed or processes > 1):
        finished = []

        def done(k, r):
            finished.append(r.scan_id)
            ctx.report(len(finished), len(ids), f"{r.scan_id}: bones fitted in {r.seconds:.1f} s")

        per_scan = ctx.map_scans(
            _scan_task,
            ids,
            shared=(str(study.root.resolve()), f, fit_kwargs, prepared),
            on_result=done,
            processes=processes,
        )
    result = estimate_poses(
        template,
        labels,
        scans,
        skeleton,
        outlier_factor=s.outlier_factor,
        progress=cb,
        scan_poses=per_scan,
        prepared=prepared,
        **fit_kwargs,
    )
    _require_placed(study, result)
    total = time.perf_counter() - t0
    ctx.timings.update(
        total=round(total, 3),
        scans={  # to study.json, not to the files (module docstring)
            r.scan_id: {"seconds": round(r.seconds, 3), "bones": {b: round(f.seconds, 4) for b, f in r.fits.items()}}
            for r in result.scans
        },
    )
    text = (
        f"workbench pose — {study.manifest.get('name', study.root.name)} — method {s.method}\n\n{format_fits(result)}"
    )
    report = finite(
        {
            "method": s.method,
            "metric": s.metric,
            "grid_factor": f,
            "failures": result.failures(),
            "eq1_rms_mm": result.overall_rms_mm(),
            "eq1_base_pose_counted": False,
            "text": text,
        }
    )
    out = {f"{r.scan_id}_pose.json": Json(r.pose.to_dict()) for r in result.scans}
    out["skeleton_estimated.json"] = Json(result.skeleton.to_dict())
    order = [j.name for j in skeleton.joints]
    out["pose_vectors.json"] = Json(
        {
            "format": "avw-pose-vectors",
            "version": 1,
            "joint_order": order,
            "dof": [j.dof for j in skeleton.joints],
            "units": "degrees (6-DOF joints: three angles, then mm)",
            "missing": "null: a joint with a bone flagged in that scan (see fits.json)",
            "scans": {
                r.scan_id: [
                    v
                    for j in order
                    for v in (
                        np.asarray(r.pose.joint_angles[j]).tolist()
                        if j in r.pose.joint_angles
                        else [None] * skeleton.joint(j).dof
                    )
                ]
                for r in result.scans
            },
        }
    )
    out["joints.json"] = Json(
        finite(
            {
                "format": "avw-joints",
                "version": 1,
                "method": s.method,
                "units": "mm",
                "eq1_rms_mm": result.overall_rms_mm(),
                "eq1_base_pose_counted": False,
                "joints": result.joints_dict(),
            }
        )
    )
    out["fits.json"] = Json(
        finite(
            {
                "format": "avw-fits",
                "version": 1,
                "method": s.method,
                "scans": {
                    r.scan_id: {"bones": {b: _untimed(f.to_dict()) for b, f in r.fits.items()}} for r in result.scans
                },
            }
        )
    )
    out["report.json"] = Json(report)
    out["report.txt"] = Text(text)
    return out


def _untimed(fit: dict) -> dict:
    """A bone fit's record without its time (``ctx.timings`` has it)."""
    return {k: v for k, v in fit.items() if k != "seconds"}


STAGE = Stage(
    name="pose",
    folder="poses",
    per_scan=False,
    settings_type=PoseSettings,
    run=_run,
    needs=lambda s: ("bones",),
    inputs=_inputs,
    version=7,  # what each version changed: docs/measurements/workbench.md
)
