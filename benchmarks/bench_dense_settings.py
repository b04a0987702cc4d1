"""Compare settings of the dense registration on the TUNING phantoms only (the seeds settings are chosen on).

Each case is the flex protocol's (``benchmarks/bench_registration.py --cases flex``): the knee bent 45° or 70°
(2.5 mm voxels) or the hand's strongest curl (1.6 mm), poses estimated by the pose stage's method, the
polyrigid start from them; then :func:`registration.dense.register_dense` once per variant, from that same
start.  Printed per variant: MED over the body, bone and soft tissue, the 200-marker MED (markers drawn by the
study's rule), folded voxels of the body, time, and each level's taken steps, refused trials, stop reason and
LNCC before -> after.  The start (pose estimation, ~1-2 min a case) is cached under ``--cache``.

Only tuning seeds are accepted: held-out seeds and the external set are for reporting
(``benchmarks/bench_registration.py``), never for choosing a setting.

Usage::

    .venv/bin/python benchmarks/bench_dense_settings.py knee 0 bend70 '{}' '{"radius_growth": 2.0}'
    .venv/bin/python benchmarks/bench_dense_settings.py hand 1 curl '{}' '{"elastic_voxels": 1.2}'

Each variant is a JSON object of :class:`registration.dense.DenseSettings` fields (lists become tuples);
``{}`` is the default.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
import tempfile
from pathlib import Path

import bench_registration  # benchmarks/bench_registration.py: the flex case's constants and a row's measures
import numpy as np

from deformation.geometry import Volume
from registration.dense import DenseSettings, register_dense
from validation.phantoms import make_phantom
from validation.registration_measures import body_on_scan, marker_med

#: the hand's middle finger curled (MCP / PIP / DIP flexion, degrees), every other joint at the template's: one
#: finger's crease and the sliding web beside straight neighbours, a motion the flex cases (every finger curling
#: together) do not have
CURL_ONE = {"middle_mcp": [70.0, 0.0, 0.0], "middle_pip": [75.0, 0.0, 0.0], "middle_dip": [50.0, 0.0, 0.0]}


def tuning_case(
    region: str,
    seed: int,
    scan: str,
    cache: Path,
    start: str = "polyrigid",
    acquisition: str = "fixed",
    without: str | None = None,
    shift: float = 0.0,
    texture: float = 1.0,
) -> dict:
    """The scan, template, held bones, polyrigid start and truth of one tuning case (cached).  ``start``
    "perturbed": the estimated poses each off by 2-5° and 2 mm (benchmarks/bench_registration.py's
    ``perturbed_transforms``, drawn from the seed and region) before the polyrigid start is made.  ``without``
    ("bias" or "noise", random acquisition only): the same draw with every bias amplitude 1e-12 or every SNR 10⁶
    (the other draws unchanged: each image's parameters come from its own stream in the same order).  ``shift``:
    the template rendered on its grid moved by that fraction of its voxel along each axis (the scans' grids, the
    draws and the anatomy unchanged; the poses estimated and the start made on that template): the phantoms
    render every image on one lattice, so that wherever nothing moves the truth reads the template at its voxel
    centres, which real scans never do.  ``texture``: the tissues' texture (its plane waves, which also modulate
    the marrow, and the spread between muscle cells and between fat lobules) scaled by that factor; 0 leaves
    muscle and fat uniform with their septa, tendons and vessels, as flat as soft tissue in CT."""
    tag = ("" if start == "polyrigid" else f"_{start}") + ("" if acquisition == "fixed" else f"_{acquisition}")
    tag += f"_no{without}" if without else ""
    tag += f"_shift{shift:g}" if shift else ""
    tag += f"_texture{texture:g}" if texture != 1.0 else ""
    if without and acquisition != "random":
        raise ValueError("without= needs acquisition='random' (the fixed acquisition draws no bias or SNR)")
    if without:
        from validation.phantoms import generate

        # a bias of 1e-12, not 0: a zero amplitude skips the bias field's draws, and the noise drawn after them
        # from the same stream would be another realisation
        name, value = {"bias": ("BIAS_RANGE", (1e-12, 1e-12)), "noise": ("SNR_RANGE", (1e6, 1e6))}[without]
        kept = getattr(generate, name)
        setattr(generate, name, value)
        try:
            return _build_case(region, seed, scan, cache, start, acquisition, tag, shift, texture)
        finally:
            setattr(generate, name, kept)
    return _build_case(region, seed, scan, cache, start, acquisition, tag, shift, texture)


def _build_case(region, seed, scan, cache, start, acquisition, tag, shift=0.0, texture=1.0) -> dict:
    """:func:`tuning_case`'s work, cached under ``tag``."""
    f = cache / f"{region}{seed}_{scan}{tag}.v2.pkl"  # v2: the study markers and the 200 drawn ones
    if f.exists():
        return pickle.loads(f.read_bytes())
    from registration.initialise import polyrigid_initial_field
    from registration.pose import estimate_poses, released_labels

    bench = bench_registration
    flex_knee, n_markers = bench.FLEX_KNEE, bench.MARKER_SAMPLE
    if region == "knee":
        ph = make_phantom(
            "knee",
            size="test",
            seed=seed,
            spacing=(2.5, 2.5, 2.5),
            poses=(("straight", {"knee": [0.0, 0.0, 0.0]}),) + flex_knee,
            acquisition=acquisition,
        )
    elif scan == "curl_one":
        ph = make_phantom(
            "hand",
            size="test",
            seed=seed,
            spacing=(1.6, 1.6, 1.6),
            acquisition=acquisition,
            poses=(("curl_one", CURL_ONE),),
        )
    else:
        ph = make_phantom("hand", size="test", seed=seed, spacing=(1.6, 1.6, 1.6), n_poses=4, acquisition=acquisition)
        scan = ph.poses[-1][0] if scan == "curl" else scan  # the strongest curl, as the flex case
    if texture != 1.0:  # before any image is rendered: the phantom renders from these at every call
        ph.contrast = dataclasses.replace(ph.contrast, texture_amplitude=texture * ph.contrast.texture_amplitude)
        ph.tissue = dataclasses.replace(
            ph.tissue,
            cell_amplitude=texture * ph.tissue.cell_amplitude,
            lobule_amplitude=texture * ph.tissue.lobule_amplitude,
        )
    template, labels = _template(ph, shift)
    sk = ph.skeleton
    sc = {s.id: s for s in ph.scans()}[scan]
    est = estimate_poses(template, labels, {scan: sc.image}, sk).scans[0]
    held = released_labels(labels, sk, [b for b, fit in est.fits.items() if not fit.ok])
    bl = {b: sk.label_of(b) for b in sk.bone_names}
    transforms = est.pose.transforms
    if start == "perturbed":
        transforms = bench.perturbed_transforms(transforms, labels, bl, seed=[seed, ("knee", "hand").index(region)])
    init, _ = polyrigid_initial_field(
        labels, bl, {b: sk.bone(b).parent for b in sk.bone_names}, transforms, sc.image.geometry
    )
    xg = template.geometry.world_coordinates().reshape(-1, 3)
    body_t = Volume(
        (ph.anatomy.distances_fast(xg)[:, -1] < 0).reshape(template.geometry.array_shape).astype(np.uint8),
        template.geometry,
    )
    body = body_on_scan(sc.correspondence, body_t)
    phi = sc.correspondence.data + sc.image.geometry.world_coordinates()
    bone = (ph.anatomy.distances_fast(phi.reshape(-1, 3))[:, :-1].min(axis=1) < 0).reshape(body.shape) & body
    d = dict(
        scan=sc.image,
        template=template,
        held=held,
        init=init,
        truth=sc.correspondence,
        body=body,
        bone=bone,
        markers=sc.markers,
        many=ph.markers(ph.posing_model(dict(ph.poses)[scan]), n=n_markers, sample=1),
    )
    f.write_bytes(pickle.dumps(d))
    return d


