"""Using a study's model: the template posed by EVD or VBD (``workbench deform``; ``workbench animate`` too).

:func:`study_poser` loads a study's template, labels, skinning weights and
EVD model once into a :class:`deformation.models.posed_template.TemplatePoser` and
says which deformation it will use; :func:`deform_study` writes one posed
volume, its labels and (optionally) its field.
"""

from __future__ import annotations

from pathlib import Path

from deformation.geometry import covering_grid, every_nth, points_bounds
from deformation.models.posed_template import WEIGHTINGS, TemplatePoser
from workbench.errors import InputFileError, OutputExistsError
from workbench.io.inputs import read_target_pose
from workbench.io.volumes import write_labels, write_volume
from workbench.study import MANIFEST, Study, read_study

__all__ = ["study_poser", "deform_study", "say_if_compiling", "METHODS", "surface_deform"]

METHODS = ("auto", "vbd", "evd")
# Folders of a study that `deform` never writes into (its inputs and the stages' outputs).
PROTECTED_FOLDERS = (
    "scans",
    "truth",
    "bones",
    "poses",
    "skinning",
    "init",
    "registration",
    "model",
    "surface",
    "validation",
    "report",
)


def study_poser(study: Study, *, method: str = "auto", weighting: str = "psd", progress=None) -> TemplatePoser:
    """A :class:`~deformation.models.posed_template.TemplatePoser` of the study, saying which deformation it uses.

    ``method``: ``auto`` (EVD when the study has a model, else VBD — and says
    so), ``vbd`` (Rhee Eq. 2) or ``evd`` (Rhee Eq. 6–7; an error without a model).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    say = progress or (lambda line: None)
    weights, body = study.weights(coarse=True)
    model = None
    template = study.template()
    grid = f"{every_nth(template.geometry.factor_of(body.geometry))} template voxel"
    on_template = body.geometry.is_close(template.geometry)
    if method == "evd" and not on_template:
        raise InputFileError(
            f"{study.output('weights', 'weights.json')}: the skinning weights are on {grid} "
            "(workbench weights --grid-factor); EVD needs them on the template's grid: use "
            "--method vbd, or recompute them with --grid-factor 1.",
            study.manifest_path,
        )
    if not on_template:
        say(
            f"skinning weights on {grid}: posing by VBD (Rhee Eq. 2), the maps solved there and the template "
            "pulled at full resolution"
        )
    if method in ("auto", "evd") and on_template:
        model = study.model(weights)
        if model is None and method == "evd":
            raise InputFileError(
                f"{study.manifest_path}: the study has no EVD model; build one with `workbench "
                f"model {study.root}` (after `workbench register`, or --source truth for a "
                "phantom) or use --method vbd.",
                study.manifest_path,
            )
        if model is None:
            say(f"no EVD model in the study (`workbench model {study.root}` builds one): posing by VBD (Rhee Eq. 2)")
    if model is not None:
        e = study.stage_entry("model") or {}
        say(
            f"posing by EVD (Rhee Eq. 6), model from {(e.get('settings') or {}).get('source', '?')} "
            f"correspondences of {model.n_scans} scans"
            f"{' and the template at rest' if model.template_example else ''}"
        )
    if weighting != "psd" and model is None:
        say("note: --weighting applies to EVD only; this is VBD")
    return TemplatePoser(
        template,
        weights,
        body,
        labels=study.template_labels() if study.has_template_labels else None,
        model=model,
        weighting=weighting,
        progress=say,
    )


def _refuse_study_files(study, paths, what: str) -> None:
    """A ValueError when an output would replace one of the study's own files (manifest, template, stage
    outputs)."""
    root = study.root.resolve()
    protected = {root / MANIFEST, root / study.manifest["template"]}
    if study.manifest.get("template_labels"):
        protected.add(root / study.manifest["template_labels"])
    for p in paths:
        inside = root in p.parents
        if p in protected or (inside and p.relative_to(root).parts[0] in PROTECTED_FOLDERS):
            raise ValueError(
                f"{p}: would overwrite one of the study's own files; write {what} elsewhere (or in a "
                "new subfolder of the study)"
            )


def say_if_compiling(say) -> None:
    """Tell the user when the deformation kernels are compiled on this first use (tens of seconds otherwise silent),
    unless the process announces every first compile itself (:func:`workbench.progress.compilation_announced`)."""
    from deformation.fields.resample import backward_kernel
    from deformation.models.evd import forward_kernel
    from workbench.progress import compilation_announced, compile_note

    if compilation_announced():
        return
    note = compile_note(forward_kernel, backward_kernel)  # a cold cache shows in these two as in the others
    if note:
        say(note)


def _sigma_summary(poser, pose) -> dict:
    """The posed expected error over the posed body (template body voxels, on the template grid): its median and
    95th percentile, the scans' part alone (median) and the share of the variance the pose interpolation makes."""
    import numpy as np

    model = poser.model
    body = poser.body.data > 0
    total = model.expected_error(pose)[body].astype(np.float64)
    interp = (1.0 - model.space.explained(pose)) * model.cross_validation_variance().reshape(body.shape)[body]
    scans = np.sqrt(np.maximum(total**2 - interp, 0.0))
    return {
        "median_mm": float(np.median(total)) if total.size else 0.0,
        "p95_mm": float(np.percentile(total, 95)) if total.size else 0.0,
        # None: the model holds no scan errors (built from the truth's exact maps, or before the model stage's v5)
        "scans_median_mm": (float(np.median(scans)) if scans.size else 0.0) if model.scan_sigma is not None else None,
        "interpolation_share": float(interp.sum() / max(float((total**2).sum()), 1e-30)),
    }


