"""Registration benchmark: the locally adaptive registration against B-spline baselines, one run, same data.

Cases (phantoms with exact ground truth):

* ``table2`` — Rhee §6.1 / Table 2: the knee bent 10° by VBD (``--posing
  vbd``), no initialisation.  The paper's figures are printed beside ours.
* ``knee`` — Rhee Table 3: the soft-posed knee (4 poses), the template
  registered to the 3 other scans after VBD initialisation from the
  ground-truth poses; MED over body voxels and at the skin markers.
* ``hand`` — Rhee Table 4: the hand (10 poses), template to the 9 others
  (slow: add it explicitly).

For every case and method (source = nothing, initialised = VBD, ours,
SimpleITK's B-spline, elastix's B-spline when itk-elastix is installed — the
``bench`` extra) it prints MED, marker MED, SSD, CC, MI, the fraction of
folded body voxels and the time, averaged over the scans, then the ratios of
our MED and time to each baseline's.  Times are measured in this run on a
shared machine: compare ratios, not seconds.

Usage::

    .venv/bin/python benchmarks/bench_registration.py                    # table2 and knee, test size (~10 min)
    .venv/bin/python benchmarks/bench_registration.py --cases table2 --paper-preset
    .venv/bin/python benchmarks/bench_registration.py --cases hand
    .venv/bin/python benchmarks/bench_registration.py --cases knee hand --from-truth   # the intensity floor
    .venv/bin/python benchmarks/bench_registration.py --cases flex --split held-out   # issue I's protocol
    .venv/bin/python benchmarks/bench_registration.py --cases flex --start vbd         # every method from VBD
    .venv/bin/python benchmarks/bench_registration.py --cases flex --start perturbed   # poses off 2-5 deg, 2 mm
    .venv/bin/python benchmarks/bench_registration.py --cases flex --start skinning-truth   # from the true poses
    nice .venv/bin/python benchmarks/bench_registration.py --cases external          # the external set (tens of
    minutes)
    nice .venv/bin/python benchmarks/bench_registration.py --cases suite --no-sitk --no-adaptive --no-vbd-starts \
        --no-elastix-rigidity --acquisition random    # all three sets, one table each (~40 min)

``suite`` (issue M part 5): the flex cases on the tuning seeds, then on the
held-out seeds (``--acquisition``, ``--start`` apply to both), then the
external set; at the end one table per set: per case the start's, ours' and
elastix's MED, ours / elastix for MED, soft tissue, P95, markers, CC, time
and peak memory, both bone MEDs, the best peer (the lowest MED among the
peers that ran) with ours / its MED and ours' marker MED / the lowest of any
peer, ours' folded voxels beside the start's, ours / start, and a last row
with the worst case of each column (for the best peer: how often each was).

Peers (issue R part 3), each from the same start as ours (the template
resampled through it, their field composed with it): elastix's B-spline
(and, in ``flex``, with the rigidity penalty on the bones), PICSL greedy
(``picsl-greedy``, NCC; ``--no-greedy``) and SimpleITK's fast
symmetric-forces demons (``--no-demons``), their settings those of
:mod:`registration.baselines` (``--greedy-settings`` / ``--demons-settings``
override them, for ``--split tuning`` only).

``flex`` (issue I): the knee flexed 10°, 45° and 70° and the hand's strongest
curl, on phantoms with structured soft tissue and an uneven soft-tissue
motion, at 2.5 mm (knee) / 1.6 mm (hand) voxels.  Poses are *estimated*
(:func:`registration.pose.estimate_poses`), and every method starts from the
same one-to-one initialisation (the polyrigid flow of those poses,
:mod:`deformation.models.polyrigid`).  ``--split tuning`` uses the seeds settings
were chosen on (:data:`TUNING_SEEDS`), ``--split held-out`` the others
(:data:`HELD_OUT_SEEDS`), never looked at while tuning.  ``--start`` changes
the start: VBD of the same poses, the poses perturbed, or (``skinning-truth``)
the polyrigid flow of the phantom's true bone poses, every bone held rigid.
Printed per case:
MED over body, bone and soft-tissue voxels, P95, marker MED, CC, folded
fraction, time and peak memory above the process's baseline (RSS sampled
every 20 ms), and each method's MED and time relative to the best peer.  The
first row is the ground truth itself: its folded voxels are those an exact
field has on that grid (det of central differences ≤ 0 where curled fingers
touch or the crease compresses tissue below the voxel: the phantom's map is
one-to-one, its samples are not).

``external``: the studies of ``--external`` (default
``<repository>/../shared/data/external-phantoms``; absent: one line, skipped),
made by a generator independent of the workbench (its README there): an
elbow MRI and a two-finger CT, three posed scans each, in the workbench's
study format with exact truth (``truth/<scan>_correspondence.mha``, the
16 markers of ``truth/<scan>_markers.json``).  These studies are never used
for choosing settings: ``--split`` does not apply to them, every run is
held out.  Each study folder is copied into ``--work`` (default a new
temporary folder; the shared folder is only read, and checked unchanged at
the end) and the copy goes through the workbench's own chain, ``workbench
run COPY --until register`` in steps (``--until weights`` for the study's
stages before it, then ``--until init`` and ``--until register`` with
``--scan`` for each scan, so that each scan's peak memory is its own).
From the init stage's start field of each scan, read from the copy,
elastix's B-spline runs when itk-elastix is installed, greedy and demons
beside it.  Each scan's table has the flex case's columns (its skin and
200-marker columns aside), over the validate stage's body: the template's
body as the weights stage segments it
(:func:`registration.segmentation.segment_body` with the bone labels),
pulled onto the scan through the truth (:func:`body_on_scan`); bone voxels
are those whose true template position is in ``template_labels``.  Times:
the init stage's recorded seconds for the start, the register stage's
recorded ``timings.registration`` for ours (the inversion onto the template
grid, which elastix does not do, is printed beside it), elastix's own.  The
summary gives ours / elastix per scan, ours / its start, the worst scan of
every column over the set, and names any scan where ours is worse than its
start.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from deformation.fields.displacement import folding_statistics
from deformation.geometry import Volume
from deformation.models.skinning import stack_transforms
from registration.adaptive import AdaptiveSettings, register_adaptive
from registration.baselines import (
    ants_available,
    ants_syn,
    elastix_available,
    elastix_bspline,
    greedy_available,
    greedy_register,
    load_itk,
    sitk_bspline,
    sitk_demons,
)
from registration.initialise import vbd_initial_field
from registration.metrics import warp_template
from validation.phantoms import make_phantom
from validation.phantoms.generate import ACQUISITIONS, describe_acquisition
from validation.protocols.registration import PAPER as RHEE_TABLES
from validation.registration_measures import (
    MEASURE_KEYS,
    body_on_scan,
    error_map,
    marker_med,
    registration_measures,
    uncertainty_calibration,
)

# Rhee Tables 2-4, one home (validation.protocols.registration); the benchmark's case names
PAPER = {"table2": RHEE_TABLES["table2"], "knee": RHEE_TABLES["table3"], "hand": RHEE_TABLES["table4"]}


OURS = "ours (dense, bones fixed)"
#: flex: the start every method registers from (--start)
START_ROWS = {
    "polyrigid": "initialised (polyrigid, estimated poses)",
    "vbd": "initialised (VBD, distance weights, estimated poses)",
    "perturbed": "initialised (polyrigid, estimated poses off by 2-5 deg and 2 mm)",
    "skinning-truth": "initialised (polyrigid, true poses)",
}
ELASTIX = "elastix B-spline"
ELASTIX_RIGIDITY = "elastix B-spline + rigidity penalty"
GREEDY = "greedy (NCC)"
DEMONS = "SimpleITK demons"
#: the set tables' short names of the peers (a peer not listed keeps its row name)
PEER_SHORT = {ELASTIX: "elastix", ELASTIX_RIGIDITY: "elastix + rigidity", GREEDY: "greedy", DEMONS: "demons"}
TRUTH = "ground truth (sampled on the scan grid)"
TUNING_SEEDS = (0, 1)
HELD_OUT_SEEDS = (100, 101)
MARKER_SAMPLE = 200  # flex: markers drawn beside the study's 12, by the same rule (validation.phantoms)
FLEX_KNEE = (
    ("bend10", {"knee": [10.0, 1.0, 2.0]}),
    ("bend45", {"knee": [45.0, 2.0, 5.0]}),
    ("bend70", {"knee": [70.0, 2.0, 8.0]}),
)


class PeakMemory:
    """Peak resident memory (MiB) above the level at entry, child processes included (ANTs runs in its own
    venv), sampled every 20 ms in a thread.  At entry the C heap's free pages are handed back to the system
    (glibc's ``malloc_trim``, where there is one); heap that an earlier method freed and the allocator still
    keeps, and this one reuses, is not counted: in-process figures are lower bounds."""

    def _rss(self):
        import psutil

        total = self._proc.memory_info().rss
        for c in self._proc.children(recursive=True):
            try:
                total += c.memory_info().rss
            except psutil.Error:  # ended between the listing and the reading
                pass
        return total

    def __enter__(self):
        import ctypes
        import gc
        import threading

        import psutil

        gc.collect()
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):  # not glibc
            pass
        self._proc = psutil.Process()
        self.base = self._rss()
        self.peak = self.base
        self._stop = threading.Event()

        def watch():
            while not self._stop.wait(0.02):
                self.peak = max(self.peak, self._rss())

        self._t = threading.Thread(target=watch, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self._rss())
        self.mib = (self.peak - self.base) / 2**20


def field_measures(scan, template, fld, truth, body, bone, markers, seconds, mem, sigma=None, **regions):
    """One row of a flex or external table: :func:`registration_measures` of ``fld`` (CC of the template warped
    through it), its MED over the ``bone`` voxels of the body and over the rest of the body (soft tissue), its
    P95 over the body, the body's folded voxels, ``seconds`` and ``mem`` (MiB), and ``<name>_mm``: its MED over
    each further mask of ``regions``."""
    m = registration_measures(
        scan,
        warp_template(template, fld),
        fld,
        truth=truth,
        body=body,
        markers=markers,
    )
    err = error_map(fld, truth, dtype=np.float64)
    m.update(
        bone_mm=float(err[bone].mean()),
        soft_mm=float(err[body & ~bone].mean()),
        p95_mm=float(np.percentile(err[body], 95)),
        n_folded=folding_statistics(fld, body)["n_folded"],
        seconds=seconds,
        mem_mib=mem,
    )
    m.update({f"{name}_mm": float(err[mask].mean()) for name, mask in regions.items()})
    if sigma is not None:  # the method's expected error (ours: registration.posterior) against the true one
        m["calibration"] = uncertainty_calibration(err, np.asarray(sigma.data), body)
    return m


def _unfold_line(u):
    """Our registration's fold repair (``DenseResult.unfold``): which attempt was taken (bones frozen down to which
    layer, which kernel)."""
    return (
        f"  ours, fold repair: {u['n_folded_before']} -> {u['n_folded_after']} folded voxels of the scan's body, "
        f"{'taken' if u['taken'] else 'not taken'}; bone layers released "
        f"{u['bone_layers_released'] if u['bone_layers_released'] is not None else 'all'}, kernel {u['kernel']}"
    )


def _flex_phantoms(seed, args):
    if not args.hand_only:
        knee = make_phantom(
            "knee",
            size="test",
            seed=seed,
            spacing=(2.5, 2.5, 2.5),
            acquisition=args.acquisition,
            poses=(("straight", {"knee": [0.0, 0.0, 0.0]}),) + FLEX_KNEE,
        )
        yield "knee", knee, ["bend10", "bend45", "bend70"]
    if not args.knee_only:
        hand = make_phantom(
            "hand", size="test", seed=seed, spacing=(1.6, 1.6, 1.6), n_poses=4, acquisition=args.acquisition
        )
        yield "hand", hand, [hand.poses[-1][0]]  # the strongest curl


def perturbed_transforms(
    transforms: dict, labels: Volume, bone_labels: dict, seed, *, degrees=(2.0, 5.0), shift_mm: float = 2.0
) -> dict:
    """A pose stage that erred (issue M part 3): each bone's template → scan transform followed by a rotation of
    ``degrees`` (uniform in the range) about a random axis through the bone's posed centroid and a ``shift_mm``
    translation in a random direction, drawn from ``seed`` (an int or a sequence of ints: numpy's SeedSequence
    entropy).  A bone without voxels in ``labels`` is left as it is."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(np.random.SeedSequence(seed))
    lab = np.asarray(labels.data)
    ijk_to_world = labels.geometry.index_to_world_matrix
    out = {}
    for bone in sorted(transforms):
        idx = np.argwhere(lab == bone_labels[bone])[:, ::-1]  # (i, j, k)
        if not len(idx):
            out[bone] = transforms[bone]
            continue
        c_t = (ijk_to_world[:3, :3] @ idx.mean(axis=0)) + ijk_to_world[:3, 3]
        t = np.asarray(transforms[bone], float)
        c = t[:3, :3] @ c_t + t[:3, 3]  # the bone's centroid in the scan
        axis = rng.normal(size=3)
        r = Rotation.from_rotvec(np.deg2rad(rng.uniform(*degrees)) * axis / np.linalg.norm(axis)).as_matrix()
        d = rng.normal(size=3)
        err = np.eye(4)
        err[:3, :3] = r
        err[:3, 3] = c - r @ c + shift_mm * d / np.linalg.norm(d)
        out[bone] = err @ t
    return out


