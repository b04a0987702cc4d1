"""``workbench pose``: bone poses, joint centres and joint angles of a study's scans (the pose stage)."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_bones_options, add_common, add_scale_options, positive_int
from workbench.cli.running import run_study_stages

DESCRIPTION = """\
Recover every bone's rigid transform in every scan, then each joint's centre
of rotation and each scan's joint angles (Rhee §3.1, Kurihara §3).

Bones are registered root first, then down the skeleton: each child starts
from its parent's transform, a grid search over rotations about the joint
picks the start, and the bone is refined by intensity (Rhee Eq. 1) or by
surfaces (Kurihara's ICP).  Each joint's centre minimises Kurihara Eq. 1
(Σ|M c − c|², closed form, with a quasi-Newton cross-check); joints that only
flex (a hinge) get an axis, and the centre is put on it nearest the bones'
contact.  Angles are intrinsic XYZ in the skeleton's joint frame (degrees).

Writes poses/<scan>_pose.json (the same schema as the phantoms' truth),
joints.json, fits.json (per bone: status, metric, iterations) and
report.txt into the study, and records them in study.json.  Bones that leave
the field of view, do not converge or match poorly are listed, with the scan
and the metric.  The pose stage never reads a phantom's ground truth:
`workbench validate` compares the poses with it.  With --seeds the bones
stage first segments the template's bones (bones/template_labels.nii.gz,
used by every later stage).

Like every stage command it skips work that is up to date (same images,
labels and settings).  Options left out keep the setting the stage last ran
with in this study (else the default shown), so every scan of a study is
treated alike; --scan chooses this run's scans only.

Seeds file for --seeds:
  {"format": "avw-seeds", "version": 1, "units": "mm",
   "seeds": {"femur": [[x, y, z]], "tibia": [[x, y, z]], ...}}
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "pose",
        help="recover bone poses, joint centres and joint angles of a study's scans",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument(
        "--method",
        choices=["intensity", "surface"],
        default=argparse.SUPPRESS,
        help="'intensity': Rhee Eq. 1, the bone region's intensities (SimpleITK, then a least-squares "
        "polish); 'surface': Kurihara §3, ICP of bone isosurfaces (VTK flying edges + Open3D). "
        "Default: intensity",
    )
    add_bones_options(p)
    p.add_argument(
        "--init",
        default=argparse.SUPPRESS,
        metavar="identity|moments|FILE",
        help="root bone's starting pose: 'identity' (scans share the template's scanner frame), "
        "'moments' (align the images' centres of mass), or a JSON file (an avw-pose file, or "
        "{'format': 'avw-initial-poses', 'version': 1, 'scans': {id: 4x4}}). Default: identity",
    )
    p.add_argument(
        "--scan",
        action="append",
        metavar="ID",
        help="only this scan (repeatable; default: all — Kurihara Eq. 1 pools the scans estimated)",
    )
    p.add_argument(
        "--metric",
        choices=["ncc", "ssd"],
        default=argparse.SUPPRESS,
        help="cost of the coarse search and the polish: 'ssd' is Rhee Eq. 1 as printed; 'ncc' is Rhee Eq. 1 "
        "after the best linear intensity map per bone (insensitive to an MRI bias field). "
        "Default: ncc",
    )
    p.add_argument(
        "--interpolation",
        choices=["linear", "bspline"],
        default=argparse.SUPPRESS,
        help="'linear' is the papers' trilinear; 'bspline' (cubic) leaves a residual about 4x smaller "
        "for a rotated bone on coarse grids. Default: bspline",
    )
    p.add_argument(
        "--prior-deg",
        type=float,
        default=argparse.SUPPRESS,
        metavar="DEG",
        help="width (degrees) of the weak prior tying each bone's rotation to its hierarchical "
        "initialisation (the translation prior is 2 mm; with --method surface, combined with "
        "the ICP fit); 0 turns it off (plain Rhee Eq. 1 through SimpleITK, plain ICP). Default: 2",
    )
    p.add_argument(
        "--margin-mm",
        default=argparse.SUPPRESS,
        type=float,
        metavar="MM",
        help="dilation of each bone's region for the intensity cost (Rhee: 'slightly dilated'); "
        "default one voxel, at least 2 mm.  Smaller keeps non-rigid soft tissue out on fine grids",
    )
    p.add_argument(
        "--bias-correction",
        choices=["auto", "on", "off"],
        default=argparse.SUPPRESS,
        help="N4 bias-field correction of template and scans before registration; 'auto' does it "
        "for MRI-like images. Default: auto",
    )
    p.add_argument(
        "--min-ncc",
        type=float,
        default=argparse.SUPPRESS,
        help="a bone whose final correlation with the template is lower is reported as a poor match. Default: 0.5",
    )
    p.add_argument(
        "--max-joint-gap-mm",
        type=float,
        default=argparse.SUPPRESS,
        metavar="MM",
        help="a bone whose joint centre (from skeleton.json) lands farther than this from where its "
        "parent puts it has left its joint and is reported as 'joint_detached'; raise it for a "
        "rough skeleton, 0 switches the check off. Default: 10",
    )
    p.add_argument(
        "--outlier-factor",
        type=float,
        default=argparse.SUPPRESS,
        metavar="K",
        help="Kurihara Eq. 1 consistency check: with 4 or more scans, a bone whose motion misses its joint's "
        "centre (estimated from all scans) by more than K times the joint's median miss, and by "
        "more than half a voxel, is reported as 'joint_outlier'; 0 switches the check off. "
        "Default: 4",
    )
    p.add_argument(
        "--grid-factor",
        type=positive_int,
        default=argparse.SUPPRESS,
        metavar="F",
        help="register the bones on every F-th voxel along each axis of the template and scans "
        "(smoothed first; F³ fewer voxels and bytes, about F times coarser). Default: 1, or the "
        "smallest F that leaves at most 60 M voxels (2 for a 512×512×750 CT)",
    )
    p.add_argument("--force", action="store_true", help="rerun even when up to date")
    add_scale_options(p)
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.stages.run import pose_settings
    from workbench.study import read_study

    settings = pose_settings(read_study(args.study), vars(args))
    study, _ = run_study_stages(args, ["pose"], settings, force={"pose"} if args.force else ())
    print(study.pose_report()["text"])
    if any(study.has_truth(sid) for sid in study.scan_ids):
        print(f"\n(accuracy against the ground truth: `workbench validate {study.root}`)")
    print(f"\nwrote {study.root / 'poses'} and updated {study.manifest_path}")
    return 0
