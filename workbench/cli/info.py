"""``workbench info``: summarise a study folder and, with ``--check``, read every image of it."""

from __future__ import annotations

import sys
from pathlib import Path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "info",
        help="summarise a study folder",
        description="Print what a study folder holds: grids, skeleton, scans and ground truth.",
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument(
        "--check",
        action="store_true",
        help="also read every image of the study (template, labels, scans, ground truth) and list "
        "each that cannot be used (unreadable, NaN voxels, another grid's labels); exit 1 if any",
    )
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.stages import ORDER
    from workbench.study import read_study, summarize

    study = read_study(args.study)
    print(summarize(study, ORDER))
    if not args.check:
        return 0
    from workbench.study import check_study_images, study_warnings

    problems = check_study_images(study)
    warnings = [] if problems else study_warnings(study)
    if warnings:
        print(f"\n{len(warnings)} warning(s):", file=sys.stderr)
        for w in warnings:
            print(f"  {w}", file=sys.stderr)
    if problems:
        print(f"\n{len(problems)} problem(s):", file=sys.stderr)
        for p in problems:
            print(f"  {p}", file=sys.stderr)
        return 1
    print("\nevery image read: no problem found" + (f" ({len(warnings)} warning(s) above)" if warnings else ""))
    return 0