def _template(ph, shift: float):
    """The phantom's template and labels, rendered on its grid moved by ``shift`` of a voxel along each axis
    (the same draws)."""
    if not shift:
        return ph.template()
    from deformation.geometry import GridGeometry

    g = ph.geometry
    delta = np.asarray(g.direction_matrix) @ (shift * np.asarray(g.spacing, float))  # world mm
    return ph.template(GridGeometry(g.size, g.spacing, tuple(np.asarray(g.origin, float) + delta), g.direction))


def score(d: dict, field: Volume, seconds: float, tag: str, levels=None, per_bone: bool = False) -> dict:
    """The flex case's row (benchmarks/bench_registration.py ``field_measures``) of ``field``, printed with the levels;
    ``per_bone``: then each held bone's MED (mm, over its voxels on the scan: its label pulled through the truth)."""
    out = bench_registration.field_measures(
        d["scan"], d["template"], field, d["truth"], d["body"], d["bone"], d["markers"], seconds, 0.0
    )
    out["markers_many_mm"] = marker_med(field, d["many"])
    lv = " ".join(
        f"[{x['iterations']} taken, {x.get('rejected', 0)} refused, {x.get('stop', '')}: "
        f"{x['lncc_before']:.4f} -> {x['lncc_after']:.4f}]"
        for x in (levels or [])
    )
    print(
        f"| {tag} | {out['med_mm']:.3f} | {out['bone_mm']:.3f} | {out['soft_mm']:.3f} | "
        f"{out['markers_many_mm']:.3f} | {out['n_folded']} | {seconds:.0f} | {lv} |",
        flush=True,
    )
    if per_bone:
        from deformation.fields.interpolate import sample_displaced_array

        held = d["held"]
        lab = sample_displaced_array(
            np.asarray(held.data), held.geometry.world_to_index_matrix, d["scan"].geometry, d["truth"].data, 0, 0
        ).astype(int)
        err = np.linalg.norm(np.asarray(field.data, float) - np.asarray(d["truth"].data, float), axis=-1)
        print(
            "|  | per bone (label: MED mm): "
            + ", ".join(f"{b}: {err[lab == b].mean():.2f}" for b in np.unique(lab) if b)
            + " |||||||",
            flush=True,
        )
    return out


