"""The ``surface`` stage: Kurihara's consistent skin meshes (Kurihara & Miyata 2004, §3–4).

* **S0**, the base mesh: the template's skin (:func:`registration.segmentation.skin_surface`: air/tissue
  isosurface, debris dropped, decimated to ``target_triangles``; the paper: ~800 k → ~100 k triangles), with every
  vertex's skinning weights — the weights stage's harmonic weights at the vertex (its tet mesh), or the nearest
  voxel's weights when it kept no tet mesh;
* the template's bones as surfaces (each label's boundary, for pictures);
* per scan ``i`` (:func:`registration.surface_fit.consistent_mesh`): the scan's skin ``T_i``; ``S^s_i``, S0 by SSD
  with the pose stage's estimated transforms (Kurihara Eq. 2–3); ``S^r_i``, RBF feature-point deformation
  (Kurihara Eq. 4–5) with ``n_features`` vertices spread over S0 whose targets come from the volume registration
  (``features="registration"``: where the register stage's inverse field puts each vertex) or from confident
  closest points on ``T_i`` (``"closest"``), or with landmarks picked on the template's and the scan's skin
  (``"landmarks"``, a JSON/CSV file: the paper picked 70–150 points by hand per pose); and ``S^f_i``, the fit to
  ``T_i`` — the smoothness- regularised one (``fit="regularised"``, for touching or missing skin) or the paper's
  nearest-point fit (``"nearest"``).  Every ``S^f_i`` has S0's connectivity, so
  :class:`deformation.models.surface_model.SurfaceModel` can interpolate them (``workbench surface-deform``).

Outputs (``surface/``): ``template_skin.vtp`` (S0 with ``weight_<bone>`` point arrays), ``template_bones.vtp`` (a
``label`` point array), per scan ``<scan>_skin.ply``, ``<scan>_ssd.ply``, ``<scan>_rbf.ply``,
``<scan>_fitted.ply``, and ``surface.json`` (what each step did, fit distances).  All in world mm: they open in
ParaView and 3D Slicer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench import __version__
from workbench.stages.mechanism import Json, MeshFile, Stage

__all__ = ["SurfaceSettings", "STAGE"]


@dataclass(frozen=True)
class SurfaceSettings:
    target_triangles: int = 100_000  #: S0 and the scans' skins decimated to about this many (Kurihara: ~100 k)
    features: str = "registration"  #: the RBF feature points' targets: "registration", "closest" or "landmarks"
    n_features: int = 150  #: feature points per scan (Kurihara picked 70–150 by hand); landmarks: all of them
    landmarks: str | None = None  #: with features="landmarks": a JSON/CSV file of landmark pairs (io.read_landmarks)
    fit: str = "regularised"  #: "regularised" (touching or missing skin) or "nearest" (Kurihara §4's fit)
    stiffness: float = 1.0  #: the regularised fit's λ (registration.surface_fit.fit_regularised)
    max_distance_mm: float = 5.0  #: a closest point farther than this is not a target
    smooth_voxels: float = 1.0  #: Gaussian smoothing of the images before the skin isosurface
    scans: tuple | None = None  #: the scans to fit (None: all)

    def __post_init__(self):
        from registration.surface_fit import FEATURE_SOURCES, FITS

        if self.features not in FEATURE_SOURCES:
            raise ValueError(f"--features must be one of {FEATURE_SOURCES}, got {self.features!r}")
        if self.fit not in FITS:
            raise ValueError(f"--fit must be one of {FITS}, got {self.fit!r}")
        if (self.features == "landmarks") != (self.landmarks is not None):
            raise ValueError(
                "a landmarks file goes with the landmarks feature source (--landmarks FILE, or "
                '--set surface.features="landmarks" --set surface.landmarks="FILE"); got features '
                f"{self.features!r} and landmarks {self.landmarks!r}"
            )
        if self.landmarks is not None:  # absolute: the recorded setting works from any folder
            from pathlib import Path

            object.__setattr__(self, "landmarks", str(Path(self.landmarks).expanduser().resolve()))
        if int(self.target_triangles) < 100:
            raise ValueError(f"--target-triangles must be at least 100, got {self.target_triangles}")
        if int(self.n_features) < 4:
            raise ValueError(f"--features-count must be at least 4 (an RBF needs points), got {self.n_features}")
        if not self.stiffness > 0:
            raise ValueError(f"--stiffness must be positive, got {self.stiffness}")
        if not self.max_distance_mm > 0:
            raise ValueError(
                f"surface.max_distance_mm (--set surface.max_distance_mm=MM) must be positive, got "
                f"{self.max_distance_mm}"
            )
        if self.smooth_voxels < 0:
            raise ValueError(
                f"surface.smooth_voxels (--set surface.smooth_voxels=V) must be ≥ 0, got {self.smooth_voxels}"
            )
        if self.scans is not None:
            object.__setattr__(self, "scans", tuple(str(v) for v in self.scans))


def _needs(s: SurfaceSettings):
    return ("weights", "pose", "register") if s.features == "registration" else ("weights", "pose")


def _inputs(study, s: SurfaceSettings, scan):
    files = {
        "template": study.path(study.manifest["template"]),
        "labels": study.template_labels_path(),
        "skeleton": study.path(study.manifest["skeleton"]),
    }
    for sid in study.check_scan_ids(s.scans):
        files[f"scan/{sid}"] = study.scan_path(sid)
    if s.landmarks is not None:
        files["landmarks"] = s.landmarks
    return files


def vertex_weights(study, points):
    """Skinning weights at world ``points``: the harmonic ones through the weights stage's tet mesh, or the
    nearest template voxel's when the stage kept none."""
    from deformation.models.harmonic import weights_at_points
    from workbench.io.tetmeshes import read_tetmesh, weights_from_point_data

    if study.has_output("weights", "tetmesh.vtu"):
        mesh, pd = read_tetmesh(study.output("weights", "tetmesh.vtu"))
        bones, dense = weights_from_point_data(pd)
        return weights_at_points(mesh, dense, bones, points), "harmonic, at the vertex (tet mesh)"
    w, _ = study.weights()
    g = study.template().geometry
    ijk = np.clip(np.rint(g.world_to_index(points)).astype(np.int64), 0, np.asarray(g.size) - 1)
    rows = (ijk[:, 2] * g.size[1] + ijk[:, 1]) * g.size[0] + ijk[:, 0]
    return w.take(rows), "the nearest template voxel's"


