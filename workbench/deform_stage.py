"""Skinning weights, EVD models and posed volumes of a study (the ``weights``, ``model`` and ``deform`` commands).

Outputs, in the study folder::

    skinning/body_mask.nii.gz      the template's body (segmented: registration.segmentation.segment_body)
    skinning/tetmesh.vtu           the body's tetrahedral mesh (pytetwild) with one point array per bone,
                                   weight_<bone>: the harmonic weights (open it in ParaView)
    skinning/weights.json          the voxel weight map (+ weights_index.mha, weights_value.mha;
                                   workbench.weights_io)
    model/evd.json                 an EVD model (Rhee Eq. 6–7): training scans, their pose vectors, the
                                   correspondence source (+ evd_displacements.mha: 3 components per
                                   training pose, the d_k of Eq. 7 in mm, template grid)

``study.json`` records them under ``stages["skinning"]`` and ``stages["model"]``.

pytetwild's meshes differ from run to run (it takes no seed), so the mesh
is made once per study and kept: ``workbench weights --force`` recomputes
the weights from the kept mesh (deterministic), ``--remesh`` makes a new one.
"""

from __future__ import annotations

import os
import secrets
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deformation.geometry import Volume
from deformation.skeleton import Pose, SkeletonError
from workbench import __version__
from workbench.errors import InputFileError, OutputExistsError
from workbench.jsonio import read_json, write_json
from workbench.study import MANIFEST, Study, read_study
from workbench.volume_io import read_labels, read_vector_image, write_labels, write_vector_image, write_volume
from workbench.weights_io import read_voxel_weights, write_voxel_weights

__all__ = ["run_weights_stage", "load_weights", "run_model_stage", "load_model", "read_target_pose",
           "deform_study", "TemplatePoser", "PosedTemplate", "SKINNING_DIR", "MODEL_DIR", "WEIGHT_METHODS"]

SKINNING_DIR = "skinning"
MODEL_DIR = "model"
WEIGHT_METHODS = ("harmonic", "distance")


def _update_manifest(root: Path, key: str, entry: dict) -> None:
    manifest = read_json(root / MANIFEST)
    stages = dict(manifest.get("stages") or {})
    stages[key] = entry
    manifest["stages"] = stages
    write_json(manifest, root / MANIFEST, overwrite=True)  # atomic replace


def _replace_dir(staging: Path, final: Path) -> None:
    """Move ``staging`` to ``final``, replacing an old ``final`` only once the new one is complete."""
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.old-{secrets.token_hex(4)}"
        os.replace(final, old)
    try:
        os.replace(staging, final)
    except BaseException:
        if old is not None:
            os.replace(old, final)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _bone_labels(study: Study) -> dict:
    sk = study.skeleton()
    return {b: sk.label_of(b) for b in sk.bone_names}


