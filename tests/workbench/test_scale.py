"""workbench.scale without a cluster: tasks over a few processes of this machine (Runner.map(processes=N))."""

import shutil

import numpy as np
import pytest

from workbench import scale
from workbench.scale import Runner, local_processes


def _square(x):
    return x * x


def _affine(shared, x):
    a, b = shared
    return a * x + b


def _fail_on_three(x):
    if x == 3:
        raise ValueError("task 3 failed")
    return x


def _processes_here(_):
    return local_processes()


def test_processes_give_the_serial_results_in_order_and_report_each():
    seen = []
    out = Runner().map(_square, range(6), processes=2, on_result=lambda i, r: seen.append((i, r)))
    assert out == [x * x for x in range(6)]
    assert sorted(seen) == [(i, i * i) for i in range(6)]  # each once, in completion order


def test_shared_value_reaches_every_task():
    assert Runner().map(_affine, [0, 1, 5], shared=(3, -1), processes=2) == [-1, 2, 14]


def test_a_failing_task_raises_here():
    with pytest.raises(ValueError, match="task 3 failed"):
        Runner().map(_fail_on_three, range(6), processes=2)


def test_a_pool_worker_does_not_start_a_pool_of_its_own():
    assert local_processes() >= 1
    assert Runner().map(_processes_here, range(2), processes=2) == [1, 1]


def test_pose_stage_same_bits_in_two_processes_as_in_one(knee_ct_study, tmp_path, monkeypatch):
    """The pose stage's scans over two processes of this machine give the one-process run's files to the bit."""
    from workbench.stages.run import run_stages
    from workbench.study import read_study

    outs, pooled = {}, []
    real = scale._map_processes
    monkeypatch.setattr(scale, "_map_processes", lambda *a: pooled.append(a[3]) or real(*a))
    from workbench.stages import pose

    monkeypatch.setattr(pose, "LOCAL_VOXELS", (0, 10**9))  # the test knee is smaller than a pool pays for
    for n in (1, 2):
        root = tmp_path / f"p{n}"
        shutil.copytree(knee_ct_study.root, root, ignore=shutil.ignore_patterns(".locks"))
        monkeypatch.setattr(scale, "LOCAL_PROCESSES", n)
        monkeypatch.setattr(scale.os, "cpu_count", lambda: 2)
        run_stages(read_study(root), ["pose"], settings={})
        outs[n] = {p.name: p.read_bytes() for p in sorted((root / "poses").iterdir())}
    assert pooled == [2]  # the one-process run took no pool, the other a pool of two
    assert len(outs[1]) >= 6 and outs[1] == outs[2]
    scans = read_study(tmp_path / "p2").stage_entry("pose")["timings"]["scans"]
    assert len(scans) == 3 and all(np.isfinite(v["seconds"]) for v in scans.values())
