"""Kurihara's surface model: the consistent-mesh fits and SSD / PSD / WPSD per pose, beside the paper's times.

    .venv/bin/python benchmarks/bench_surface.py [--triangles 100000] [--repeat 5]

Kurihara & Miyata 2004 (§4–5, a 2.2 GHz Pentium IV): RBF fitting 1.0 s and
the final nearest-point fitting 9.0 s per pose (§4), PSD ("the shape
interpolation", Fig. 9) 62 ms and WPSD (Fig. 10) 157 ms per pose on their
~100 k-triangle skin (§2: "about 800,000" triangles, decimated).

Here, in one run, on the CT-like hand phantom's skin decimated to
``--triangles`` (Open3D's quadric simplification of the phantom's true skin,
the template's and each pose's; the same meshes the ``surface`` stage would
fit, without the scans' noise): for each of the 5 poses of the ``kurihara``
protocol, the RBF feature-point deformation (Kurihara Eq. 4–5, 150 feature
points, its solve and its evaluation at every vertex), the nearest-point fit
(Open3D's ray-casting scene built and queried) and the regularised fit; then
the model of the 5 fitted meshes (+ S0 at rest) deformed by SSD, PSD and
WPSD to each pose.  Skinning weights: distance weights (Kurihara set them by
hand; the timing depends on the bones per vertex, not on where the weights
come from).  Times are the best of ``--repeat`` after a warm-up (numba
compilation excluded), threads as the machine has; the ratios WPSD / PSD
and PSD / SSD come from the same run.  Never asserts times.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from timing import best_of  # benchmarks/timing.py

PAPER = {"rbf": 1.0, "nearest": 9.0, "psd": 0.062, "wpsd": 0.157}  # seconds per pose, Kurihara §4, §5.1–5.2


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--triangles", type=int, default=100_000, help="triangles of S0 and each pose's skin")
    ap.add_argument("--repeat", type=int, default=5, help="best of this many timed calls (after a warm-up)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if a.triangles < 1000 or a.repeat < 1:
        ap.error("--triangles must be at least 1000 and --repeat at least 1")

    from deformation.fields.splines import KURIHARA_D_MM, RBFDeformation
    from deformation.meshes.isosurface import decimate
    from deformation.meshes.mesh import SurfaceMesh
    from deformation.models.skinning import distance_weights, lbs
    from deformation.models.surface_model import SurfaceModel
    from registration.surface_fit import (
        confident_targets,
        farthest_points,
        fit_nearest,
        fit_regularised,
        raycasting_scene,
        triangle_normals,
        vertex_normals,
    )
    from validation.phantoms import Phantom, PhantomSpec
    from validation.protocols.kurihara import PHANTOM
    from validation.surface_measures import posed_truth, true_skin

    t0 = time.perf_counter()
    ph = Phantom(PhantomSpec(size="test", seed=a.seed, spacing=(1.6, 1.6, 1.6), **PHANTOM))
    sk = ph.skeleton
    # the true skin on a 0.8 mm grid has ~180 k triangles; decimated to the paper's ~100 k
    fine = true_skin(ph, refine=2.0)
    base = decimate(fine, a.triangles)
    bones = tuple(sk.bone_names)
    d = ph.anatomy.distances_fast(base.vertices)[:, : len(bones)]
    weights = distance_weights(d, bones)
    targets = {
        pid: decimate(SurfaceMesh(posed_truth(ph, ang, fine.vertices), fine.triangles), a.triangles)
        for pid, ang in ph.poses
    }
    poses = {pid: ph.pose_of(ang) for pid, ang in ph.poses}
    print(
        f"CT hand phantom skin: S0 {base.n_triangles} triangles, {base.n_vertices} vertices; {len(poses)} poses; "
        f"set-up {time.perf_counter() - t0:.0f} s; {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}"
    )

    rows = {k: [] for k in ("rbf", "nearest", "regularised")}
    fitted = {}
    for pid, target in targets.items():
        ssd = SurfaceMesh(lbs(base.vertices, weights, poses[pid].transforms), base.triangles)
        tgt, has = confident_targets(
            ssd.vertices,
            vertex_normals(ssd.vertices, ssd.triangles),
            target,
            raycasting_scene(target),
            triangle_normals(target.vertices, target.triangles),
            5.0,
            np.cos(np.deg2rad(60.0)),
        )
        idx = farthest_points(base.vertices, 150, candidates=has)

        def rbf_fit():  # Kurihara Eq. 4–5: solve for the 150 points' coefficients, evaluate at every vertex
            r = RBFDeformation(ssd.vertices[idx], tgt[idx], D=KURIHARA_D_MM)
            return SurfaceMesh(r(ssd.vertices), base.triangles)

        t_rbf, rbf = best_of(rbf_fit, a.repeat)
        t_near, _ = best_of(lambda: fit_nearest(rbf, target), a.repeat)
        t_reg, res = best_of(lambda: fit_regularised(rbf, target), max(1, a.repeat // 2))
        fitted[pid] = res.mesh
        rows["rbf"].append(t_rbf)
        rows["nearest"].append(t_near)
        rows["regularised"].append(t_reg)
        print(
            f"  {pid:9s} RBF {t_rbf:7.3f} s   nearest {t_near:7.3f} s   regularised {t_reg:7.3f} s "
            f"({res.info.get('cg_iterations')} CG iterations)"
        )

    model = SurfaceModel.from_meshes(base, weights, sk, list(poses.values()), list(fitted.values()))
    deform = {m: [] for m in ("ssd", "psd", "wpsd")}
    for _pid, pose in poses.items():
        for m in deform:
            model.deform(pose, m)  # warm-up: numba compilation, WPSD's per-vertex Φ⁻¹
            deform[m].append(best_of(lambda: model.deform(pose, m), a.repeat)[0])
    ssd_t, psd_t, wpsd_t = (float(np.mean(deform[m])) for m in ("ssd", "psd", "wpsd"))
    print(
        f"\nper pose (mean of {len(poses)} poses; best of {a.repeat}), {base.n_triangles} triangles, "
        f"{model.n_examples} examples:"
    )
    print(f"{'':28s}{'ours':>10s}{'paper':>10s}{'ours / paper':>14s}")
    for label, key, ours in (
        ("RBF fit (Kurihara Eq. 4-5)", "rbf", np.mean(rows["rbf"])),
        ("nearest-point fit", "nearest", np.mean(rows["nearest"])),
        ("regularised fit", None, np.mean(rows["regularised"])),
        ("SSD (Kurihara Eq. 2)", None, ssd_t),
        ("PSD (Kurihara Eq. 7-8)", "psd", psd_t),
        ("WPSD (Kurihara Eq. 16)", "wpsd", wpsd_t),
    ):
        p = PAPER.get(key)
        print(f"{label:28s}{ours * 1e3:8.1f}ms" + (f"{p * 1e3:8.0f}ms{ours / p:14.3f}" if p else ""))
    print(
        f"\nWPSD / PSD = {wpsd_t / psd_t:.2f} (paper {PAPER['wpsd'] / PAPER['psd']:.2f}); "
        f"PSD / SSD = {psd_t / ssd_t:.2f}"
    )


if __name__ == "__main__":
    main()
