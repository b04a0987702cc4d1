"""The ``study.json`` manifest: its format, its errors, and reading and checking it.

A study is a folder holding a template scan, its bone label map, a skeleton, posed scans and (for phantoms)
their ground truth; ``study.json`` names every file by role, with paths relative to the folder::

    {"format": "avw-study", "version": 1, "name": "knee phantom", "units": "mm",
     "template": "template.nii.gz", "template_labels": "template_labels.nii.gz", "skeleton": "skeleton.json",
     "scans": [{"id": "pose00", "image": "scans/pose00.nii.gz",
                "truth": {"correspondence": "truth/pose00_correspondence.mha",
                          "template_to_scan": "truth/pose00_template_to_scan.mha",
                          "pose": "truth/pose00_pose.json", "markers": "truth/pose00_markers.json"}}, ...],
     "phantom": {...generator parameters...}, "stages": {}}

``template_labels`` and ``truth`` are optional (a user's own study may have neither; ``workbench bones
--seeds`` segments the bones).  The ``correspondence`` field is ``scan_to_template``: an ITK displacement field
on the scan's grid whose vector at scan voxel ``x`` is ``template_position − x`` in mm, so
``sitk.DisplacementFieldTransform`` resamples the template onto the scan directly.  The optional
``template_to_scan`` field is the exact forward map on the template grid (scan position − template voxel
position, mm); it differs from the inverse of ``correspondence`` where the posing folds.  Markers are
``{"markers": [{"name", "template": [x, y, z], "scan": [x, y, z]}]}``.  The pipeline's stages record their
outputs under ``stages`` (:class:`workbench.study.Study`, :mod:`workbench.stages.mechanism`); the estimated pose
of a scan is the pose stage's ``poses/<id>_pose.json``, in the same schema as the truth pose.
"""

from __future__ import annotations

import json
from pathlib import Path

from workbench.errors import InputFileError, MissingFileError
from workbench.io.jsonio import read_json

__all__ = [
    "StudyError",
    "StageOutputMissing",
    "STAGE_COMMANDS",
    "STUDY_FORMAT",
    "MANIFEST",
    "MANIFEST_VERSION",
    "LOCK_NAME",
    "read_manifest",
]

STUDY_FORMAT = "avw-study"
MANIFEST = "study.json"
#: The manifest version this workbench reads and writes.
MANIFEST_VERSION = 1


class StudyError(InputFileError):
    """A study folder or manifest that does not hold what it should."""


# The command that produces each stage's outputs, for "run X first" messages.
STAGE_COMMANDS = {
    "bones": "workbench bones",
    "pose": "workbench pose",
    "weights": "workbench weights",
    "init": "workbench register",
    "register": "workbench register",
    "model": "workbench model",
    "surface": "workbench surface",
    "validate": "workbench validate",
    "report": "workbench report",
}
LOCK_NAME = ".study.json.lock"


class StageOutputMissing(StudyError):
    """A stage's output that a later step needs has not been made yet (or was deleted)."""


def read_manifest(root: Path) -> dict:
    """The manifest of the study folder ``root``, checked: its format and version, its keys, and that every file
    it names exists inside the folder."""
    manifest_path = root / MANIFEST
    if not root.is_dir():
        raise MissingFileError(
            f"{root}: no such study folder. Create one with `workbench phantom` or give "
            f"the folder that holds {MANIFEST}.",
            root,
        )
    if not manifest_path.is_file():
        raise MissingFileError(f"{root}: not a study folder ({MANIFEST} is missing).", manifest_path)
    m = read_json(
        manifest_path,
        expected=f'a study manifest, an object {{"format": "{STUDY_FORMAT}", "template": ..., "skeleton": ..., '
        '"scans": [...]} (docs/user-guide/study-folders.md)',
    )
    if "format" not in m:
        raise StudyError(
            f'{manifest_path}: no \'format\' key; add "format": "{STUDY_FORMAT}", "version": 1 '
            "at the top of the manifest (docs/user-guide/study-folders.md has a minimal one).",
            manifest_path,
        )
    if m.get("format") != STUDY_FORMAT:
        raise StudyError(
            f"{manifest_path}: 'format' is {m.get('format')!r}, not a study manifest; a study's is {STUDY_FORMAT!r}.",
            manifest_path,
        )
    version = m.get("version", MANIFEST_VERSION)  # a hand-written manifest may leave it out
    if type(version) is not int or version != MANIFEST_VERSION:
        raise StudyError(
            f"{manifest_path}: unsupported manifest version {json.dumps(version)} (this workbench reads "
            f'{MANIFEST_VERSION}); a newer workbench wrote it, or set "version": {MANIFEST_VERSION}.',
            manifest_path,
        )
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
                raise StudyError(
                    f"{manifest_path}: scans[{i}]['truth'] must name 'correspondence', 'pose' and 'markers' files.",
                    manifest_path,
                )
            files.extend(truth[k] for k in ("correspondence", "pose", "markers", "template_to_scan") if k in truth)
        # A scan's "pose" (written by `workbench pose`) is not required to exist: a study whose poses/ folder
        # was deleted must still open, so that `workbench pose --force` can write it again.
    for f in files:
        if not isinstance(f, str):
            raise StudyError(f"{manifest_path}: file entries must be strings (paths), got {f!r}.", manifest_path)
        if Path(f).is_absolute() or ".." in Path(f).parts:
            raise StudyError(
                f"{manifest_path}: {f!r} must be a path inside the study folder (no '..', not "
                "absolute), so that the manifest names the same files wherever the folder is moved; "
                "to use a file kept elsewhere, put a symbolic link to it in the folder "
                "(ln -s /data/scan.nii.gz scans/scan.nii.gz) and name the link.",
                manifest_path,
            )
        if not (root / f).exists():
            raise MissingFileError(f"{root / f}: named in {manifest_path} but missing.", root / f)
    return m