def _run(ctx) -> dict:
    from deformation.meshes.isosurface import label_surfaces
    from registration.segmentation import skin_surface
    from registration.surface_fit import landmark_sites
    from workbench.io.tetmeshes import weight_arrays

    study, s = ctx.study, ctx.settings
    ids = study.check_scan_ids(s.scans)
    marks = None
    if s.features == "landmarks":  # checked before any work
        from workbench.io.inputs import read_landmarks

        marks = read_landmarks(s.landmarks, study.scan_ids, ids)
    template = study.template()
    ctx.report(0, len(ids) + 1, "template skin (S0)")
    base = skin_surface(template, target_triangles=s.target_triangles, smooth_voxels=s.smooth_voxels)
    weights, how_w = vertex_weights(study, base.vertices)
    bones, vlab = label_surfaces(study.template_labels())
    out = {
        "template_skin.vtp": MeshFile(base, weight_arrays(weights.bones, weights.dense())),
        "template_bones.vtp": MeshFile(bones, {"label": vlab.astype(float)}),
    }
    doc = {
        "format": "avw-surface",
        "version": 1,
        "scans": list(ids),
        "template": {
            "vertices": base.n_vertices,
            "triangles": base.n_triangles,
            "weights": how_w,
            "bones_vertices": bones.n_vertices,
        },
        "per_scan": {},
        "settings": _settings_doc(study, s),
        "workbench_version": __version__,
    }
    sites = {}
    if marks is not None:  # every landmark the user picked, where it lies on S0
        from workbench.errors import InputFileError

        for sid in ids:
            try:
                sites[sid] = landmark_sites(base, marks[sid][0], max_snap_mm=s.max_distance_mm)
            except ValueError as e:
                raise InputFileError(
                    f"{s.landmarks}: scan {sid!r}: {e} (the limit is surface.max_distance_mm, "
                    f"--set surface.max_distance_mm=MM)",
                    s.landmarks,
                ) from None
    ctx.report(1, len(ids) + 1, f"S0: {base.n_triangles} triangles")
    shared = (str(study.root.resolve()), s, base, weights, template.geometry, sites, marks)

    finished = []

    def done(k, r):  # k: the scan's place in ids; on a cluster scans finish in any order
        sid, entry, meshes, confident = r
        finished.append(sid)
        d = entry["fit_distance_mm"]
        ctx.report(
            len(finished) + 1,
            len(ids) + 1,
            f"{sid}: fitted, {100 * confident:.0f} % of the vertices on a confident "
            f"target, mean distance {d['mean']:.2f} mm",
        )

    # each scan's meshes: one Dask task per scan on a cluster, else over a few processes of this machine (most of a
    # fit runs on one core), or one after the other (workbench.scale)
    from workbench.scale import local_processes
    from workbench.stages.pose import LOCAL_VOXELS

    distributed = ctx.runner is not None and ctx.runner.distributed
    lo, hi = LOCAL_VOXELS  # the pose stage's rule, on the template's grid (the skin mesh follows its voxels)
    processes = 1 if distributed or not lo <= template.geometry.n_voxels <= hi else local_processes()
    for sid, entry, meshes, _ in ctx.map_scans(_fit_scan, ids, shared=shared, on_result=done, processes=processes):
        doc["per_scan"][sid] = entry
        for name in ("ssd", "rbf", "fitted"):
            out[f"{sid}_{name}.ply"] = MeshFile(meshes[name])
        out[f"{sid}_skin.ply"] = MeshFile(meshes["skin"])
    out["surface.json"] = Json(doc)
    return out


