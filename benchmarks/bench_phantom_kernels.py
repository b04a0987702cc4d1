"""Compiled phantom kernels vs their NumPy definitions on the same points (one run, ratios).

    .venv/bin/python benchmarks/bench_phantom_kernels.py [--region hand] [--points 200000]

Prints, for the signed distances, the intensity model, the soft and vbd forward
maps, the time of each implementation and the speed-up ratio.  Numba's
compilation is excluded (one warm-up call).  Never asserts times.
"""

from __future__ import annotations

import argparse

import numpy as np

# The project root first: this folder holds a ``deformation.py`` benchmark that would shadow the package.
from timing import best_of  # benchmarks/timing.py

from validation.phantoms import make_phantom


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--region", choices=["knee", "hand"], default="hand")
    ap.add_argument("--points", type=int, default=200_000)
    args = ap.parse_args(argv)
    ph = make_phantom(args.region, size="paper", seed=0)
    g = ph.geometry
    rng = np.random.default_rng(0)
    p = rng.uniform(g.index_to_world([0, 0, 0]), g.index_to_world(np.array(g.size) - 1), size=(args.points, 3))
    _, angles = ph.poses[-1]
    a = ph.anatomy
    cases = {
        "distances": (lambda: a.distances_fast(p), lambda: (a.bone_distances(p), a.body_distance(p))),
        "intensity": (
            lambda: a.intensity_fast(p, ph.contrast, edge_mm=ph.edge_mm, texture=ph.texture),
            lambda: a.intensity(p, ph.contrast, edge_mm=ph.edge_mm, texture=ph.texture),
        ),
    }
    for mode in ("soft", "vbd"):
        m = ph.posing_model(angles, mode=mode)
        cases[f"forward ({mode})"] = (lambda m=m: m.forward(p), lambda m=m: m.forward_reference(p))
    print(f"{args.region}, {args.points} random points in the paper-size field of view, {len(a.bone_names)} bones")
    print(f"{'kernel':<18}{'compiled s':>12}{'numpy s':>10}{'ratio':>8}")
    for name, (fast, ref) in cases.items():
        fast()  # compile / warm up
        tf, tr = best_of(fast)[0], best_of(ref, repeat=1)[0]
        print(f"{name:<18}{tf:>12.3f}{tr:>10.3f}{tr / tf:>7.1f}x")


if __name__ == "__main__":
    main()
