"""The ``init`` stage: the registration's articulated start for each scan (Rhee §3, Rhee Eq. 2).

``method="polyrigid"`` (default): the bones' rigid motions to the scan's pose blended as a flow
(:func:`registration.initialise.polyrigid_initial_field`, :mod:`deformation.models.polyrigid`): one-to-one by
construction, every bone exactly rigid, and its forward map (template → scan) is written beside it, so the
register stage inverts only its own correction; no fold of its own in a flexed joint's crease
(docs/measurements/workbench.md). ``method="vbd"``: every template voxel moved by the weighted blend of its bones'
transforms (VBD, Rhee Eq. 2) to the scan's pose — the *estimated* pose of the pose stage, or with ``pose="truth"``
the phantom's true pose (an explicit protocol choice, e.g. Rhee's Table 4; the pipeline never falls back to it) —
inverted onto the scan grid by the backward map (:func:`registration.initialise.vbd_initial_field`).  ``unfold``
repairs the folds of VBD in the crease of a flexed joint (:func:`deformation.fields.displacement.unfold`).
``method="identity"``: no start (Rhee's Table 2 protocol).

The polyrigid flow is integrated voxel by voxel; on a grid of more than ``POLYRIGID_VOXELS`` voxels (a CT at
0.5 mm) it is integrated on every f-th voxel and blended up, integrated exactly where the map jumps
(``map_factor``, :meth:`deformation.models.polyrigid.PolyrigidFlow.scan_to_template`).

Outputs (``init/<scan>/``): ``field.mha`` (``scan_to_template`` on the scan grid, mm; not for the identity),
``forward.mha`` (polyrigid only: the flow's ``template_to_scan`` field on the template grid) and ``init.json``
(the method, the bone transforms it blended — what the register stage needs to invert its result — and the
backward map's summary).
"""

from __future__ import annotations

from dataclasses import dataclass

from deformation.geometry import every_nth
from workbench.stages.mechanism import Field, Json, Stage

__all__ = ["InitSettings", "STAGE", "METHODS"]

METHODS = ("polyrigid", "vbd", "identity")
#: the most voxels of a grid the polyrigid flow is integrated at every voxel of (about half an hour a map: see
#: docs/measurements/workbench.md); a bigger grid gets the smallest map factor that leaves at most this many
POLYRIGID_VOXELS = 16_000_000


@dataclass(frozen=True)
class InitSettings:
    method: str = "polyrigid"  #: "polyrigid", "vbd" or "identity"
    pose: str = "estimated"  #: "estimated" (the pose stage's) or "truth" (a phantom's, for protocols)
    unfold: bool = False
    map_factor: int | None = None  #: polyrigid: integrate every f-th voxel (None: 1 up to POLYRIGID_VOXELS)

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(
                f"the init method must be one of {METHODS} (--init polyrigid|vbd|none), got {self.method!r}"
            )
        if self.pose not in ("estimated", "truth"):
            raise ValueError(f"--pose must be 'estimated' or 'truth', got {self.pose!r}")
        if self.unfold and self.method != "vbd":
            raise ValueError("--unfold-init repairs the VBD initialisation: it needs --init vbd")
        if self.map_factor is not None:
            if isinstance(self.map_factor, bool) or not isinstance(self.map_factor, int) or self.map_factor < 1:
                raise ValueError(f"--map-factor must be a whole number ≥ 1, got {self.map_factor!r}")
            if self.method != "polyrigid":
                raise ValueError(
                    "--map-factor sets the polyrigid start's sampling: it needs --init polyrigid (VBD's "
                    "maps follow the weights' --grid-factor; workbench run: --set init.map_factor=null)"
                )


def _needs(s: InitSettings):
    if s.method == "identity":
        return ()
    if s.method == "polyrigid":  # the bones' labels and the skeleton, no skinning weights
        return ("bones",) if s.pose == "truth" else ("bones", "pose")
    return ("weights",) if s.pose == "truth" else ("weights", "pose")


def _inputs(study, s: InitSettings, scan):
    files = {"template": study.path(study.manifest["template"]), "scan": study.scan_path(scan)}
    if s.method == "polyrigid":
        files["labels"] = study.template_labels_path()
        files["skeleton"] = study.path(study.manifest["skeleton"])
        if s.map_factor is not None:  # before any work: the grids' headers
            from deformation.models.polyrigid import max_map_factor
            from workbench.io.volumes import read_image_geometry

            for name, path in (("scan", files["scan"]), ("template", files["template"])):
                g = read_image_geometry(path)
                if s.map_factor > max_map_factor(g):
                    raise ValueError(
                        f"--map-factor {s.map_factor} leaves the {name}'s {g.size}-voxel grid less "
                        f"than 2 voxels along an axis: at most {max_map_factor(g)} here"
                    )
    if s.method != "identity" and s.pose == "truth":
        if not study.has_truth(scan):
            from workbench.study import StudyError

            raise StudyError(
                f"{study.manifest_path}: scan {scan!r} has no ground truth for --pose truth; use the "
                "estimated pose (`workbench pose`).",
                study.manifest_path,
            )
        files["truth_pose"] = study.truth_files(scan)["pose"]
    return files


