"""The ``register`` stage: the non-rigid registration of the template to each scan.

``method="dense"`` (default, see docs/measurements/workbench.md): :func:`registration.dense.register_dense` —
local-correlation diffeomorphic steps over the whole scan, every step one-to-one, the bones held where the pose
stage put them.

``method="adaptive"`` (``--preset paper`` selects it; Rhee §4, Algorithm 1): from the init stage's start, the
worst-matching block of a hierarchy gets 8 clamped-plate-spline control points whose displacements an NLopt
simplex optimises; each accepted step is composed into the running field
(:func:`registration.adaptive.register_adaptive`).  After VBD the template's bone voxels are zero-displacement
control points (Rhee §4.3).  The result is inverted onto the template grid for EVD (Rhee Eq. 7) by
:func:`deformation.fields.resample.invert_scan_to_template`, through the start's exact forward map (VBD's, or the
polyrigid flow's ``forward.mha``), so that only the registration's own correction is inverted numerically.

Outputs (``registration/<scan>/``)::

    correspondence.mha     scan_to_template on the scan grid (template position − voxel, mm; the convention
                           of truth/<id>_correspondence.mha, usable by sitk.DisplacementFieldTransform)
    template_to_scan.mha   its inverse on the template grid (scan position − voxel, mm)
    uncertainty.mha        (dense) the map's expected error at each scan voxel, σ in mm (registration.posterior)
    inverse_status.nii.gz  where the inverse was found: 0 ok, 1 folded, 2 not found, 3 outside the scan
    registered.nii.gz      the template resampled onto the scan grid through the field
    log.json               settings, per-level and per-step log, similarity before/after, folding

The times are in the scan's ``study.json`` entry (``timings``), not in its files: the same inputs, the same bytes.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from workbench import __version__
from workbench.stages.mechanism import Field, Image, Json, Labels, Stage
from workbench.stages.settings import setting_value

__all__ = ["RegisterSettings", "STAGE", "PRESETS", "adaptive_registration", "held_bones"]

PRESETS = ("auto", "default", "initialised", "paper")
METHODS = ("auto", "dense", "adaptive")


@dataclass(frozen=True)
class RegisterSettings:
    """The registration's settings: a preset and the overrides the command line exposes.

    ``method``: ``dense`` (:mod:`registration.dense`), ``adaptive`` (Rhee's
    Algorithm 1) or ``auto`` (adaptive when a preset is named, else dense).
    ``preset`` (adaptive): ``auto`` (``initialised`` after an articulated
    start, ``default`` after none), ``default``, ``initialised`` or ``paper``
    (Rhee's published settings) — :class:`registration.adaptive.AdaptiveSettings`.
    ``levels``/``optimizer``/``metric``/``max_steps_per_level`` are the adaptive
    method's; ``fix_bones`` is both methods'.  ``dense_settings``: ``(name, value)`` pairs applied over
    :class:`registration.dense.DenseSettings`' defaults (the dense method's; ``bones`` follows ``fix_bones``).
    """

    method: str = "auto"
    preset: str = "auto"
    levels: tuple | None = None
    optimizer: str | None = None
    metric: str | None = None
    max_steps_per_level: int | None = None
    fix_bones: bool = True
    seed: int = 0
    dense_settings: tuple = ()

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"--preset must be one of {PRESETS}, got {self.preset!r}")
        if self.method not in METHODS:
            raise ValueError(f"--method must be one of {METHODS[1:]}, got {self.method!r}")
        if self.method == "dense" and self.preset != "auto":
            raise ValueError(
                f"the preset {self.preset!r} is a setting of Rhee's Algorithm 1: give --method adaptive "
                "(or leave --method out)"
            )
        if self.levels is not None:
            object.__setattr__(self, "levels", tuple(int(v) for v in self.levels))
        object.__setattr__(self, "dense_settings", _dense_pairs(self.dense_settings))
        if self.dense_settings and self.resolved_method != "dense":
            raise ValueError(
                f"--dense {self.dense_settings[0][0]}=...: the dense registration's settings do not "
                "apply to Rhee's Algorithm 1 (--method adaptive, --preset): leave them out"
            )
        self.adaptive("vbd")  # validates the overrides now, not after the first scan

    @property
    def resolved_method(self) -> str:
        if self.method != "auto":
            return self.method
        return "adaptive" if self.preset != "auto" else "dense"  # a preset names Algorithm 1's settings

    def dense(self, articulated: bool = True):
        """The :class:`~registration.dense.DenseSettings` of the dense method (bones held after an articulated
        start, which placed them)."""
        from registration.dense import DenseSettings

        return DenseSettings(**dict(self.dense_settings), bones="fixed" if (self.fix_bones and articulated) else "free")

    def adaptive(self, init_method: str):
        """The :class:`~registration.adaptive.AdaptiveSettings` for a start made by ``init_method``."""
        from registration.adaptive import AdaptiveSettings

        over = {
            k: v
            for k, v in (
                ("levels", self.levels),
                ("optimizer", self.optimizer),
                ("metric", self.metric),
                ("max_steps_per_level", self.max_steps_per_level),
            )
            if v is not None
        }
        over.update(fix_bones=self.fix_bones, seed=self.seed)
        preset = self.preset
        if preset == "auto":
            preset = "initialised" if init_method in ("vbd", "polyrigid") else "default"
        if preset == "paper":
            return AdaptiveSettings.paper(**over)
        if preset == "initialised":
            return AdaptiveSettings.initialised(**over)
        return AdaptiveSettings(**over)


def _dense_pairs(pairs) -> tuple:
    """``dense_settings`` as ``((name, value), ...)`` sorted by name (one digest for one set of settings), each
    name a setting of :class:`~registration.dense.DenseSettings` (not ``bones``: ``fix_bones``) given once, each
    value of the type it declares (a number finite; ``shrink`` whole numbers ≥ 1, ``iterations`` ≥ 0) and the
    whole accepted by ``DenseSettings``; else one clear :class:`ValueError`.  JSON lists (a recorded study)
    become tuples."""
    import math
    import typing

    from registration.dense import DenseSettings

    hints = typing.get_type_hints(DenseSettings)
    out, seen = [], set()
    for pair in pairs or ():
        if not isinstance(pair, (list, tuple)) or len(pair) != 2 or not isinstance(pair[0], str):
            raise ValueError(f"dense_settings: expected [name, value] pairs, got {pair!r}")
        name, value = pair
        if name == "bones":
            raise ValueError("--dense bones=...: the bones are held or not by --no-fix-bones (fix_bones)")
        if name not in hints:
            raise ValueError(
                f"--dense {name}=...: the dense registration has no setting {name!r}; its settings are "
                f"{sorted(k for k in hints if k != 'bones')}"
            )
        if name in seen:
            raise ValueError(f"--dense {name}=... is given twice: give each setting once")
        seen.add(name)
        value = setting_value(name, list(value) if isinstance(value, tuple) else value, hints[name], option="--dense")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"--dense {name}: the setting must be a finite number, got {value}")
        if isinstance(value, list):  # shrink, iterations: one whole number per level
            low = 1 if name == "shrink" else 0
            value = [int(v) if isinstance(v, float) and v.is_integer() else v for v in value]
            if not all(isinstance(v, int) and not isinstance(v, bool) and v >= low for v in value):
                raise ValueError(
                    f"--dense {name}: the setting is a list of whole numbers ≥ {low}, one per level, got {value}"
                )
            value = tuple(value)
        out.append((name, value))
    out.sort(key=lambda kv: kv[0])
    try:
        DenseSettings(**dict(out))
    except (TypeError, ValueError) as e:
        raise ValueError(f"--dense: {e}") from e
    return tuple(out)


def _inputs(study, s, scan):
    return {
        "template": study.path(study.manifest["template"]),
        "scan": study.scan_path(scan),
        "labels": study.template_labels_path(),
    }


def _forward(study, sid, start, template_geometry):
    """The start's forward map (template voxel → scan position, ``(nz, ny, nx, 3)``), or ``None`` (identity)."""
    from deformation.models.evd import vbd_forward

    if start["method"] == "vbd":
        weights, _ = study.weights()  # the weights that made the start (their digest reaches ours through it)
        # Rhee Eq. 2: the VBD start
        return vbd_forward(template_geometry, weights.reorder(start["bones"]), np.asarray(start["transforms"]))
    if start["method"] == "polyrigid":
        fwd = study.init_forward(sid)
        template_geometry.check_same(
            fwd.geometry,
            names=("template", "init forward.mha"),
            remedy="rerun the init stage: workbench register --force",
        )
        return np.asarray(fwd.data, np.float64) + template_geometry.world_coordinates()
    return None


