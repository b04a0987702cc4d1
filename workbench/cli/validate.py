"""``workbench validate``: each scan's registration and pose against its ground truth (the validate stage)."""

from __future__ import annotations

from pathlib import Path

from workbench.cli.options import add_common, add_scale_options
from workbench.cli.running import run_study_stages


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "validate",
        help="each scan's registration and pose against its ground truth",
        description="The validate stage (Rhee §6.1, Tables 2-4): for each scan with ground truth, "
        "MED over body voxels and at the markers (mm), SSD, CC, MI (nats, 32 bins) and "
        "the folded fraction of body voxels for the source, the initialised and the "
        "registered template, and the estimated pose's errors.  Writes "
        "validation/<scan>/measures.json.  The only stage that reads the truth.",
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    p.add_argument("--force", action="store_true", help="rerun even when up to date")
    add_scale_options(p)
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.report.text import format_registration_table

    study, _ = run_study_stages(args, ["validate"], force={"validate"} if args.force else (), scans=args.scan)
    print(format_registration_table(study, study.check_scan_ids(args.scan)))
    return 0
