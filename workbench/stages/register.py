"""The ``register`` stage: the locally adaptive registration of the template to each scan (Rhee §4, Algorithm 1).

From the init stage's start (VBD, or the identity), the worst-matching block
of a hierarchy gets 8 clamped-plate-spline control points whose
displacements an NLopt simplex optimises; each accepted step is composed into
the running field (:func:`registration.adaptive.register_adaptive`).  After
VBD the template's bone voxels are zero-displacement control points (Rhee
§4.3).  The result is inverted onto the template grid
(:func:`deformation.resample.invert_scan_to_template`; after VBD through its
exact forward map, so that only the registration's own correction is
inverted numerically) for EVD (Rhee Eq. 7).

Outputs (``registration/<scan>/``)::

    correspondence.mha     scan_to_template on the scan grid (template position − voxel, mm; the convention
                           of truth/<id>_correspondence.mha, usable by sitk.DisplacementFieldTransform)
    template_to_scan.mha   its inverse on the template grid (scan position − voxel, mm)
    inverse_status.nii.gz  where the inverse was found: 0 ok, 1 folded, 2 not found, 3 outside the scan
    registered.nii.gz      the template resampled onto the scan grid through the field
    log.json               settings, per-level and per-step log, similarity before/after, folding
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from workbench import __version__
from workbench.stages.mechanism import Field, Image, Json, Labels, Stage

__all__ = ["RegisterSettings", "STAGE", "PRESETS"]

PRESETS = ("auto", "default", "initialised", "paper")


@dataclass(frozen=True)
class RegisterSettings:
    """The registration's settings: a preset and the overrides the command line exposes.

    ``preset``: ``auto`` (``initialised`` after a VBD start, ``default``
    after none), ``default``, ``initialised`` or ``paper`` (Rhee's published
    settings) — :class:`registration.adaptive.AdaptiveSettings`.
    """

    preset: str = "auto"
    levels: tuple | None = None
    optimizer: str | None = None
    metric: str | None = None
    max_steps_per_level: int | None = None
    fix_bones: bool = True
    seed: int = 0

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"--preset must be one of {PRESETS}, got {self.preset!r}")
        if self.levels is not None:
            object.__setattr__(self, "levels", tuple(int(v) for v in self.levels))
        self.adaptive("vbd")  # validates the overrides now, not after the first scan

    def adaptive(self, init_method: str):
        """The :class:`~registration.adaptive.AdaptiveSettings` for a start made by ``init_method``."""
        from registration.adaptive import AdaptiveSettings

        over = {k: v for k, v in (("levels", self.levels), ("optimizer", self.optimizer), ("metric", self.metric),
                                  ("max_steps_per_level", self.max_steps_per_level)) if v is not None}
        over.update(fix_bones=self.fix_bones, seed=self.seed)
        preset = self.preset
        if preset == "auto":
            preset = "initialised" if init_method == "vbd" else "default"
        if preset == "paper":
            return AdaptiveSettings.paper(**over)
        if preset == "initialised":
            return AdaptiveSettings.initialised(**over)
        return AdaptiveSettings(**over)


def _inputs(study, s, scan):
    return {"template": study.path(study.manifest["template"]), "scan": study.scan_path(scan),
            "labels": study.template_labels_path()}


def _run(ctx) -> dict:
    from deformation.evd import vbd_forward
    from deformation.geometry import Volume
    from deformation.resample import invert_scan_to_template
    from registration.adaptive import register_adaptive

    study, s, sid = ctx.study, ctx.settings, ctx.scan
    start = study.init_info(sid)  # the start, as the init stage made it: no pose (nor truth) is read here
    method = start["method"]
    settings = s.adaptive(method)
    template, scan = study.template(), study.scan(sid)
    initial = study.init_field(sid)
    rigid = study.template_labels() if (method == "vbd" and settings.fix_bones) else None
    forward = None
    if method == "vbd":
        weights, _ = study.weights()  # the weights that made the start (their digest reaches ours through it)
        forward = vbd_forward(template.geometry, weights.reorder(start["bones"]), np.asarray(start["transforms"]))

    def step(info):
        if "level_done" in info:
            lv = info["level_done"]
            ctx.say(f"{sid} level {lv.level}: {lv.steps} steps ({lv.accepted} accepted), {lv.control_points} "
                    f"control points, {lv.metric} {lv.metric_before:.4g} -> {lv.metric_after:.4g}, stopped: "
                    f"{lv.stopped}, {lv.seconds:.1f} s")
        else:
            ctx.report(info["step"], 0, f"{sid} level {info['level']} step {info['step']} block "
                                        f"{tuple(info['block'])}: {info['metric']} {info['block_before']:.4g} -> "
                                        f"{info['block_after']:.4g}; ~{info['eta']:.0f} s left in this level")

    result = register_adaptive(scan, template, initial=initial, rigid_mask=rigid, settings=settings, progress=step)
    ctx.say(f"{sid}: inverting the field onto the template grid ...")
    # φ = VBD⁻¹ ∘ U: only the registration's own correction U is inverted numerically
    bm = invert_scan_to_template(result.correspondence, template.geometry, forward=forward)
    summary = {"scan": sid, "init": method, "registration_seconds": round(result.seconds, 2),
               "control_points": result.control_points, "steps": len(result.steps),
               "evaluations": result.evaluations, "inverse": bm.summary(), "folding": result.folding,
               "similarity_before": result.similarity_before, "similarity_after": result.similarity_after}
    return {"correspondence.mha": Field(result.correspondence),
            "template_to_scan.mha": Field(bm.scan_to_template()),
            "inverse_status.nii.gz": Labels(Volume(bm.status.astype(np.uint8), template.geometry)),
            "registered.nii.gz": Image(result.registered),
            "log.json": Json({"format": "avw-registration", "version": 1,
                              "method": "locally adaptive (Rhee §4, Alg. 1)",
                              "direction": "correspondence: scan_to_template on the scan grid (template position − "
                                           "voxel, mm); template_to_scan: its inverse on the template grid",
                              "settings": dataclasses.asdict(s), "summary": summary, "log": result.log(),
                              "workbench_version": __version__})}


STAGE = Stage(name="register", folder="registration", per_scan=True, settings_type=RegisterSettings, run=_run,
              needs=lambda s: ("init", "bones"), inputs=_inputs, version=3)
