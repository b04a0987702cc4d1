"""EVD beyond the examples' range: the blended displacement capped at the longest example's, or not.

Leave one pose out of an EVD model built from the phantom's *true* template → scan maps (harmonic skinning
weights, the ``workbench weights`` path) and predict it (:func:`validation.leave_one_out.leave_one_out`):
the last (most bent) pose of a phantom lies outside the others' range, where the normalised RBF pose weights
extrapolate; the first is at or near rest, which the template's own example anchors; the others lie inside.
Prints, per held-out pose, where it lies and the MED (mm, over the template's body) of VBD (Rhee Eq. 2), EVD
as the workbench poses it (capped, the default) and Rhee Eq. 6 as written (uncapped).  Tuning phantoms only
(seeds 0–99): the choice it informs is made here.

    python benchmarks/bench_evd_range.py [--cases knee:0:5 hand:4:10 knee:1:6]   # region:seed:poses
"""

from __future__ import annotations

import argparse

import numpy as np


def weights_of(ph):
    """Harmonic voxel weights of a phantom (segmented body, lattice tet mesh, Laplace solve)."""
    from deformation.meshes.tetmesh import lattice_tetmesh
    from deformation.models.harmonic import harmonic_weights, weights_on_grid
    from registration.segmentation import segment_body

    template, labels = ph.template()
    mesh = lattice_tetmesh(segment_body(template, labels=labels))
    bone_labels = {b: ph.skeleton.label_of(b) for b in ph.skeleton.bone_names}
    dense, _ = harmonic_weights(mesh, labels, bone_labels)
    return weights_on_grid(mesh, dense, tuple(bone_labels), ph.geometry, labels, bone_labels)


def main(argv=None) -> int:
    from validation.leave_one_out import leave_one_out
    from validation.phantoms import make_phantom

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["knee:0:5", "hand:4:10", "knee:1:6"], help="region:seed:poses")
    args = ap.parse_args(argv)
    print("case | held-out pose | place | VBD | EVD capped | EVD uncapped (Rhee Eq. 6 as written)")
    for spec in args.cases:
        region, seed, n = spec.split(":")
        if int(seed) >= 100:
            ap.error(f"--cases {spec}: seeds 100 and up are held out; tune on seeds 0-99")
        ph = make_phantom(region, size="test", modality="mri", n_poses=int(n), seed=int(seed), noise=False)
        w = weights_of(ph)
        capped = leave_one_out(ph, w)
        plain = leave_one_out(ph, w, cap=False)
        last = len(capped) - 1
        for i, (a, b) in enumerate(zip(capped, plain)):
            where = "first" if i == 0 else ("last (beyond)" if i == last else "inside")
            print(
                f"{region} s{seed} | {a.pose_id} | {where} | {a.med_template_vbd:.3f} | {a.med_template_evd:.3f} | "
                f"{b.med_template_evd:.3f}",
                flush=True,
            )
        inside = [i for i in range(len(capped)) if i not in (0, last)]
        ratio = capped[last].med_template_evd / max(plain[last].med_template_evd, 1e-12)
        print(
            f"{region} s{seed}: inside the range capped / uncapped "
            f"{np.mean([capped[i].med_template_evd for i in inside]):.3f} / "
            f"{np.mean([plain[i].med_template_evd for i in inside]):.3f} mm; the last pose {ratio:.2f}x"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