def run_weights_stage(folder, *, method: str = "harmonic", edge_length_mm: float | None = None,
                      remesh: bool = False, overwrite: bool = False, progress=None) -> dict:
    """Compute the study's voxel skinning weights and write ``skinning/`` (see the module docstring).

    ``method`` is ``"harmonic"`` (a tet mesh of the body, each bone a Dirichlet
    boundary) or ``"distance"`` (the fallback: inverse-distance weights on the
    distance to each bone's voxels, :func:`deformation.skinning.distance_weights`).
    """
    from scipy import ndimage

    from deformation.skinning import distance_weights
    from registration.segmentation import segment_body

    if method not in WEIGHT_METHODS:
        raise ValueError(f"method must be one of {WEIGHT_METHODS}, got {method!r}")
    say = progress or (lambda line: None)
    study = read_study(folder)
    root = study.root
    final = root / SKINNING_DIR
    if (final / "weights.json").exists() and not overwrite:
        raise OutputExistsError(final, f"{final} holds weights already (an earlier `workbench weights`); pass "
                                       "--force to recompute them (from the kept tet mesh; --remesh for a new one).")
    if not study.has_template_labels:
        raise InputFileError(f"{root / MANIFEST}: the study has no bone label map; run `workbench pose --seeds` to "
                             "segment the bones first.", root / MANIFEST)
    template, labels = study.template(), study.template_labels()
    bone_labels = _bone_labels(study)
    bones = tuple(bone_labels)
    g = template.geometry
    t0 = time.perf_counter()
    body = segment_body(template, labels=labels)
    staging = root / f".{SKINNING_DIR}.partial-{secrets.token_hex(4)}"
    staging.mkdir()
    try:
        info: dict = {"method": method}
        write_labels(body, staging / "body_mask.nii.gz")
        if method == "harmonic":
            from deformation.harmonic import harmonic_weights, weights_on_grid
            from deformation.tetmesh import body_surface, tetrahedralize
            from workbench.tetmesh_io import read_tetmesh, weight_arrays, write_tetmesh

            old_mesh = final / "tetmesh.vtu"
            if old_mesh.exists() and not remesh:
                if edge_length_mm is not None:
                    say("note: --edge-length-mm is ignored: the study's kept mesh is used (pass --remesh)")
                mesh, _ = read_tetmesh(old_mesh)
                say(f"using the study's tet mesh {old_mesh} ({mesh.n_vertices} vertices, {mesh.n_tets} tets)")
                info["mesh"] = "kept"
            else:
                say("meshing the body surface with pytetwild (random: made once per study and kept) ...")
                surface = body_surface(body)
                mesh = tetrahedralize(surface, edge_length_mm=edge_length_mm)
                info["mesh"] = "new"
            say(f"harmonic weights on {mesh.n_vertices} vertices ...")
            dense, hinfo = harmonic_weights(mesh, labels, bone_labels)
            info.update({k: v for k, v in hinfo.items() if isinstance(v, (int, float, str, bool))})
            write_tetmesh(mesh, staging / "tetmesh.vtu", point_data=weight_arrays(bones, dense))
            say("weights of every voxel (barycentric; one-hot in bones) ...")
            weights = weights_on_grid(mesh, dense, bones, g, labels, bone_labels)
            info.update(n_vertices=int(mesh.n_vertices), n_tets=int(mesh.n_tets))
        else:
            if (final / "tetmesh.vtu").exists():  # keep the study's mesh for a later harmonic run
                shutil.copy2(final / "tetmesh.vtu", staging / "tetmesh.vtu")
            lab = np.asarray(labels.data)
            sp = np.asarray(g.spacing)[::-1]  # array order (z, y, x)
            dist = np.empty((g.n_voxels, len(bones)))
            for k, b in enumerate(bones):
                inside = lab == bone_labels[b]
                if not inside.any():
                    raise InputFileError(f"the label map has no voxel of bone {b!r} (label {bone_labels[b]})",
                                         root / study.manifest["template_labels"])
                dist[:, k] = np.where(inside, 0.0, ndimage.distance_transform_edt(~inside, sampling=sp)).ravel()
            weights = distance_weights(dist, bones)
        seconds = time.perf_counter() - t0
        write_voxel_weights(weights, g, staging / "weights.json", method=method, seconds=round(seconds, 2),
                            workbench_version=__version__)
        _replace_dir(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    entry = {"method": method, "folder": SKINNING_DIR, "weights": f"{SKINNING_DIR}/weights.json",
             "tetmesh": f"{SKINNING_DIR}/tetmesh.vtu" if (final / "tetmesh.vtu").exists() else None,
             "body_mask": f"{SKINNING_DIR}/body_mask.nii.gz", "seconds": round(seconds, 2),
             "workbench_version": __version__}
    _update_manifest(root, "skinning", entry)
    info["seconds"] = seconds
    return info


def _weights_digest(weights) -> str:
    """A digest of a weight map's arrays: an EVD model is only valid with the weights it was built with."""
    import hashlib

    h = hashlib.sha256()
    h.update("\n".join(weights.bones).encode())
    h.update(np.ascontiguousarray(weights.index).tobytes())
    h.update(np.ascontiguousarray(weights.value).tobytes())
    return h.hexdigest()


def load_weights(study: Study):
    """``(weights, body_mask Volume)`` of a study; a clear error when ``workbench weights`` has not run."""
    path = study.root / SKINNING_DIR / "weights.json"
    if not path.exists():
        raise InputFileError(f"{path}: the study has no skinning weights yet; run `workbench weights "
                             f"{study.root}` first.", path)
    weights, geometry, _ = read_voxel_weights(path)
    template_geometry = study.template().geometry
    template_geometry.check_same(geometry, names=("template", str(path)),
                                 remedy="recompute the weights: workbench weights --force")
    body = read_labels(study.root / SKINNING_DIR / "body_mask.nii.gz")
    return weights, body


# -- poses ---------------------------------------------------------------------------------------
def read_target_pose(path, skeleton) -> Pose:
    """A target pose from a file: an ``avw-pose`` (bone transforms) or joint angles.

    Joint angles: ``{"angles": {joint: [degrees...]}}`` (missing joints stay at
    0; 6-DOF joints add mm), run through the skeleton's forward kinematics.
    """
    path = Path(path)
    d = read_json(path)
    if isinstance(d, dict) and d.get("format") == "avw-pose":
        try:
            pose = Pose.from_dict(d)
        except (SkeletonError, ValueError) as e:
            raise InputFileError(f"{path}: {e}", path) from e
        missing = set(skeleton.bone_names) - set(pose.transforms)
        if missing:
            raise InputFileError(f"{path}: the pose lacks transforms for bones {sorted(missing)}.", path)
        return pose
    if isinstance(d, dict) and isinstance(d.get("angles"), dict):
        try:
            return skeleton.pose({k: np.asarray(v, dtype=float) for k, v in d["angles"].items()})
        except (SkeletonError, ValueError) as e:
            raise InputFileError(f"{path}: {e}", path) from e
    raise InputFileError(f"{path}: expected an avw-pose file (bone transforms) or {{\"angles\": {{joint: "
                         "[degrees, ...]}}}}.", path)


# -- EVD models ------------------------------------------------------------------------------------
def _template_to_scan(study: Study, scan_id: str, pose: Pose, body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Template → scan positions of every template voxel from the truth's scan → template field.

    The truth field gives, on the scan grid, each scan voxel's template
    position: a forward map from the scan grid into template space, inverted
    by the backward map onto the template grid (candidates: the inverse bone
    transforms), so that no phantom code is needed.  Returns the positions and
    where they were found: template voxels that leave the scan's field of view
    have no correspondence in it.
    """
    from deformation.resample import backward_map
    from deformation.skinning import stack_transforms

    field = study.truth_correspondence(scan_id)
    g_scan = field.geometry
    g_t = study.template().geometry
    fwd = (field.data + g_scan.world_coordinates()).astype(np.float32)  # scan voxel → template position
    inv = np.stack([np.linalg.inv(t) for t in stack_transforms(pose.transforms, study.skeleton().bone_names)])
    # prefer scan voxels that came from the template's body (where the map is not one-to-one)
    ijk = np.rint(g_t.world_to_index(fwd.reshape(-1, 3))).astype(np.int64)
    ijk = np.clip(ijk, 0, np.asarray(g_t.size) - 1)
    prefer = body[ijk[:, 2], ijk[:, 1], ijk[:, 0]].reshape(g_scan.array_shape).astype(bool)
    bm = backward_map(fwd, g_scan, g_t, transforms=inv, prefer=prefer)
    found = bm.status <= 1  # OK or FOLDED; the rest left the scan's field of view (or was not solved)
    return bm.template_positions().reshape(g_t.array_shape + (3,)), found


def run_model_stage(folder, *, source: str = "truth", scan_ids=None, overwrite: bool = False, progress=None) -> dict:
    """Build an EVD model (Rhee Eq. 7) from the study's correspondences and write ``model/``.

    ``source="truth"``: the phantoms' ground-truth correspondences and poses
    (registrations of issue D will be the other source).
    """
    from deformation.evd import ExampleVolumeDeformation, vbd_forward
    from deformation.posespace import pose_vector

    say = progress or (lambda line: None)
    study = read_study(folder)
    root = study.root
    final = root / MODEL_DIR
    if (final / "evd.json").exists() and not overwrite:
        raise OutputExistsError(final, f"{final} holds a model already; pass --force to rebuild it.")
    if source != "truth":
        raise ValueError(f"source must be 'truth' (registered correspondences come with issue D), got {source!r}")
    ids = list(scan_ids or study.scan_ids)
    missing = [s for s in ids if not study.has_truth(s)]
    if missing:
        raise InputFileError(f"{root / MANIFEST}: scans {missing} have no ground truth to build a model from.",
                             root / MANIFEST)
    weights, body = load_weights(study)
    sk = study.skeleton()
    g = study.template().geometry
    poses, fields, unmatched = [], [], {}
    t0 = time.perf_counter()
    for k, sid in enumerate(ids):
        pose = study.truth_pose(sid)
        poses.append(pose)
        if study.has_truth_template_to_scan(sid):  # the exact forward map (phantom studies)
            f = study.truth_template_to_scan(sid)
            g.check_same(f.geometry, names=("template", f"{sid} template_to_scan"))
            pos = f.data + g.world_coordinates()
            found = np.ones(g.array_shape, bool)
            say(f"[{k + 1}/{len(ids)}] {sid}: the truth's exact template → scan map")
        else:
            pos, found = _template_to_scan(study, sid, pose, body.data)
            say(f"[{k + 1}/{len(ids)}] {sid}: template → scan map by inverting the truth's scan → template field")
        # voxels with no correspondence in the scan (outside its field of view) keep VBD: d_k = 0
        pos[~found] = vbd_forward(g, weights, pose.transforms)[~found]
        unmatched[sid] = int((~found).sum())
        fields.append(pos)
    model = ExampleVolumeDeformation.from_correspondences(g, weights, sk, poses, fields)
    del fields
    seconds = time.perf_counter() - t0
    staging = root / f".{MODEL_DIR}.partial-{secrets.token_hex(4)}"
    staging.mkdir()
    try:
        disp = model.displacements.reshape(g.array_shape + (3 * len(ids),))
        write_vector_image(Volume(disp, g), staging / "evd_displacements.mha")
        write_json({"format": "avw-evd", "version": 1, "source": source, "scans": ids,
                    "pose_vectors": {sid: pose_vector(sk, p).tolist() for sid, p in zip(ids, poses)},
                    "joint_order": [j.name for j in sk.joints],
                    "displacements": "evd_displacements.mha",
                    "layout": "per voxel: (d_x, d_y, d_z) of each training scan in turn, mm, template frame "
                              "(Rhee Eq. 7)",
                    "weights": f"../{SKINNING_DIR}/weights.json", "weights_sha256": _weights_digest(weights),
                    "seconds": round(seconds, 2),
                    "unmatched_voxels": unmatched,
                    "unmatched": "template voxels with no correspondence in that scan (they leave its field of "
                                 "view): d_k = 0 there, i.e. VBD",
                    "workbench_version": __version__}, staging / "evd.json")
        _replace_dir(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    _update_manifest(root, "model", {"method": "evd", "folder": MODEL_DIR, "model": f"{MODEL_DIR}/evd.json",
                                     "source": source, "scans": ids, "seconds": round(seconds, 2),
                                     "workbench_version": __version__})
    return {"scans": ids, "seconds": seconds}


def load_model(study: Study, weights=None):
    """The study's EVD model (``model/evd.json``), or ``None`` when there is none."""
    from deformation.evd import ExampleVolumeDeformation
    from deformation.posespace import PoseSpace

    path = study.root / MODEL_DIR / "evd.json"
    if not path.exists():
        return None
    doc = read_json(path)
    if doc.get("format") != "avw-evd":
        raise InputFileError(f"{path}: not an EVD model ('format' is {doc.get('format')!r}).", path)
    missing = [k for k in ("scans", "pose_vectors", "displacements", "joint_order") if k not in doc]
    if missing or any(s not in doc["pose_vectors"] for s in doc.get("scans", [])):
        raise InputFileError(f"{path}: the model lacks {missing or 'a pose vector of a training scan'}; rebuild it "
                             f"with `workbench model {study.root} --force`.", path)
    if weights is None:
        weights, _ = load_weights(study)
    stale = f"rebuild the model with `workbench model {study.root} --force`"
    if doc.get("weights_sha256") != _weights_digest(weights):
        raise InputFileError(f"{path}: the model was built with other skinning weights than the study's "
                             f"skinning/weights.json (recomputed since?); {stale}.", path)
    sk = study.skeleton()
    if doc["joint_order"] != [j.name for j in sk.joints]:
        raise InputFileError(f"{path}: the model's joints {doc['joint_order']} are not the skeleton's "
                             f"{[j.name for j in sk.joints]}; {stale}.", path)
    vol = read_vector_image(path.parent / doc["displacements"])
    g = vol.geometry
    study.template().geometry.check_same(g, names=("template", str(path.parent / doc["displacements"])),
                                         remedy=stale)
    n = len(doc["scans"])
    if vol.n_components != 3 * n:
        raise InputFileError(f"{path.parent / doc['displacements']}: {vol.n_components} components, expected "
                             f"3 × {n} training scans.", path.parent / doc["displacements"])
    space = PoseSpace(sk, [np.asarray(doc["pose_vectors"][s], dtype=float) for s in doc["scans"]])
    return ExampleVolumeDeformation(g, weights, space, vol.data.reshape(-1, n, 3))


# -- posed volumes -----------------------------------------------------------------------------------
@dataclass
class PosedTemplate:
    """The template deformed to one pose, on the template's grid."""

    volume: Volume
    labels: Volume | None
    backward: object  #: the :class:`deformation.resample.BackwardMap`
    forward_seconds: float
    backward_seconds: float


class TemplatePoser:
    """A study's template, skinning weights and (when present) EVD model, loaded once, posed many times.

    ``method``: ``auto`` (EVD when the study has a model, VBD otherwise),
    ``vbd`` (Rhee Eq. 2) or ``evd`` (Eq. 6–7; an error without a model).
    :meth:`pose` deforms the template (and its labels) to a pose: forward
    map, backward map (Newton, seeded by the bones' transforms), resampling
    — what ``workbench deform`` writes and ``workbench animate`` renders.
    """

    def __init__(self, study: Study, *, method: str = "auto", weighting: str = "psd", progress=None):
        if method not in ("auto", "vbd", "evd"):
            raise ValueError(f"method must be 'auto', 'vbd' or 'evd', got {method!r}")
        if weighting not in ("psd", "wpsd"):
            raise ValueError(f"weighting must be 'psd' or 'wpsd', got {weighting!r}")
        say = progress or (lambda line: None)
        self.study = study
        self.skeleton = study.skeleton()
        self.weights, self.body = load_weights(study)
        self.model = load_model(study, self.weights) if method in ("auto", "evd") else None
        if method == "evd" and self.model is None:
            raise InputFileError(f"{study.root / MODEL_DIR / 'evd.json'}: the study has no EVD model; build one "
                                 f"with `workbench model {study.root}` or use --method vbd.", study.root / MODEL_DIR)
        self.method = "evd" if self.model is not None else "vbd"
        self.weighting = weighting
        if self.method == "vbd" and weighting != "psd":
            say("note: --weighting applies to EVD only; this is VBD")
        self.template = study.template()
        self.template_labels = study.template_labels() if study.has_template_labels else None
        air = np.asarray(self.template.data)[self.body.data == 0]
        self.fill = float(np.median(air)) if air.size else float(np.min(self.template.data))  # the template's air
        self._say = say

    def forward(self, pose) -> np.ndarray:
        """Template voxels' posed world positions ``(nz, ny, nx, 3)`` (EVD or VBD)."""
        from deformation.evd import vbd_forward
        from deformation.skinning import stack_transforms

        if self.method == "evd":
            return self.model.forward(pose, weighting=self.weighting)
        return vbd_forward(self.template.geometry, self.weights, stack_transforms(pose.transforms, self.weights.bones))

    def pose(self, pose, *, labels: bool = True, target=None) -> PosedTemplate:
        """The template (and labels) posed, on the template's grid or on ``target`` (a GridGeometry)."""
        from deformation.resample import backward_map, resample_forward
        from deformation.skinning import stack_transforms

        g = self.template.geometry
        t = stack_transforms(pose.transforms, self.weights.bones)
        t0 = time.perf_counter()
        self._say(f"forward map ({self.method.upper()}) of {g.n_voxels:,} template voxels ...")
        fwd = self.forward(pose)
        t1 = time.perf_counter()
        self._say("backward map and resampling ...")
        bm = backward_map(fwd, g, target, transforms=t, prefer=self.body.data.astype(bool))
        vol = resample_forward(bm, self.template, fill=self.fill)
        lab = (resample_forward(bm, self.template_labels, labels=True)
               if labels and self.template_labels is not None else None)
        t2 = time.perf_counter()
        return PosedTemplate(vol, lab, bm, t1 - t0, t2 - t1)


def deform_study(folder, pose_path, out, *, method: str = "auto", weighting: str = "psd", labels_out=None,
                 field_out=None, overwrite: bool = False, progress=None) -> dict:
    """Deform the template to a pose (VBD, Rhee Eq. 2, or EVD, Eq. 6) and write the posed volume and labels.

    The posed volume lies on the template's grid (same geometry).  Returns a
    summary: the method, the backward map's status counts, timings.
    """
    from workbench.atomic import split_suffix
    from workbench.volume_io import image_format

    if method not in ("auto", "vbd", "evd"):
        raise ValueError(f"method must be 'auto', 'vbd' or 'evd', got {method!r}")
    if weighting not in ("psd", "wpsd"):
        raise ValueError(f"weighting must be 'psd' or 'wpsd', got {weighting!r}")
    say = progress or (lambda line: None)
    study = read_study(folder)
    out = Path(out)
    stem, suffix = split_suffix(out.name)
    labels_out = Path(labels_out) if labels_out else out.with_name(f"{stem}_labels{suffix}")
    outputs = [out, labels_out] + ([Path(field_out)] if field_out else [])
    # every check before any work, so that no output set is left half-written
    for p in outputs:
        image_format(p, for_writing=True)
        if p.exists() and not overwrite:
            raise OutputExistsError(p, f"{p} exists; pass --force to replace it.")
    resolved = [p.resolve() for p in outputs]
    if len(set(resolved)) != len(resolved):
        raise ValueError(f"the output files must differ: {[str(p) for p in outputs]}")
    root = study.root.resolve()
    protected = {root / MANIFEST, root / study.manifest["template"]}
    if study.manifest.get("template_labels"):
        protected.add(root / study.manifest["template_labels"])
    for p in resolved:
        inside = root in p.parents
        if p in protected or (inside and p.relative_to(root).parts[0] in
                              ("scans", "truth", "poses", SKINNING_DIR, MODEL_DIR)):
            raise ValueError(f"{p}: would overwrite one of the study's own files; write the posed volume "
                             "elsewhere (or in a new subfolder of the study)")
    pose = read_target_pose(pose_path, study.skeleton())  # a bad pose file is reported before any loading
    poser = TemplatePoser(study, method=method, weighting=weighting, progress=say)
    if poser.template_labels is None:
        raise InputFileError(f"{study.root / MANIFEST}: the study has no template label map; `workbench deform` "
                             "writes the posed labels beside the posed volume and needs one.", study.root / MANIFEST)
    used = poser.method
    posed = poser.pose(pose)
    bm = posed.backward
    write_volume(posed.volume, out, overwrite=overwrite)
    write_labels(posed.labels, labels_out, overwrite=overwrite)
    if field_out:
        from workbench.volume_io import write_displacement

        write_displacement(bm.scan_to_template(), field_out, overwrite=overwrite)
    summary = {"method": used, "weighting": weighting if used == "evd" else None, "out": str(out),
               "labels": str(labels_out), "field": str(field_out) if field_out else None,
               "forward_seconds": posed.forward_seconds, "backward_seconds": posed.backward_seconds, **bm.summary()}
    return summary
