"""Trilinear sampling and displacement-field operations vs SciPy and SimpleITK (one run, ratios).

    .venv/bin/python benchmarks/bench_interpolation.py [--repeat 3] [--invert-iter 20]

On the paper-size hand grid (255×255×90 float32 at 0.78×0.78×1.0 mm) every
voxel is sampled at ``x + u(x)`` for a smooth displacement field ``u`` (three
sinusoidal modes, a few mm): a full "pull" resampling pass.  Prints the best of
``--repeat`` wall-clock times (after a warm-up call, so numba compilation and
cache loading are excluded) for

* ``interpolate.sample`` at the stored world points, and the fused
  ``sample_displaced_array`` (forms ``x + u`` itself);
* ``scipy.ndimage.map_coordinates(order=1)`` at the same points (index
  conversion excluded; SciPy runs on one thread);
* ``sitk.Resample`` with a ``DisplacementFieldTransform`` of the same field;
* a memory-bandwidth floor: the bytes one pass must move (points, output and
  the volume once) at the bandwidth of a large ``np.copyto`` in this process;

then, for the field operations, ``compose``, ``jacobian_determinant`` (vs
``sitk.DisplacementFieldJacobianDeterminant``) and ``invert`` (vs
``sitk.InvertDisplacementFieldImageFilter`` with the same number of
iterations), with the interior residuals.  Never asserts times; the load
average is printed because other processes share the cores.
"""

from __future__ import annotations

import argparse
import os

import numba
import numpy as np
import scipy.ndimage as ndi
import SimpleITK as sitk

# The project root first: this folder holds a ``deformation.py`` benchmark that would shadow the package.
from timing import best_of  # benchmarks/timing.py

from deformation.fields import displacement as F
from deformation.fields.interpolate import sample, sample_displaced_array
from deformation.geometry import GridGeometry, Volume


