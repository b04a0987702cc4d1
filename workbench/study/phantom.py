"""Writing a phantom (:mod:`validation.phantoms`) as a study folder with its exact ground truth.

The study is written into a staging folder beside the target and renamed into place at the end, so an
interrupted run leaves no half-written study; ``study.json`` holds only deterministic content (the generation
statistics go to ``logs/phantom.json``), so the same seed gives byte-identical files.
"""

from __future__ import annotations

import os
import secrets
import shutil
import time
from pathlib import Path

import numpy as np

from workbench import __version__
from workbench.errors import OutputExistsError
from workbench.io.atomic import naming_staged, replace_dir
from workbench.io.jsonio import write_json
from workbench.io.volumes import write_displacement, write_labels, write_volume
from workbench.study.folder import Study, read_study
from workbench.study.manifest import MANIFEST, STUDY_FORMAT

__all__ = ["write_phantom_study"]


def _staging_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.partial-{secrets.token_hex(4)}"


def write_phantom_study(
    phantom, out: str | os.PathLike, *, overwrite: bool = False, progress=None, name: str | None = None
) -> Study:
    """Generate a phantom's template and posed scans and write them as a study folder.

    Parameters
    ----------
    phantom : validation.phantoms.Phantom
    out : path of the study folder to create
    overwrite : replace an existing folder (otherwise :class:`~workbench.errors.OutputExistsError`)
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
    try:
        with naming_staged(stage, out):  # a failed write named by its place in the study
            _write_phantom_files(phantom, stage, report, name)
        replace_dir(stage, out)  # an old study is replaced only once the new one is complete
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return read_study(out)


def _write_phantom_files(phantom, stage: Path, report, name: str | None) -> None:
    """Generate the phantom's images and truth and write them, with the manifest, into the folder ``stage``."""
    n = len(phantom.poses)
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
        truth = {
            "correspondence": f"truth/{sid}_correspondence.mha",
            "pose": f"truth/{sid}_pose.json",
            "markers": f"truth/{sid}_markers.json",
        }
        write_volume(scan.image, stage / f"scans/{sid}.nii.gz")
        write_displacement(scan.correspondence, stage / truth["correspondence"])
        if scan.template_to_scan is not None:
            truth["template_to_scan"] = f"truth/{sid}_template_to_scan.mha"
            write_displacement(scan.template_to_scan, stage / truth["template_to_scan"])
        write_json(scan.pose.to_dict(), stage / truth["pose"])
        write_json(
            {"format": "avw-markers", "version": 1, "units": "mm", "markers": scan.markers}, stage / truth["markers"]
        )
        entries.append({"id": sid, "image": f"scans/{sid}.nii.gz", "truth": truth})
        log["scans"].append({"id": sid, **scan.stats, "write_seconds": round(time.perf_counter() - t1, 3)})
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
        "phantom": {
            **spec,
            "poses": [
                {"id": pid, "angles_deg": {k: np.asarray(v).tolist() for k, v in a.items()}} for pid, a in phantom.poses
            ],
            "generator": "validation.phantoms",
            "workbench_version": __version__,
            "correspondence": "scan_to_template: template position minus scan voxel position, mm",
            # acquisition="random": what was drawn (validation.phantoms.draw_acquisition)
            **({"acquisition_drawn": phantom.acquisition} if getattr(phantom, "acquisition", None) is not None else {}),
        },
        "stages": {},
    }
    log["total_seconds"] = round(time.perf_counter() - t0, 3)
    write_json(log, stage / "logs" / "phantom.json")
    write_json(manifest, stage / MANIFEST)