def deform_study(
    folder,
    pose_path,
    out,
    *,
    method: str = "auto",
    weighting: str = "psd",
    labels_out=None,
    field_out=None,
    uncertainty_out=None,
    grow: bool = False,
    overwrite: bool = False,
    map_factor: int = 1,
    progress=None,
) -> dict:
    """Deform the template to a pose (VBD, Rhee Eq. 2, or EVD, Rhee Eq. 6) and write the posed volume and labels.

    The posed volume lies on the template's grid (same geometry), or with
    ``grow`` on that grid extended by whole voxels to hold the posed body
    (a bent limb leaves a slab scanned straight).  With ``uncertainty_out``
    (EVD only) the model's expected error at the pose is written on the
    posed grid too.  Returns a summary: the method, the backward map's
    status counts, timings.
    """
    from workbench.io.atomic import check_output_folder, split_suffix
    from workbench.io.volumes import image_format

    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    say = progress or (lambda line: None)
    study = read_study(folder)
    out = Path(out)
    stem, suffix = split_suffix(out.name)
    labels_out = Path(labels_out) if labels_out else out.with_name(f"{stem}_labels{suffix}")
    extra = [(Path(p), o) for p, o in ((field_out, "--field-out"), (uncertainty_out, "--uncertainty-out")) if p]
    outputs = [out, labels_out] + [p for p, _ in extra]
    # every check before any work, so that no output set is left half-written
    for p, option in zip(outputs, ["--out", "--labels-out"] + [o for _, o in extra]):
        check_output_folder(p, option)
        image_format(p, for_writing=True)
        if p.exists() and not overwrite:
            raise OutputExistsError(p, f"{p} exists; pass --force to replace it.")
    resolved = [p.resolve() for p in outputs]
    if len(set(resolved)) != len(resolved):
        raise ValueError(f"the output files must differ: {[str(p) for p in outputs]}")
    _refuse_study_files(study, resolved, "the posed volume")
    pose = read_target_pose(pose_path, study.skeleton())  # a bad pose file is reported before any loading
    if not study.has_template_labels:
        raise InputFileError(
            f"{study.root / MANIFEST}: the study has no template label map; `workbench deform` "
            "writes the posed labels beside the posed volume and needs one.",
            study.root / MANIFEST,
        )
    if uncertainty_out and (method == "vbd" or not study.has_model):
        raise InputFileError(
            f"--uncertainty-out {uncertainty_out}: the expected error comes from an EVD model; "
            + (
                "leave --method vbd out"
                if study.has_model
                else f"build one first (`workbench model {study.root}`) or leave --uncertainty-out out"
            )
            + ".",
            study.root / MANIFEST,
        )
    say_if_compiling(say)
    poser = study_poser(study, method=method, weighting=weighting, progress=say)
    used = poser.method
    if uncertainty_out and poser.model is None:  # weights on a coarse grid: study_poser fell back to VBD
        raise InputFileError(
            f"--uncertainty-out {uncertainty_out}: the study's skinning weights lie on a coarse grid, so it is "
            "posed by VBD, which has no expected error; leave --uncertainty-out out.",
            study.root / MANIFEST,
        )
    target = None
    if grow:  # the template's grid (same spacing and direction) extended to hold the posed body
        g = poser.template.geometry
        target = covering_grid(g, points_bounds(poser.forward(pose)[poser.body.data > 0], 2.0 * max(g.spacing)))
        say(f"posed volume on the grid grown to hold the posed body: {target.describe()}")
    posed = poser.pose(pose, target=target, map_factor=map_factor, uncertainty=bool(uncertainty_out))
    bm, forward_seconds, backward_seconds = posed.backward, posed.forward_seconds, posed.backward_seconds
    sigma_summary = _sigma_summary(poser, pose) if uncertainty_out else None  # before any file is written
    write_volume(posed.volume, out, overwrite=overwrite)
    write_labels(posed.labels, labels_out, overwrite=overwrite)
    if uncertainty_out:
        write_volume(posed.uncertainty, uncertainty_out, overwrite=overwrite)
    if field_out:
        from workbench.io.volumes import write_displacement

        # the field (12 B a voxel) and SimpleITK's copy of it to write: the posed volume, its labels and the
        # poser's template are let go first, to stay within 8 GiB at Kurihara's size (docs/measurements/workbench.md)
        del posed, poser
        write_displacement(bm.scan_to_template(), field_out, overwrite=overwrite)
    summary = {
        "method": used,
        "weighting": weighting if used == "evd" else None,
        "out": str(out),
        "labels": str(labels_out),
        "field": str(field_out) if field_out else None,
        "uncertainty": str(uncertainty_out) if uncertainty_out else None,
        "uncertainty_summary": sigma_summary,
        "forward_seconds": forward_seconds,
        "backward_seconds": backward_seconds,
        **bm.summary(),
    }
    return summary


