"""Peak memory of the pipeline on a CT the size of Kurihara's (issue L item 3): pose, weights, VBD start, deform.

Kurihara & Miyata's hand CT is 512×512×750 voxels at 0.468×0.468×0.3 mm
(197 M voxels).  This builds a study of that size — the CT hand phantom of
``workbench phantom hand --modality ct`` (two poses), its template, label map
and scans resampled onto a 512×512×750 grid of Kurihara's spacing centred on
the hand (SimpleITK: linear for images, nearest for labels; the ground truth
is left out: validate is not measured here) — then runs ``workbench pose``,
``workbench weights``, the init stage's VBD of each scan (Rhee Eq. 2, DESIGN
step 5: ``workbench run --until init --set init.method=vbd``) and
``workbench deform --method vbd`` on it (``unfold``: the VBD start with
``--unfold-init``; ``field``: deform with ``--field-out``, the posed-to-template
displacement; ``animate``: a two-keyframe ``workbench animate`` of 6 frames at
320×240), each in its own process, and prints each one's peak resident memory
(the process and its children, sampled every 50 ms) and time against the 8 GiB
budget.  A stage
whose memory passes ``--kill-gib`` (default 20, the machine has 24) is
stopped and reported as over.

Usage::

    .venv/bin/python benchmarks/bench_big_volume.py [--out /tmp/avw-big] [--size 512 512 750]
        [--stages pose weights init unfold deform field animate] [--kill-gib 20]

``--size`` makes a smaller grid over the same field of view (e.g. ``256 256
375``, an eighth of the voxels at twice the spacing) to see how the peaks
scale.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# this folder holds registration.py, which would shadow the project's `registration` package

BUDGET_GIB = 8.0
KURIHARA_SIZE = (512, 512, 750)
KURIHARA_SPACING = (0.468, 0.468, 0.3)  # mm: a 240 × 240 × 225 mm field of view


def spacing_for(size) -> tuple:
    """Kurihara's field of view on a grid of ``size`` (his spacing at his size)."""
    return tuple(n0 * s0 / n for n0, s0, n in zip(KURIHARA_SIZE, KURIHARA_SPACING, size))


def _tree_rss_gib(pid: int) -> float:
    """Resident memory of a process and all its descendants (GiB), from /proc."""
    children: dict[int, list[int]] = {}
    rss = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            ppid = int(fields[1])
            with open(f"/proc/{d}/statm") as f:
                pages = int(f.read().split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(d))
        rss[int(d)] = pages * os.sysconf("SC_PAGE_SIZE")
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        total += rss.get(p, 0)
        todo += children.get(p, [])
    return total / 2**30


def run_measured(cmd: list[str], kill_gib: float) -> tuple[int, float, float, str]:
    """Run ``cmd``; returns (exit code, peak GiB of its process tree, seconds, the last lines of stderr)."""
    t0 = time.perf_counter()
    log = Path(os.environ.get("TMPDIR", "/tmp")) / f"avw-big-{os.getpid()}.err"
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        peak, killed = 0.0, False
        while proc.poll() is None:
            peak = max(peak, _tree_rss_gib(proc.pid))
            if peak > kill_gib and not killed:
                proc.kill()
                killed = True
            time.sleep(0.05)
    tail = "\n".join(log.read_text(encoding="utf-8").strip().splitlines()[-3:])
    log.unlink()
    if killed:
        tail = f"stopped above {kill_gib:g} GiB\n" + tail
    return proc.returncode, peak, time.perf_counter() - t0, tail


def keyframes(out: Path) -> Path:
    """Two keyframes for ``animate``: the rest pose and the fingers flexed 40° at the MCP joints."""
    bend = {f"{f}_mcp": [40, 0, 0] for f in ("index", "middle", "ring", "little")}
    path = out / "keyframes.json"
    path.write_text(
        json.dumps(
            {
                "format": "avw-keyframes",
                "version": 1,
                "skeleton": "hand",
                "fps": 24,
                "keyframes": [{"time": 0.0, "angles": {}}, {"time": 1.0, "angles": bend}],
            }
        )
    )
    return path


def build_study(out: Path, size) -> tuple[Path, Path]:
    """The CT hand phantom resampled onto a Kurihara-size grid; returns (study folder, a target pose file)."""
    import SimpleITK as sitk

    small = out / "phantom"
    study = out / "study"
    if (study / "study.json").exists():
        return study, out / "target_pose.json"
    if small.exists():
        shutil.rmtree(small)
    subprocess.run(
        [
            sys.executable,
            "-m",
            "workbench",
            "phantom",
            "hand",
            "--modality",
            "ct",
            "--poses",
            "2",
            "--out",
            str(small),
            "--quiet",
        ],
        check=True,
    )
    m = json.loads((small / "study.json").read_text(encoding="utf-8"))
    shutil.copyfile(small / m["scans"][-1]["truth"]["pose"], out / "target_pose.json")
    ref = sitk.ReadImage(str(small / m["template"]))
    centre = np.asarray(ref.TransformContinuousIndexToPhysicalPoint([(s - 1) / 2 for s in ref.GetSize()]))
    grid = sitk.Image([int(v) for v in size], sitk.sitkInt16)
    spacing = spacing_for(size)
    grid.SetSpacing(spacing)
    grid.SetOrigin(tuple(centre - (np.asarray(size) - 1) / 2 * np.asarray(spacing)))
    study.mkdir(parents=True, exist_ok=True)

    def resample(rel: str, name: str, labels: bool = False) -> str:
        img = sitk.ReadImage(str(small / rel))
        fill = 0 if labels else float(sitk.GetArrayViewFromImage(img).min())
        big = sitk.Resample(
            img,
            grid,
            sitk.Transform(),
            sitk.sitkNearestNeighbor if labels else sitk.sitkLinear,
            fill,
            sitk.sitkUInt16 if labels else sitk.sitkInt16,
        )
        sitk.WriteImage(big, str(study / name))
        return name

    new = {k: v for k, v in m.items() if k not in ("stages",)}
    new["template"] = resample(m["template"], "template.nii")
    new["template_labels"] = resample(m["template_labels"], "template_labels.nii", labels=True)
    shutil.copyfile(small / m["skeleton"], study / "skeleton.json")
    new["skeleton"] = "skeleton.json"
    new["scans"] = [{"id": s["id"], "image": resample(s["image"], f"{s['id']}.nii")} for s in m["scans"]]
    new["name"] = f"{m.get('name', 'hand')} at Kurihara's grid"
    (study / "study.json").write_text(json.dumps(new, indent=1))
    return study, out / "target_pose.json"


