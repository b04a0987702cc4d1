"""Readers of the files a user hands the workbench: poses, seeds, initial poses, phantom pose lists.

Each checks the file before any work and raises one
:class:`~workbench.errors.InputFileError` naming the file and the fix.
(Keyframe files are read by :func:`workbench.viz.animate.read_keyframes`.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deformation.kinematics.skeleton import Pose, SkeletonError
from deformation.kinematics.transforms import check_rigid
from registration.segmentation import SEEDS_FORMAT
from workbench.errors import InputFileError
from workbench.io.jsonio import read_json

__all__ = [
    "read_target_pose",
    "read_seeds",
    "read_initial_poses",
    "read_poses_file",
    "read_landmarks",
    "check_limits",
    "SEEDS_FORMAT",
    "LANDMARKS_FORMAT",
]

LANDMARKS_FORMAT = "avw-landmarks"
LANDMARKS_CSV_HEADER = ("scan", "template_x", "template_y", "template_z", "scan_x", "scan_y", "scan_z")


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
        for joint, v in d["angles"].items():
            if not (_is_number(v) or isinstance(v, list) and all(_is_number(x) for x in v)):
                raise InputFileError(
                    f"{path}: joint {joint!r} needs a list of numbers (degrees, then mm for a "
                    f"6-DOF joint; a number alone for a 1-DOF joint), got {v!r}.",
                    path,
                )
        try:
            pose = skeleton.pose({k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in d["angles"].items()})
        except (SkeletonError, ValueError) as e:
            raise InputFileError(f"{path}: {e}", path) from e
        check_limits(skeleton, d["angles"], path)
        return pose
    raise InputFileError(
        f'{path}: expected an avw-pose file (bone transforms) or {{"angles": {{joint: [degrees, ...]}}}}.', path
    )


def _is_number(v) -> bool:
    """A JSON number (not a string, not a boolean), finite."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def check_limits(skeleton, angles: dict, where, what: str = "") -> None:
    """One line naming ``where`` (a file) when a joint value of ``angles`` lies outside the skeleton's range of
    motion (``limits`` of skeleton.json; a joint without them takes rotations within ±180°)."""
    bad = skeleton.limit_problems({k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in angles.items()})
    if bad:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        where_from = (
            "" if "half a turn" in bad[0] else ", the range of motion of the study's skeleton (skeleton.json, 'limits')"
        )
        raise InputFileError(f"{where}: {what}{bad[0]}{more}{where_from}; give angles within it.", where)


def read_seeds(path, skeleton) -> dict[str, np.ndarray]:
    """Read a seeds file; every skeleton bone needs at least one point."""
    d = read_json(path)
    if d.get("format") != SEEDS_FORMAT:
        raise InputFileError(
            f"{path}: not a seeds file ('format' is {d.get('format')!r}, expected "
            f"{SEEDS_FORMAT!r}); see `workbench pose --help` for the schema.",
            path,
        )
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
            raise InputFileError(f"{path}: seeds of {b!r} must be a list of [x, y, z] points in mm, got {pts!r}.", path)
        out[b] = a
    return out


def read_initial_poses(path, scan_ids, skeleton) -> dict[str, np.ndarray]:
    """Root-bone initial transforms per scan from a JSON file.

    Either an ``avw-pose`` file (its root transform is used for every scan) or
    ``{"format": "avw-initial-poses", "version": 1, "scans": {"<id>": [[4x4]], ...}}``.
    """
    d = read_json(path)
    try:
        if d.get("format") == "avw-pose":
            t = Pose.from_dict(d).transforms.get(skeleton.root)
            if t is None:
                raise InputFileError(f"{path}: the pose has no transform for the root bone {skeleton.root!r}.", path)
            return {sid: t for sid in list(scan_ids)}
        if d.get("format") == "avw-initial-poses":
            scans = d.get("scans", {})
            unknown = sorted(set(scans) - set(list(scan_ids)))
            if unknown:
                raise InputFileError(f"{path}: unknown scans {unknown}; the study has {list(scan_ids)}.", path)
            return {sid: check_rigid(np.asarray(t, float), name=f"initial pose of {sid}") for sid, t in scans.items()}
    except ValueError as e:
        raise InputFileError(f"{path}: {e}", path) from e
    raise InputFileError(
        f"{path}: expected an 'avw-pose' file or {{'format': 'avw-initial-poses', 'version': 1, "
        "'scans': {scan id: 4x4 root transform}}.",
        path,
    )


