"""Study folders and their ``study.json`` manifest.

A study is a folder holding a template scan, its bone label map, a skeleton,
posed scans and (for phantoms) their ground truth.  ``study.json`` names
every file by role, with paths relative to the folder::

    {
      "format": "avw-study", "version": 1, "name": "knee phantom",
      "units": "mm",
      "template": "template.nii.gz",
      "template_labels": "template_labels.nii.gz",
      "skeleton": "skeleton.json",
      "scans": [
        {"id": "pose00", "image": "scans/pose00.nii.gz",
         "truth": {"correspondence": "truth/pose00_correspondence.mha",
                   "template_to_scan": "truth/pose00_template_to_scan.mha",
                   "pose": "truth/pose00_pose.json",
                   "markers": "truth/pose00_markers.json"},
         "pose": "poses/pose00_pose.json"},
        ...
      ],
      "phantom": {...generator parameters...},
      "stages": {}
    }

``template_labels`` and ``truth`` are optional (a user's own study may have
neither; ``workbench pose --seeds`` segments the bones); ``pose`` appears once
``workbench pose`` has run, in the same schema as the truth pose.  The correspondence
field is ``scan_to_template``: an ITK displacement field on the scan's grid
whose vector at scan voxel ``x`` is ``template_position − x`` in mm, so
``sitk.DisplacementFieldTransform`` resamples the template onto the scan
directly.  The optional ``template_to_scan`` field is the exact forward map
on the template grid (scan position − template voxel position, mm); it
differs from the inverse of ``correspondence`` where the posing folds.  Markers are ``{"markers": [{"name", "template": [x,y,z],
"scan": [x,y,z]}]}``.  Later pipeline stages record their outputs under
``stages``.

Phantom studies are written into a staging folder beside the target and
renamed into place at the end, so an interrupted run leaves no half-written
study.
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
from deformation.skeleton import Pose, Skeleton
from workbench import __version__
from workbench.errors import InputFileError, MissingFileError, OutputExistsError
from workbench.jsonio import read_json, write_json
from workbench.volume_io import read_displacement, read_labels, read_volume, write_displacement, write_labels, \
    write_volume

__all__ = ["Study", "StudyError", "read_study", "write_phantom_study", "STUDY_FORMAT", "MANIFEST"]

STUDY_FORMAT = "avw-study"
MANIFEST = "study.json"


class StudyError(InputFileError):
    """A study folder or manifest that does not hold what it should."""


@dataclass
class Study:
    """A study folder opened through its manifest (paths resolved, files checked to exist)."""

    root: Path
    manifest: dict

    def path(self, relative: str) -> Path:
        return self.root / relative

    @property
    def scan_ids(self) -> list[str]:
        return [s["id"] for s in self.manifest["scans"]]

    def _scan_entry(self, scan_id: str) -> dict:
        for s in self.manifest["scans"]:
            if s["id"] == scan_id:
                return s
        raise StudyError(f"no scan {scan_id!r} in this study; scans: {self.scan_ids}", self.root / MANIFEST)

    def skeleton(self) -> Skeleton:
        return Skeleton.from_dict(read_json(self.path(self.manifest["skeleton"])))

    def template(self) -> Volume:
        return read_volume(self.path(self.manifest["template"]))

    @property
    def has_template_labels(self) -> bool:
        return bool(self.manifest.get("template_labels"))

    def template_labels(self) -> Volume:
        if not self.has_template_labels:
            raise StudyError(f"{self.root / MANIFEST}: the study has no 'template_labels' (bone label map); give "
                             "one, or segment the bones with `workbench pose STUDY --seeds FILE`.",
                             self.root / MANIFEST)
        return read_labels(self.path(self.manifest["template_labels"]),
                           reference=self.path(self.manifest["template"]))

    def scan(self, scan_id: str) -> Volume:
        return read_volume(self.path(self._scan_entry(scan_id)["image"]))

    def has_truth(self, scan_id: str) -> bool:
        return "truth" in self._scan_entry(scan_id)

    def truth_pose(self, scan_id: str) -> Pose:
        return Pose.from_dict(read_json(self.path(self._scan_entry(scan_id)["truth"]["pose"])))

    def has_pose(self, scan_id: str) -> bool:
        return "pose" in self._scan_entry(scan_id)

    def pose(self, scan_id: str) -> Pose:
        """The estimated pose of a scan (``workbench pose``); same schema as :meth:`truth_pose`."""
        entry = self._scan_entry(scan_id)
        if "pose" not in entry:
            raise StudyError(f"scan {scan_id!r} has no estimated pose yet; run `workbench pose {self.root}`.",
                             self.root / MANIFEST)
        path = self.path(entry["pose"])
        if not path.is_file():
            raise MissingFileError(f"{path}: named in {self.root / MANIFEST} but missing; run `workbench pose "
                                   f"{self.root} --force` to estimate the poses again.", path)
        return Pose.from_dict(read_json(path))

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


def read_study(folder: str | os.PathLike) -> Study:
    """Open a study folder, validating its manifest and that every named file exists."""
    root = Path(folder)
    manifest_path = root / MANIFEST
    if not root.is_dir():
        raise MissingFileError(f"{root}: no such study folder. Create one with `workbench phantom` or give "
                               f"the folder that holds {MANIFEST}.", root)
    if not manifest_path.is_file():
        raise MissingFileError(f"{root}: not a study folder ({MANIFEST} is missing).", manifest_path)
    m = read_json(manifest_path)
    if m.get("format") != STUDY_FORMAT:
        raise StudyError(f"{manifest_path}: 'format' is {m.get('format')!r}, expected {STUDY_FORMAT!r}.",
                         manifest_path)
    for key in ("template", "skeleton", "scans"):
        if key not in m:
            raise StudyError(f"{manifest_path}: the manifest lacks the key {key!r}.", manifest_path)
    # A user's study may come without a bone label map: `workbench pose --seeds` segments one.
    files = [m["template"], m["skeleton"]] + ([m["template_labels"]] if m.get("template_labels") else [])
    ids = set()
    if not isinstance(m["scans"], list):
        raise StudyError(f"{manifest_path}: 'scans' must be a list of {{'id', 'image'[, 'truth']}}.", manifest_path)
    for i, s in enumerate(m["scans"]):
        if not isinstance(s, dict) or "id" not in s or "image" not in s:
            raise StudyError(f"{manifest_path}: scans[{i}] needs 'id' and 'image'.", manifest_path)
        if s["id"] in ids:
            raise StudyError(f"{manifest_path}: scan id {s['id']!r} appears twice.", manifest_path)
        ids.add(s["id"])
        files.append(s["image"])
        truth = s.get("truth")
        if truth is not None:
            if not isinstance(truth, dict) or not {"correspondence", "pose", "markers"} <= set(truth):
                raise StudyError(f"{manifest_path}: scans[{i}]['truth'] must name 'correspondence', 'pose' "
                                 "and 'markers' files.", manifest_path)
            files.extend(truth[k] for k in ("correspondence", "pose", "markers", "template_to_scan") if k in truth)
        # A scan's "pose" (written by `workbench pose`) is not required to exist: a study whose poses/ folder
        # was deleted must still open, so that `workbench pose --force` can write it again.
    for f in files:
        if not isinstance(f, str):
            raise StudyError(f"{manifest_path}: file entries must be strings (paths), got {f!r}.", manifest_path)
        if Path(f).is_absolute() or ".." in Path(f).parts:
            raise StudyError(f"{manifest_path}: {f!r} must be a path relative to the study folder.",
                             manifest_path)
        if not (root / f).exists():
            raise MissingFileError(f"{root / f}: named in {manifest_path} but missing.", root / f)
    return Study(root, m)


# -- writing phantom studies ----------------------------------------------------------------------
def _staging_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.partial-{secrets.token_hex(4)}"


def write_phantom_study(phantom, out: str | os.PathLike, *, overwrite: bool = False, progress=None,
                        name: str | None = None) -> Study:
    """Generate a phantom's template and posed scans and write them as a study folder.

    Parameters
    ----------
    phantom : validation.phantoms.Phantom
    out : path of the study folder to create
    overwrite : replace an existing folder (otherwise :class:`OutputExistsError`)
    progress : callable(stage: str, done: int, total: int), optional
        Called after each file group is written.

    Returns
    -------
    Study
        The written study, opened through its manifest.  Per-scan generation
        statistics (inversion residuals, folding, timings) are written to
        ``logs/phantom.json``; ``study.json`` holds only deterministic content,
        so the same seed gives byte-identical files.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise OutputExistsError(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = _staging_dir(out)
    stage.mkdir()
    report = (lambda *a: None) if progress is None else progress
    n = len(phantom.poses)
    try:
        t0 = time.perf_counter()
        for sub in ("scans", "truth", "logs"):
            (stage / sub).mkdir()
        tpl, labels = phantom.template()
        write_volume(tpl, stage / "template.nii.gz")
        write_labels(labels, stage / "template_labels.nii.gz")
        write_json(phantom.skeleton.to_dict(), stage / "skeleton.json")
        log = {"template_seconds": round(time.perf_counter() - t0, 3), "scans": []}
        report("template", 0, n)
        entries = []
        for i, scan in enumerate(phantom.scans()):
            t1 = time.perf_counter()
            sid = scan.id
            truth = {"correspondence": f"truth/{sid}_correspondence.mha", "pose": f"truth/{sid}_pose.json",
                     "markers": f"truth/{sid}_markers.json"}
            write_volume(scan.image, stage / f"scans/{sid}.nii.gz")
            write_displacement(scan.correspondence, stage / truth["correspondence"])
            if scan.template_to_scan is not None:
                truth["template_to_scan"] = f"truth/{sid}_template_to_scan.mha"
                write_displacement(scan.template_to_scan, stage / truth["template_to_scan"])
            write_json(scan.pose.to_dict(), stage / truth["pose"])
            write_json({"format": "avw-markers", "version": 1, "units": "mm", "markers": scan.markers},
                       stage / truth["markers"])
            entries.append({"id": sid, "image": f"scans/{sid}.nii.gz", "truth": truth})
            log["scans"].append({"id": sid, **scan.stats,
                                 "write_seconds": round(time.perf_counter() - t1, 3)})
            report("scan", i + 1, n)
        spec = phantom.spec.to_dict()
        manifest = {
            "format": STUDY_FORMAT,
            "version": 1,
            "name": name or f"{spec['region']} phantom ({spec['modality']}, {spec['size']}, {spec['posing']})",
            "units": "mm",
            "template": "template.nii.gz",
            "template_labels": "template_labels.nii.gz",
            "skeleton": "skeleton.json",
            "scans": entries,
            "phantom": {**spec, "poses": [{"id": pid, "angles_deg": {k: np.asarray(v).tolist() for k, v in a.items()}}
                                          for pid, a in phantom.poses],
                        "generator": "validation.phantoms", "workbench_version": __version__,
                        "correspondence": "scan_to_template: template position minus scan voxel position, mm"},
            "stages": {},
        }
        log["total_seconds"] = round(time.perf_counter() - t0, 3)
        write_json(log, stage / "logs" / "phantom.json")
        write_json(manifest, stage / MANIFEST)
        if out.exists():
            trash = out.parent / f".{out.name}.old-{secrets.token_hex(4)}"
            os.replace(out, trash)
            try:
                os.replace(stage, out)
            except BaseException:
                os.replace(trash, out)  # put the old study back
                raise
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(stage, out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return read_study(out)