def agreement_measures(d: dict, field: Volume) -> dict:
    """``--measures``: how well the scan and the template through ``field`` agree over the scan's body
    (``segment_body``): ``cc0`` the Pearson correlation, ``cc1`` the same with both images smoothed by one scan
    voxel (Gaussian σ), neither climbed by the optimiser; ``lncc3`` / ``lncc9`` the mean of each voxel's squared
    local correlation in Gaussian windows of σ 3 and 9 mm (scipy's default truncation; ``lncc3`` is close to the
    finest level's LNCC, over the whole body and without its penalties); and ``MED`` against the truth, for the
    ranking."""
    from scipy import ndimage

    from registration.metrics import cc, warp_template
    from registration.segmentation import segment_body

    f = np.asarray(d["scan"].data, np.float64)
    w = np.asarray(warp_template(d["template"], field).data, np.float64)
    body = segment_body(d["scan"]).data > 0
    err = np.linalg.norm(np.asarray(field.data, float) - np.asarray(d["truth"].data, float), axis=-1)
    out = {
        "MED": float(err[d["body"]].mean()),
        "cc0": cc(f, w, body),
        "cc1": cc(ndimage.gaussian_filter(f, 1.0), ndimage.gaussian_filter(w, 1.0), body),
    }
    sp = np.asarray(d["scan"].geometry.spacing, float)[::-1]
    for win in (3.0, 9.0):

        def g(z):
            return ndimage.gaussian_filter(z, win / sp)

        mf, mw = g(f), g(w)
        local = (g(f * w) - mf * mw) ** 2 / np.maximum((g(f * f) - mf**2) * (g(w * w) - mw**2), 1e-12)
        out[f"lncc{win:g}"] = float(local[body].mean())
    return out


def _print_measures(tag: str, m: dict) -> None:
    print(
        f"| {tag} | "
        + " | ".join(f"{m[k]:.3f}" if k == "MED" else f"{m[k]:.4f}" for k in ("MED", "cc0", "cc1", "lncc3", "lncc9"))
        + " |",
        flush=True,
    )


