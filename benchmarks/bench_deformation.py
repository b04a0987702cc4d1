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
  (Kurihara Eq. 6–8, 12–15) and WPSD (Kurihara Eq. 16), all compiled kernels on the same
  threads, and the ratios PSD/LBS and WPSD/LBS.

Usage::

    .venv/bin/python benchmarks/bench_deformation.py            # paper-size hand (a few minutes, ~6 GB)
    .venv/bin/python benchmarks/bench_deformation.py --size test
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from timing import best_of  # benchmarks/timing.py

from deformation.fields.resample import backward_map, resample_forward
from deformation.geometry import Volume
from deformation.models.evd import ExampleVolumeDeformation, vbd_forward
from deformation.models.posespace import PoseSpace, psd_training, skin, wpsd_deform
from deformation.models.skinning import distance_weights, lbs, stack_transforms
from validation.phantoms import make_phantom


class Memory:
    """Resident memory per phase: the current RSS and the peak since the previous phase (Linux: VmHWM, reset
    through /proc/self/clear_refs), so that a peak is attributed to the step that made it."""

    def __init__(self):
        self.rows = []
        self._reset()

    @staticmethod
    def _status(key: str) -> float:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 2**20  # kB → GiB
        return float("nan")

    def _reset(self):
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
        except OSError:
            pass

    def phase(self, name: str):
        self.rows.append((name, self._status("VmHWM"), self._status("VmRSS")))
        self._reset()

    def report(self):
        print("resident memory per phase (GiB): peak during the phase / held at its end")
        for name, peak, now in self.rows:
            print(f"  {name:<58} {peak:6.2f} / {now:5.2f}")


