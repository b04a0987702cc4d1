"""Where the pipeline's time goes: ``workbench run`` stage by stage, profiled, against one elastix registration.

Two cases (``--cases``):

* ``demo``: the knee of ``make demo`` (the test phantom's field of view at 2.5 mm, 128 × 128 × 59 voxels, four
  scans);
* ``knee125``: a knee at 1.25 mm framed as a user's CT or MRI of a knee would be (about 1.1 M voxels), with one
  scan at a 60° bend.  The phantom is generated on the test field of view at 1.25 mm and each image (template,
  labels, scan, its truth) is cut to a 105 × 152 × 140 mm box around the knee's joint centre, within its body's
  box plus ``--margin-mm``; the scan and the template have grids of their own.

The studies are built once into ``--out`` and copied afresh for each run.  Each stage from ``bones`` to
``model`` (``--until``) runs in this process through the stage mechanism (as ``workbench run`` does), timed
and profiled with cProfile (numba's compiled kernels show as one call each; ``--no-profile`` to time without
the profiler's overhead, a few per cent here).  Then elastix's B-spline (its default map, MI, 20 mm grid, the
harness's settings in ``bench_registration.py``) registers the last scan's pair (the demo's most flexed) from the same
start (the init stage's field), in the same run.

It prints per case: each stage's seconds and share; the functions with the most time of their own; and the
ratios of issue P: the whole pipeline for one scan (pose + weights + init + register + model, that scan's
share of the per-scan stages) over one elastix registration, and one added scan (its pose share + init +
register) over elastix.  The pose stage registers every scan's bones in one unit; its per-scan seconds come from
its recorded timings.

Usage::

    .venv/bin/python benchmarks/bench_pipeline.py [--cases demo knee125] [--out /tmp/avw-pipeline]
        [--until model] [--top 15] [--no-profile] [--no-elastix] [--rebuild]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

STAGES = ("bones", "pose", "weights", "init", "register", "model", "surface", "validate", "report")
PER_SCAN = ("init", "register", "validate")
KNEE125_POSES = {"poses": [{"id": "bend60", "angles": {"knee": [60, 0, 0]}}]}
#: knee125's frame: this box around the knee's joint centre (the femur does not move), cut to the body
KNEE_CENTRE_MM = (19.0, 20.0, 0.0)
KNEE_HALF_BOX_MM = (52.5, 76.0, 70.0)


def _phantom(out: Path, *args: str) -> None:
    subprocess.run(
        [sys.executable, "-m", "workbench", "phantom", "knee", "--out", str(out), "--quiet", *args], check=True
    )


def _knee_box(image, margin_mm: float) -> tuple[slice, slice, slice]:
    """The array slices ``(z, y, x)`` of the knee's frame on the image's grid: the body's bounding box plus
    ``margin_mm``, within ``KNEE_HALF_BOX_MM`` of the joint centre (the image's grid is axis-aligned)."""
    from registration.segmentation import segment_body

    g = image.geometry
    body = np.asarray(segment_body(image).data) > 0
    centre = g.world_to_index(np.asarray([KNEE_CENTRE_MM]))[0][::-1]  # (z, y, x) index
    half = np.asarray(KNEE_HALF_BOX_MM[::-1]) / np.asarray(g.spacing[::-1])
    pad = [int(np.ceil(margin_mm / s)) for s in g.spacing[::-1]]
    out = []
    for axis, p in enumerate(pad):
        other = tuple(a for a in range(3) if a != axis)
        hit = np.flatnonzero(body.any(axis=other))
        lo = max(0, hit[0] - p, int(np.floor(centre[axis] - half[axis])))
        hi = min(body.shape[axis], hit[-1] + p + 1, int(np.ceil(centre[axis] + half[axis])) + 1)
        out.append(slice(lo, hi))
    return tuple(out)


def _crop(volume, box):
    """The volume cut to ``box`` (array slices z, y, x): the same world positions, a smaller grid."""
    from deformation.geometry import GridGeometry, Volume

    g = volume.geometry
    start = np.array([box[2].start, box[1].start, box[0].start], float)  # x, y, z indices
    size = (box[2].stop - box[2].start, box[1].stop - box[1].start, box[0].stop - box[0].start)
    origin = tuple(g.index_to_world(start[None])[0])
    return Volume(np.ascontiguousarray(volume.data[box]), GridGeometry(size, g.spacing, origin, g.direction))


def _build_knee125(folder: Path, margin_mm: float) -> None:
    """The 1.25 mm knee on the test field of view, then every image cut to its body's box (see the docstring)."""
    from workbench.io.jsonio import write_json
    from workbench.io.volume_writers import write_displacement, write_labels, write_volume
    from workbench.io.volumes import read_displacement, read_labels, read_volume

    full = folder.with_name(folder.name + "-full")
    if not (full / "study.json").exists():
        poses = folder.with_name("knee125-poses.json")
        poses.write_text(json.dumps(KNEE125_POSES))
        print(f"generating the 1.25 mm knee on the test field of view in {full} (minutes) ...", flush=True)
        _phantom(full, "--spacing", "1.25", "--poses-file", str(poses), "--force")
    m = json.loads((full / "study.json").read_text(encoding="utf-8"))
    stage = folder.with_name(folder.name + ".partial")
    shutil.rmtree(stage, ignore_errors=True)
    shutil.copytree(full, stage, ignore=shutil.ignore_patterns("*.nii.gz", "*.mha", "study.json"))
    tpl = read_volume(full / m["template"])
    box = _knee_box(tpl, margin_mm)
    write_volume(_crop(tpl, box), stage / m["template"])
    write_labels(_crop(read_labels(full / m["template_labels"]), box), stage / m["template_labels"])
    for s in m["scans"]:
        scan = read_volume(full / s["image"])
        sbox = _knee_box(scan, margin_mm)
        write_volume(_crop(scan, sbox), stage / s["image"])
        write_displacement(
            _crop(read_displacement(full / s["truth"]["correspondence"]), sbox), stage / s["truth"]["correspondence"]
        )
        if "template_to_scan" in s["truth"]:  # on the template grid
            write_displacement(
                _crop(read_displacement(full / s["truth"]["template_to_scan"]), box),
                stage / s["truth"]["template_to_scan"],
            )
    m["name"] = f"knee phantom at 1.25 mm cut to the limb (+{margin_mm:g} mm)"
    write_json(m, stage / "study.json")
    shutil.rmtree(folder, ignore_errors=True)
    stage.rename(folder)


def build(case: str, out: Path, margin_mm: float, rebuild: bool) -> Path:
    folder = out / f"{case}-study"
    if rebuild:
        shutil.rmtree(folder, ignore_errors=True)
    if (folder / "study.json").exists():
        return folder
    if case == "demo":
        _phantom(folder, "--spacing", "2.5", "--force")  # the Makefile's DEMO_SPACING
    else:
        _build_knee125(folder, margin_mm)
    return folder


def run_case(case: str, source: Path, out: Path, args) -> dict:
    from workbench.stages.run import run_stages
    from workbench.study import read_study

    folder = out / f"{case}-run"
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(source, folder)
    study = read_study(folder)
    g = study.template().geometry
    scans = study.scan_ids
    print(f"\n# {case}: template {g.size} voxels ({g.n_voxels / 1e6:.2f} M) at {g.spacing} mm, {len(scans)} scan(s)")
    for sid in scans:
        print(f"  {sid}: {study.scan(sid).geometry.size} voxels")
    stages = STAGES[: STAGES.index(args.until) + 1]
    seconds, profiles = {}, []
    for name in stages:
        prof = None if args.no_profile else cProfile.Profile()
        t0 = time.perf_counter()
        if prof is not None:
            prof.enable()
        run_stages(study, [name], settings={}, progress=None)
        if prof is not None:
            prof.disable()
        seconds[name] = time.perf_counter() - t0
        study = study.reload()
        print(f"  {name:<9} {seconds[name]:7.1f} s", flush=True)
        if prof is not None:
            profiles.append(prof)
    flagged = {sid: study.pose_flagged(sid) for sid in scans if "pose" in seconds and study.pose_flagged(sid)}
    if flagged:
        print(f"  the pose stage could not place (their pose follows their parent's): {flagged}")
    per_scan = {n: {sid: _unit_seconds(study, n, sid) for sid in scans} for n in PER_SCAN if n in seconds}
    pose_scans = _pose_scan_seconds(study)
    scan = scans[-1]  # the demo's most flexed scan (knee125 has one)
    el = None if args.no_elastix else _elastix(study, scan)
    total = sum(seconds.values())
    print(f"\n  stage      seconds  share   (total {total:.1f} s)")
    for name, s in seconds.items():
        extra = ""
        if name in per_scan:
            extra = "  per scan: " + ", ".join(f"{sid} {v:.1f}" for sid, v in per_scan[name].items())
        elif name == "pose" and pose_scans:
            extra = "  per scan: " + ", ".join(f"{sid} {v:.1f}" for sid, v in pose_scans.items())
        print(f"  {name:<9} {s:8.1f}  {100 * s / total:5.1f} %{extra}")
    if profiles:
        stats = pstats.Stats(profiles[0], stream=io.StringIO())
        for p in profiles[1:]:
            stats.add(p)
        print(f"\n  the {args.top} functions with the most time of their own (all stages, cProfile):")
        print(_top(stats, args.top))
    result = {"case": case, "seconds": seconds, "per_scan": per_scan, "pose_per_scan": pose_scans}
    one_scan = (
        _pose_share(seconds, pose_scans, scan)
        + sum(seconds.get(n, 0.0) for n in ("bones", "weights", "model"))
        + sum(per_scan[n][scan] for n in ("init", "register") if n in per_scan)
    )
    added = _pose_share(seconds, pose_scans, scan) + sum(
        per_scan[n][scan] for n in ("init", "register") if n in per_scan
    )
    result.update(one_scan_seconds=one_scan, added_scan_seconds=added)
    if el is not None:
        seconds_el, med = el
        result["elastix"] = seconds_el
        print(f"\n  elastix B-spline on {scan}'s pair from the same start: {seconds_el:.1f} s")
        if med:
            print(
                "  MED over the scan's body against the truth, mm: " + ", ".join(f"{k} {v:.2f}" for k, v in med.items())
            )
        print(f"  whole pipeline for one scan ({scan}): {one_scan:.1f} s = {one_scan / seconds_el:.2f} x elastix")
        print(f"  an added scan ({scan}: pose + init + register): {added:.1f} s = {added / seconds_el:.2f} x elastix")
    return result


def _pose_share(seconds: dict, pose_scans: dict, sid: str) -> float:
    """The pose stage's seconds for scan ``sid``: its recorded per-scan time plus its share of the rest."""
    if "pose" not in seconds:
        return 0.0
    if not pose_scans:
        return seconds["pose"]
    rest = max(0.0, seconds["pose"] - sum(pose_scans.values()))
    return pose_scans[sid] + rest / len(pose_scans)


def _unit_seconds(study, stage: str, sid: str) -> float:
    return float(study.manifest["stages"][stage]["scans"][sid]["seconds"])


def _pose_scan_seconds(study) -> dict:
    timings = (study.manifest.get("stages", {}).get("pose") or {}).get("timings") or {}
    return {s: float(t["seconds"]) for s, t in (timings.get("scans") or {}).items() if "seconds" in t}


def _elastix(study, sid: str) -> tuple[float, dict] | None:
    """elastix's seconds on scan ``sid``'s pair from the init stage's start, and (with a truth) the MED over the
    scan's body of the start, ours and elastix."""
    from registration.baselines import elastix_available, elastix_bspline, load_itk
    from registration.segmentation import segment_body
    from validation.registration_measures import error_map

    if not elastix_available():
        print("  elastix: itk-elastix is not installed (make bench): no ratio")
        return None
    load_itk()
    scan, start = study.scan(sid), study.init_field(sid)
    b = elastix_bspline(scan, study.template(), initial=start, metric="mi", seed=0)
    med = {}
    if study.has_truth(sid):
        truth = study.truth_correspondence(sid)
        body = np.asarray(segment_body(scan).data) > 0
        fields = {"start": start, "ours": study.registration_correspondence(sid), "elastix": b.correspondence}
        med = {k: float(error_map(f, truth)[body].mean()) for k, f in fields.items()}
    return float(b.seconds), med


def _top(stats: pstats.Stats, n: int) -> str:
    rows = sorted(stats.stats.items(), key=lambda kv: kv[1][2], reverse=True)[:n]  # (cc, nc, tottime, cumtime, ..)
    total = sum(v[2] for v in stats.stats.values())
    lines = ["    own s   share   calls  function"]
    for (path, line, func), (_, nc, tt, _ct, _) in rows:
        where = func if path == "~" else f"{_short(path)}:{line} {func}"
        lines.append(f"  {tt:7.1f}  {100 * tt / total:5.1f} %  {nc:6d}  {where}")
    return "\n".join(lines)


def _short(path: str) -> str:
    for root in ("site-packages/", str(Path(__file__).resolve().parents[1]) + os.sep):
        if root in path:
            return path.split(root, 1)[1]
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", choices=("demo", "knee125"), default=["demo", "knee125"])
    p.add_argument("--out", type=Path, default=Path("/tmp/avw-pipeline"), help="studies and runs (kept)")
    p.add_argument("--until", choices=STAGES, default="model", help="the last stage run (default model)")
    p.add_argument("--top", type=int, default=15, help="how many hot functions to print")
    p.add_argument("--margin-mm", type=float, default=10.0, help="knee125: air kept around the body's box")
    p.add_argument("--no-profile", action="store_true", help="time the stages without cProfile")
    p.add_argument("--no-elastix", action="store_true", help="no elastix registration (no ratios)")
    p.add_argument("--rebuild", action="store_true", help="generate the studies anew")
    p.add_argument("--json", type=Path, help="write the figures here")
    args = p.parse_args(argv)
    if "register" not in STAGES[: STAGES.index(args.until) + 1]:
        args.no_elastix = True  # the ratios need the registration
    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for case in args.cases:
        source = build(case, args.out, args.margin_mm, args.rebuild)
        results.append(run_case(case, source, args.out, args))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
