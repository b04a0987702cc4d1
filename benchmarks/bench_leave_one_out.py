"""Leave one scan out, with the model built the way a user builds it: registrations and estimated poses.

For each case (test-size phantoms by default) a study is written and run
through the pipeline's stages (``workbench run``: bones, pose, weights,
init, register; the truth is hidden from them).  Then, for each scan ``k``,
an EVD model (Rhee Eq. 7) is built from the *other* scans' registrations
(their inverse fields, VBD where a voxel left the scan) and *estimated*
poses, and the held-out scan is predicted at its estimated pose by EVD
(Rhee Eq. 6) and by VBD (Rhee Eq. 2).  Both are compared with the scan's
true forward map over the template's body voxels (MED, mm) and by the
correlation of the posed template with the scan (CC, whole grid)
(:func:`validation.leave_one_out.leave_one_out_correspondences`), and how the model's expected error at
the held-out pose (its scans' registration σ blended, and the cross-validated interpolation's) predicts
the true error (within 2σ, RMS error / RMS σ, rank correlation, over the body).  The same
table with models built from the *truth* (exact correspondences, true
poses) shows what the model itself can do.

    python benchmarks/bench_leave_one_out.py [--cases knee hand] [--size test] [--seed 0] [--out DIR]
    python benchmarks/bench_leave_one_out.py --cases hand --spacing 0.8 --n-poses 6   # a phalanx >= 5 voxels across

Each case prints how many voxels its thinnest bone is across (2 x its deepest voxel's distance - 1): at the
test size's 1.6 mm a phalanx is 2-3 voxels, too few for a registration to hold it (5 or more are wanted).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from validation.leave_one_out import (
    leave_one_out_correspondences,
    registration_training_positions,
    registration_training_sigma,
)
from validation.phantoms import make_phantom
from workbench.stages.run import run_stages
from workbench.study import write_phantom_study


def _say(event):
    if event.kind in ("start", "done", "message"):
        print(f"  {event.message}", flush=True)


def thinnest_bone_voxels(labels) -> float:
    """Voxels across the thinnest bone of a label volume, at its thickest point (2 x deepest distance - 1)."""
    from scipy import ndimage

    lab = np.asarray(labels.data)
    out = []
    for b, box in enumerate(ndimage.find_objects(lab), start=1):
        if box is not None:
            out.append(2.0 * float(ndimage.distance_transform_edt(np.pad(lab[box] == b, 1)).max()) - 1.0)
    return min(out) if out else float("nan")


def run_case(case: str, size: str, seed: int, out: Path, spacing=None, n_poses=None) -> list[tuple]:
    from workbench.study import read_study

    if (out / case / "study.json").exists():  # a study from an earlier run: its stages skip what is up to date
        study = read_study(out / case)
    else:
        kw = {
            k: v
            for k, v in (("spacing", None if spacing is None else (spacing,) * 3), ("n_poses", n_poses))
            if v is not None
        }
        study = write_phantom_study(make_phantom(case, size=size, seed=seed, **kw), out / case)
    print(
        f"{case}: {study.template().geometry.describe()}; thinnest bone "
        f"{thinnest_bone_voxels(study.template_labels()):.1f} voxels across",
        flush=True,
    )
    t0 = time.perf_counter()
    run_stages(study, ["bones", "pose", "weights", "init", "register"], progress=_say)
    print(f"{case}: pipeline {time.perf_counter() - t0:.1f} s", flush=True)
    study.reload()
    weights, body = study.weights()
    template, sk = study.template(), study.skeleton()
    ids = study.scan_ids
    g = template.geometry
    est_poses, reg_pos, reg_sigma = {}, {}, {}
    for sid in ids:
        est_poses[sid], reg_pos[sid], found = registration_training_positions(study, sid, g, weights)
        reg_sigma[sid] = registration_training_sigma(study, sid, reg_pos[sid], found)
    if any(v is None for v in reg_sigma.values()):
        reg_sigma = None  # a registration without its expected error: the model's is the cross-validation's alone
    true_poses = {sid: study.truth_pose(sid) for sid in ids}
    true_pos = {sid: study.truth_template_to_scan(sid).data + g.world_coordinates() for sid in ids}
    images = {sid: study.scan(sid) for sid in ids}
    rows = []
    for label, poses, pos, sig in (
        ("registrations + estimated poses", est_poses, reg_pos, reg_sigma),
        ("truth (exact correspondences, true poses)", true_poses, true_pos, None),
    ):
        res = leave_one_out_correspondences(
            template, weights, body, sk, poses, pos, true_pos, images=images, sigmas=sig
        )
        rows.append((case, label, res))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=["knee", "hand"], choices=["knee", "hand"])
    ap.add_argument("--size", choices=["test", "paper"], default="test")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--spacing", type=float, help="isotropic voxel size of the phantoms, mm (default: the size's)")
    ap.add_argument("--n-poses", type=int, help="scans per phantom (default: the case's)")
    ap.add_argument(
        "--out",
        type=Path,
        help="where the studies are written (default: a temporary folder); studies "
        "already there are reused, their stages rerun only where out of date",
    )
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="avw-loo-"))
    out.mkdir(parents=True, exist_ok=True)
    table = []
    for case in args.cases:
        table += run_case(case, args.size, args.seed, out, args.spacing, args.n_poses)
    print(
        "\n| case | model from | held-out scan | MED VBD mm | MED EVD mm | CC VBD | CC EVD | EVD wins (MED) | "
        "sigma: within 2 / RMS ratio / rank |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for case, label, res in table:
        for r in res:
            c = r.calibration or {}
            cal = " / ".join(
                "-" if c.get(k) is None else f"{c[k]:.2f}" for k in ("within_2sigma", "rms_ratio", "spearman")
            )
            print(
                f"| {case} | {label} | {r.scan} | {r.med_vbd:.2f} | {r.med_evd:.2f} | {r.cc_vbd:.3f} | "
                f"{r.cc_evd:.3f} | {'yes' if r.med_evd < r.med_vbd else 'no'} | {cal} |"
            )
        mv, me = np.mean([r.med_vbd for r in res]), np.mean([r.med_evd for r in res])
        cv, ce = np.mean([r.cc_vbd for r in res]), np.mean([r.cc_evd for r in res])
        print(
            f"| {case} | {label} | mean | {mv:.2f} | {me:.2f} | {cv:.3f} | {ce:.3f} | "
            f"{sum(r.med_evd < r.med_vbd for r in res)}/{len(res)} | |"
        )
    print(f"studies in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