def volume_benchmark(size: str, n_poses: int, repeats: int, weights_kind: str):
    from scipy import ndimage

    t0 = time.perf_counter()
    mem = Memory()
    ph = make_phantom("hand", size=size, modality="mri", n_poses=n_poses + 1, seed=5)
    g = ph.geometry
    x = g.world_coordinates().reshape(-1, 3)
    print(
        f"grid {g.size[0]}×{g.size[1]}×{g.size[2]} = {g.n_voxels:,} voxels at "
        f"{'×'.join(f'{s:.2f}' for s in g.spacing)} mm; {n_poses} example poses + 1 query pose"
    )
    template = ph.template()[0].data.astype(np.float32)
    mem.phase("phantom and its template image")
    if weights_kind != "distance":
        raise SystemExit("only --weights distance is wired here")
    # the phantom's distances to every bone and to the skin, in chunks of points into one float32 array (at
    # once, the analytic distances' float64 temporaries took 5 GB on this grid)
    n_bones = len(ph.skeleton.bone_names)
    d = np.empty((len(x), n_bones + 1), dtype=np.float32)
    for lo in range(0, len(x), 1 << 18):
        d[lo : lo + (1 << 18)] = ph.anatomy.distances_fast(x[lo : lo + (1 << 18)])
    body = (d[:, -1] < 0).reshape(g.array_shape)
    w = distance_weights(d[:, :-1], ph.skeleton.bone_names)
    del d
    mem.phase("distances to every bone, distance weights")
    poses, fields = [], []
    for _pid, ang in ph.poses[:n_poses]:
        poses.append(ph.pose_of(ang))
        fields.append(ph.posing_model(ang).forward(x).reshape(g.array_shape + (3,)).astype(np.float32))
    query = ph.pose_of(ph.poses[n_poses][1])
    mem.phase(f"ground-truth forward maps of {n_poses} poses")
    model = ExampleVolumeDeformation.from_correspondences(g, w, ph.skeleton, poses, fields)
    del fields
    mem.phase("EVD model (Rhee Eq. 7)")
    print(f"set-up (phantom, weights, ground truth of {n_poses} poses, Rhee Eq. 7): {time.perf_counter() - t0:.1f} s")
    t = stack_transforms(query.transforms, w.bones)

    def floor():
        return (
            float(template.sum())
            + float(w.index.sum(dtype=np.uint64))
            + float(w.value.sum())
            + float(model.displacements.sum())
        )

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
    mem.phase("before timing (warm-up: one EVD + backward map + resample)")
    t_vbd, (vol_vbd, bm_vbd) = best_of(vbd, repeats)
    t_evd, (vol_evd, bm_evd) = best_of(evd, repeats)
    t_fwd, _ = best_of(lambda: model.forward(query), repeats)
    t_wpsd, _ = best_of(lambda: evd("wpsd"), 1)
    from deformation.models.posed_template import TemplatePoser

    poser = TemplatePoser(template_volume, w, Volume(body.astype(np.uint8), g), model=model)
    poser.fill = 0.0  # as resample_forward's default above
    t_evd2, posed2 = best_of(lambda: poser.pose(query, labels=False, map_factor=2), repeats)
    coords = np.moveaxis(bm_evd.template_index[..., ::-1], -1, 0).astype(np.float32)  # (k, j, i) for scipy
    mem.phase("VBD, EVD and WPSD-EVD, each with backward map and resample")
    t_scipy, _ = best_of(lambda: ndimage.map_coordinates(template, coords, order=1, mode="constant"), repeats)
    summ = bm_evd.summary()
    print(
        f"memory floor (one NumPy sum over {nbytes / 2**20:,.0f} MiB: template, weights, "
        f"{n_poses} example fields): {t_floor * 1e3:8.1f} ms"
    )
    print(f"naive: one scipy map_coordinates trilinear pass of the grid:           {t_scipy * 1e3:8.1f} ms")
    print(
        f"VBD + resample:                                                        {t_vbd * 1e3:8.1f} ms"
        f"   ratio to floor {t_vbd / t_floor:5.2f}"
    )
    print(
        f"EVD + resample (Rhee Eq. 6, normalised RBF pose weights):             {t_evd * 1e3:8.1f} ms"
        f"   ratio to floor {t_evd / t_floor:5.2f}   (forward pass alone {t_fwd * 1e3:.1f} ms, "
        f"{t_fwd / t_floor:.2f}× floor)"
    )
    print(
        f"EVD + resample with per-voxel WPSD weights (Kurihara Eq. 16):          {t_wpsd * 1e3:8.1f} ms"
        f"   ratio to floor {t_wpsd / t_floor:5.2f}"
    )
    print(
        f"EVD + resample, maps on every other voxel (--map-factor 2):           {t_evd2 * 1e3:8.1f} ms"
        f"   ratio to floor {t_evd2 / t_floor:5.2f}"
    )
    print(f"EVD + resample vs the naive scipy pass: {t_evd / t_scipy:.2f}×;  Rhee's EVD took 3.5 s on this grid")
    fine2 = posed2.backward.full()  # the blended fine map (pose() pulls through it without making it)
    good = (bm_evd.status <= 1) & (fine2.status <= 1) & body
    diff = np.linalg.norm(fine2.template_positions()[good] - bm_evd.template_positions()[good], axis=1)
    print(
        f"--map-factor 2 against the exact map over {good.sum():,} voxels inside the body mask: preimage "
        f"difference mean {diff.mean():.3f} mm, P99 {np.percentile(diff, 99):.2f} mm; |intensity difference| "
        f"mean {np.abs(posed2.volume.data - vol_evd.data)[good].mean():.2f} (template range "
        f"{np.ptp(template):.0f})"
    )
    print(
        f"backward map of the EVD pose: {summ['n_ok']:,} ok, {summ['n_folded']:,} folded, "
        f"{summ['n_not_converged']:,} not converged, {summ['n_outside']:,} outside the template; "
        f"max residual {summ['max_residual_mm']:.2e} mm"
    )
    mem.report()
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
    folded = pts_space.fold(base)  # with Φ⁻¹, precomputed once per mesh (deformation.models.surface_model does so)
    t_pre = time.perf_counter() - t0
    t = stack_transforms(query.transforms, w.bones)
    skin(v, w, t)
    skin(base, w, t, space.weights(query))
    wpsd_deform(base, w, pts_space, query, t, folded=folded)
    import os

    import numba

    # Stable figures (issue L: one run gave WPSD/LBS 4.95, another 1.16 with the compiled LBS slower than
    # NumPy's): every kernel timed as the best of many calls, on one thread pinned to one core (the per-core
    # ratio, which the machine's other work disturbs least), then on all of numba's threads.
    n_threads = numba.get_num_threads()
    cores = sorted(os.sched_getaffinity(0))
    print(
        f"mesh: {n_vertices:,} vertices near the hand phantom's skin, {n_poses} example poses "
        f"({sk.n_dof} DOF); best of {repeats * 20} calls each"
    )
    try:
        for threads in dict.fromkeys((1, n_threads)):
            numba.set_num_threads(threads)
            os.sched_setaffinity(0, cores[:threads] if threads < len(cores) else cores)
            t_lbs, _ = best_of(lambda: skin(v, w, t), repeats * 20)
            t_np, _ = best_of(lambda: lbs(v, w, t), repeats * 5)
            t_psd, _ = best_of(lambda: skin(base, w, t, space.weights(query)), repeats * 20)
            t_wpsd, _ = best_of(lambda: wpsd_deform(base, w, pts_space, query, t, folded=folded), repeats * 20)
            print(f"  {threads} thread(s){' pinned to core ' + str(cores[0]) if threads == 1 else ''}:")
            print(f"    LBS (compiled):  {t_lbs * 1e3:7.2f} ms   (NumPy LBS {t_np * 1e3:.2f} ms)")
            print(
                f"    PSD:             {t_psd * 1e3:7.2f} ms   ratio PSD / LBS  {t_psd / t_lbs:5.2f}   "
                "(Kurihara: 62 ms)"
            )
            print(
                f"    WPSD:            {t_wpsd * 1e3:7.2f} ms   ratio WPSD / LBS {t_wpsd / t_lbs:5.2f}   "
                f"(Kurihara: 157 ms; per-vertex coefficients and folded samples precomputed once "
                f"in {t_pre * 1e3:.0f} ms)"
            )
    finally:
        numba.set_num_threads(n_threads)
        os.sched_setaffinity(0, cores)


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