def _other_peers(args, scan, template, init, add):
    """greedy and SimpleITK's demons (issue R part 3) from the start ``init`` every method starts from, as elastix
    (the template resampled through it, their field composed with it; registration.baselines), each measured by
    ``add(method, field, seconds, peak MiB)``; left out by ``--no-greedy`` / ``--no-demons`` (greedy also when
    picsl-greedy is not installed)."""
    if greedy_available() and not args.no_greedy:
        with PeakMemory() as pm:
            b = greedy_register(scan, template, initial=init, seed=args.seed, **args.greedy)
        add(GREEDY, b.correspondence, b.seconds, pm.mib)
    if not args.no_demons:
        with PeakMemory() as pm:
            b = sitk_demons(scan, template, initial=init, seed=args.seed, **args.demons)
        add(DEMONS, b.correspondence, b.seconds, pm.mib)


def run_flex(args):
    """Issue I's protocol (module docstring): one table per case, methods side by side on the same start."""
    from registration.dense import DenseSettings, register_dense
    from registration.initialise import polyrigid_initial_field
    from registration.pose import estimate_poses, released_labels

    seeds = TUNING_SEEDS if args.split == "tuning" else HELD_OUT_SEEDS
    if args.seeds:
        seeds = tuple(args.seeds)
    summary = []
    for seed in seeds:
        for region, ph, wanted in _flex_phantoms(seed, args):
            template, labels = ph.template()
            sk = ph.skeleton
            bl = {b: sk.label_of(b) for b in sk.bone_names}
            xg = ph.geometry.world_coordinates().reshape(-1, 3)
            body_t = Volume(
                (ph.anatomy.distances_fast(xg)[:, -1] < 0).reshape(ph.geometry.array_shape).astype(np.uint8),
                ph.geometry,
            )
            scans = {sc.id: sc for sc in ph.scans()}
            t0 = time.perf_counter()
            est = estimate_poses(template, labels, {k: v.image for k, v in scans.items()}, sk)
            poses = {s.scan_id: s.pose for s in est.scans}
            # bones the pose stage could not place: their pose follows an ancestor (placed_transforms) and no
            # method holds them rigid (the workbench's init and register stages do the same)
            held = {
                s.scan_id: released_labels(labels, sk, [b for b, f in s.fits.items() if not f.ok]) for s in est.scans
            }
            if ph.acquisition is not None:  # --acquisition random: what was drawn
                print(f"\n{region} seed {seed}: {describe_acquisition(ph.acquisition)}", flush=True)
            print(
                f"\n{region} seed {seed} ({args.split}): {ph.geometry.describe()}; poses estimated in "
                f"{time.perf_counter() - t0:.0f} s",
                flush=True,
            )
            parents = {b: sk.bone(b).parent for b in sk.bone_names}
            vbd_weights = {}
            for sid in wanted:
                sc = scans[sid]
                # the study's 12 markers estimate the mean over marker-like skin points with ~0.3 mm of sampling
                # noise a marker: MARKER_SAMPLE more, drawn by the same rule, measure it without
                many = ph.markers(ph.posing_model(dict(ph.poses)[sid]), n=MARKER_SAMPLE, sample=1)
                truth = sc.correspondence
                body = body_on_scan(truth, body_t)
                phi = truth.data + sc.image.geometry.world_coordinates()
                bone = (ph.anatomy.distances_fast(phi.reshape(-1, 3))[:, :-1].min(axis=1) < 0).reshape(body.shape)
                bone &= body
                # the skin: the body's outermost voxel layer (face neighbours), thousands of points where the
                # study's markers are a dozen (Rhee Table 3's measure, one marker moving the mean by ~0.3 mm); a
                # limb cut by the grid's edge has no skin there (border_value=1)
                skin = body & ~ndimage.binary_erosion(body, border_value=1)
                # … and its part near the joints, where the markers are drawn (validation.phantoms: a joint radius
                # r from the axis, N(0, r/2) along it): template position within 1.5 r of a joint centre
                near = np.zeros(body.shape, bool)
                for jn, rad in ph.anatomy.joint_radius_mm.items():
                    near |= np.linalg.norm(phi - np.asarray(sk.joint(jn).center), axis=-1) < 1.5 * rad
                skin_joint = skin & near
                rows = {}

                def add(method, fld, seconds, mem, sigma=None):
                    rows[method] = field_measures(
                        sc.image,
                        template,
                        fld,
                        truth,
                        body,
                        bone,
                        sc.markers,
                        seconds,
                        mem,
                        sigma,
                        skin=skin,
                        skin_joint=skin_joint,
                    )
                    rows[method]["markers_many_mm"] = marker_med(fld, many)

                # the truth sampled on the scan grid folds too, where curled fingers touch or the crease compresses
                # tissue below the voxel: its row says how many of a method's folded voxels any exact field has
                add(TRUTH, truth, 0.0, 0.0)
                transforms = poses[sid].transforms
                # the bones every method holds rigid: those the pose stage placed (all of them from the true poses)
                hold = held[sid]
                if args.start == "skinning-truth":  # the same polyrigid start from the phantom's true bone poses
                    transforms, hold = sc.pose.transforms, labels
                if args.start == "perturbed":  # the estimated poses, each bone off by 2-5 degrees and 2 mm
                    # its own draw per study seed, region and scan
                    transforms = perturbed_transforms(
                        transforms, labels, bl, seed=[seed, ("knee", "hand").index(region), wanted.index(sid)]
                    )
                if args.start == "vbd" and "distance" not in vbd_weights:  # the weights stage's work, not timed
                    vbd_weights["distance"] = _weights(ph, "distance")
                with PeakMemory() as pm:
                    t1 = time.perf_counter()
                    if args.start == "vbd":  # what `--init vbd` starts from: distance weights, estimated poses
                        w, _ = vbd_weights["distance"]
                        init, _ = vbd_initial_field(
                            ph.geometry, sc.image.geometry, w, stack_transforms(transforms, w.bones), body=body_t.data
                        )
                    else:
                        init, _ = polyrigid_initial_field(labels, bl, parents, transforms, sc.image.geometry)
                    t_init = time.perf_counter() - t1
                add(START_ROWS[args.start], init, t_init, pm.mib)
                if (
                    not args.no_vbd_starts and args.start == "polyrigid"
                ):  # issue I part 3: the same poses blended by VBD, two kinds of weights
                    for kind in ("distance", "harmonic"):
                        if kind not in vbd_weights:
                            vbd_weights[kind] = _weights(ph, kind)
                        w, _ = vbd_weights[kind]
                        t1 = time.perf_counter()
                        v, _ = vbd_initial_field(
                            ph.geometry,
                            sc.image.geometry,
                            w,
                            stack_transforms(poses[sid].transforms, w.bones),
                            body=body_t.data,
                        )
                        add(f"initialised (VBD, {kind} weights)", v, time.perf_counter() - t1, 0.0)
                with PeakMemory() as pm:
                    r = register_dense(
                        sc.image,
                        template,
                        initial=init,
                        moving_labels=hold,
                        settings=getattr(args, "dense", None) or DenseSettings(),
                    )
                add(OURS, r.correspondence, r.seconds, pm.mib, sigma=r.uncertainty)
                if r.unfold:
                    print(_unfold_line(r.unfold), flush=True)
                if not args.no_adaptive:
                    with PeakMemory() as pm:
                        r = register_adaptive(
                            sc.image,
                            template,
                            initial=init,
                            rigid_mask=hold,
                            settings=AdaptiveSettings.initialised(seed=args.seed),
                        )
                    add("ours (Rhee Alg. 1, initialised preset)", r.correspondence, r.seconds, pm.mib)
                if elastix_available() and not args.no_elastix:
                    with PeakMemory() as pm:
                        b = elastix_bspline(sc.image, template, initial=init, metric="mi", seed=args.seed)
                    add(ELASTIX, b.correspondence, b.seconds, pm.mib)
                    if not args.no_elastix_rigidity:
                        with PeakMemory() as pm:
                            b = elastix_bspline(
                                sc.image, template, initial=init, metric="mi", seed=args.seed, rigidity_labels=hold
                            )
                        add(ELASTIX_RIGIDITY, b.correspondence, b.seconds, pm.mib)
                _other_peers(args, sc.image, template, init, add)
                if not args.no_sitk:
                    with PeakMemory() as pm:
                        b = sitk_bspline(sc.image, template, initial=init, metric="mi", seed=args.seed)
                    add("SimpleITK B-spline", b.correspondence, b.seconds, pm.mib)
                if ants_available():
                    with PeakMemory() as pm:
                        b = ants_syn(sc.image, template, initial=init, seed=args.seed)
                    add("ANTs SyN", b.correspondence, b.seconds, pm.mib)
                out = flex_report(f"{region} {sid}, seed {seed} ({args.split}), {args.start} start", rows)
                summary.append(out or {"case": f"{region} {sid} s{seed}", "rows": rows})
                summary[-1]["label"] = f"{region} {sid} s{seed}"
    flex_summary([s for s in summary if "med_ratio" in s], args.split)
    return summary