def held_bones(study, start):
    """The bones a registration holds rigid: the template's labels less those the pose stage could not place
    (the init stage lists them; their start follows an ancestor, which the image may correct)."""
    from registration.pose import released_labels

    return released_labels(study.template_labels(), study.skeleton(), start.get("flagged_bones", []))


def adaptive_registration(study, sid: str, s: RegisterSettings, *, template=None, scan=None, progress=None):
    """Rhee's Algorithm 1 on scan ``sid`` as this stage runs it (``method="adaptive"``), nothing written: from the
    init stage's start (its field, or the identity), with :meth:`RegisterSettings.adaptive` for that start's
    method and, after an articulated start, the bones ``held_bones`` holds.  ``template``/``scan``: the
    study's, when already read.  Returns the :class:`~registration.adaptive.AdaptiveResult` (its
    ``correspondence`` and ``registered`` are what the stage writes; ``workbench reproduce``'s Tables 2–4 score
    them directly)."""
    from registration.adaptive import register_adaptive

    start = study.init_info(sid)  # the start, as the init stage made it: no pose (nor truth) is read here
    articulated = start["method"] in ("vbd", "polyrigid")
    settings = s.adaptive(start["method"])
    rigid = held_bones(study, start) if (articulated and settings.fix_bones) else None
    template = study.template() if template is None else template
    scan = study.scan(sid) if scan is None else scan
    return register_adaptive(
        scan, template, initial=study.init_field(sid), rigid_mask=rigid, settings=settings, progress=progress
    )