def _settings_doc(study, s: SurfaceSettings) -> dict:
    """The settings as surface.json holds them: a landmarks file inside the study named by its path relative to
    the study (as study.json's inputs), not by the machine's absolute path — a copy of the study writes the same
    bytes."""
    from pathlib import Path

    doc = {k: getattr(s, k) for k in s.__dataclass_fields__}
    if s.landmarks is not None:
        try:
            doc["landmarks"] = str(Path(s.landmarks).relative_to(study.root.resolve()))
        except ValueError:  # outside the study: the path the setting holds
            pass
    return doc


def _fit_scan(shared, sid: str):
    """One scan's consistent mesh (Kurihara §4): ``(scan, its surface.json entry, its meshes, confident
    fraction)``; reads the scan, its pose and registration from the study folder (a Dask task's input)."""
    from deformation.fields.interpolate import sample
    from deformation.geometry import Volume
    from registration.segmentation import skin_surface
    from registration.surface_fit import consistent_mesh
    from workbench.study import read_study

    root, s, base, weights, g, sites, marks = shared
    study = read_study(root)
    scan = study.scan(sid)
    target = skin_surface(scan, target_triangles=s.target_triangles, smooth_voxels=s.smooth_voxels)
    pose = study.pose(sid)
    feats = None
    if s.features == "registration":
        pos, found = study.registration_positions(sid)
        feats = sample(Volume(pos.astype(np.float64), g), base.vertices, order=1, fill=np.nan)
        ok = sample(Volume(found.astype(np.float32), g), base.vertices, order=1, fill=0.0) > 0.999
        feats[~ok] = np.nan
    res = consistent_mesh(
        base,
        weights,
        pose.transforms,
        target,
        feature_targets=feats,
        landmarks=None if marks is None else (sites[sid], marks[sid][1]),
        n_features=s.n_features,
        fit=s.fit,
        max_distance_mm=s.max_distance_mm,
        stiffness=s.stiffness,
    )
    d = res["fit"].distance_mm
    entry = {
        **res["info"],
        "skin_triangles": target.n_triangles,
        "pose": pose.to_dict(),  # the pose the mesh was fitted with (surface_model reads it)
        "fit_distance_mm": {"mean": float(d.mean()), "p95": float(np.percentile(d, 95)), "max": float(d.max())},
        "feature_vertices": res["features"].tolist(),
    }
    meshes = {name: res[name] for name in ("ssd", "rbf", "fitted")}
    meshes["skin"] = target
    return sid, entry, meshes, float(res["fit"].confident.mean())


STAGE = Stage(
    name="surface",
    folder="surface",
    per_scan=False,
    settings_type=SurfaceSettings,
    run=_run,
    needs=_needs,
    inputs=_inputs,
    uses=lambda study, s: s.scans,
    version=3,  # what each version changed: docs/measurements/workbench.md
)
