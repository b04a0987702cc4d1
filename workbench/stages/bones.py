"""The ``bones`` stage: the template's bone label map and each bone's frame (Rhee §3.1).

* ``source="labels"``: the study's own ``template_labels`` (given);
* ``source="seeds"``: segmented from a seeds file (one world point in mm
  inside each bone) — thresholding and connected components for CT, a
  marrow flood inside the cortex for MRI (:func:`registration.segmentation.segment_bones`);
* ``source="auto"``: segmented when a seeds file is given, else the study's
  own labels.

Outputs (``bones/``): ``bone_frames.json`` (each bone's oriented box from the
principal axes of its voxels, the centre of the box's base its origin),
``bones.json`` (voxels per bone), and when segmented
``template_labels.nii.gz`` and ``segmentation.json``.  The label map written
here is the one every later stage uses (``workbench.study.Study.template_labels()``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from registration.bone_frames import bone_frames
from registration.segmentation import guess_modality, segment_bones
from workbench.errors import InputFileError
from workbench.io.inputs import read_seeds
from workbench.io.volumes import read_labels
from workbench.stages.mechanism import Json, Labels, Stage
from workbench.study.checks import unknown_labels, unknown_labels_text

__all__ = ["BonesSettings", "STAGE"]

SOURCES = ("auto", "labels", "seeds")


@dataclass(frozen=True)
class BonesSettings:
    source: str = "auto"  #: "auto", "labels" or "seeds"
    seeds: str | None = None  #: seeds file (``avw-seeds``), for ``source="seeds"``
    modality: str | None = None  #: "ct" or "mri" for segmentation (None: guessed from the intensities)
    threshold: float | None = None  #: CT bone threshold, HU (None: the segmenter's default, 400)

    def __post_init__(self):
        if self.source not in SOURCES:
            raise ValueError(f"bones source must be one of {SOURCES}, got {self.source!r}")
        if self.source == "seeds" and self.seeds is None:
            raise ValueError("segmenting the bones needs a seeds file (--seeds FILE)")
        if self.modality not in (None, "ct", "mri"):
            raise ValueError(f"--modality must be 'ct' or 'mri', got {self.modality!r}")
        if self.seeds is not None:
            object.__setattr__(self, "seeds", str(self.seeds))


def _segments(study, s: BonesSettings) -> bool:
    if s.source == "auto":
        return not study.manifest.get("template_labels") or s.seeds is not None
    return s.source == "seeds"


def _inputs(study, s: BonesSettings, scan):
    files = {"template": study.path(study.manifest["template"]), "skeleton": study.path(study.manifest["skeleton"])}
    if s.source == "labels" and not study.manifest.get("template_labels"):
        raise InputFileError(
            f"{study.manifest_path}: the study has no bone label map ('template_labels'); pass "
            "--seeds FILE to segment the template's bones (see `workbench pose --help`).",
            study.manifest_path,
        )
    if _segments(study, s):
        if s.seeds is None:
            raise InputFileError(
                f"{study.root}: the study has no bone label map; pass --seeds FILE to segment the "
                "template's bones (see `workbench pose --help` for the seeds schema).",
                study.root,
            )
        files["seeds"] = Path(s.seeds)
    else:
        files["labels"] = study.path(study.manifest["template_labels"])
    return files


def _run(ctx) -> dict:
    study, s = ctx.study, ctx.settings
    skeleton = study.skeleton()
    template = study.template()
    out = {}
    if _segments(study, s):
        seeds = read_seeds(s.seeds, skeleton)
        modality = s.modality or guess_modality(template)
        if s.threshold is not None and modality != "ct":
            raise InputFileError(
                f"--threshold applies to CT segmentation, but the template segments as "
                f"{modality.upper()}; pass --modality ct if it is a CT.",
                study.root,
            )
        ctx.say(f"segmenting {len(seeds)} bones ({modality.upper()}) from {s.seeds} ...")
        kw = {} if s.threshold is None else {"threshold": s.threshold}
        labels, rep = segment_bones(template, skeleton, seeds, modality=modality, **kw)
        for w in rep.warnings:
            ctx.say(f"segmentation: {w}")
        empty = [b for b, n in rep.voxels.items() if n == 0]
        if empty:
            raise InputFileError(
                f"segmentation found no voxels for bones {empty}: "
                + " ".join(rep.warnings)
                + " — or give the study a label map.",
                Path(s.seeds),
            )
        out["template_labels.nii.gz"] = Labels(labels)
        out["segmentation.json"] = Json(rep.to_dict())
        source = f"segmented ({modality})"
    else:
        labels = read_labels(
            study.path(study.manifest["template_labels"]), reference=study.path(study.manifest["template"])
        )
        source = "given"
    counts = np.bincount(
        np.asarray(labels.data).ravel().astype(np.int64), minlength=max(b.label for b in skeleton.bones) + 1
    )
    unknown = unknown_labels(counts, skeleton)
    if unknown:
        ctx.say(
            f"warning: {study.template_labels_path()}: {unknown_labels_text(unknown)} not the label of any bone of "
            f"{study.manifest['skeleton']}; those voxels are taken as soft tissue (give them a bone in the "
            "skeleton, or 0 in the label map)"
        )
    frames = bone_frames(labels, skeleton)
    out["bone_frames.json"] = Json(
        {
            "format": "avw-bone-frames",
            "version": 1,
            "units": "mm",
            "convention": "Rhee §3.1: principal axes of the bone's voxels; z the longest, pointing away from the "
            "parent; origin at the centre of the box's base; frame maps bone coordinates to template world",
            "bones": {
                b: {
                    "frame": f.frame.tolist(),
                    "half_extents_mm": f.half_extents.tolist(),
                    "centroid": f.centroid.tolist(),
                    "voxels": f.n_voxels,
                }
                for b, f in frames.items()
            },
        }
    )
    out["bones.json"] = Json(
        {
            "format": "avw-bones",
            "version": 1,
            "source": source,
            "voxels": {b.name: int(counts[b.label]) for b in skeleton.bones},
            "unknown_labels": {str(k): n for k, n in unknown.items()},
        }
    )
    return out


STAGE = Stage(
    name="bones",
    folder="bones",
    per_scan=False,
    settings_type=BonesSettings,
    run=_run,
    inputs=_inputs,
    version=2,  # what each version changed: docs/measurements/workbench.md
)
