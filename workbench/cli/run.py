"""``workbench run``: every stage of the pipeline on a study, in order."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from workbench.cli.options import STAGE_NAMES, add_common, add_scale_options
from workbench.cli.running import run_study_stages

DESCRIPTION = """\
Run the whole pipeline on a study, stage by stage, each through one mechanism:

  bones     the template's bone labels (given, or segmented from --seeds)
  pose      every bone's transform in every scan, joint centres and angles
  weights   harmonic skinning weights of every template voxel
  init      the articulated start to each scan's estimated pose  (per scan)
  register  dense registration (or Rhee Algorithm 1, --method)  (per scan)
  model     EVD (Rhee Eq. 7) from the registrations and the estimated poses
  surface   Kurihara's consistent skin meshes (S0, and each scan's fitted mesh)
  validate  each scan against its ground truth, when it has one  (per scan)
  report    one self-contained HTML validation report (report/report.html)

The ground truth of a phantom is read by `validate` alone.  Each stage
records in study.json a digest of its inputs and settings; a stage whose
digest is unchanged is skipped (and says so), so a second `run` does nothing
and a changed setting reruns only the stages that depend on it.  Per-scan
stages commit each scan as it finishes: after Ctrl-C (or SIGTERM) no partial
file is left and the next `run` resumes with the first unfinished scan.

Settings: each stage keeps the settings it last ran with (e.g. those given to
`workbench register`); --set STAGE.SETTING=VALUE changes one for this run and
after (JSON values: --set register.method=adaptive,
--set register.seed=1, --set weights.method=distance).  Each value is
checked against the setting's type before anything runs or is recorded.

Before any work the study folder and study.json must be writable; a scan
whose field of view holds none of the template's bones, or of which no bone
could be placed, stops the pose stage with one line naming it.  A write that
does not complete (a full disk) is an error naming the file; nothing is left
half-written, and the previous outputs stay.

examples:
  workbench run knee-study                        # everything; truth only in validate
  workbench run knee-study                        # again: every stage skipped
  workbench run knee-study --until register       # stop after the registrations
  workbench run knee-study --force register       # rerun register, then model, surface, validate, report
  workbench run my-ct-study --seeds seeds.json    # no label map: segment the bones first
  workbench run knee-study --scan pose01 --until register
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "run",
        help="run every stage in order: bones, pose, weights, init, register, model, surface, validate, report",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument("--until", metavar="STAGE", choices=STAGE_NAMES, help="stop after this stage")
    p.add_argument(
        "--force",
        action="append",
        default=[],
        metavar="STAGE",
        choices=STAGE_NAMES,
        help="rerun this stage even when up to date, and what depends on it (repeatable)",
    )
    p.add_argument("--scan", action="append", metavar="ID", help="per-scan stages only for this scan (repeatable)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="STAGE.SETTING=VALUE",
        dest="set_",
        help="change one stage setting (repeatable; see above)",
    )
    p.add_argument(
        "--seeds",
        type=Path,
        metavar="FILE",
        help="segment the template's bones from this seeds file (a study without a label map)",
    )
    add_scale_options(p)
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.report.text import format_registration_table
    from workbench.stages import ORDER
    from workbench.stages.run import dependents, run_settings
    from workbench.study import read_study

    settings = run_settings(read_study(args.study), args.set_, args.seeds)
    targets = list(ORDER[: ORDER.index(args.until) + 1]) if args.until else list(ORDER)
    force = dependents(args.force) & set(targets) if args.force else set()
    t0 = time.perf_counter()
    study, outcomes = run_study_stages(args, targets, settings, force=force, scans=args.scan)
    ran = [o for o in outcomes if o.status == "ran"]
    print(
        f"{len(ran)} stage run(s), {len(outcomes) - len(ran)} up to date or nothing to do; "
        f"{time.perf_counter() - t0:.1f} s"
    )
    if "validate" in targets:
        print(format_registration_table(study, study.check_scan_ids(args.scan)))
    return 0