def read_poses_file(path) -> tuple:
    """A phantom poses file: ``{"poses": [{"id": ..., "angles": {joint: [...]}}]}`` → ``((id, angles), ...)``."""
    d = read_json(path)
    poses = d.get("poses") if isinstance(d, dict) else None
    if not isinstance(poses, list) or not poses:
        raise InputFileError(
            f'{path}: expected {{"poses": [{{"id": ..., "angles": {{joint: [...]}}}}]}} with at least one pose.', path
        )
    out, seen = [], set()
    for i, entry in enumerate(poses):
        if not isinstance(entry, dict) or not isinstance(entry.get("angles"), dict):
            raise InputFileError(f"{path}: poses[{i}] needs an 'angles' object mapping joint names to lists.", path)
        pid = str(entry.get("id", f"pose{i:02d}"))
        if pid in seen:
            raise InputFileError(f"{path}: pose id {pid!r} appears twice.", path)
        seen.add(pid)
        angles = {}
        for joint, values in entry["angles"].items():
            if not isinstance(values, list) or not all(_is_number(v) for v in values):
                raise InputFileError(
                    f"{path}: poses[{i}] joint {joint!r}: angles must be a list of numbers "
                    f"(degrees, then mm for 6-DOF joints), got {values!r}.",
                    path,
                )
            angles[joint] = values
        out.append((pid, angles))
    return tuple(out)


def read_landmarks(path, scan_ids=None, selected=None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Skin landmarks picked on the template and on each scan (Kurihara §4's feature points), world mm:
    ``{scan: (template points (k, 3), scan points (k, 3))}``.

    JSON: ``{"format": "avw-landmarks", "scans": {"<scan id>": [{"template": [x, y, z], "scan": [x, y, z]},
    ...]}}``; or CSV with the header ``scan,template_x,template_y,template_z,scan_x,scan_y,scan_z``.  Scan ids
    not among the study's ``scan_ids`` are refused; every scan of ``selected`` (default: all of them) needs
    at least 4 landmarks (an RBF needs points).
    """
    import csv

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: no such landmarks file; give --landmarks an existing .json or .csv file.", path)
    pairs: dict[str, list] = {}
    if path.suffix.lower() == ".csv":
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
        if not rows or tuple(c.strip() for c in rows[0]) != LANDMARKS_CSV_HEADER:
            raise InputFileError(f"{path}: the first line must be the header {','.join(LANDMARKS_CSV_HEADER)}.", path)
        for n, r in enumerate(rows[1:], start=2):
            if not r or not "".join(r).strip():
                continue
            try:
                v = [float(x) for x in r[1:7]]
                if len(r) != 7:
                    raise ValueError
            except ValueError:
                raise InputFileError(
                    f"{path}: line {n} must be a scan id and 6 numbers (mm), got {r!r}.", path
                ) from None
            pairs.setdefault(r[0].strip(), []).append(v)
    else:
        d = read_json(path)
        if not isinstance(d, dict) or d.get("format") != LANDMARKS_FORMAT or not isinstance(d.get("scans"), dict):
            raise InputFileError(
                f'{path}: expected {{"format": "{LANDMARKS_FORMAT}", "scans": {{scan id: '
                '[{"template": [x, y, z], "scan": [x, y, z]}, ...]}} (mm), or a .csv with the '
                f"header {','.join(LANDMARKS_CSV_HEADER)}.",
                path,
            )
        for sid, items in d["scans"].items():
            for k, it in enumerate(items if isinstance(items, list) else [None]):
                try:
                    a, b = [float(x) for x in it["template"]], [float(x) for x in it["scan"]]
                    if len(a) != 3 or len(b) != 3:
                        raise ValueError
                    v = a + b
                except (TypeError, KeyError, ValueError):
                    raise InputFileError(
                        f'{path}: landmark {k} of scan {sid!r} must be {{"template": [x, y, z], '
                        f'"scan": [x, y, z]}} in mm, got {it!r}.',
                        path,
                    ) from None
                pairs.setdefault(str(sid), []).append(v)
    out = {}
    for sid, v in pairs.items():
        a = np.asarray(v, float)
        if not np.all(np.isfinite(a)):
            raise InputFileError(f"{path}: scan {sid!r} has a landmark that is not a finite number.", path)
        out[sid] = (a[:, :3], a[:, 3:])
    if scan_ids is not None:
        ids = [str(s) for s in scan_ids]
        unknown = sorted(set(out) - set(ids))
        if unknown:
            raise InputFileError(f"{path}: unknown scans {unknown}; the study has {ids}.", path)
        want = ids if selected is None else [str(s) for s in selected]
        few = [s for s in want if len(out.get(s, ((),))[0]) < 4]
        if few:
            raise InputFileError(
                f"{path}: scans {few} have fewer than 4 landmarks; give at least 4 per scan "
                "(Kurihara picked 70-150), or fit only the others with --scan ID.",
                path,
            )
    return out