def _run(ctx) -> dict:
    from deformation.fields.resample import invert_scan_to_template

    study, s, sid = ctx.study, ctx.settings, ctx.scan
    start = study.init_info(sid)  # the start, as the init stage made it: no pose (nor truth) is read here
    method = start["method"]
    template, scan = study.template(), study.scan(sid)
    if s.resolved_method == "dense":
        return _run_dense(ctx, start, template, scan, study.init_field(sid), method in ("vbd", "polyrigid"))
    forward = _forward(study, sid, start, template.geometry)

    def step(info):
        if "level_done" in info:
            lv = info["level_done"]
            ctx.say(
                f"{sid} level {lv.level}: {lv.steps} steps ({lv.accepted} accepted), {lv.control_points} "
                f"control points, {lv.metric} {lv.metric_before:.4g} -> {lv.metric_after:.4g}, stopped: "
                f"{lv.stopped}, {lv.seconds:.1f} s"
            )
        else:
            ctx.report(
                info["step"],
                0,
                f"{sid} level {info['level']} step {info['step']} block "
                f"{tuple(info['block'])}: {info['metric']} {info['block_before']:.4g} -> "
                f"{info['block_after']:.4g}; ~{info['eta']:.0f} s left in this level",
            )

    result = adaptive_registration(study, sid, s, template=template, scan=scan, progress=step)
    ctx.say(f"{sid}: inverting the field onto the template grid ...")
    t0 = time.perf_counter()
    # φ = F⁻¹ ∘ U (F the start's forward map): only the registration's own correction U is inverted numerically
    bm = invert_scan_to_template(result.correspondence, template.geometry, forward=forward)
    inner = result.log()
    del inner["seconds"]
    inner["levels"], level_seconds = _untimed(inner["levels"])
    inner["steps"], step_seconds = _untimed(inner["steps"])
    ctx.timings.update(
        registration=round(result.seconds, 3),
        inverse=round(time.perf_counter() - t0, 3),
        levels=[round(v, 3) for v in level_seconds],
        steps=[round(v, 4) for v in step_seconds],
    )
    summary = {
        "scan": sid,
        "init": method,
        "control_points": result.control_points,
        "steps": len(result.steps),
        "evaluations": result.evaluations,
        "inverse": bm.summary(),
        "folding": result.folding,
        "similarity_before": result.similarity_before,
        "similarity_after": result.similarity_after,
    }
    return _outputs(
        result,
        bm,
        template,
        {
            "method": "locally adaptive (Rhee §4, Alg. 1)",
            "settings": dataclasses.asdict(s),
            "summary": summary,
            "log": inner,
        },
    )


def _untimed(records: list) -> tuple[list, list]:
    """``(records without their "seconds", those seconds)``: the times go to ``ctx.timings``, not to log.json
    (nor do the dense level's bone refinement rounds' own)."""

    def strip(r):
        out = {k: v for k, v in r.items() if k != "seconds"}
        if out.get("bone_refinement"):
            out["bone_refinement"] = [{k: v for k, v in rd.items() if k != "seconds"} for rd in out["bone_refinement"]]
        return out

    return [strip(r) for r in records], [r["seconds"] for r in records]