def pose_accuracy(out: Path) -> str:
    """The pose stage's bones against the phantom's truth (world mm: resampling onto the big grid keeps them),
    per scan: mean and worst rotation (°) and centroid translation (mm) over the bones the stage kept."""
    from validation.pose_measures import pose_errors
    from workbench.study import read_study

    small, big = read_study(out / "phantom"), read_study(out / "study")
    labels, sk = small.template_labels(), small.skeleton()
    centroids = {
        b: small.template().geometry.index_to_world(np.argwhere(labels.data == sk.label_of(b))[:, ::-1].mean(0))
        for b in sk.bone_names
    }
    flagged = json.loads((out / "study" / "poses" / "fits.json").read_text(encoding="utf-8"))["scans"]
    lines = []
    for sid in big.scan_ids:
        est = big.pose(sid)
        kept = {b: t for b, t in est.transforms.items() if flagged[sid]["bones"][b]["status"] == "ok"}
        e = pose_errors(type(est)(kept, skeleton=est.skeleton), small.truth_pose(sid), centroids)
        lines.append(
            f"{sid}: {len(kept)} bones, rotation mean {e['mean_rotation_deg']:.2f}° max "
            f"{e['max_rotation_deg']:.2f}°, translation mean {e['mean_translation_mm']:.2f} mm max "
            f"{e['max_translation_mm']:.2f} mm"
        )
    return "; ".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("/tmp/avw-big"))
    p.add_argument("--size", type=int, nargs=3, default=[512, 512, 750], metavar=("NX", "NY", "NZ"))
    p.add_argument(
        "--stages",
        nargs="+",
        default=["pose", "weights", "init", "deform"],
        choices=["pose", "weights", "init", "unfold", "deform", "field", "animate"],
    )
    p.add_argument("--kill-gib", type=float, default=20.0)
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    study, target = build_study(a.out, a.size)
    n = int(np.prod(a.size))
    print(
        f"study: {study} — {a.size[0]}×{a.size[1]}×{a.size[2]} = {n / 1e6:.0f} M voxels at "
        f"{'×'.join(f'{v:.3f}' for v in spacing_for(a.size))} mm, 2 scans (built or reused in "
        f"{time.perf_counter() - t0:.0f} s)",
        flush=True,
    )
    wb = [sys.executable, "-m", "workbench"]
    commands = {
        "pose": wb + ["pose", str(study), "--force", "--quiet"],
        "weights": wb + ["weights", str(study), "--force", "--quiet"],
        "init": wb + ["run", str(study), "--until", "init", "--set", "init.method=vbd", "--force", "init", "--quiet"],
        "unfold": wb
        + [
            "run",
            str(study),
            "--until",
            "init",
            "--set",
            "init.method=vbd",
            "--set",
            "init.unfold=true",
            "--force",
            "init",
            "--quiet",
        ],
        "deform": wb
        + [
            "deform",
            str(study),
            "--pose",
            str(target),
            "--method",
            "vbd",
            "--force",
            "--out",
            str(a.out / "posed.nii"),
            "--quiet",
        ],
        "field": wb
        + [
            "deform",
            str(study),
            "--pose",
            str(target),
            "--method",
            "vbd",
            "--force",
            "--out",
            str(a.out / "posed.nii"),
            "--field-out",
            str(a.out / "posed_field.mha"),
            "--quiet",
        ],
        "animate": wb
        + [
            "animate",
            str(study),
            "--keyframes",
            str(a.out / "keyframes.json"),
            "--method",
            "vbd",
            "--size",
            "320x240",
            "--frames",
            "6",
            "--force",
            "--out",
            str(a.out / "anim.gif"),
            "--quiet",
        ],
    }
    if "animate" in a.stages:
        keyframes(a.out)
    print(f"| stage | exit | peak GiB (budget {BUDGET_GIB:g}) | bytes per voxel | seconds |")
    print("|---|---|---|---|---|")
    for name in a.stages:
        rc, peak, sec, tail = run_measured(commands[name], a.kill_gib)
        verdict = "within" if rc == 0 and peak <= BUDGET_GIB else "OVER" if rc == 0 or "stopped" in tail else "failed"
        print(f"| {name} | {rc} | {peak:.2f} ({verdict}) | {peak * 2**30 / n:.0f} | {sec:.0f} |", flush=True)
        if rc == 0 and name == "pose":
            print(f"   pose against the phantom's truth: {pose_accuracy(a.out)}", flush=True)
        if rc != 0:
            print("   " + tail.replace("\n", "\n   "), flush=True)
            if name != a.stages[-1]:
                print("   (the stages after it need its outputs: stopping)")
                break
    return 0


if __name__ == "__main__":
    sys.exit(main())
