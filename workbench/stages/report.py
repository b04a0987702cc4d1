"""The ``report`` stage: the study's HTML validation report (:mod:`workbench.report`), the last stage of a run.

Reads what the stages before it wrote — poses and joints, each scan's
registration, the validate stage's measures where there is truth, pictures in
``renders/`` — and writes one self-contained HTML file that opens offline.

Outputs (``report/``): ``report.html``, which holds no time, date or machine name: the same results give the
same bytes (the times are ``study.json``'s, ``workbench info``).
"""

from __future__ import annotations

from dataclasses import dataclass

from workbench.report import RENDER_SUFFIXES, study_report
from workbench.stages.mechanism import Stage, Text

__all__ = ["ReportSettings", "STAGE"]


@dataclass(frozen=True)
class ReportSettings:
    pictures: bool = True  #: slice overlays, error and Jacobian maps per scan (off: tables and plots only)


def _inputs(study, s, scan):
    files = {"template": study.path(study.manifest["template"])}
    for sid in study.scan_ids:
        files[f"scan/{sid}"] = study.scan_path(sid)  # the truth reaches it only through validate's outputs
    for name in ("joints.json", "report.json"):  # the pose stage's, when it ran (a start from the identity needs none)
        if study.has_output("pose", name):
            files[f"pose/{name}"] = study.output("pose", name)
    renders = study.root / "renders"
    if renders.is_dir():
        for p in sorted(renders.glob("*")):
            if p.suffix.lower() in RENDER_SUFFIXES:
                files[f"renders/{p.name}"] = p
    return files


def _run(ctx) -> dict:
    ctx.report(0, 1, "building the report")
    html = study_report(ctx.study, pictures=ctx.settings.pictures)
    ctx.report(1, 1, f"report: {len(html) / 2**20:.1f} MB")
    return {"report.html": Text(html)}


STAGE = Stage(
    name="report",
    folder="report",
    per_scan=False,
    settings_type=ReportSettings,
    run=_run,
    needs=lambda s: ("register", "validate"),
    inputs=_inputs,
    version=4,  # what each version changed: docs/measurements/workbench.md
)
