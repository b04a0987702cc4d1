"""``workbench surface``: Kurihara's consistent skin meshes of the template and every scan (the surface stage)."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common, add_scale_options
from workbench.cli.running import read_output, run_study_stages

DESCRIPTION = """Kurihara's consistent skin meshes (Kurihara & Miyata 2004, §3-4).

The template's skin becomes the base mesh S0 (an isosurface between air and
tissue, cleaned of debris, decimated to --target-triangles; the paper's
hand: ~100k).  For each scan: S0 posed by SSD with the scan's estimated bone
transforms (Kurihara Eq. 2-3), moved by RBF feature points (Kurihara Eq. 4-5:
--features registration takes their targets from `workbench register`'s map
of the template onto the scan, --features closest from confident closest
points on the scan's skin, --landmarks FILE from points picked on the
template's and each scan's skin, as the paper did: 70-150 per pose), then fitted to the scan's
skin: --fit regularised (default) follows the skin where it is seen and keeps
the mesh's shape where it is not (fingers touching), --fit nearest is the
paper's nearest-point fit.  Every fitted mesh has S0's connectivity, so
`workbench surface-deform` interpolates them to any pose (SSD, PSD, WPSD).

Writes surface/template_skin.vtp (with the vertices' skinning weights),
surface/template_bones.vtp, and per scan <scan>_skin.ply, _ssd.ply, _rbf.ply
and _fitted.ply (world mm: they open in ParaView and 3D Slicer), and
surface/surface.json.  Runs the stages it needs first (weights, pose, and
register for --features registration).

Example:
  workbench surface hand-study
  workbench surface hand-study --fit nearest --force
  workbench surface hand-study --landmarks picked.csv
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "surface",
        help="Kurihara's consistent skin meshes of the template and every scan",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json)")
    p.add_argument(
        "--target-triangles",
        type=int,
        default=argparse.SUPPRESS,
        metavar="N",
        help="decimate S0 and the scans' skins to about N triangles. Default: 100000",
    )
    p.add_argument(
        "--features",
        choices=["registration", "closest", "landmarks"],
        default=argparse.SUPPRESS,
        help="targets of the RBF feature points. Default: registration (landmarks with --landmarks)",
    )
    p.add_argument(
        "--landmarks",
        type=Path,
        default=argparse.SUPPRESS,
        metavar="FILE",
        help="landmark pairs picked on the template's skin and each scan's (JSON "
        '{"format": "avw-landmarks", "scans": {id: [{"template": [x,y,z], "scan": [x,y,z]}]}} or '
        "CSV scan,template_x,template_y,template_z,scan_x,scan_y,scan_z; mm): every one is a "
        "feature point",
    )
    p.add_argument(
        "--features-count",
        dest="n_features",
        type=int,
        default=argparse.SUPPRESS,
        metavar="N",
        help="feature points per scan, spread over S0. Default: 150",
    )
    p.add_argument(
        "--fit",
        choices=["regularised", "nearest"],
        default=argparse.SUPPRESS,
        help="the fit to the scan's skin. Default: regularised",
    )
    p.add_argument(
        "--stiffness",
        type=float,
        default=argparse.SUPPRESS,
        help="the regularised fit's weight on keeping the mesh's shape. Default: 1",
    )
    p.add_argument("--scan", action="append", metavar="ID", help="only this scan (repeatable; default: all)")
    p.add_argument("--force", action="store_true", help="rerun even when up to date")
    add_scale_options(p)
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.stages.run import surface_settings
    from workbench.study import read_study

    ss = surface_settings(read_study(args.study), vars(args))
    study, out = run_study_stages(args, ["surface"], {"surface": ss}, force={"surface"} if args.force else ())
    doc = read_output(study, "surface", "surface.json")
    t = doc["template"]
    print(
        f"S0: {t['triangles']} triangles, {t['vertices']} vertices (weights: {t['weights']})"
        f"{' (up to date)' if out[-1].status == 'skipped' else ''}"
    )
    for sid, r in doc["per_scan"].items():
        f = r["fit_distance_mm"]
        print(
            f"  {sid}: {r['features']} feature points ({r['feature_source']}), {r['fit']} fit: distance to the "
            f"scan's skin mean {f['mean']:.2f} mm, P95 {f['p95']:.2f} mm"
        )
    print(f"in {study.root / 'surface'}")
    return 0
