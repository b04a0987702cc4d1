"""``workbench surface-deform``: pose Kurihara's surface model (SSD, PSD or WPSD) and write the skin mesh."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common

DESCRIPTION = """Pose Kurihara's surface model (workbench surface's meshes) and write the skin.

--method ssd: S0 skinned by the pose's bone transforms (Kurihara Eq. 2);
psd: the scans' meshes taken back to the base pose (Kurihara Eq. 6), blended
with one set of RBF weights of the pose (Kurihara Eq. 7, 12-14), then skinned
(Kurihara Eq. 8); wpsd: the blend weighted per vertex by its bones' joints
(Kurihara Eq. 16), so each finger follows its own joints.  POSE.json: joint angles or bone transforms (as for
`workbench deform`).

Example:
  workbench surface-deform hand-study --pose fist.json --method wpsd --out fist.ply
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "surface-deform",
        help="pose the surface model (SSD, PSD or WPSD) and write the skin mesh",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json, after `workbench surface`)")
    p.add_argument("--pose", required=True, type=Path, metavar="POSE.json", help="target pose")
    p.add_argument(
        "--method",
        choices=["ssd", "psd", "wpsd"],
        default="wpsd",
        help="SSD (Kurihara Eq. 2), PSD (Kurihara Eq. 6-8) or WPSD (Kurihara Eq. 16). Default: wpsd",
    )
    p.add_argument("--out", required=True, type=Path, metavar="MESH", help="output mesh (.ply, .vtp, .obj, .stl)")
    p.add_argument("--force", action="store_true", help="overwrite --out")
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.deform import surface_deform

    s = surface_deform(args.study, args.pose, args.out, method=args.method, overwrite=args.force)
    print(f"{args.method.upper()}: {s['vertices']} vertices in {s['seconds']:.3f} s; wrote {s['out']}")
    return 0