def _ratio(key):
    def f(rows):
        o, e = rows.get(OURS), rows.get(ELASTIX)
        return o[key] / e[key] if o and e and e[key] else float("nan")

    return f


def _start_row(rows):
    return next(v for m, v in rows.items() if m.startswith("initialised"))


def _peers(rows):
    """The peers that ran on a case: every method but ours (and Rhee's Algorithm 1), the starts and the truth —
    elastix, elastix + rigidity penalty, greedy, demons, and SimpleITK's B-spline and ANTs SyN when they ran."""
    return {m: v for m, v in rows.items() if not m.startswith(("ours", "initialised")) and m != TRUTH}


def _lowest(peers, key):
    """The lowest finite ``key`` among ``peers``' rows (NaN if none)."""
    vals = [v[key] for v in peers.values() if key in v and np.isfinite(v[key])]
    return min(vals) if vals else float("nan")


def best_peer(rows):
    """A case's best peer (issue R part 3): ``(name, ours' MED / its MED, ours' marker MED / the lowest marker MED
    among the peers)`` — the marker ratio is over the lowest of any peer, not necessarily the best-MED one's;
    ``(None, nan, nan)`` without ours or a peer."""
    peers, ours = _peers(rows), rows.get(OURS)
    if not peers or not ours:
        return None, float("nan"), float("nan")
    best = min(peers, key=lambda m: peers[m]["med_mm"])
    return best, ours["med_mm"] / peers[best]["med_mm"], ours["marker_med_mm"] / _lowest(peers, "marker_med_mm")