def main(argv=None) -> int:
    bench = bench_registration
    tuning, n_markers = bench.TUNING_SEEDS, bench.MARKER_SAMPLE
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("region", choices=["knee", "hand"])
    p.add_argument("seed", type=int, help=f"a tuning seed {tuning}")
    p.add_argument(
        "scan",
        help="knee: bend10 / bend45 / bend70; hand: curl (its strongest), curl_one (the middle "
        "finger alone curled) or a pose id",
    )
    p.add_argument("variants", nargs="*", default=["{}"], help="DenseSettings fields as JSON, one per variant")
    p.add_argument(
        "--start",
        choices=["polyrigid", "perturbed"],
        default="polyrigid",
        help="perturbed: every estimated pose off by 2-5 degrees and 2 mm before the polyrigid start",
    )
    p.add_argument(
        "--acquisition",
        choices=["fixed", "random"],
        default="fixed",
        help="the phantom's acquisition, as benchmarks/bench_registration.py's --acquisition",
    )
    p.add_argument(
        "--without",
        choices=["bias", "noise"],
        help="with --acquisition random: the same draw without bias fields, or without noise (SNR 10^6)",
    )
    p.add_argument(
        "--noise-free",
        choices=["template", "scan"],
        help="with --acquisition random: that image from the same draw without noise (SNR 10^6), the "
        "other as drawn: which image's noise moves the registration",
    )
    p.add_argument(
        "--from-truth",
        action="store_true",
        help="every variant starts at the true correspondence: how far its objective's maximum lies from the truth",
    )
    p.add_argument(
        "--template-shift",
        type=float,
        default=0.0,
        metavar="F",
        help="render the template on its grid moved by F of its voxel along each axis (poses and start "
        "made on it): the phantoms render every image on one lattice, real scans never share the "
        "template's",
    )
    p.add_argument(
        "--texture",
        type=float,
        default=1.0,
        metavar="F",
        help="the tissues' texture (its plane waves, which also modulate the marrow, and the spread "
        "between muscle cells and fat lobules) scaled by F: 0 leaves muscle and fat uniform (with "
        "their septa, tendons and vessels), as flat as soft tissue in CT",
    )
    p.add_argument(
        "--per-bone",
        action="store_true",
        help="also print each held bone's MED (its voxels on the scan): which bones a start's error stays on",
    )
    p.add_argument(
        "--measures",
        action="store_true",
        help="print instead how well the images agree through the start, the truth and each variant "
        "(correlations over the scan's body, raw and smoothed by a voxel; local correlations in "
        "3 and 9 mm windows): measures the optimiser does not climb, beside the MED",
    )
    p.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "avw-dense-settings")
    args = p.parse_args(argv)
    if args.region == "knee" and args.scan not in ("bend10", "bend45", "bend70"):
        p.error(f"the knee's scans are bend10, bend45 and bend70, got {args.scan!r}")
    if args.seed not in tuning:
        p.error(f"seed {args.seed} is not a tuning seed {tuning}: held-out seeds are for reporting only")
    variants = []
    for v in args.variants:
        try:
            kw = {k: tuple(x) if isinstance(x, list) else x for k, x in json.loads(v).items()}
            variants.append((v, DenseSettings(**kw)))
        except (ValueError, TypeError) as e:
            p.error(f"variant {v!r}: {e}")
    if (args.without or args.noise_free) and args.acquisition != "random":
        p.error("--without and --noise-free need --acquisition random (the fixed acquisition draws no bias or SNR)")
    if args.without and args.noise_free:
        p.error("--noise-free takes one image's noise away; --without takes it from both: give one of them")
    args.cache.mkdir(parents=True, exist_ok=True)
    if not (np.isfinite(args.texture) and args.texture >= 0):
        p.error(f"--texture must be a number >= 0, got {args.texture}")
    d = tuning_case(
        args.region,
        args.seed,
        args.scan,
        args.cache,
        args.start,
        args.acquisition,
        args.without,
        args.template_shift,
        args.texture,
    )
    if args.noise_free:  # the same draw without noise (its images only: its poses were estimated on clean images)
        clean = tuning_case(
            args.region,
            args.seed,
            args.scan,
            args.cache,
            args.start,
            args.acquisition,
            "noise",
            args.template_shift,
            args.texture,
        )
        d = dict(d, **{args.noise_free: clean[args.noise_free]})
    print(
        f"\n{args.region} seed {args.seed}, {args.scan} (tuning), start: {args.start}, acquisition: "
        f"{args.acquisition}{f', without {args.without}' if args.without else ''}"
        f"{', every variant from the truth' if args.from_truth else ''}"
        f"{f', the {args.noise_free} without noise' if args.noise_free else ''}"
        f"{f', template moved by {args.template_shift} voxel' if args.template_shift else ''}"
        f"{f', texture x {args.texture:g}' if args.texture != 1.0 else ''}\n"
    )
    if args.measures:
        print("| map | MED mm | cc0 | cc1 | lncc3 | lncc9 |\n|---|---|---|---|---|---|")
        _print_measures("start", agreement_measures(d, d["init"]))
        _print_measures("truth", agreement_measures(d, d["truth"]))
    else:
        print(f"| variant | MED mm | bone | soft | {n_markers} markers | folded | s | levels |")
        print("|---|---|---|---|---|---|---|---|")
        score(
            d,
            d["init"],
            0.0,
            f"start ({args.start}, estimated poses)"
            + ("; the variants below start at the truth" if args.from_truth else ""),
            per_bone=args.per_bone,
        )
    for tag, st in variants:
        r = register_dense(
            d["scan"],
            d["template"],
            initial=d["truth"] if args.from_truth else d["init"],
            moving_labels=d["held"],
            settings=st,
        )
        if args.measures:
            _print_measures(tag, agreement_measures(d, r.correspondence))
        else:
            score(d, r.correspondence, r.seconds, tag, r.levels, args.per_bone)
    return 0


if __name__ == "__main__":
    sys.exit(main())
