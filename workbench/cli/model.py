"""``workbench model``: an EVD model (Rhee Eq. 7) from the study's correspondences (the model stage)."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common
from workbench.cli.running import read_output, run_study_stages

DESCRIPTION = """Build an example-based volume deformation model (Rhee Eq. 7) from the
study's scans: for each scan, the displacement of every template voxel in
the template frame after undoing VBD with the scan's pose.

--source registration (the default): the correspondences of `workbench
register` (their inverse fields) and the poses of `workbench pose` — a
model from your own scans, no truth needed.  --source truth: a phantom's
exact correspondences and true poses (a protocol's reference model; never
taken unless asked).

Writes model/evd.json and model/evd_displacements.mha; `workbench deform`
and `workbench animate` then pose the template by EVD.  Runs the stages it
needs first when they have not run (weights; pose and register for the
registration source).
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "model",
        help="build an EVD model (Rhee Eq. 7) from the study's correspondences",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument(
        "--source",
        choices=["registration", "truth"],
        default="registration",
        help="correspondences: 'registration' (`workbench register` + estimated poses) or 'truth' (a "
        "phantom's exact ones and true poses; never taken unless asked). Default: registration",
    )
    p.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    p.add_argument("--force", action="store_true", help="rebuild even when up to date")
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.stages.model import ModelSettings

    source = args.source
    ms = ModelSettings(source=source, scans=tuple(args.scan) if args.scan else None)
    study, out = run_study_stages(args, ["model"], {"model": ms}, force={"model"} if args.force else ())
    doc = read_output(study, "model", "evd.json")
    print(
        f"EVD model from the {doc.get('source', source)} correspondences of {len(doc['scans'])} scans "
        f"({', '.join(doc['scans'])}){' (up to date)' if out[-1].status == 'skipped' else ''}; "
        f"in {study.root / 'model'}"
    )
    return 0
