"""Deformation benchmarks: EVD and VBD with resampling on the paper-size hand grid; PSD and WPSD on a mesh.

Prints times measured in one run and their ratios (never asserted; the
machine is shared):

* volume, on the paper-size hand grid (255×255×90 at 0.78×0.78×1.0 mm) with
  10 example poses taken from the phantom's ground truth (Rhee Eq. 7):
  - the memory floor: one NumPy sum over every array the EVD step reads
    (template, voxel weights, example displacements);
  - one ``scipy.ndimage.map_coordinates`` trilinear pass of the grid (the
    naive baseline);
  - VBD + resample and EVD + resample (Rhee Eq. 2 and 6, forward pass, then
    the backward map and the trilinear pull), and their ratios to the floor;
    also EVD with per-voxel WPSD weights (Kurihara Eq. 16);
  - the process's peak resident memory.
* mesh, 50k vertices with 5 example poses: LBS (Kurihara Eq. 2), PSD
  (Eq. 6–8, 12–15) and WPSD (Eq. 16), all compiled kernels on the same
  threads, and the ratios PSD/LBS and WPSD/LBS.

Usage::

    .venv/bin/python benchmarks/deformation.py            # paper-size hand (a few minutes, ~6 GB)
    .venv/bin/python benchmarks/deformation.py --size test
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from timing import best_of  # noqa: E402  (benchmarks/timing.py)

from deformation.geometry import Volume  # noqa: E402
from deformation.evd import ExampleVolumeDeformation, vbd_forward  # noqa: E402
from deformation.posespace import PoseSpace, psd_training, skin, wpsd_deform  # noqa: E402
from deformation.resample import backward_map, resample_forward  # noqa: E402
from deformation.skinning import distance_weights, lbs, stack_transforms  # noqa: E402
from validation.phantoms import make_phantom  # noqa: E402


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def volume_benchmark(size: str, n_poses: int, repeats: int, weights_kind: str):
    from scipy import ndimage

    t0 = time.perf_counter()
    ph = make_phantom("hand", size=size, modality="mri", n_poses=n_poses + 1, seed=5)
    g = ph.geometry
    x = g.world_coordinates().reshape(-1, 3)
    print(f"grid {g.size[0]}×{g.size[1]}×{g.size[2]} = {g.n_voxels:,} voxels at "
          f"{'×'.join(f'{s:.2f}' for s in g.spacing)} mm; {n_poses} example poses + 1 query pose")
    template = ph.template()[0].data.astype(np.float32)
    d = ph.anatomy.distances_fast(x)
    body = (d[:, -1] < 0).reshape(g.array_shape)
    if weights_kind == "distance":
        w = distance_weights(d[:, :-1], ph.skeleton.bone_names)
    else:
        raise SystemExit("only --weights distance is wired here")
    del d
    poses, fields = [], []
    for pid, ang in ph.poses[:n_poses]:
        poses.append(ph.pose_of(ang))
        fields.append(ph.posing_model(ang).forward(x).reshape(g.array_shape + (3,)).astype(np.float32))
    query = ph.pose_of(ph.poses[n_poses][1])
    model = ExampleVolumeDeformation.from_correspondences(g, w, ph.skeleton, poses, fields)
    del fields
    print(f"set-up (phantom, weights, ground truth of {n_poses} poses, Eq. 7): {time.perf_counter() - t0:.1f} s")
    t = stack_transforms(query.transforms, w.bones)

    def floor():
        return (float(template.sum()) + float(w.index.sum(dtype=np.uint64)) + float(w.value.sum())
                + float(model.displacements.sum()))

    nbytes = template.nbytes + w.index.nbytes + w.value.nbytes + model.displacements.nbytes
    t_floor, _ = best_of(floor, repeats)

    template_volume = Volume(template, g)

    def vbd():
        fwd = vbd_forward(g, w, t)
        bm = backward_map(fwd, g, transforms=t, prefer=body)
        return resample_forward(bm, template_volume), bm

    def evd(weighting="psd"):
        fwd = model.forward(query, weighting=weighting)
        bm = backward_map(fwd, g, transforms=t, prefer=body)
        return resample_forward(bm, template_volume), bm

    # warm-up (numba compilation is cached on disk, but the first call still loads it)
    evd()
    t_vbd, (vol_vbd, bm_vbd) = best_of(vbd, repeats)
    t_evd, (vol_evd, bm_evd) = best_of(evd, repeats)
    t_fwd, _ = best_of(lambda: model.forward(query), repeats)
    t_wpsd, _ = best_of(lambda: evd("wpsd"), 1)
    coords = np.moveaxis(bm_evd.template_index[..., ::-1], -1, 0).astype(np.float32)  # (k, j, i) for scipy
    t_scipy, _ = best_of(lambda: ndimage.map_coordinates(template, coords, order=1, mode="constant"), repeats)
    summ = bm_evd.summary()
    print(f"memory floor (one NumPy sum over {nbytes / 2**20:,.0f} MiB: template, weights, "
          f"{n_poses} example fields): {t_floor * 1e3:8.1f} ms")
    print(f"naive: one scipy map_coordinates trilinear pass of the grid:           {t_scipy * 1e3:8.1f} ms")
    print(f"VBD + resample:                                                        {t_vbd * 1e3:8.1f} ms"
          f"   ratio to floor {t_vbd / t_floor:5.2f}")
    print(f"EVD + resample (Rhee Eq. 6, normalised RBF pose weights):             {t_evd * 1e3:8.1f} ms"
          f"   ratio to floor {t_evd / t_floor:5.2f}   (forward pass alone {t_fwd * 1e3:.1f} ms, "
          f"{t_fwd / t_floor:.2f}× floor)")
    print(f"EVD + resample with per-voxel WPSD weights (Kurihara Eq. 16):          {t_wpsd * 1e3:8.1f} ms"
          f"   ratio to floor {t_wpsd / t_floor:5.2f}")
    print(f"EVD + resample vs the naive scipy pass: {t_evd / t_scipy:.2f}×;  Rhee's EVD took 3.5 s on this grid")
    print(f"backward map of the EVD pose: {summ['n_ok']:,} ok, {summ['n_folded']:,} folded, "
          f"{summ['n_not_converged']:,} not converged, {summ['n_outside']:,} outside the template; "
          f"max residual {summ['max_residual_mm']:.2e} mm")
    print(f"peak resident memory of the process: {peak_rss_gb():.2f} GiB")
    del vol_vbd, vol_evd, bm_vbd


def mesh_benchmark(n_vertices: int, n_poses: int, repeats: int):
    ph = make_phantom("hand", size="test", modality="mri", n_poses=n_poses + 1, seed=5)
    sk = ph.skeleton
    rng = np.random.default_rng(0)
    # vertices near the skin: body-surface samples of the analytic hand, jittered
    lo = np.array(ph.geometry.origin) - 10
    hi = lo + np.array(ph.geometry.extent_mm) + 20
    pts = []
    while sum(len(p) for p in pts) < n_vertices:
        cand = rng.uniform(lo, hi, (400_000, 3))
        dist = ph.anatomy.distances_fast(cand)
        pts.append(cand[np.abs(dist[:, -1]) < 1.0])
    v = np.concatenate(pts)[:n_vertices]
    w = distance_weights(ph.anatomy.distances_fast(v)[:, :-1], sk.bone_names)
    poses = [ph.pose_of(a) for _, a in ph.poses[:n_poses]]
    query = ph.pose_of(ph.poses[n_poses][1])
    samples = [ph.posing_model(a).forward(v) for _, a in ph.poses[:n_poses]]
    base = np.ascontiguousarray(psd_training(samples, w, [p.transforms for p in poses]).transpose(1, 0, 2))
    space = PoseSpace(sk, poses)
    t0 = time.perf_counter()
    pts_space = space.point_space(w)
    t_pre = time.perf_counter() - t0
    t = stack_transforms(query.transforms, w.bones)
    skin(v, w, t)
    skin(base, w, t, space.weights(query))
    wpsd_deform(base, w, pts_space, query, t)
    t_lbs, _ = best_of(lambda: skin(v, w, t), repeats * 3)
    t_np, _ = best_of(lambda: lbs(v, w, t), repeats)
    t_psd, _ = best_of(lambda: skin(base, w, t, space.weights(query)), repeats * 3)
    t_wpsd, _ = best_of(lambda: wpsd_deform(base, w, pts_space, query, t), repeats * 3)
    print(f"mesh: {n_vertices:,} vertices near the hand phantom's skin, {n_poses} example poses "
          f"({sk.n_dof} DOF)")
    print(f"LBS (compiled):  {t_lbs * 1e3:7.2f} ms   (NumPy LBS {t_np * 1e3:.2f} ms)")
    print(f"PSD:             {t_psd * 1e3:7.2f} ms   ratio PSD / LBS  {t_psd / t_lbs:5.2f}   (Kurihara: 62 ms)")
    print(f"WPSD:            {t_wpsd * 1e3:7.2f} ms   ratio WPSD / LBS {t_wpsd / t_lbs:5.2f}   (Kurihara: 157 ms;"
          f" per-vertex coefficients precomputed once in {t_pre * 1e3:.0f} ms)")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", choices=["test", "paper"], default="paper")
    p.add_argument("--poses", type=int, default=10, help="example poses of the volume benchmark (default 10)")
    p.add_argument("--vertices", type=int, default=50_000)
    p.add_argument("--mesh-poses", type=int, default=5)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--weights", choices=["distance"], default="distance")
    p.add_argument("--skip-volume", action="store_true")
    a = p.parse_args(argv)
    import numba

    print(f"numba threads: {numba.get_num_threads()}")
    if not a.skip_volume:
        volume_benchmark(a.size, a.poses, a.repeats, a.weights)
    mesh_benchmark(a.vertices, a.mesh_poses, a.repeats)


if __name__ == "__main__":
    main()