def surface_deform(folder, pose_path, out, *, method: str = "wpsd", overwrite: bool = False) -> dict:
    """Pose the study's surface model (Kurihara §5: SSD, PSD or WPSD) and write the skin mesh ``out``."""
    import time

    from deformation.models.surface_model import SURFACE_METHODS
    from workbench.io.meshes import MESH_SUFFIXES, write_mesh

    if method not in SURFACE_METHODS:
        raise ValueError(f"--method must be one of {SURFACE_METHODS}, got {method!r}")
    out = Path(out)
    if out.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"--out {out}: a mesh file ending in one of {', '.join(MESH_SUFFIXES)}")
    if out.exists() and not overwrite:
        raise OutputExistsError(out, f"{out} exists; pass --force to replace it.")
    from workbench.io.atomic import check_output_folder

    check_output_folder(out, "--out")
    study = read_study(folder)
    _refuse_study_files(study, [out.resolve()], "the posed mesh")
    pose = read_target_pose(pose_path, study.skeleton())  # a bad pose file is reported before any loading
    model = study.surface_model()
    t0 = time.perf_counter()
    mesh = model.deform(pose, method)
    seconds = time.perf_counter() - t0
    write_mesh(mesh, out, overwrite=overwrite)
    return {"out": str(out), "vertices": mesh.n_vertices, "seconds": seconds, "method": method}
