"""What `workbench info --check` says of a study before any work: problems (it cannot run) and warnings.

Problems: an image that cannot be read (its reader's one-line message: missing, corrupt, truncated, not 3-D,
NaN voxels, a spacing or field of view no scan of a body has), a label map off the template's grid.
Warnings: label ids that are no bone of the skeleton (taken as soft tissue), a scan whose field of view holds
none of the template's bones (the pose stage refuses it unless the root bone is given a start), an image that is
a symbolic link to a file outside the study folder (followed; copying the folder copies the link, not the data),
a joint without limits (its rotations are taken within ±180°).
"""

from __future__ import annotations

import numpy as np

from workbench.errors import WorkbenchError

__all__ = ["check_study_images", "study_warnings", "unknown_labels", "unknown_labels_text"]


def check_study_images(study) -> list[str]:
    """Read every image a study names; one line per image that cannot be used (its reader's message)."""
    from workbench.io.volumes import read_displacement, read_labels, read_volume

    m = study.manifest
    todo = [(read_volume, m["template"])]
    if m.get("template_labels"):
        todo.append((read_labels, m["template_labels"]))
    for s in m["scans"]:
        todo.append((read_volume, s["image"]))
        for key in ("correspondence", "template_to_scan"):
            if (s.get("truth") or {}).get(key):
                todo.append((read_displacement, s["truth"][key]))
    problems = []
    grid = None
    for reader, rel in todo:
        try:
            v = reader(study.path(rel))
        except (WorkbenchError, ValueError, OSError) as e:
            problems.append(str(e))
            continue
        if rel == m.get("template_labels") and grid is not None and not v.geometry.is_close(grid):
            problems.append(
                f"{study.path(rel)}: the label map is not on the template's grid "
                f"({v.geometry.describe()} against {grid.describe()}); resample it (nearest neighbour)"
            )
        if rel == m["template"]:
            grid = v.geometry
    return problems


def study_warnings(study) -> list[str]:
    """One line per thing a study's user should know before the work (see the module docstring)."""
    from workbench.io.volumes import read_image_geometry

    m = study.manifest
    sk = study.skeleton()
    out = []
    root = study.root.resolve()
    named = (
        [m["template"], m["skeleton"]]
        + ([m["template_labels"]] if m.get("template_labels") else [])
        + [s["image"] for s in m["scans"]]
    )
    for rel in named:
        p = study.path(rel)
        if p.is_symlink() and root not in p.resolve().parents:
            out.append(
                f"{p}: a symbolic link to {p.resolve()}, outside the study folder: it is read, and copying "
                "the folder copies the link, not the file (cp -rL copies the file)"
            )
    if study.has_template_labels:
        try:
            labels = study.template_labels()
        except (WorkbenchError, ValueError, OSError):
            labels = None  # said by check_study_images
        if labels is not None:
            counts = np.bincount(
                np.asarray(labels.data).ravel().astype(np.int64), minlength=max(b.label for b in sk.bones) + 1
            )
            unknown = unknown_labels(counts, sk)
            if unknown:
                out.append(
                    f"{study.template_labels_path()}: {unknown_labels_text(unknown)} no bone of "
                    f"{m['skeleton']}; those voxels are taken as soft tissue"
                )
            from registration.bone_frames import bone_frames

            try:
                centres = np.array([f.centroid for f in bone_frames(labels, sk).values()])
            except ValueError:
                centres = np.zeros((0, 3))  # a bone without voxels: the bones stage says so
            for s in m["scans"]:
                try:
                    g = read_image_geometry(study.path(s["image"]))
                except (WorkbenchError, ValueError, OSError):
                    continue  # said by check_study_images
                if len(centres) and not g.contains_world(centres).any():
                    out.append(
                        f"{study.path(s['image'])}: no bone of the template lies in this scan's field of "
                        "view: the pose stage will refuse it unless the root bone is given a start "
                        "(--init moments or an initial-pose file); check the scan's origin and direction"
                    )
    loose = [j.name for j in sk.joints if j.limits is None]
    if loose:
        out.append(
            f"{study.path(m['skeleton'])}: joint(s) {', '.join(loose)} have no 'limits': poses are checked "
            "only to keep their rotations within ±180°"
        )
    return out


def unknown_labels(counts: np.ndarray, skeleton) -> dict[int, int]:
    """``{label id: voxels}`` of the non-zero ids in a label map's ``counts`` (a bincount) that are no bone's."""
    known = {b.label for b in skeleton.bones} | {0}
    return {int(k): int(counts[k]) for k in np.flatnonzero(counts) if int(k) not in known}


def unknown_labels_text(unknown: dict) -> str:
    """``"label ids 7 (3 voxels), 200 (5 voxels) are"``: the start of a sentence about :func:`unknown_labels`."""
    ids = ", ".join(f"{k} ({n} voxels)" for k, n in sorted(unknown.items()))
    return f"label id{'s' if len(unknown) > 1 else ''} {ids} {'are' if len(unknown) > 1 else 'is'}"
