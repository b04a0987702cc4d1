"""``workbench weights``: skinning weights of every template voxel (the weights stage)."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common, positive_int
from workbench.cli.running import run_study_stages

DESCRIPTION = """Skinning weights for every template voxel (Kurihara Eq. 3).

'harmonic' (default): the body is segmented from the template and filled
with tetrahedra on a lattice of its voxel centres (each cube that is mostly
body cut into 6 Kuhn tetrahedra; every voxel, or every few voxels above 150 k
vertices, or --edge-length-mm), and each bone's weight solved as the harmonic
function that is 1 on that bone and 0 on the others (P1 finite elements, one
sparse LU); voxels take the barycentric interpolation of the vertex weights,
bones are one-hot, at most 4 influences per voxel.  The mesh is written to
skinning/tetmesh.vtu, with each bone's weight as a point array for ParaView.
'distance': inverse-distance weights on each voxel's distance to the bones
(fast; a fallback and a comparison).

Writes skinning/weights.json with weights_index.mha and weights_value.mha
(4-component images on the template grid) and skinning/body_mask.nii.gz.
A template of more than 60 M voxels (a CT the size of Kurihara's, 512×512×750)
gets its weights and body mask on every 2nd (3rd, ...) voxel along each axis
instead, which keeps the stage and `workbench deform` within 8 GiB: deform
then solves its maps on that grid and pulls the full-resolution template
through them (VBD only: register after a VBD start, model and validate need --grid-factor 1).
Options left out keep the setting the stage last ran with in this study
(else the default shown); an up-to-date stage is skipped.
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "weights",
        help="skinning weights of every template voxel (harmonic on a tet mesh)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument(
        "--method",
        choices=["harmonic", "distance"],
        default=argparse.SUPPRESS,
        help="'harmonic' (tet mesh + Laplace solve) or 'distance' (inverse distance). Default: harmonic",
    )
    p.add_argument(
        "--edge-length-mm",
        default=argparse.SUPPRESS,
        type=float,
        metavar="MM",
        help="spacing of the tet lattice in mm, rounded to whole voxels along each axis (default: every "
        "voxel, or every 2nd, 3rd, ... when that would make more than 150 k vertices)",
    )
    p.add_argument(
        "--grid-factor",
        type=positive_int,
        default=argparse.SUPPRESS,
        metavar="F",
        help="weights on every F-th template voxel along each axis (F³ fewer voxels and bytes). "
        "Default: 1, or the smallest F that leaves at most 60 M voxels",
    )
    p.add_argument("--force", action="store_true", help="rerun even when up to date")
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.stages.run import weights_settings
    from workbench.study import read_study

    ws = weights_settings(read_study(args.study), vars(args))
    study, out = run_study_stages(args, ["weights"], {"weights": ws}, force={"weights"} if args.force else ())
    e = study.stage_entry("weights")
    when = "up to date" if out[-1].status == "skipped" else f"{e['seconds']:.1f} s"
    print(f"{e['settings']['method']} weights ({when}); in {study.root / 'skinning'}")
    return 0
