"""``workbench report``: one self-contained HTML validation report of a study or a reproduce folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common
from workbench.cli.running import run_study_stages

DESCRIPTION = """Write one self-contained HTML validation report (opens offline, in any browser).

For a study (the report stage, which `workbench run` ends with; the file is
also kept as STUDY/report/report.html):
  - bone poses: joint angles per scan, Kurihara Eq. 1 residual per joint
  - registration: similarity (SSD, CC, MI) before and after, folded voxels,
    time, convergence plots, the registration's displacement and Jacobian maps
  - overlays of the registered template (green) on its scan (magenta) on three
    planes, with a toggle / flicker between the two
  - with ground truth: MED (body, markers), SSD, CC, MI per volume, error maps,
    each marker's error
  - pictures in STUDY/renders/ (e.g. from `workbench render STUDY --out
    STUDY/renders/knee.png`)
  - software versions, every stage's settings, the study digest
For a `workbench reproduce` folder: every table with its definitions, then the
last registration of each study it ran.

examples:
  workbench report knee-study --out knee-report.html
  workbench report tables --out tables.html
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help="one self-contained HTML validation report of a study or a reproduce folder",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "source",
        type=Path,
        metavar="STUDY_OR_DIR",
        help="a study folder (holding study.json) or a `workbench reproduce` output folder",
    )
    p.add_argument("--out", type=Path, required=True, metavar="FILE.html", help="the report to write")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file; for a study, also rebuild the report stage's report",
    )
    p.add_argument(
        "--no-pictures", action="store_true", help="tables and plots only, no slice pictures (a smaller file)"
    )
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.errors import InputFileError, OutputExistsError
    from workbench.io.atomic import write_text_atomic

    out = args.out
    if out.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"--out {out}: the report is an HTML file; give a name ending in .html")
    if out.exists() and not args.force:
        raise OutputExistsError(out, f"{out}: already exists; choose another --out or pass --force to replace it.")
    if not out.parent.exists():
        raise InputFileError(f"--out {out}: the folder {out.parent} does not exist; create it first", out.parent)
    src = args.source
    if (src / "study.json").exists():
        from workbench.stages.report import ReportSettings

        args.study = src
        study, _ = run_study_stages(
            args,
            ["report"],
            {"report": ReportSettings(pictures=not args.no_pictures)},
            force={"report"} if args.force else (),
        )
        html = study.output("report", "report.html").read_text(encoding="utf-8")
    elif src.is_dir() and any(_is_table(p) for p in src.glob("*.json")):
        from workbench.report import tables_report

        html = tables_report(src)
    else:
        raise InputFileError(
            f"{src}: neither a study folder (no study.json) nor a `workbench reproduce` folder "
            "(no tables); give one of them",
            src,
        )
    write_text_atomic(out, html, overwrite=args.force)
    print(f"wrote {out} ({len(html.encode()) / 2**20:.1f} MB)")
    return 0


def _is_table(path: Path) -> bool:
    import json

    try:
        return json.loads(path.read_text(encoding="utf-8")).get("format") == "avw-table"
    except (OSError, ValueError, AttributeError):
        return False