def _short(method):
    return "–" if method is None else PEER_SHORT.get(method, method)


def _name_counts(names):
    """The worst row's cell of a column of names: how often each was the one (most often first)."""
    counts = {}
    for n in names:
        counts[n] = counts.get(n, 0) + 1
    return ", ".join(f"{n} ×{k}" for n, k in sorted(counts.items(), key=lambda t: (-t[1], t[0])))


#: the one table per set (set_table): (header, value from a case's rows, the worse of two, cell format)
SET_COLUMNS = (
    ("start MED", lambda r: _start_row(r)["med_mm"], max, "{:.2f}"),
    ("ours MED", lambda r: r[OURS]["med_mm"], max, "{:.2f}"),
    ("elastix MED", lambda r: r[ELASTIX]["med_mm"] if ELASTIX in r else float("nan"), max, "{:.2f}"),
    ("MED ours / elastix", _ratio("med_mm"), max, "{:.2f}"),
    ("best peer", lambda r: _short(best_peer(r)[0]), "names", "{}"),
    ("MED ours / best peer", lambda r: best_peer(r)[1], max, "{:.2f}"),
    ("markers ours / lowest peer's", lambda r: best_peer(r)[2], max, "{:.2f}"),
    (
        "bone ours / elastix mm",
        lambda r: (r[OURS]["bone_mm"], r[ELASTIX]["bone_mm"] if ELASTIX in r else float("nan")),
        None,
        "{:.3f} / {:.3f}",
    ),
    ("soft ours / elastix", _ratio("soft_mm"), max, "{:.2f}"),
    ("P95 ours / elastix", _ratio("p95_mm"), max, "{:.2f}"),
    ("markers ours / elastix", _ratio("marker_med_mm"), max, "{:.2f}"),
    ("CC ours / elastix", _ratio("cc"), min, "{:.3f}"),
    ("folded ours (start)", lambda r: (r[OURS]["n_folded"], _start_row(r)["n_folded"]), None, "{} ({})"),
    ("time ours / elastix", _ratio("seconds"), max, "{:.2f}"),
    ("peak MiB ours / elastix", _ratio("mem_mib"), max, "{:.2f}"),
    ("MED ours / start", lambda r: r[OURS]["med_mm"] / _start_row(r)["med_mm"], max, "{:.2f}"),
    # issue R's calibration of ours' expected error σ over the body: the share within 2σ (≥ 0.85 asked), RMS error /
    # RMS σ (0.67-1.5; worst: the farthest from 1 by ratio) and the rank correlation of σ and the error (≥ 0.4)
    ("within 2σ", lambda r: _cal(r, "within_2sigma"), min, "{:.2f}"),
    (
        "RMS error / σ",
        lambda r: _cal(r, "rms_ratio"),
        lambda seq, key: max(seq, key=lambda t: abs(np.log(key(t)))),
        "{:.2f}",
    ),
    ("σ rank corr.", lambda r: _cal(r, "spearman"), min, "{:.2f}"),
)


def _cal(rows, key):
    """Ours' calibration measure ``key`` (field_measures' "calibration"), NaN when it has none."""
    v = (rows[OURS].get("calibration") or {}).get(key)
    return float("nan") if v is None else float(v)


def set_table(name, summary):
    """One set's table (issue M part 5): per case ours against elastix from the same start, against the best peer
    (:func:`best_peer`: the lowest MED of the peers that ran; markers: over the lowest marker MED of any peer) and
    against the start, then the worst case of each column (the largest ratio, the smallest CC ratio; bone: ours'
    largest; folded: ours' most added to the start's) naming the case; for the best peer, how often each was."""
    items = [(s["label"], s["rows"]) for s in summary if OURS in s.get("rows", {})]
    print(f"\n## {name}: ours (dense) against elastix and the best peer from the same start ({len(items)} cases)\n")
    if not items:
        print("(no case ran)")
        return
    print("| case | " + " | ".join(c[0] for c in SET_COLUMNS) + " |")
    print("|---" * (len(SET_COLUMNS) + 1) + "|")

    def cell(fmt, v):
        if isinstance(v, tuple):  # a pair: each part on its own ("–" where one is missing)
            parts = fmt.replace(" (", " / ").rstrip(")").split(" / ")
            text = ["–" if isinstance(x, float) and not np.isfinite(x) else f.format(x) for f, x in zip(parts, v)]
            return f"{text[0]} ({text[1]})" if " (" in fmt else " / ".join(text)
        return "–" if isinstance(v, float) and not np.isfinite(v) else fmt.format(v)

    for label, rows in items:
        print(f"| {label} | " + " | ".join(cell(fmt, f(rows)) for _, f, _, fmt in SET_COLUMNS) + " |")
    worst = []
    for _, f, worse, fmt in SET_COLUMNS:
        vals = [(label, f(rows)) for label, rows in items]
        if worse == "names":  # which peer was best: how often each
            worst.append(_name_counts(v for _, v in vals))
            continue
        if worse is None:  # a pair: ours' value decides (bone: the largest; folded: the most added)
            key = (lambda v: v[0]) if "{:.3f}" in fmt else (lambda v: v[0] - v[1])
            finite = [t for t in vals if np.isfinite(key(t[1]))]
        else:
            key = None
            finite = [t for t in vals if np.isfinite(t[1])]
        if not finite:
            worst.append("–")
            continue
        label, v = max(finite, key=lambda t: key(t[1])) if key else worse(finite, key=lambda t: t[1])
        of = f", {len(finite)} of {len(vals)}" if len(finite) < len(vals) else ""
        worst.append(f"{cell(fmt, v)} [{label}{of}]")
    print("| **worst** | " + " | ".join(worst) + " |", flush=True)


