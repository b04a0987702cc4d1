"""``workbench register``: the template registered to each scan from an articulated start (the init and
register stages).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common, add_scale_options
from workbench.cli.running import run_study_stages

DESCRIPTION = """\
Register the template to each scan by intensity alone, starting from an
articulated start to the scan's estimated pose.

--method dense (default) moves every voxel at every iteration: local
normalised cross-correlation (3 mm window) pulls the template, each step is
smoothed and composed so that no step folds (det > 0.2 everywhere) and is
taken only when it raises the level's similarity (a trust region), the bones
stay where the pose stage put them up to a rigid refinement, coarse to fine
over 3 levels (registration.dense).  --dense NAME=VALUE sets any of its
settings (registration.dense.DenseSettings; the value is JSON), e.g.
--dense holdout=true --dense 'iterations=[200, 200, 50]'.

--method adaptive is Rhee et al. 2011's locally adaptive block registration
(§4, Algorithm 1): the worst-matching block gets 8 clamped-plate-spline
control points whose 24 displacements an NLopt simplex optimises, level by
level; --preset paper gives its published settings (levels 3-5, Nelder-Mead,
tolerance 1.5 x the base MI, no regulariser) and selects --method adaptive.
The registration benchmark (benchmarks/bench_registration.py) compares both
with elastix, SimpleITK and ANTs on the same starts.

