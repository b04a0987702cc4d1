"""``workbench phantom``: write a synthetic knee or hand study with exact ground truth."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from workbench.cli.options import add_common, positive_int

DESCRIPTION = """\
Write a synthetic study with exact ground truth: the template scan, its bone
label map, skeleton.json, N posed scans and, for every posed scan, its bone
transforms and joint angles (truth/<id>_pose.json), the dense scan-to-template
correspondence as an ITK displacement field (truth/<id>_correspondence.mha:
template position minus voxel position, mm; sitk.DisplacementFieldTransform
resamples the template onto the scan with it directly) and 12 skin markers
(truth/<id>_markers.json).  Open the .nii.gz/.mha files in 3D Slicer or
ITK-SNAP.
"""

POSES_FILE_HELP = """\
JSON file of explicit joint angles (degrees; 6-DOF joints add mm):
{"poses": [{"id": "bend10", "angles": {"knee": [10, 0, 0]}}]}.
Joints left out stay at 0; on the knee the fibula and patella follow the
knee's angles automatically. Overrides --poses.
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "phantom",
        help="write a synthetic knee or hand study with exact ground truth",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("region", choices=["knee", "hand"], help="body region")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="study folder to create")
    p.add_argument(
        "--size",
        choices=["test", "paper"],
        default="test",
        help="'test': ≤64 voxels a side, under a minute; 'paper': the papers' grids (knee "
        "255×255×123 at 1.25×1.25×1.2 mm, hand 255×255×90 at 0.78×0.78×1.0 mm; "
        "minutes). Default: test",
    )
    p.add_argument(
        "--spacing",
        metavar="MM|X,Y,Z",
        help="voxel spacing in mm (one value, or x,y,z) instead of the size's; the field of view is "
        "kept, so e.g. --size test --spacing 2.5 gives a knee of 128x128x59 voxels, between the "
        "test and paper grids",
    )
    p.add_argument(
        "--modality",
        choices=["mri", "ct"],
        default="mri",
        help="MRI-like (dark cortex, overlapping soft tissues, Rician noise, bias field) "
        "or CT-like (bright cortex, Gaussian noise, HU). Default: mri",
    )
    p.add_argument(
        "--poses",
        type=positive_int,
        metavar="N",
        help="number of posed scans (default: knee 4, straight to 70° flexion; hand 10, spread to fist)",
    )
    p.add_argument("--poses-file", type=Path, metavar="FILE", help=POSES_FILE_HELP)
    p.add_argument(
        "--posing",
        choices=["soft", "vbd"],
        default="soft",
        help="'soft': rigid bones, soft tissue blended by dual quaternions with flexor-side "
        "bulge and skin sliding (not linear blending, so a VBD initialisation leaves a "
        "residual); 'vbd': plain volume blend deformation (Rhee Eq. 2), as in Rhee's "
        "Table 2 protocol. Default: soft",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (texture, noise, jitter, markers). Default: 0")
    p.add_argument("--noise-free", action="store_true", help="no noise and no bias field (for exact-resampling checks)")
    p.add_argument(
        "--acquisition",
        choices=["fixed", "random"],
        default="fixed",
        help="'fixed': every image gets the modality's tissue intensities, noise and bias; 'random': "
        "drawn from the seed: per study a tissue-intensity table between the MRI (T1-like, bright "
        "fat) and CT (dark fat, bright cortex) ones and, without --spacing, anisotropic voxels "
        "(one axis up to 3x coarser relative to the others, same field of view); per image Rician or Gaussian "
        "noise at an SNR of 8-40 (muscle signal above air over sigma), a 0-20%% bias field, a "
        "gain of 0.9-1.1 (and a small offset with Gaussian noise). Recorded in study.json "
        "(phantom.acquisition_drawn). Default: fixed",
    )
    p.add_argument("--force", action="store_true", help="replace DIR if it exists")
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from validation.phantoms import Phantom, PhantomSpec
    from workbench.errors import InputFileError, OutputExistsError
    from workbench.stages import ORDER
    from workbench.study import summarize, write_phantom_study

    if args.out.exists() and not args.force:
        raise OutputExistsError(
            args.out, f"{args.out}: already exists; choose another --out or pass --force to replace it."
        )
    from workbench.io.inputs import read_poses_file

    poses = read_poses_file(args.poses_file) if args.poses_file else None
    try:
        spec = PhantomSpec(
            region=args.region,
            size=args.size,
            modality=args.modality,
            n_poses=args.poses,
            posing=args.posing,
            seed=args.seed,
            noise=not args.noise_free,
            poses=poses,
            spacing=_spacing(args.spacing),
            acquisition=args.acquisition,
        )
        phantom = Phantom(spec)
    except ValueError as e:
        if args.poses_file:
            raise InputFileError(f"{args.poses_file}: {e}", args.poses_file) from e
        raise
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(
            total=len(phantom.poses) + 1, desc=f"{args.region} phantom ({args.size})", unit="image", file=sys.stderr
        )
    t0 = time.perf_counter()

    def progress(stage, done, total):
        if bar is not None:
            bar.update(1)

    try:
        study = write_phantom_study(phantom, args.out, overwrite=args.force, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    if not args.quiet:
        print(f"wrote {args.out} in {time.perf_counter() - t0:.1f} s")
        print(summarize(study, ORDER))
    return 0


def _spacing(text):
    """``--spacing``: one value (mm) for every axis, or x,y,z."""
    if text is None:
        return None
    try:
        v = tuple(float(t) for t in text.split(","))
    except ValueError:
        v = ()
    if len(v) == 1:
        v = v * 3
    if len(v) != 3 or not all(x > 0 for x in v):
        raise ValueError(f"--spacing {text!r}: expected one positive number (mm) or three, x,y,z")
    return v