def flex_summary(summary, split):
    """One line per case: issue I's acceptance figures for ours against the best peer of the same run (the lowest
    MED; the marker and skin columns: over the lowest of any peer, not necessarily the best-MED one's), and a last
    row with the worst case of each column (the largest; best peer: how often each was)."""
    summary = [s for s in summary if s]
    if not summary:
        return
    print(f"\n## summary ({split} seeds): ours (dense) against the best peer per case\n")
    print(
        f"| case | best peer | MED ours / best | marker MED ours / lowest peer's | {MARKER_SAMPLE} markers ours / "
        "lowest peer's | skin MED ours / lowest peer's | skin near joints ours / lowest peer's | folded voxels ours "
        "(truth's) | bone MED ours mm | time ours / elastix |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    nan = float("nan")
    keys = ("med_ratio", "marker_ratio", "many_ratio", "skin_ratio", "skin_joint_ratio")
    for s in summary:
        print(
            f"| {s['case']} | {_short(s['best'])} | "
            + " | ".join(f"{s.get(k, nan):.2f}" for k in keys)
            + f" | {s['n_folded']} ({s['n_folded_truth']}) | {s['bone_mm']:.3f} | {s['time_ratio']:.2f} |"
        )

    def worst(key, fmt):
        finite = [(s.get("label", s["case"]), s.get(key, nan)) for s in summary if np.isfinite(s.get(key, nan))]
        if not finite:
            return "–"
        case, v = max(finite, key=lambda t: t[1])
        return f"{fmt.format(v)} [{case}]"

    print(
        f"| **worst** | {_name_counts(_short(s['best']) for s in summary)} | "
        + " | ".join(worst(k, "{:.2f}") for k in keys)
        + f" | {worst('n_folded', '{}')} | {worst('bone_mm', '{:.3f}')} | {worst('time_ratio', '{:.2f}')} |"
    )
    print(
        "\n(issue I asks: MED ratio ≤ 0.8, marker ratio ≤ 1, 0 folded, bone ≤ 0.1 mm, time ratio ≤ 2; the skin MED is "
        f"the markers' measure over the body's outer voxel layer, near the joints its part where the markers "
        f"are drawn; "
        f"{MARKER_SAMPLE} markers: drawn by the study's rule, beside its 12)",
        flush=True,
    )


# the columns of flex_report's tables: (header, measure, cell text of a row, the worse of two values); a table has
# those its rows all measured (the external set has no skin nor 200-marker columns)
REPORT_COLUMNS = (
    ("MED mm", "med_mm", lambda v: f"{v['med_mm']:.2f}", max),
    ("bone", "bone_mm", lambda v: f"{v['bone_mm']:.3f}", max),
    ("soft", "soft_mm", lambda v: f"{v['soft_mm']:.2f}", max),
    ("P95", "p95_mm", lambda v: f"{v['p95_mm']:.2f}", max),
    ("marker MED", "marker_med_mm", lambda v: f"{v['marker_med_mm']:.2f}", max),
    (f"{MARKER_SAMPLE} markers", "markers_many_mm", lambda v: f"{v['markers_many_mm']:.2f}", max),
    ("skin MED", "skin_mm", lambda v: f"{v['skin_mm']:.2f}", max),
    ("near joints", "skin_joint_mm", lambda v: f"{v['skin_joint_mm']:.2f}", max),
    ("CC", "cc", lambda v: f"{v['cc']:.3f}", min),
    ("folded (voxels)", "n_folded", lambda v: f"{v['folded_fraction']:.5f} ({v['n_folded']})", max),
    ("s", "seconds", lambda v: f"{v['seconds']:.1f}", max),
    ("peak MiB", "mem_mib", lambda v: f"{v['mem_mib']:.0f}", max),
)


def _columns(rows):
    rows = list(rows)
    return [c for c in REPORT_COLUMNS if all(c[1] in v for v in rows)]


def flex_report(title, rows):
    """One case's table (the columns its rows have) and ours against the best peer (:func:`best_peer`; the marker,
    200-marker and skin ratios over the lowest of any peer); returns the summary's figures (``None`` without ours
    or a peer)."""
    cols = _columns(rows.values())
    print(f"\n### {title}\n")
    print("| method | " + " | ".join(c[0] for c in cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for m, v in rows.items():
        print(f"| {m} | " + " | ".join(c[2](v) for c in cols) + " |")
    peers = _peers(rows)
    ours = rows.get(OURS)
    if peers and ours:
        best, med_ratio, marker_ratio = best_peer(rows)
        el = peers.get(ELASTIX)
        out = {
            "case": title,
            "best": best,
            "rows": rows,
            "med_ratio": med_ratio,
            "marker_ratio": marker_ratio,
            "n_folded": ours["n_folded"],
            "n_folded_truth": rows[TRUTH]["n_folded"] if TRUTH in rows else None,
            "bone_mm": ours["bone_mm"],
            "time_ratio": ours["seconds"] / el["seconds"] if el else float("nan"),
        }
        for k in ("markers_many", "skin", "skin_joint"):  # over the lowest of any peer, as the markers
            if f"{k}_mm" in ours:
                out["many_ratio" if k == "markers_many" else f"{k}_ratio"] = ours[f"{k}_mm"] / _lowest(peers, f"{k}_mm")
        print(
            f"\nours / best peer ({best}): MED {out['med_ratio']:.2f}; marker MED ours / lowest peer's "
            f"{out['marker_ratio']:.2f}" + (f"; time / elastix {out['time_ratio']:.2f}" if el else ""),
            flush=True,
        )
        _print_calibration(ours)
        return out
    _print_calibration(ours)
    return None


def _print_calibration(ours) -> None:
    """Ours' expected error against the true one (field_measures' "calibration"), when it has one."""
    cal = (ours or {}).get("calibration")
    if cal:
        print(
            f"ours' expected error σ against the true error over the body: {100 * cal['within_2sigma']:.0f} % "
            f"within 2σ, RMS error / RMS σ {cal['rms_ratio']:.2f}, rank correlation {cal['spearman']:.2f}",
            flush=True,
        )


def calibration_plot(sets, path) -> None:
    """Ours' calibration per case (:func:`field_measures`' "calibration" bins: per σ decile the mean σ and the RMS
    true error, mm), one panel per set, one line per case, the diagonal where σ is the RMS error; written to
    ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = [
        (name, [s for s in summary if (s.get("rows", {}).get(OURS) or {}).get("calibration")]) for name, summary in sets
    ]
    sets = [(name, summary) for name, summary in sets if summary]
    if not sets:
        print(f"--calibration-plot {path}: no case has ours' expected error; nothing drawn", flush=True)
        return
    fig, axes = plt.subplots(1, len(sets), figsize=(5.2 * len(sets), 4.8), squeeze=False)
    for ax, (name, summary) in zip(axes[0], sets):
        top = 0.0
        for s in summary:
            bins = np.asarray(s["rows"][OURS]["calibration"]["bins"], float)
            if bins.size:
                ax.plot(bins[:, 0], bins[:, 1], marker="o", ms=3, label=s.get("label", s.get("case", "")))
                top = max(top, float(bins.max()))
        ax.plot([0, top], [0, top], color="grey", lw=1, ls="--", label="σ = RMS error")
        ax.set(xlabel="expected error σ, decile mean (mm)", ylabel="RMS true error in the decile (mm)", title=name)
        ax.set_xlim(0, top * 1.05)
        ax.set_ylim(0, top * 1.05)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"calibration plot: {path}", flush=True)


def _tree_state(root):
    """``{relative path: (size, modification time ns)}`` of every file under ``root``."""
    return {
        str(f.relative_to(root)): (f.stat().st_size, f.stat().st_mtime_ns)
        for f in sorted(root.rglob("*"))
        if f.is_file()
    }


def _workbench(argv):
    """``workbench ARGV`` in this process (:func:`workbench.cli.main`); returns ``(exit code, error text)``, the
    text being the command's stderr lines that name an error, or the traceback of an exception it let through."""
    import contextlib
    import io
    import traceback

    from workbench.cli import main as workbench_main

    class Tee(io.StringIO):  # what the command writes to stderr, still shown as it goes
        def write(self, text):
            sys.__stderr__.write(text)
            return super().write(text)

    err = Tee()
    print(f"  workbench {' '.join(argv)}", flush=True)
    try:
        with contextlib.redirect_stderr(err):
            rc = workbench_main(argv)
    except Exception:  # noqa: BLE001 — reported as the study's failure, the other studies still run
        return 1, traceback.format_exc()
    lines = [ln for ln in err.getvalue().splitlines() if "error" in ln.lower()]
    return rc, "\n".join(lines) or err.getvalue().strip()


def run_external(args):
    """The external set (module docstring): each study copied into ``args.work``, run through ``workbench run``,
    elastix from the init stage's start; one table per scan and the set's summary.  Returns the number of
    studies whose ``workbench run`` failed."""
    import json
    import shutil
    import tempfile

    from registration.segmentation import segment_body
    from workbench.stages import ORDER
    from workbench.study import read_study, recorded_times

    src = Path(args.external).resolve()
    if not src.is_dir():
        print(f"external: {src} is absent; the external case is skipped", flush=True)
        return 0
    studies = sorted(d for d in src.iterdir() if (d / "study.json").is_file())
    work = Path(args.work).resolve() if args.work else Path(tempfile.mkdtemp(prefix="avw-external-"))
    print(
        f"\nexternal set {src} ({', '.join(d.name for d in studies)}; held out: never used for choosing settings), "
        f"study copies in {work}",
        flush=True,
    )
    before = _tree_state(src)
    if elastix_available() and not args.no_elastix:
        load_itk()  # ITK's modules loaded before any sampler starts: elastix's peak memory is its registration's
    summary, failures = [], []
    for d in studies:
        copy = work / d.name
        if copy.exists():
            raise SystemExit(
                f"external: {copy} exists; give --work a folder without it (each run starts from a fresh copy)"
            )
        shutil.copytree(d, copy)
        print(f"\n{d.name}: copied to {copy}", flush=True)
        scan_ids = read_study(copy).scan_ids
        mem = {}
        # workbench run COPY --until register, in steps: the whole-study stages before it (bones, pose, weights),
        # then each scan's init and register, each under its own memory sampler
        steps = [("weights", None, ["run", str(copy), "--until", "weights", "--quiet"])]
        for sid in scan_ids:
            steps += [
                (stage, sid, ["run", str(copy), "--until", stage, "--scan", sid, "--quiet"])
                for stage in ("init", "register")
            ]
        for stage, sid, argv in steps:
            with PeakMemory() as pm:
                rc, error = _workbench(argv)
            if rc != 0:
                break
            mem[stage, sid] = pm.mib
        if rc != 0:
            print(f"{d.name}: `workbench {' '.join(argv)}` failed (exit {rc}); the study is skipped", flush=True)
            failures.append((d.name, argv, rc, error))
            continue
        st = read_study(copy)
        print(f"{d.name}: the workbench's recorded times (study.json)", flush=True)
        print("\n".join(recorded_times(st, ORDER)), flush=True)
        template, labels = st.template(), st.template_labels()
        body_t = segment_body(template, labels=labels)  # the weights stage's body mask, which validate scores over
        bones_t = Volume((np.asarray(labels.data) > 0).astype(np.uint8), labels.geometry)
        log = st.path("logs/phantom.json")
        logged = (
            {s["id"]: s.get("body_voxels_scan") for s in json.loads(log.read_text(encoding="utf-8")).get("scans", [])}
            if log.is_file()
            else {}
        )
        for sid in scan_ids:
            scan, truth, markers = st.scan(sid), st.truth_correspondence(sid), st.truth_markers(sid)
            body = body_on_scan(truth, body_t)
            bone = body_on_scan(truth, bones_t) & body
            init, ours = st.init_field(sid), st.registration_correspondence(sid)
            start_info, reg_log = st.init_info(sid), st.registration_log(sid)
            e_init, e_reg = st.stage_entry("init", sid), st.stage_entry("register", sid)
            t_reg = e_reg.get("timings") or {}
            print(
                f"\n{d.name} / {sid}: {scan.geometry.describe()}; body {int(body.sum())} voxels"
                + (f" (the generator's log: {logged[sid]})" if logged.get(sid) is not None else "")
                + f", bone {int(bone.sum())}; start: {start_info['method']} "
                f"({start_info.get('pose', 'estimated')} pose), bones the pose stage flagged: "
                f"{start_info.get('flagged_bones') or 'none'}; ours: {reg_log.get('method')}, register stage "
                f"{e_reg['seconds']:.1f} s (registration {t_reg.get('registration', float('nan')):.1f} s, "
                f"inversion onto the template grid {t_reg.get('inverse', float('nan')):.1f} s)",
                flush=True,
            )
            unfold = (reg_log.get("summary") or {}).get("unfold")
            if unfold:
                print(_unfold_line(unfold), flush=True)
            rows = {}

            def add(method, fld, seconds, mib, sigma=None):
                rows[method] = field_measures(scan, template, fld, truth, body, bone, markers, seconds, mib, sigma)

            add(TRUTH, truth, 0.0, 0.0)
            add(
                f"initialised ({start_info['method']}, {start_info.get('pose', 'estimated')} poses)",
                init,
                e_init["seconds"],
                mem["init", sid],
            )
            add(
                OURS,
                ours,
                t_reg.get("registration", e_reg["seconds"]),
                mem["register", sid],
                st.registration_uncertainty(sid),
            )
            if elastix_available() and not args.no_elastix:
                with PeakMemory() as pm:
                    b = elastix_bspline(scan, template, initial=init, metric="mi", seed=args.seed)
                add(ELASTIX, b.correspondence, b.seconds, pm.mib)
            _other_peers(args, scan, template, init, add)
            out = flex_report(f"{d.name} / {sid} (external, held out)", rows) or {"case": d.name, "rows": rows}
            out["label"] = f"{d.name}/{sid}"
            summary.append(out)
    external_summary(summary, failures, elastix_available() and not args.no_elastix)
    after = _tree_state(src)
    changed = sorted(f for f in set(before) | set(after) if before.get(f) != after.get(f))
    print(
        f"\nthe shared folder {src}: "
        + (
            "CHANGED: " + ", ".join(changed)
            if changed
            else "unchanged (every file's size and modification time as before)"
        ),
        flush=True,
    )
    print(f"study copies (the stages' outputs) left in {work}", flush=True)
    args.external_summary = summary
    return len(failures)


def external_summary(summary, failures, elastix):
    """The external set's summary: per scan ours against elastix, against the best peer (:func:`best_peer`: the
    lowest MED of the peers that ran; markers: over the lowest marker MED of any peer) and against its own start,
    the worst scan of every column (for the best peer: how often each was), and the scans where ours is worse than
    its start."""
    print(
        "\n## summary: the external set (held out), ours (dense) against elastix and the best peer from the same "
        "start\n"
    )
    if not elastix:
        print("(elastix unavailable: itk-elastix not installed, `make bench`, or --no-elastix)")
    for name, argv, rc, error in failures:
        print(f"{name}: `workbench {' '.join(argv)}` failed (exit {rc}):\n{error}\n")
    if not summary:
        return
    start_of = {s["label"]: next(m for m in s["rows"] if m.startswith("initialised")) for s in summary}
    print(
        "| scan | MED ours / elastix | marker MED ours / elastix | best peer | MED ours / best peer | markers ours / "
        "lowest peer's | time ours / elastix | MED ours / start | marker MED ours / start |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    table = []
    for s in summary:
        rows = s["rows"]
        o, i = rows[OURS], rows[start_of[s["label"]]]
        best, med_best, markers_lowest = best_peer(rows)
        table.append(
            (
                s["label"],
                _ratio("med_mm")(rows),  # elastix's own row (the best peer's ratios are the next columns)
                _ratio("marker_med_mm")(rows),
                _short(best),
                med_best,
                markers_lowest,
                _ratio("seconds")(rows),
                o["med_mm"] / i["med_mm"],
                o["marker_med_mm"] / i["marker_med_mm"],
            )
        )
    for r in table:
        print(f"| {r[0]} | " + " | ".join(v if isinstance(v, str) else f"{v:.2f}" for v in r[1:]) + " |")

    def worst(k):
        if isinstance(table[0][k], str):  # the best peer: how often each
            return _name_counts(r[k] for r in table)
        finite = [r for r in table if np.isfinite(r[k])]
        if not finite:
            return "–"
        r = max(finite, key=lambda r: r[k])
        return f"{r[k]:.2f} [{r[0]}]"

    print("| **worst** | " + " | ".join(worst(k) for k in range(1, len(table[0]))) + " |")

    print("\n### worst scan of each column over the external set\n")
    methods = [TRUTH, "start (init stage)", OURS, ELASTIX, GREEDY, DEMONS]
    per_method = {
        m: [
            (s["label"], s["rows"][start_of[s["label"]]] if m == "start (init stage)" else s["rows"][m])
            for s in summary
            if m == "start (init stage)" or m in s["rows"]
        ]
        for m in methods
    }
    cols = _columns(v for s in summary for v in s["rows"].values())
    print("| method | " + " | ".join(c[0] for c in cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for m, items in per_method.items():
        if not items:
            continue
        cells = []
        for _, key, cell, worse in cols:
            finite = [(lab, v) for lab, v in items if np.isfinite(v[key])]
            if not finite:
                cells.append("–")
                continue
            lab, v = worse(finite, key=lambda t: t[1][key])
            cells.append(f"{cell(v)} [{lab}]")
        print(f"| {m} | " + " | ".join(cells) + " |")
    worse_than_start = [
        f"{lab} (MED {s['rows'][OURS]['med_mm']:.2f} vs {s['rows'][start_of[lab]]['med_mm']:.2f} mm, "
        f"marker MED {s['rows'][OURS]['marker_med_mm']:.2f} vs "
        f"{s['rows'][start_of[lab]]['marker_med_mm']:.2f} mm)"
        for s in summary
        for lab in [s["label"]]
        if s["rows"][OURS]["med_mm"] > s["rows"][start_of[lab]]["med_mm"]
        or s["rows"][OURS]["marker_med_mm"] > s["rows"][start_of[lab]]["marker_med_mm"]
    ]
    print(
        "\nours worse than its own start (MED or marker MED): "
        + ("; ".join(worse_than_start) if worse_than_start else "no scan")
    )
    print(
        "(worst: the largest value of a column over the scans [which scan], the smallest for CC; ratios > 1: ours "
        "is worse. Times: the start's is the init stage's, ours the register stage's registration without the "
        "inversion, "
        "on a shared machine: compare ratios, not seconds)",
        flush=True,
    )


def _cases(args):
    if "table2" in args.cases:
        ph = make_phantom(
            "knee", size=args.size, posing="vbd", poses=(("bend10", {"knee": [10.0, 0.0, 0.0]}),), seed=args.seed
        )
        yield "table2", ph, False
    if "knee" in args.cases:
        yield "knee", make_phantom("knee", size=args.size, seed=args.seed), True
    if "hand" in args.cases:
        yield "hand", make_phantom("hand", size=args.size, seed=args.seed), True


def _weights(ph, method):
    """Skinning weights and body mask of the phantom's template, from the library (as the weights stage does)."""
    from deformation.models.harmonic import harmonic_voxel_weights
    from deformation.models.skinning import distance_voxel_weights
    from registration.segmentation import segment_body

    template, labels = ph.template()
    sk = ph.skeleton
    bone_labels = {b: sk.label_of(b) for b in sk.bone_names}
    body = segment_body(template, labels=labels)
    if method == "harmonic":
        return harmonic_voxel_weights(labels, bone_labels, body).weights, body
    return distance_voxel_weights(labels, bone_labels), body


def _level_progress(tag):
    """Print each finished block level of our registration (paper-size runs take many minutes)."""

    def show(info):
        lv = info.get("level_done")
        if lv is not None:
            print(
                f"    {tag} level {lv.level}: {lv.steps} steps, {lv.accepted} accepted, "
                f"{lv.metric} {lv.metric_before:.4g} -> {lv.metric_after:.4g}, {lv.seconds:.1f} s",
                flush=True,
            )

    return show


def run_case(name, ph, articulated, args):
    template, labels = ph.template()
    body_t = Volume(
        (ph.anatomy.distances_fast(ph.geometry.world_coordinates().reshape(-1, 3))[:, -1] < 0)
        .reshape(ph.geometry.array_shape)
        .astype(np.uint8),
        ph.geometry,
    )
    weights = _weights(ph, args.weights)[0] if articulated and not args.from_truth else None  # VBD only
    rows: dict[str, list] = {}
    scans = list(ph.scans())
    if articulated:
        scans = scans[1:]  # the template is pose 0 (Rhee: the template registered to the others)
    for sc in scans:
        truth = sc.correspondence
        body = body_on_scan(truth, body_t)
        markers = sc.markers if articulated else None
        zero = Volume(np.zeros(truth.data.shape, np.float32), truth.geometry)

        def add(method, field, registered, seconds):
            m = registration_measures(sc.image, registered, field, truth=truth, body=body, markers=markers)
            m["seconds"] = seconds
            rows.setdefault(method, []).append(m)

        add("source", zero, warp_template(template, zero), 0.0)
        initial = None
        if args.from_truth:  # the intensity floor: how far each method drifts from the exact answer
            initial = truth
            add(
                "initialised",
                truth,
                warp_template(template, truth),
                0.0,
            )
        elif articulated:
            t0 = time.perf_counter()
            t = stack_transforms(sc.pose.transforms, weights.bones)
            initial, _ = vbd_initial_field(
                ph.geometry, sc.image.geometry, weights, t, body=body_t.data, unfold=args.unfold_init
            )
            add(
                "initialised",
                initial,
                warp_template(template, initial),
                time.perf_counter() - t0,
            )
        if articulated or args.from_truth:
            st = AdaptiveSettings.initialised(seed=args.seed)
        else:
            st = AdaptiveSettings(seed=args.seed)
        res = register_adaptive(
            sc.image,
            template,
            initial=initial,
            rigid_mask=labels if articulated else None,
            settings=st,
            progress=_level_progress(f"{sc.id} ours"),
        )
        add("ours", res.correspondence, res.registered, res.seconds)
        rows["ours"][-1]["control_points"] = res.control_points
        from registration.dense import register_dense

        d = register_dense(sc.image, template, initial=initial, moving_labels=labels if articulated else None)
        add("ours (dense)", d.correspondence, d.registered, d.seconds)
        if args.paper_preset:
            res = register_adaptive(
                sc.image,
                template,
                initial=initial,
                rigid_mask=labels if articulated else None,
                settings=AdaptiveSettings.paper(seed=args.seed),
                progress=_level_progress(f"{sc.id} ours (paper preset)"),
            )
            add("ours (paper preset)", res.correspondence, res.registered, res.seconds)
        b = sitk_bspline(sc.image, template, initial=initial, metric="mi", seed=args.seed)
        add("sitk-bspline", b.correspondence, b.registered, b.seconds)
        if elastix_available() and not args.no_elastix:
            b = elastix_bspline(sc.image, template, initial=initial, metric="mi", seed=args.seed)
            add("elastix-bspline", b.correspondence, b.registered, b.seconds)
        line = "; ".join(f"{m} {rows[m][-1]['med_mm']:.2f}" for m in rows if m != "source")
        print(f"  {name}/{sc.id} MED mm: {line}", flush=True)
    return rows


def report(name, rows):
    keys = list(MEASURE_KEYS) + ["seconds"]

    def avg(values):
        v = np.asarray(values, float)
        return float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else float("nan")

    mean = {m: {k: avg([r[k] for r in rs]) for k in keys} for m, rs in rows.items()}
    print(f"\n## {name} ({len(next(iter(rows.values())))} scans, means)\n")
    print("| volume | MED mm | marker MED mm | SSD | CC | MI | folded | s |")
    print("|---|---|---|---|---|---|---|---|")
    for m, v in mean.items():
        print(
            f"| {m} | {v['med_mm']:.2f} | {v['marker_med_mm']:.2f} | {v['ssd']:.1f} | {v['cc']:.3f} | "
            f"{v['mi']:.3f} | {v['folded_fraction']:.5f} | {v['seconds']:.1f} |"
        )
    for m, v in PAPER.get(name, {}).items():
        print(
            f"| paper {m} | {v.get('med_mm', float('nan')):.2f} | {v.get('marker_med_mm', float('nan')):.2f} | "
            f"{v.get('ssd', float('nan')):.1f} | {v.get('cc', float('nan')):.3f} | "
            f"{v.get('mi', float('nan')):.3f} | | |"
        )
    src = mean["source"]["med_mm"]
    ours = mean["ours"]
    print(
        f"\nours: MED reduced by {100 * (1 - ours['med_mm'] / src):.0f} % from the source; "
        f"{np.mean([r.get('control_points', 0) for r in rows['ours']]):.0f} control points per scan"
    )
    if "initialised" in mean:
        better = sum(o["med_mm"] < i["med_mm"] for o, i in zip(rows["ours"], rows["initialised"]))
        print(f"ours beats the initialisation on MED on {better}/{len(rows['ours'])} scans")
    for method in ("ours", "ours (dense)"):
        for base in ("sitk-bspline", "elastix-bspline"):
            if base in mean and method in mean:
                b, o = mean[base], mean[method]
                print(
                    f"{method} / {base}: MED ratio {o['med_mm'] / b['med_mm']:.2f}, time ratio "
                    f"{o['seconds'] / b['seconds']:.2f}"
                )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--cases",
        nargs="+",
        choices=["table2", "knee", "hand", "flex", "external", "suite"],
        default=["table2", "knee"],
    )
    p.add_argument(
        "--split",
        choices=["tuning", "held-out"],
        default="held-out",
        help="flex: the seeds settings were tuned on, or the held-out ones (default). external: no "
        "split, its studies are never used for choosing settings (always held out)",
    )
    p.add_argument(
        "--external",
        default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "external-phantoms"),
        help="external: the folder of study folders (default: <repository>/../shared/data/"
        "external-phantoms); only read: each study is copied into --work",
    )
    p.add_argument(
        "--work",
        help="external: the folder the study copies are made and run in (default: a new "
        "temporary folder); it must not hold folders of the studies' names",
    )
    p.add_argument("--seeds", type=int, nargs="+", help="flex: these seeds instead of the split's")
    p.add_argument("--knee-only", action="store_true", help="flex: leave the hand out")
    p.add_argument("--hand-only", action="store_true", help="flex: leave the knee out")
    p.add_argument("--no-adaptive", action="store_true", help="flex: leave Rhee's Algorithm 1 out")
    p.add_argument("--no-sitk", action="store_true")
    p.add_argument(
        "--start",
        choices=list(START_ROWS),
        default="polyrigid",
        help="flex: the start every method registers from (issue M part 3): the polyrigid flow of the "
        "estimated poses (the workbench's default), VBD of the same poses (it folds in the crease), "
        "the polyrigid flow of the estimated poses with every bone off by 2-5 degrees and 2 mm, "
        "or the polyrigid flow of the phantom's true bone poses (skinning-truth: no pose error; every bone "
        "held rigid)",
    )
    p.add_argument(
        "--acquisition",
        choices=list(ACQUISITIONS),
        default="fixed",
        help="flex: the phantoms' acquisition: the modality's fixed noise, bias and contrast, or drawn per "
        "seed (noise model and SNR 8-40, bias 0-20 %%, gain, a contrast between T1-like and CT-like; "
        "validation.phantoms.generate.draw_acquisition). The voxel spacing stays the case's",
    )
    p.add_argument(
        "--no-vbd-starts",
        action="store_true",
        help="flex: leave out the VBD starts (distance and harmonic weights) measured beside the polyrigid one",
    )
    p.add_argument("--size", choices=["test", "paper"], default="test")
    p.add_argument(
        "--weights",
        choices=["distance", "harmonic"],
        default="distance",
        help="skinning weights for the VBD initialisation. Default: distance (fast)",
    )
    p.add_argument("--paper-preset", action="store_true", help="also run Rhee's settings (levels 3-5, NM)")
    p.add_argument(
        "--unfold-init",
        action="store_true",
        help="repair the folds of the VBD initialisation (deformation.fields.displacement.unfold) before every method",
    )
    p.add_argument(
        "--from-truth",
        action="store_true",
        help="start every method from the ground-truth field instead (the 'initialised' row is then "
        "the truth): each method's MED is how far intensity alone pulls it off the exact answer, "
        "the floor below which no start can be improved",
    )
    p.add_argument("--no-elastix", action="store_true")
    p.add_argument(
        "--no-elastix-rigidity",
        action="store_true",
        help="flex: leave out elastix with the rigidity penalty on the bones (the slowest peer)",
    )
    p.add_argument(
        "--no-greedy",
        action="store_true",
        help="flex, external: leave out PICSL greedy (registration.baselines.greedy_register; also left out "
        "without picsl-greedy)",
    )
    p.add_argument(
        "--no-demons",
        action="store_true",
        help="flex, external: leave out SimpleITK's demons (registration.baselines.sitk_demons)",
    )
    for peer, fn in (("greedy", "greedy_register"), ("demons", "sitk_demons")):
        p.add_argument(
            f"--{peer}-settings",
            metavar="JSON",
            default="{}",
            help=f"flex, external: keyword arguments of registration.baselines.{fn} as a JSON object (default: its "
            "defaults); choose them on --split tuning only",
        )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--calibration-plot",
        metavar="PNG",
        type=Path,
        help="flex, external, suite: also draw ours' calibration (per σ decile, RMS true error against mean σ; one "
        "line per case, one panel per set) to this PNG",
    )
    p.add_argument(
        "--dense-settings",
        metavar="JSON",
        default="{}",
        help="flex: the dense registration's settings (registration.dense.DenseSettings fields as a JSON "
        "object, e.g. '{\"interpolation_noise\": true}'; default: its defaults).  The external set "
        "runs the workbench's own chain, which does not take them",
    )
    args = p.parse_args(argv)
    try:
        from registration.dense import DenseSettings

        kw = json.loads(args.dense_settings)
        if not isinstance(kw, dict):
            raise ValueError("not a JSON object")
        args.dense = DenseSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()})
    except (ValueError, TypeError) as e:
        p.error(f"--dense-settings {args.dense_settings!r}: {e}")
    for peer in ("greedy", "demons"):
        text = getattr(args, f"{peer}_settings")
        try:
            peer_kw = json.loads(text)
            if not isinstance(peer_kw, dict):
                raise ValueError("not a JSON object")
        except ValueError as e:
            p.error(f"--{peer}-settings {text!r}: {e}")
        setattr(args, peer, {k: tuple(v) if isinstance(v, list) else v for k, v in peer_kw.items()})
    if kw and any(c in args.cases for c in ("external", "suite", "table2", "knee", "hand")):
        p.error(
            "--dense-settings applies to --cases flex only (the external set runs the workbench's own chain, "
            "the others the defaults): run the flex cases with it"
        )
    if args.knee_only and args.hand_only:
        p.error("--knee-only and --hand-only leave nothing to run: give one of them")
    if args.from_truth and args.unfold_init:
        p.error("--from-truth starts from the ground truth, --unfold-init repairs the VBD start: give one of them")
    elx = "available" if elastix_available() else "not installed (pip install -e .[bench])"
    elx += "; greedy " + (
        "off" if args.no_greedy else "available" if greedy_available() else "not installed (pip install -e .[bench])"
    )
    elx += "; demons " + ("off" if args.no_demons else "on")
    if args.cases == ["flex"]:  # its own seeds and start (run_flex prints them per case)
        print(
            f"registration benchmark, issue I's flex cases ({args.split} seeds), start: "
            f"{START_ROWS[args.start].removeprefix('initialised ')}; elastix {elx}"
            + (f"; ours with the dense settings {args.dense_settings}" if kw else "")
        )
    elif args.cases == ["suite"]:
        print(
            f"registration benchmark, the three sets: tuning and held-out draws ({args.acquisition} acquisition, "
            f"{START_ROWS[args.start].removeprefix('initialised ')}) and the external set; elastix {elx}"
        )
    elif args.cases == ["external"]:  # the workbench's own chain and start (run_external prints them per study)
        print(f"registration benchmark, the external set (held out), the workbench's start; elastix {elx}")
    else:
        print(
            f"registration benchmark, {args.size} size, seed {args.seed}, "
            f"{'ground-truth' if args.from_truth else 'unfolded VBD' if args.unfold_init else 'raw VBD'} "
            f"initialisation; elastix {elx}"
        )
    if "suite" in args.cases:  # issue M part 5: the tuning draws, the held-out draws and the external set
        import copy

        sets = []
        for split in ("tuning", "held-out"):
            a = copy.copy(args)
            a.split, a.seeds = split, None
            sets.append((f"{split} draws ({a.acquisition} acquisition, {a.start} start)", run_flex(a)))
        failed = run_external(args)
        sets.append(("the external set (held out, the workbench's own start)", getattr(args, "external_summary", [])))
        print("\n# The three sets, one table each\n")
        for name, summary in sets:
            set_table(name, summary)
        if args.calibration_plot:
            calibration_plot(sets, args.calibration_plot)
        print(
            "\n(ratios > 1: ours is worse; CC ratio < 1: ours is worse; bone: ours' and elastix's bone MED; best "
            "peer: the peer with the lowest MED of those that ran (elastix, + rigidity penalty, greedy, demons, ...); "
            "markers ours / lowest peer's: over the lowest marker MED of any peer; folded: ours' folded voxels of "
            "the body (the start's); times on a shared machine in one run: compare ratios)"
        )
        return 1 if failed else 0
    sets = []
    if "flex" in args.cases:
        sets.append((f"{args.split} draws ({args.acquisition} acquisition, {args.start} start)", run_flex(args)))
    failed = run_external(args) if "external" in args.cases else 0
    if "external" in args.cases:
        sets.append(("the external set (held out, the workbench's own start)", getattr(args, "external_summary", [])))
    if args.calibration_plot and sets:
        calibration_plot(sets, args.calibration_plot)
    for name, ph, articulated in _cases(args):
        print(f"\n{name}: {ph.geometry.describe()}", flush=True)
        report(name, run_case(name, ph, articulated, args))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