--init polyrigid (default) starts from the bones' rigid motions to the
scan's pose blended as a flow: one-to-one by construction (no fold in the
crease), bones exactly rigid.  --init vbd starts from VBD (Rhee Eq. 2), which
folds in the crease of a flexed joint (~0.2 % of the body voxels; --method
adaptive never adds a fold but keeps those; dense's final local repair cannot
remove them; --unfold-init repairs them first by local smoothing).  --init none starts from the identity (Rhee's Table 2
protocol).  The pose comes from `workbench pose` (--pose truth: a phantom's
true pose, for protocols such as Rhee's Table 4; never taken silently); the
stages a start needs run first when they have not.

Writes init/<scan>/ (the start) and registration/<scan>/ (correspondence.mha:
scan -> template field in mm on the scan grid, the convention of the truth
field; template_to_scan.mha and inverse_status.nii.gz, its inverse on the
template grid; registered.nii.gz; log.json) and records them in study.json,
scan by scan: an interrupted run resumes with the first unfinished scan, and
scans already registered with the same settings are skipped.  Open the field in
3D Slicer as a transform, the registered volume beside the scan.

Options left out keep the setting the stage last ran with in this study (else
the default shown), so a scan registered later is treated like the others.

examples:
  workbench register knee-study                       # all scans: polyrigid start, dense
  workbench register knee-study --scan pose01 --init none
  workbench register knee-study --preset paper --init vbd --seed 3   # Rhee as published
  workbench register knee-study --method adaptive --levels 3 5
  workbench register knee-study --dense window_mm=4 --dense refine_bones=false
  workbench register knee-study --dense default          # the dense settings' defaults again
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "register",
        help="non-rigid registration of the template to the scans (dense, or Rhee §4's locally adaptive one)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    p.add_argument(
        "--method",
        choices=["dense", "adaptive"],
        default=argparse.SUPPRESS,
        help="dense LNCC steps over the whole scan, or Rhee's Algorithm 1. Default: dense (adaptive "
        "with --preset paper)",
    )
    p.add_argument(
        "--init",
        choices=["polyrigid", "vbd", "none"],
        default=argparse.SUPPRESS,
        help="start from the bones' motions blended as a one-to-one flow, from VBD (Rhee Eq. 2), or "
        "from the identity. Default: polyrigid",
    )
    p.add_argument(
        "--unfold-init",
        default=argparse.SUPPRESS,
        action="store_true",
        help="repair the folds of the VBD initialisation in the crease of a flexed joint before "
        "registering (one-to-one wherever the map reaches into the template; ~0.1-1 mm less "
        "accurate on the knee phantom, more on the hand)",
    )
    p.add_argument(
        "--map-factor",
        type=int,
        default=argparse.SUPPRESS,
        metavar="F",
        help="integrate the polyrigid start on every F-th voxel and blend it up (exactly where the map "
        "jumps, where fingers touch): ~4x less work at F=2, 0.07 mm off on average on the test "
        "hand at 1.6 mm, 0.02 mm at 0.8 mm. Default: 1 up to 16 M voxels a grid, else the smallest F within",
    )
    p.add_argument(
        "--pose",
        choices=["estimated", "truth"],
        default=argparse.SUPPRESS,
        dest="pose_source",
        help="pose of the start: the pose stage's estimate, or a phantom's true pose (protocols). Default: estimated",
    )
    p.add_argument(
        "--preset",
        choices=["default", "paper"],
        default=argparse.SUPPRESS,
        help="--method adaptive's settings: ours (after an articulated start its 'initialised' "
        "variant), or Rhee's as published (selects --method adaptive). Default: default",
    )
    p.add_argument(
        "--levels",
        default=argparse.SUPPRESS,
        nargs=2,
        type=int,
        metavar=("FIRST", "LAST"),
        help="block levels (2**level blocks a side; level 3 = 32^3-voxel blocks on a 256^3 grid). "
        "--method adaptive only. Default: 3 4 after an articulated start, 1 4 after --init none "
        "(paper preset: 3 5)",
    )
    p.add_argument(
        "--optimizer",
        default=argparse.SUPPRESS,
        choices=["neldermead", "sbplx", "bobyqa", "cobyla"],
        help="NLopt algorithm of each local step (--method adaptive). Default: bobyqa (paper preset: neldermead)",
    )
    p.add_argument(
        "--metric",
        default=argparse.SUPPRESS,
        choices=["auto", "ssd", "mi"],
        help="--method adaptive: 'auto' is normalised MI at coarse levels, SSD from level 4 (Rhee §4.1). Default: auto",
    )
    p.add_argument(
        "--max-steps",
        default=argparse.SUPPRESS,
        type=int,
        metavar="N",
        help="local steps per level at most (--method adaptive). Default: 200",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=argparse.SUPPRESS,
        help="seed of the simplex restarts (--method adaptive; after an articulated start the default "
        "preset makes none, so the seed has no effect there; the dense method's one random choice, "
        "--dense holdout=true's noise, has its own seed: --dense holdout_seed=N). "
        "Default: 0",
    )
    p.add_argument(
        "--no-unfold-init",
        action="store_false",
        dest="unfold_init",
        default=argparse.SUPPRESS,
        help="start from the plain VBD field again after an earlier --unfold-init",
    )
    p.add_argument(
        "--dense",
        action="append",
        default=argparse.SUPPRESS,
        metavar="NAME=VALUE",
        help="a setting of the dense registration (registration.dense.DenseSettings), the value as JSON "
        "(true, 4, [200, 200, 50], null); repeatable; given, the list replaces the one the study "
        "last ran with; 'default' alone clears it",
    )
    p.add_argument(
        "--no-fix-bones",
        default=argparse.SUPPRESS,
        action="store_true",
        help="let the bones move with the soft tissue (dense: no force is zeroed on them; adaptive: no "
        "zero-displacement control points on bone voxels)",
    )
    p.add_argument("--force", action="store_true", help="register these scans again even when up to date")
    add_scale_options(p)
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.report.text import format_registration_table
    from workbench.stages.run import register_settings
    from workbench.study import read_study

    settings = register_settings(read_study(args.study), vars(args))
    force = {"init", "register"} if args.force else ()
    study, _ = run_study_stages(args, ["init", "register"], settings, force=force, scans=args.scan)
    print(format_registration_table(study, study.check_scan_ids(args.scan)))
    print(f"in {study.root / 'registration'}")
    return 0