def _outputs(result, bm, template, log: dict) -> dict:
    """The register stage's files, the same for both methods; ``log`` fills log.json beside the conventions."""
    from deformation.geometry import Volume

    out = {
        "correspondence.mha": Field(result.correspondence),
        "template_to_scan.mha": Field(bm.scan_to_template()),
        "inverse_status.nii.gz": Labels(Volume(bm.status.astype(np.uint8), template.geometry)),
        "registered.nii.gz": Image(result.registered),
        "log.json": Json(
            {
                "format": "avw-registration",
                "version": 1,
                "direction": "correspondence: scan_to_template on the scan grid (template position − "
                "voxel, mm); template_to_scan: its inverse on the template grid",
                **log,
                "workbench_version": __version__,
            }
        ),
    }
    if getattr(result, "uncertainty", None) is not None:  # the dense registration's expected error (mm)
        out["uncertainty.mha"] = Image(result.uncertainty)
    return out


def _run_dense(ctx, start, template, scan, initial, articulated) -> dict:
    from deformation.fields.resample import invert_scan_to_template
    from registration.dense import register_dense

    study, s, sid = ctx.study, ctx.settings, ctx.scan
    settings = s.dense(articulated)
    labels = held_bones(study, start) if settings.bones == "fixed" else None
    forward = _forward(study, sid, start, template.geometry)

    def level(rec):
        moved = [rd for rd in rec.get("bone_refinement") or [] if rd["taken"]]
        bones = (
            f"; bones refined in {len(moved)} round(s), {len(moved[-1]['poses'])} moved from the pose stage's estimate"
            if moved
            else ""
        )
        ctx.say(
            f"{sid} level {rec['level']} (1/{rec['shrink']} of the grid): {rec['iterations']} steps taken, "
            f"{rec['rejected']} tried and refused, stopped: {rec['stop']}; "
            f"objective {rec['lncc_before']:.4f} -> {rec['lncc_after']:.4f}{bones}, {rec['seconds']:.1f} s"
        )

    result = register_dense(scan, template, initial=initial, moving_labels=labels, settings=settings, progress=level)
    ctx.say(f"{sid}: inverting the field onto the template grid ...")
    t0 = time.perf_counter()
    bm = invert_scan_to_template(result.correspondence, template.geometry, forward=forward)
    levels, level_seconds = _untimed(result.levels)
    ctx.timings.update(
        registration=round(result.seconds, 3), inverse=round(time.perf_counter() - t0, 3), levels=level_seconds
    )
    summary = {
        "scan": sid,
        "init": start["method"],
        "control_points": None,
        "levels": levels,
        "inverse": bm.summary(),
        "folding": result.folding,
        "unfold": result.unfold,
        "similarity_before": result.similarity_before,
        "similarity_after": result.similarity_after,
        # settings.posterior: the prior's SD, the share of the finest level's change the images measure, the median
        # expected error
        # (registration.posterior); None when off
        "posterior": result.posterior,
    }
    if result.posterior is not None and result.posterior.get("sigma_median_mm") is not None:
        p = result.posterior
        ctx.say(
            f"{sid}: expected error σ median {p['sigma_median_mm']:.2f} mm over the scan's body (uncertainty.mha); "
            f"the images measure {100 * p['kept']:.0f} % of the finest level's change over the soft tissue"
            + (" (kept: --dense posterior_mean=true)" if settings.posterior_mean else "")
            + (
                "; the images measured no correction (the prior's SD at its lower bound): σ there is not checked"
                if p.get("prior_at_bound")
                else ""
            )
        )
    return _outputs(
        result,
        bm,
        template,
        {
            "method": f"dense (LNCC diffeomorphic steps, bones {settings.bones}; registration.dense)",
            "settings": dataclasses.asdict(s),
            "dense_settings": settings.to_dict(),
            "summary": summary,
        },
    )


STAGE = Stage(
    name="register",
    folder="registration",
    per_scan=True,
    settings_type=RegisterSettings,
    run=_run,
    needs=lambda s: ("init", "bones"),
    inputs=_inputs,
    version=21,  # what each version changed: docs/measurements/workbench.md
)
