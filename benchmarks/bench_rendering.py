"""Rendering benchmark: per-frame render time of the volume mappers, and a 60-frame animation split by stage.

1. The same test-size phantom template rendered at 640×480 by the CPU ray
   caster we pick on software OpenGL (``vtkFixedPointVolumeRayCastMapper``)
   and by VTK's GPU ray caster (``vtkGPUVolumeRayCastMapper``, which on a
   machine without a GPU runs on Mesa's llvmpipe): seconds per frame and their
   ratio, measured in this run, plus the mean pixel difference of the two
   images (they should show the same thing).
2. ``workbench animate`` of the test-size hand (and knee): 60 frames at
   640×480 to MP4 (ready keyframes; EVD from a model built on the phantom's
   truth, or ``--method vbd``), the time split into deformation, rendering
   and encoding.

Times are measured in one run on a shared machine: compare the ratios.

Usage::

    .venv/bin/python benchmarks/bench_rendering.py                 # hand and knee, ~2 min
    .venv/bin/python benchmarks/bench_rendering.py --cases hand --frames 60 --repeats 5
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from validation.phantoms import make_phantom
from workbench.stages.model import ModelSettings
from workbench.stages.run import run_stages
from workbench.stages.weights import WeightsSettings
from workbench.study import write_phantom_study
from workbench.viz.animate import animate_study
from workbench.viz.render import Camera, VolumeRenderer, opengl_backend


def _time_mapper(vol, mapper, repeats, size):
    with VolumeRenderer(vol.geometry, size=size, mapper=mapper, camera=Camera("auto")) as r:
        img = r.render(vol)  # first frame: pipeline set-up, transfer functions, camera
        t0 = time.perf_counter()
        for _ in range(repeats):
            r._volume.Modified()  # re-render the same data (as an animation frame would)
            img = r.render(vol)
        return (time.perf_counter() - t0) / repeats, img


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=["hand", "knee"], choices=["hand", "knee"])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=5, help="renders per mapper for the per-frame time")
    ap.add_argument(
        "--weights",
        choices=["distance", "harmonic"],
        default="distance",
        help="skinning weights of the animated study (the per-frame cost does not depend on it)",
    )
    ap.add_argument(
        "--method",
        choices=["evd", "vbd"],
        default="evd",
        help="deformation per frame: EVD (a model is built from the phantom's truth first) or VBD",
    )
    args = ap.parse_args(argv)
    size = (640, 480)
    print(f"OpenGL: {opengl_backend().describe()}")
    tmp = Path(tempfile.mkdtemp(prefix="avw-render-bench-"))
    rows = []
    for case in args.cases:
        ph = make_phantom(case, size="test", seed=0)
        template, _ = ph.template()
        t_fixed, a = _time_mapper(template, "fixed", args.repeats, size)
        t_gpu, b = _time_mapper(template, "gpu", args.repeats, size)
        diff = float(np.abs(a.astype(int) - b).mean())
        print(
            f"{case}: render {size[0]}x{size[1]} of {template.geometry.size} voxels: fixed-point CPU ray cast "
            f"{t_fixed:.3f} s/frame, GPU ray cast on this OpenGL {t_gpu:.3f} s/frame; ratio gpu/fixed "
            f"{t_gpu / t_fixed:.1f}x; mean |pixel difference| {diff:.1f} of 255",
            flush=True,
        )
        study = write_phantom_study(ph, tmp / case)
        root = study.root
        run_stages(
            study,
            ["weights"] + (["model"] if args.method == "evd" else []),
            settings={"weights": WeightsSettings(method=args.weights), "model": ModelSettings(source="truth")},
        )
        s = animate_study(root, tmp / f"{case}.mp4", size=size, n_frames=args.frames, method=args.method)
        rows.append((case, s, t_fixed, t_gpu))
        print(
            f"{case}: {s['frames']} frames {size[0]}x{size[1]} ({s['method'].upper()}, {s['mapper']} mapper): "
            f"deformation {s['deform_seconds']:.1f} s ({s['deform_seconds_per_frame']:.3f} s/frame), rendering "
            f"{s['render_seconds']:.1f} s ({s['render_seconds_per_frame']:.3f} s/frame), encoding "
            f"{s['encode_seconds']:.1f} s; total {s['total_seconds']:.1f} s",
            flush=True,
        )
    print(
        "\n| case | frames | deformation s | rendering s | encoding s | total s | render s/frame | "
        "GPU mapper / ours (per frame) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for case, s, tf, tg in rows:
        print(
            f"| {case} | {s['frames']} | {s['deform_seconds']:.1f} | {s['render_seconds']:.1f} | "
            f"{s['encode_seconds']:.1f} | {s['total_seconds']:.1f} | {s['render_seconds_per_frame']:.3f} | "
            f"{tg / tf:.1f}x |"
        )
    print(f"videos in {tmp}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
