"""Same inputs and settings, same bytes: every file under every stage folder of a study is the same in two fresh
`workbench run` processes.  The times are the manifest's only (each entry's ``seconds`` and the stage's own
``timings``), so study.json alone may differ — and logs/, which holds the phantom generator's statistics and
timings (logs/phantom.json, written by `workbench phantom`, no stage's).

One test-size knee phantom with 2 poses (straight and the knee bent 40°) is copied to two folders of the same
name under different parents (an absolute path written into an output shows as a difference) and run by two
processes at once, the second started a moment after the first (a time shows too; a date is looked for).
Every stage runs with its default methods — harmonic weights through the tet mesh, the polyrigid start, the
dense registration, the report with its pictures —; the bones are registered and the polyrigid start
integrated on every 2nd voxel to save time: each run takes ~35–40 s of CPU (the weights stage ~15 s of it).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import pytest

from workbench.cli import main
from workbench.stages import STAGES
from workbench.study import read_study

# slow (~30 s in the default suite's 2 workers: two whole runs at once, harmonic weights included), to keep the
# default suite under 6 minutes on CI; `make test-slow` runs it.  The default suite keeps the same rule piecewise:
# a Dask worker's registrations are the synchronous run's bytes (tests/workbench/test_run.py), a phantom is the
# same files for the same seed (tests/workbench/cli/test_cli.py), the dense registration the same bits on 1 and 2
# threads (tests/registration/test_dense.py).
pytestmark = pytest.mark.slow

SETTINGS = ["--set", "pose.grid_factor=2", "--set", "init.map_factor=2"]
#: what may differ between two runs: the manifest (its entries' times and dates) and the phantom's log
ALLOWED = ("study.json", "logs/")


def _files(root: Path) -> dict[str, str]:
    """``{path relative to the study: sha256}`` of every file of a study folder."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _keys(obj) -> set:
    if isinstance(obj, dict):
        return set(obj) | {k for v in obj.values() for k in _keys(v)}
    if isinstance(obj, list):
        return {k for v in obj for k in _keys(v)}
    return set()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """``(root a, root b, seconds)``: the same phantom study after a `workbench run` in each of two processes."""
    base = tmp_path_factory.mktemp("repro")
    phantom = base / "phantom"
    poses = base / "poses.json"
    poses.write_text(
        json.dumps(
            {
                "poses": [
                    {"id": "pose00", "angles": {"knee": [0, 0, 0]}},
                    {"id": "pose01", "angles": {"knee": [40, 0, 0]}},
                ]
            }
        )
    )
    assert main(["phantom", "knee", "--poses-file", str(poses), "--out", str(phantom), "--quiet"]) == 0
    roots = [base / k / "knee" for k in ("a", "b")]
    for root in roots:
        shutil.copytree(phantom, root)
    t0 = time.perf_counter()
    procs = []
    for root in roots:
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "workbench", "run", str(root), *SETTINGS, "--quiet"],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                encoding="utf-8",
            )
        )
        time.sleep(1.5)  # the runs' clocks apart: a time in a file differs
    for p in procs:
        out, err = p.communicate(timeout=900)
        assert p.returncode == 0, err
    return roots[0], roots[1], time.perf_counter() - t0


def test_the_pose_stage_files_hold_no_time_and_are_the_same_bytes_in_two_processes(runs):
    a, b, _ = runs
    names = sorted(p.name for p in (a / "poses").iterdir())
    assert "fits.json" in names and "report.json" in names and "report.txt" in names
    assert names == sorted(p.name for p in (b / "poses").iterdir())
    for name in names:
        assert (a / "poses" / name).read_bytes() == (b / "poses" / name).read_bytes(), name
        if name.endswith(".json"):
            assert not [
                k for k in _keys(json.loads((a / "poses" / name).read_text(encoding="utf-8"))) if "seconds" in k
            ], name
    assert "seconds" not in (a / "poses" / "report.txt").read_text(encoding="utf-8")
    fits = json.loads((a / "poses" / "fits.json").read_text(encoding="utf-8"))["scans"]
    # the times are the manifest's: the stage's, each scan's and each bone's fit
    for root in (a, b):
        t = read_study(root).stage_entry("pose")["timings"]
        assert t["total"] > 0
        assert set(t["scans"]) == set(fits) == {"pose00", "pose01"}
        assert all(set(t["scans"][s]["bones"]) == set(fits[s]["bones"]) for s in fits)
        assert all(v >= 0 for s in t["scans"].values() for v in [s["seconds"], *s["bones"].values()])


def test_the_registration_logs_hold_no_time_and_are_the_same_bytes_in_two_processes(runs):
    a, b, _ = runs
    for sid in ("pose00", "pose01"):
        log = a / "registration" / sid / "log.json"
        assert log.read_bytes() == (b / "registration" / sid / "log.json").read_bytes(), sid
        doc = json.loads(log.read_text(encoding="utf-8"))
        assert not [k for k in _keys(doc) if "seconds" in k]
        for root in (a, b):
            t = read_study(root).stage_entry("register", sid)["timings"]
            assert t["registration"] > 0 and t["inverse"] >= 0
            assert len(t["levels"]) == len(doc["summary"]["levels"])  # the dense method's levels


def test_every_file_under_every_stage_folder_is_the_same_bytes_in_two_processes(runs):
    """The end-to-end rule: same inputs and settings, the same bytes in every file but the manifest."""
    a, b, seconds = runs
    print(f"\ntwo `workbench run` of a 2-pose test knee at once: {seconds:.0f} s")
    fa, fb = _files(a), _files(b)
    for root in (a, b):  # every stage ran and wrote its folder: the comparison covers them all
        st = read_study(root)
        assert set(st.manifest["stages"]) == set(STAGES)
        assert not [
            n
            for n, e in st.manifest["stages"].items()
            if "scans" in e and any(u.get("skipped") for u in e["scans"].values())
        ]
    folders = sorted({s.folder for s in STAGES.values()})
    assert all(any(f.startswith(folder + "/") for f in fa) for folder in folders), folders
    assert sorted(fa) == sorted(fb)
    compared = [f for f in fa if not f.startswith(ALLOWED)]
    differ = sorted(f for f in compared if fa[f] != fb[f])
    assert not differ, f"{len(differ)} of {len(compared)} files differ between the two runs: {differ}"
    # nor does a file hold what is the same in both runs but not in a third: today's date, the study's path
    today = datetime.now(UTC).strftime("%Y-%m-%d").encode()
    for f in compared:
        if f.endswith((".json", ".txt", ".html")):
            data = (a / f).read_bytes()
            assert today not in data and str(a).encode() not in data and str(a.parent).encode() not in data, f