def smooth_field(g: GridGeometry) -> np.ndarray:
    x = g.world_coordinates()
    modes = [
        ((1.5, 0.5, -1.0), (0.05, 0.08, -0.06), 0.3),
        ((-1.0, 1.2, 0.4), (-0.07, 0.03, 0.09), 1.1),
        ((0.6, -0.8, 1.3), (0.04, -0.09, 0.05), 2.0),
    ]
    u = np.zeros_like(x)
    for a, k, ph in modes:
        u += np.asarray(a) * np.sin(x @ np.asarray(k) + ph)[..., None]
    return u


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--invert-iter", type=int, default=20)
    args = ap.parse_args(argv)
    rep = args.repeat

    g = GridGeometry((255, 255, 90), (0.78, 0.78, 1.0), (-99.06, -99.06, -44.5))
    rng = np.random.default_rng(0)
    data = ndi.gaussian_filter(rng.standard_normal(g.array_shape).astype(np.float32), 2.0)
    vol = Volume(data, g)
    u = smooth_field(g)
    field = Volume(u, g)
    pts = g.world_coordinates() + u
    n = g.n_voxels
    print(
        f"grid {g.size} (x, y, z) = {n} voxels, spacing {g.spacing} mm, float32 data; "
        f"|u| ≤ {np.linalg.norm(u, axis=-1).max():.2f} mm"
    )
    print(
        f"threads: numba {numba.get_num_threads()} ({numba.config.THREADING_LAYER}), "
        f"SimpleITK {sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()}, SciPy 1; "
        f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs"
    )

    # -- sampling ------------------------------------------------------------------------------
    w2i = g.world_to_index_matrix
    sample(vol, pts[:2, :2, :2])
    sample(vol, pts[:2, :2, :2], order=0)
    sample_displaced_array(data, w2i, GridGeometry((2, 2, 2), (1, 1, 1)), np.zeros((2, 2, 2, 3)))
    t_ours, ours = best_of(lambda: sample(vol, pts), rep)
    t_fused, fused = best_of(lambda: sample_displaced_array(data, w2i, g, u), rep)
    t_near, _ = best_of(lambda: sample(vol, pts, order=0), rep)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # per-core speed, less sensitive to other work on the machine
    t_one, _ = best_of(lambda: sample(vol, pts), rep)
    numba.set_num_threads(threads)
    coords = np.ascontiguousarray(np.moveaxis(g.world_to_index(pts)[..., ::-1], -1, 0))  # (k, j, i) for SciPy
    t_scipy, ref_scipy = best_of(lambda: ndi.map_coordinates(data, coords, order=1, mode="nearest"), rep)
    img = vol.to_sitk()
    tx = F.to_sitk_transform(field)
    t_sitk, ref_sitk = best_of(lambda: sitk.GetArrayFromImage(sitk.Resample(img, img, tx, sitk.sitkLinear, 0.0)), rep)
    big = np.empty(pts.size, dtype=np.float64)
    src = pts.reshape(-1)
    t_copy, _ = best_of(lambda: np.copyto(big, src), rep)
    bandwidth = 2 * src.nbytes / t_copy
    floor = (pts.nbytes + ours.nbytes + data.nbytes) / bandwidth
    floor_fused = (u.nbytes + ours.nbytes + data.nbytes) / bandwidth

    inside = np.all((coords >= 0) & (coords <= np.asarray(g.array_shape)[:, None, None, None] - 1), axis=0)
    print(f"\nfull trilinear pass ({n} points)            seconds   vs ours")
    rows = [
        ("interpolate.sample (float64 points)", t_ours),
        ("sample_displaced_array (fused)", t_fused),
        ("interpolate.sample order=0", t_near),
        ("interpolate.sample, 1 thread", t_one),
        ("scipy map_coordinates order=1 (1 thread)", t_scipy),
        ("sitk.Resample + DisplacementFieldTransform", t_sitk),
        (f"bandwidth floor ({bandwidth / 1e9:.1f} GB/s), sample", floor),
        ("bandwidth floor, fused", floor_fused),
    ]
    for name, t in rows:
        print(f"  {name:<42}{t:>8.3f}{t / t_ours:>9.1f}x")
    print(
        f"  speed-up vs SciPy {t_scipy / t_ours:.1f}x (fused {t_scipy / t_fused:.1f}x, "
        f"one thread each {t_scipy / t_one:.1f}x); "
        f"vs sitk.Resample {t_sitk / t_ours:.1f}x (fused {t_sitk / t_fused:.1f}x)"
    )
    print(
        f"  agreement: |ours - sitk| ≤ {np.abs(ours - ref_sitk).max():.2e}, "
        f"|ours - scipy| ≤ {np.abs(ours - ref_scipy)[inside].max():.2e} (inside the voxel-centre box), "
        f"|fused - sample| ≤ {np.abs(fused - ours).max():.2e}; data range ±{np.abs(data).max():.2f}"
    )

    # -- field operations ----------------------------------------------------------------------
    small = Volume(u[:3, :3, :3].copy(), GridGeometry((3, 3, 3), (1, 1, 1)))
    F.compose(small, small), F.jacobian_determinant(small), F.invert(small, max_iter=1)  # warm-up
    print("\nfield operations on the same grid (float64 field)     seconds")
    t_comp, _ = best_of(lambda: F.compose(field, field), rep)
    t_jac, det = best_of(lambda: F.jacobian_determinant(field), rep)
    fimg = field.to_sitk()
    t_sjac, sdet = best_of(lambda: sitk.GetArrayFromImage(sitk.DisplacementFieldJacobianDeterminant(fimg, True)), rep)
    t_pos, _ = best_of(lambda: F.positions(field), rep)
    t_tx, _ = best_of(lambda: F.from_sitk_transform(tx, g), 1)
    print(f"  {'compose(field, field)':<44}{t_comp:>8.3f}")
    print(f"  {'positions(field)':<44}{t_pos:>8.3f}")
    print(f"  {'from_sitk_transform(tx, grid)':<44}{t_tx:>8.3f}")
    print(f"  {'jacobian_determinant':<44}{t_jac:>8.3f}")
    print(
        f"  {'sitk.DisplacementFieldJacobianDeterminant':<44}{t_sjac:>8.3f}  "
        f"(interior |diff| ≤ {np.abs(det - sdet)[1:-1, 1:-1, 1:-1].max():.1e})"
    )

    k = args.invert_iter
    margin = 8  # voxels: the preimages of the interior lie inside the grid (|u| ≤ 4.5 mm)
    interior = (slice(margin, -margin),) * 3
    t_inv, (v, resid) = best_of(lambda: F.invert(field, max_iter=k, tol_mm=0.0, stall_iter=None), 1)
    flt = sitk.InvertDisplacementFieldImageFilter()
    flt.SetMaximumNumberOfIterations(k)
    flt.SetMaxErrorToleranceThreshold(0.0)
    flt.SetMeanErrorToleranceThreshold(0.0)
    flt.SetEnforceBoundaryCondition(False)
    t_sinv, sinv = best_of(lambda: flt.Execute(fimg), 1)
    _, sresid = F.invert(field, initial=Volume.from_sitk(sinv).data, max_iter=0)  # residual with our U
    print(
        f"  invert, {k} iterations: ours {t_inv:.2f} s, max/mean interior residual "
        f"{resid[interior].max():.1e}/{resid[interior].mean():.1e} mm"
    )
    print(
        f"  sitk.InvertDisplacementFieldImageFilter, {k} iterations: {t_sinv:.2f} s "
        f"({t_sinv / t_inv:.1f}x ours), max/mean interior residual "
        f"{sresid[interior].max():.1e}/{sresid[interior].mean():.1e} mm"
    )
    t_def, (_, r_def) = best_of(lambda: F.invert(field), 1)
    print(
        f"  invert with defaults (tol 1e-3 mm, stall rule): {t_def:.2f} s, interior max residual "
        f"{r_def[interior].max():.1e} mm, whole-grid max {r_def.max():.2f} mm (boundary: preimage outside)"
    )


if __name__ == "__main__":
    main()