def _run(ctx) -> dict:
    from deformation.models.skinning import stack_transforms
    from registration.initialise import vbd_initial_field
    from workbench.io.volumes import read_image_geometry

    study, s, sid = ctx.study, ctx.settings, ctx.scan
    if s.method == "identity":
        return {"init.json": Json({"format": "avw-init", "version": 1, "method": "identity"})}
    pose = study.truth_pose(sid) if s.pose == "truth" else study.pose(sid)
    # bones the pose stage could not place: their pose follows their ancestor's, and the registration does not
    # hold them rigid (registration.pose.placed_transforms / released_labels)
    flagged = [] if s.pose == "truth" else study.pose_flagged(sid)
    g_t = read_image_geometry(study.path(study.manifest["template"]))
    g_s = read_image_geometry(study.scan_path(sid))
    if s.method == "polyrigid":
        return _polyrigid(ctx, pose, g_s, flagged)
    weights, body = study.weights(coarse=True)
    f = g_t.factor_of(body.geometry)  # 1, or the weights' --grid-factor (a big template; checked by weights())
    ctx.say(
        f"{sid}: VBD ({s.pose} pose) onto {g_s.describe()}"
        f"{f' (the maps on {every_nth(f)} voxel, as the weights)' if f > 1 else ''} ..."
    )
    transforms = stack_transforms(pose.transforms, weights.bones)
    field, summary = vbd_initial_field(g_t, g_s, weights, transforms, body=body.data, unfold=s.unfold, factor=f)
    return {
        "field.mha": Field(field),
        "init.json": Json(
            {
                "format": "avw-init",
                "version": 1,
                "method": "vbd",
                "pose": s.pose,
                "flagged_bones": flagged,
                "direction": "scan_to_template: template position − scan voxel, mm",
                "bones": list(weights.bones),
                "transforms": transforms,
                "transforms_are": "each bone's template → scan 4x4 that VBD blended",
                "backward_map": summary,
            }
        ),
    }


def _polyrigid(ctx, pose, g_s, flagged) -> dict:
    from deformation.models.polyrigid import max_map_factor
    from deformation.models.skinning import stack_transforms
    from registration.initialise import polyrigid_initial_field

    study, s, sid = ctx.study, ctx.settings, ctx.scan
    sk = study.skeleton()
    labels = study.template_labels()
    bone_labels = {b: sk.label_of(b) for b in sk.bone_names}
    parents = {b: sk.bone(b).parent for b in sk.bone_names}
    g_t = labels.geometry
    if s.map_factor is not None:  # checked against both grids before the work (_inputs)
        f_s = f_t = s.map_factor
    else:  # a cell to blend along every axis, however thin the grid
        f_s, f_t = (min(g.factor_within(POLYRIGID_VOXELS), max_map_factor(g)) for g in (g_s, g_t))

    def on(f):
        return f" (integrated on {every_nth(f)} voxel, exactly where the map jumps; --map-factor)" if f > 1 else ""

    ctx.say(f"{sid}: polyrigid flow ({s.pose} pose) onto {g_s.describe()}{on(f_s)} ...")
    field, flow = polyrigid_initial_field(
        labels,
        bone_labels,
        parents,
        pose.transforms,
        g_s,
        factor=f_s,
        progress=lambda d, n: ctx.report(d, n, "the start on the scan grid"),
    )
    ctx.say(f"{sid}: its forward map on the template grid{on(f_t)} ...")
    forward = flow.template_to_scan(factor=f_t, progress=lambda d, n: ctx.report(d, n, "its forward map"))
    bones = list(sk.bone_names)
    return {
        "field.mha": Field(field),
        "forward.mha": Field(forward),
        "init.json": Json(
            {
                "format": "avw-init",
                "version": 1,
                "method": "polyrigid",
                "pose": s.pose,
                "flagged_bones": flagged,
                "direction": "field: scan_to_template (template position − scan voxel, mm) on the "
                "scan grid; forward: template_to_scan on the template grid",
                "bones": bones,
                "transforms": stack_transforms(pose.transforms, bones),
                "transforms_are": "each bone's template → scan 4x4 that the flow blended",
                "weights": {
                    "kind": "distance, moving with the bones",
                    "power": flow.power,
                    "falloff_mm": flow.falloff_mm,
                },
                "rk4_steps": int(flow.steps),
                "map_factor": {"scan": int(f_s), "template": int(f_t)},
            }
        ),
    }


STAGE = Stage(
    name="init",
    folder="init",
    per_scan=True,
    settings_type=InitSettings,
    run=_run,
    needs=_needs,
    inputs=_inputs,
    version=8,  # what each version changed: docs/measurements/workbench.md
)
