"""A study folder opened through its manifest: :class:`Study`, the stages' outputs' accessors and the one
(locked) writer of ``study.json``; :func:`read_study` opens one (the manifest's format:
:mod:`workbench.study.manifest`).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deformation.geometry import Volume, every_nth
from deformation.kinematics.skeleton import Pose, Skeleton
from workbench.errors import InputFileError, MissingFileError
from workbench.io.jsonio import read_json, write_json
from workbench.io.volumes import (
    read_displacement,
    read_image_geometry,
    read_labels,
    read_vector_image,
    read_volume,
)
from workbench.study.manifest import LOCK_NAME, MANIFEST, STAGE_COMMANDS, StageOutputMissing, StudyError, read_manifest

__all__ = ["Study", "read_study"]


@dataclass
class Study:
    """A study folder opened through its manifest (paths resolved, files checked to exist).

    ``Study`` owns ``study.json``: stage outputs are found through the
    accessors below (``template_labels()``, ``pose(sid)``, ``weights()``,
    ``init_field(sid)``, ``registration(sid)``, ``model()``, ...), and every
    change goes through :meth:`update`, which holds an exclusive lock on
    ``.study.json.lock`` while it re-reads the manifest, applies the change and
    renames the new manifest into place — so several processes (four
    ``workbench register --scan`` at once, Dask workers' coordinator) never
    lose each other's entries.

    Stage entries live under ``stages[<name>]``; a whole-study stage's entry
    holds ``digest``, ``settings``, ``inputs``, ``needs``, ``outputs`` (file
    name → path relative to the study), ``outputs_digest``, ``seconds``, the
    stage's own ``timings`` (if any: no stage writes a time into its files),
    ``finished``, versions; a per-scan stage's entry holds one such entry per
    scan under ``scans``.
    """

    root: Path
    manifest: dict

    def path(self, relative: str) -> Path:
        return self.root / relative

    @property
    def manifest_path(self) -> Path:
        return self.root / MANIFEST

    @property
    def scan_ids(self) -> list[str]:
        return [s["id"] for s in self.manifest["scans"]]

    def check_scan_ids(self, ids) -> list[str]:
        """``ids`` as a list (all scans when empty), every one a scan of the study — else one clear error."""
        ids = list(ids) if ids else self.scan_ids
        unknown = [sid for sid in ids if sid not in self.scan_ids]
        if unknown:
            raise StudyError(
                f"{self.manifest_path}: no scan {unknown} in this study (--scan); its scans are {self.scan_ids}.",
                self.manifest_path,
            )
        return ids

    def _scan_entry(self, scan_id: str) -> dict:
        for s in self.manifest["scans"]:
            if s["id"] == scan_id:
                return s
        raise StudyError(f"no scan {scan_id!r} in this study; scans: {self.scan_ids}", self.manifest_path)

    # -- the one writer ----------------------------------------------------------------------------
    @contextlib.contextmanager
    def locked(self):
        """Hold the study's manifest lock (exclusive, across processes) for the body."""
        import fcntl

        with open(self.root / LOCK_NAME, "a+") as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)

    def update(self, change) -> dict:
        """Apply ``change(manifest)`` (in place) to the manifest on disk, under the lock; returns the new one.

        The manifest is re-read inside the lock, so a change made meanwhile by
        another process is kept; it is written to a temporary file and renamed
        (atomic), so a reader never sees half a manifest.
        """
        with self.locked():
            m = read_json(self.manifest_path)
            change(m)
            write_json(m, self.manifest_path, overwrite=True)
        self.manifest = m
        return m

    def check_writable(self) -> None:
        """Before any work: the study folder takes new files and ``study.json`` can be replaced — else one
        clear :class:`~workbench.study.StudyError` naming the folder (a read-only mount, missing permissions, an
        immutable manifest), instead of a failure after minutes of work."""
        import tempfile

        try:  # a real write: os.access does not see a read-only mount for root, nor an immutable file
            fd, probe = tempfile.mkstemp(prefix=".avw-write-test-", dir=self.root)
            os.close(fd)
            os.unlink(probe)
            with open(self.manifest_path, "a"):  # opens for writing without changing a byte
                pass
        except OSError as e:
            what = self.manifest_path if e.filename == str(self.manifest_path) else self.root
            raise StudyError(
                f"{what}: cannot write there ({e.strerror or e}); the stages write their outputs and "
                f"{MANIFEST} into the study folder {self.root}. Make it writable (chmod -R u+w "
                f"{self.root}) or run on a copy (cp -r {self.root} COPY).",
                what,
            ) from None

    def reload(self) -> Study:
        self.manifest = read_json(self.manifest_path)
        return self

    def stage_entry(self, stage: str, scan_id: str | None = None) -> dict | None:
        """The manifest entry of a stage (of one scan, for per-scan stages), or ``None``."""
        e = (self.manifest.get("stages") or {}).get(stage)
        if not isinstance(e, dict):
            return None
        if scan_id is not None:
            e = (e.get("scans") or {}).get(scan_id)
        elif "scans" in e and "digest" not in e:
            return None  # a per-scan stage asked for as a whole
        return e if isinstance(e, dict) and "digest" in e else None

    def recorded_settings(self, stage: str) -> dict | None:
        """The settings a stage last ran with (for per-scan stages, those of the scan it finished last), or None."""
        e = (self.manifest.get("stages") or {}).get(stage)
        if not isinstance(e, dict):
            return None
        if "digest" in e:
            return e.get("settings")
        done = [se for se in (e.get("scans") or {}).values() if isinstance(se, dict) and se.get("settings") is not None]
        return max(done, key=lambda se: se.get("finished", ""))["settings"] if done else None

    def record(self, stage: str, entry: dict, scan_id: str | None = None, *, stage_info: dict | None = None) -> None:
        """Record a stage's entry (one scan's, for per-scan stages) in ``study.json``."""

        def change(m):
            stages = m.setdefault("stages", {})
            if scan_id is None:
                stages[stage] = entry
            else:
                s = stages.get(stage)
                if not isinstance(s, dict) or "scans" not in s:
                    s = {"scans": {}}
                s.update(stage_info or {})
                s["scans"][scan_id] = entry
                stages[stage] = s

        self.update(change)

    def forget(self, stage: str, scan_id: str | None = None) -> None:
        """Remove a stage's entry (one scan's) from the manifest (its files are left to the caller)."""

        def change(m):
            stages = m.get("stages") or {}
            if scan_id is None:
                stages.pop(stage, None)
            elif isinstance(stages.get(stage), dict):
                (stages[stage].get("scans") or {}).pop(scan_id, None)

        self.update(change)

    def output(self, stage: str, name: str, scan_id: str | None = None) -> Path:
        """Path of a stage's output file; a clear "run X first" when the stage has not made it."""
        e = self.stage_entry(stage, scan_id)
        what = f"{stage} stage" + (f" of scan {scan_id!r}" if scan_id else "")
        run = f"run `{STAGE_COMMANDS.get(stage, 'workbench run')} {self.root}`" + (
            f" (or `workbench run {self.root}`)" if stage in STAGE_COMMANDS else ""
        )
        if e is None:
            raise StageOutputMissing(f"{self.manifest_path}: no {what} yet; {run} first.", self.manifest_path)
        rel = (e.get("outputs") or {}).get(name)
        if rel is None:
            raise StageOutputMissing(
                f"{self.manifest_path}: the {what} has no output {name!r}; {run} again.", self.manifest_path
            )
        p = self.path(rel)
        if not p.exists():
            raise MissingFileError(f"{p}: named in {self.manifest_path} but missing; {run} again (with --force).", p)
        return p

    def has_output(self, stage: str, name: str, scan_id: str | None = None) -> bool:
        e = self.stage_entry(stage, scan_id)
        rel = None if e is None else (e.get("outputs") or {}).get(name)
        return rel is not None and self.path(rel).exists()

    # -- inputs ---------------------------------------------------------------------------------
    def skeleton(self) -> Skeleton:
        return Skeleton.from_dict(read_json(self.path(self.manifest["skeleton"])))

    def template(self) -> Volume:
        return read_volume(self.path(self.manifest["template"]))

    def scan(self, scan_id: str) -> Volume:
        return read_volume(self.path(self._scan_entry(scan_id)["image"]))

    def scan_path(self, scan_id: str) -> Path:
        return self.path(self._scan_entry(scan_id)["image"])

    # -- bones (template labels) -------------------------------------------------------------------
    def template_labels_path(self) -> Path | None:
        """The label map every stage uses: the bones stage's, else the study's own ``template_labels``."""
        if self.has_output("bones", "template_labels.nii.gz"):
            return self.output("bones", "template_labels.nii.gz")
        if self.manifest.get("template_labels"):
            return self.path(self.manifest["template_labels"])
        return None

    @property
    def has_template_labels(self) -> bool:
        return self.template_labels_path() is not None

    def template_labels(self) -> Volume:
        p = self.template_labels_path()
        if p is None:
            raise StudyError(
                f"{self.manifest_path}: the study has no bone label map ('template_labels'); give "
                "one, or segment the bones with `workbench bones STUDY --seeds FILE` (or `workbench "
                "pose STUDY --seeds FILE`).",
                self.manifest_path,
            )
        return read_labels(p, reference=self.path(self.manifest["template"]))

    # -- ground truth (read by the validate stage and explicit protocols only) ---------------------
    def has_truth(self, scan_id: str) -> bool:
        return "truth" in self._scan_entry(scan_id)

    def truth_pose(self, scan_id: str) -> Pose:
        return Pose.from_dict(read_json(self.path(self._scan_entry(scan_id)["truth"]["pose"])))

    def truth_correspondence(self, scan_id: str) -> Volume:
        """The ``scan_to_template`` displacement field of a scan (template position − voxel position, mm)."""
        return read_displacement(self.path(self._scan_entry(scan_id)["truth"]["correspondence"]))

    def has_truth_template_to_scan(self, scan_id: str) -> bool:
        return "template_to_scan" in (self._scan_entry(scan_id).get("truth") or {})

    def truth_template_to_scan(self, scan_id: str) -> Volume:
        """The exact forward map of a phantom scan on the template grid (scan position − voxel position, mm)."""
        return read_displacement(self.path(self._scan_entry(scan_id)["truth"]["template_to_scan"]))

    def truth_markers(self, scan_id: str) -> list[dict]:
        return read_json(self.path(self._scan_entry(scan_id)["truth"]["markers"]))["markers"]

    def truth_files(self, scan_id: str) -> dict[str, Path]:
        return {k: self.path(v) for k, v in (self._scan_entry(scan_id).get("truth") or {}).items()}

    # -- pose stage --------------------------------------------------------------------------------
    def has_pose(self, scan_id: str) -> bool:
        return self.has_output("pose", f"{scan_id}_pose.json")

    def pose(self, scan_id: str) -> Pose:
        """The estimated pose of a scan (``workbench pose``); same schema as ``truth_pose``."""
        return Pose.from_dict(read_json(self.output("pose", f"{scan_id}_pose.json")))

    def pose_flagged(self, scan_id: str) -> list[str]:
        """The bones the pose stage could not place in a scan (``fits.json`` status other than ``ok``): their
        pose follows the nearest placed ancestor (``registration.pose.placed_transforms``)."""
        bones = read_json(self.output("pose", "fits.json"))["scans"][scan_id]["bones"]
        return sorted(b for b, f in bones.items() if f["status"] != "ok")

    def pose_report(self) -> dict:
        return read_json(self.output("pose", "report.json"))

    # -- weights stage -----------------------------------------------------------------------------
    def weights(self, *, coarse: bool = False):
        """``(SkinningWeights, body mask Volume)`` of the template (``workbench weights``), checked against its grid.

        Weights made on every f-th template voxel (``workbench weights --grid-factor f``, a big template) are
        returned only to a caller that takes them (``coarse=True``: deform, animate, the init stage's VBD); any
        other is told to recompute them on the template's grid.
        """
        from workbench.io.weights import read_voxel_weights, read_voxel_weights_geometry

        path = self.output("weights", "weights.json")
        geometry = read_voxel_weights_geometry(path)  # checked from the headers, before the map is read
        tg = read_image_geometry(self.path(self.manifest["template"]))
        f = tg.factor_of(geometry)
        if f is not None and f > 1:
            if not coarse:
                raise InputFileError(
                    f"{path}: the skinning weights are on {every_nth(f)} template voxel (workbench "
                    f"weights --grid-factor {f}); only deform, animate and the VBD start use them there. "
                    f"Recompute them on the template's grid: `workbench weights {self.root} "
                    "--grid-factor 1 --force`.",
                    path,
                )
        else:
            tg.check_same(
                geometry, names=("template", str(path)), remedy="recompute the weights: workbench weights --force"
            )
        weights, _, _ = read_voxel_weights(path)
        return weights, read_labels(self.output("weights", "body_mask.nii.gz"))

    # -- init and register stages ------------------------------------------------------------------
    def init_field(self, scan_id: str) -> Volume | None:
        """The registration's starting ``scan_to_template`` field of a scan (VBD), or ``None`` (identity)."""
        if self.has_output("init", "field.mha", scan_id):
            return read_displacement(self.output("init", "field.mha", scan_id))
        self.output("init", "init.json", scan_id)  # "run register first" when the stage has not run
        return None

    def init_forward(self, scan_id: str) -> Volume:
        """The polyrigid start's forward map: ``template_to_scan`` on the template grid (mm)."""
        return read_displacement(self.output("init", "forward.mha", scan_id))

    def init_info(self, scan_id: str) -> dict:
        """The init stage's record of a scan: ``method`` and, for VBD, the ``bones`` and their ``transforms``."""
        return read_json(self.output("init", "init.json", scan_id))

    def has_registration(self, scan_id: str) -> bool:
        return self.has_output("register", "log.json", scan_id)

    def registration_correspondence(self, scan_id: str) -> Volume:
        """The registration's ``scan_to_template`` field on the scan grid (mm)."""
        return read_displacement(self.output("register", "correspondence.mha", scan_id))

    def registration_inverse(self, scan_id: str) -> tuple[Volume, Volume]:
        """``(template_to_scan field, status labels)`` on the template grid (status 0 ok, 1 folded, 2 not
        converged, 3 outside the scan: ``deformation.fields.resample.STATUS_NAMES``)."""
        return (
            read_displacement(self.output("register", "template_to_scan.mha", scan_id)),
            read_labels(self.output("register", "inverse_status.nii.gz", scan_id)),
        )

    def registration_positions(self, scan_id: str):
        """``(positions (nz, ny, nx, 3), found)``: where each template voxel lies in the scan by the registration
        (world mm), and where the inverse found it (ok or folded; elsewhere it left the scan's field of view)."""
        from deformation.fields.resample import FOLDED

        inv, status = self.registration_inverse(scan_id)
        read_image_geometry(self.path(self.manifest["template"])).check_same(
            inv.geometry,
            names=("template", f"{scan_id} template_to_scan"),
            remedy=f"register again: workbench register {self.root} --scan {scan_id} --force",
        )
        return inv.data + inv.geometry.world_coordinates(), np.asarray(status.data) <= FOLDED

    def registration_uncertainty(self, scan_id: str) -> Volume | None:
        """The dense registration's expected error σ (mm) at each scan voxel (``uncertainty.mha``), or ``None``
        (Rhee's Algorithm 1, or the posterior off)."""
        if not self.has_output("register", "uncertainty.mha", scan_id):
            return None
        return read_volume(self.output("register", "uncertainty.mha", scan_id))

    def registered(self, scan_id: str) -> Volume:
        return read_volume(self.output("register", "registered.nii.gz", scan_id))

    def registration_log(self, scan_id: str) -> dict:
        return read_json(self.output("register", "log.json", scan_id))

    # -- model stage -------------------------------------------------------------------------------
    @property
    def has_model(self) -> bool:
        return self.has_output("model", "evd.json")

    def model(self, weights=None):
        """The study's EVD model (``workbench model``), or ``None`` when there is none."""
        from deformation.models.evd import ExampleVolumeDeformation

        if not self.has_model:
            return None
        path = self.output("model", "evd.json")
        doc = read_json(path)
        if doc.get("format") != "avw-evd":
            raise InputFileError(f"{path}: not an EVD model ('format' is {doc.get('format')!r}).", path)
        missing = [k for k in ("scans", "pose_vectors", "displacements", "joint_order") if k not in doc]
        if missing or any(s not in doc["pose_vectors"] for s in doc.get("scans", [])):
            raise InputFileError(
                f"{path}: the model lacks {missing or 'a pose vector of a training scan'}; "
                f"rebuild it with `workbench model {self.root} --force`.",
                path,
            )
        if weights is None:
            weights, _ = self.weights()
        stale = f"rebuild the model with `workbench model {self.root} --force`"
        if doc.get("weights_sha256") != weights.digest():
            raise InputFileError(
                f"{path}: the model was built with other skinning weights than the study's "
                f"(recomputed since?); {stale}.",
                path,
            )
        sk = self.skeleton()
        if doc["joint_order"] != [j.name for j in sk.joints]:
            raise InputFileError(
                f"{path}: the model's joints {doc['joint_order']} are not the skeleton's "
                f"{[j.name for j in sk.joints]}; {stale}.",
                path,
            )
        dpath = path.parent / doc["displacements"]
        vol = read_vector_image(dpath)
        read_image_geometry(self.path(self.manifest["template"])).check_same(
            vol.geometry, names=("template", str(dpath)), remedy=stale
        )
        n = len(doc["scans"])
        if vol.n_components != 3 * n:
            raise InputFileError(f"{dpath}: {vol.n_components} components, expected 3 × {n} training scans.", dpath)
        sigma = None
        sig_file = (doc.get("uncertainty") or {}).get("file")
        if sig_file:  # the scans' expected errors (model stage version 5 with registrations that wrote theirs)
            spath = path.parent / sig_file
            svol = read_vector_image(spath, components=n)  # one per training scan (a scalar image for one scan)
            vol.geometry.check_same(svol.geometry, names=(str(dpath), str(spath)), remedy=stale)
            sigma = np.asarray(svol.data, np.float32).reshape(-1, n)
        return ExampleVolumeDeformation.from_examples(
            vol.geometry,
            weights,
            sk,
            [np.asarray(doc["pose_vectors"][s], dtype=float) for s in doc["scans"]],
            vol.data.reshape(-1, n, 3),
            template_example=bool(doc.get("template_example", False)),
            scan_sigma=sigma,
        )

    # -- surface stage -----------------------------------------------------------------------------
    @property
    def has_surface(self) -> bool:
        return self.has_output("surface", "surface.json")

    def surface_mesh(self, scan_id: str, kind: str = "fitted"):
        """A mesh of the surface stage for a scan: ``kind`` "fitted" (S^f, S0's connectivity), "rbf", "ssd" or
        "skin" (the scan's own skin)."""
        from workbench.io.meshes import read_mesh

        if kind not in ("fitted", "rbf", "ssd", "skin"):
            raise ValueError(f"kind must be fitted, rbf, ssd or skin, got {kind!r}")
        return read_mesh(self.output("surface", f"{scan_id}_{kind}.ply"))

    def surface_model(self):
        """Kurihara's surface model (``workbench surface``): S0 with its vertices' weights, the fitted meshes of
        the scans and their estimated poses, as a :class:`deformation.models.surface_model.SurfaceModel`."""
        from deformation.models.skinning import SkinningWeights
        from deformation.models.surface_model import SurfaceModel
        from workbench.io.meshes import read_mesh, read_mesh_point_data
        from workbench.io.tetmeshes import weights_from_point_data

        if not self.has_surface:
            raise StageOutputMissing(
                f"{self.root}: no surface model yet; run `workbench surface {self.root}`.", self.manifest_path
            )
        path = self.output("surface", "surface.json")
        doc = read_json(path)
        stale = f"rebuild it with `workbench surface {self.root} --force`"
        if (
            doc.get("format") != "avw-surface"
            or not isinstance(doc.get("per_scan"), dict)
            or any("pose" not in doc["per_scan"].get(s, {}) for s in doc.get("scans", []))
        ):
            raise InputFileError(
                f"{path}: not a surface model of this version (no pose per fitted scan); {stale}.", path
            )
        skin = self.output("surface", "template_skin.vtp")
        base = read_mesh(skin)
        try:
            bones, dense = weights_from_point_data(read_mesh_point_data(skin))
        except ValueError as e:
            raise InputFileError(f"{skin}: {e}; {stale}.", skin) from e
        weights = SkinningWeights.from_dense(dense, bones)
        ids = list(doc["scans"])
        meshes = [read_mesh(self.output("surface", f"{sid}_fitted.ply")) for sid in ids]
        # the poses the meshes were fitted with (a later `workbench pose` does not pair new poses with old meshes)
        poses = [Pose.from_dict(doc["per_scan"][sid]["pose"]) for sid in ids]
        return SurfaceModel.from_meshes(base, weights, self.skeleton(), poses, meshes)

    # -- validate stage ----------------------------------------------------------------------------
    def validation(self, scan_id: str) -> dict:
        return read_json(self.output("validate", "measures.json", scan_id))

    def validation_maps(self, scan_id: str) -> tuple[Volume, Volume]:
        """``(error_mm, body)`` on the scan grid: the registration's correspondence error at every body voxel
        (mm, 0 elsewhere) and the body voxels the validate stage measured over."""
        return (
            read_volume(self.output("validate", "error_mm.nii.gz", scan_id)),
            read_labels(self.output("validate", "body.nii.gz", scan_id)),
        )


def read_study(folder: str | os.PathLike) -> Study:
    """Open a study folder, validating its manifest and that every named file exists."""
    root = Path(folder)
    return Study(root, read_manifest(root))
