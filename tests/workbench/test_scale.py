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


class _Unpicklable(Exception):
    def __init__(self, message, extra):
        super().__init__(message)
        self.extra = extra


def _raise_study_error(x):
    from workbench.study import StudyError

    if x == 1:
        raise StudyError("scan 1 could not be read", "/nowhere/study.json")
    return x


def _raise_unpicklable(x):
    if x == 1:
        raise _Unpicklable("odd failure", extra=3)
    return x


def test_the_workbench_errors_survive_pickling():
    """A task's error reaches the coordinator pickled (Dask, the process pool): each keeps its class, message and
    path."""
    import pickle

    from workbench.errors import InputFileError, MissingFileError, OutputExistsError, OutputWriteError
    from workbench.study import StudyError

    for e in (
        InputFileError("bad file", "/a/b.nii"),
        MissingFileError("no file", "/a/c.nii"),
        StudyError("bad study", "/a/study.json"),
        OutputExistsError("/a/out.nii"),
        OutputWriteError("/a/out.nii", "[Errno 28] No space left on device"),
    ):
        back = pickle.loads(pickle.dumps(e))
        assert type(back) is type(e) and str(back) == str(e) and back.path == e.path


def test_a_task_error_the_pool_could_not_return_is_raised_not_hung():
    """An error that does not survive pickling (the pool's result thread would die on it and the map hang) comes
    back as a WorkbenchError naming it; the workbench's own errors come back as themselves."""
    from workbench.errors import WorkbenchError
    from workbench.study import StudyError

    with pytest.raises(StudyError, match="scan 1 could not be read"):
        Runner().map(_raise_study_error, range(3), processes=2)
    with pytest.raises(WorkbenchError, match="_Unpicklable: odd failure"):
        Runner().map(_raise_unpicklable, range(3), processes=2)


def test_a_script_without_the_main_guard_gets_one_process(tmp_path):
    """A spawned process imports the main module again: a script whose work is not under the __main__ guard would
    run it again there, so it gets one process; a guarded script gets the pool."""
    import subprocess
    import sys

    probe = "from workbench.scale import local_processes\n"
    for name, body, want in (
        ("bare.py", probe + "print(local_processes())\n", 1),
        ("guarded.py", probe + 'if __name__ == "__main__":\n    print(local_processes())\n', 2),
    ):
        (tmp_path / name).write_text(body)
        out = subprocess.run([sys.executable, str(tmp_path / name)], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert int(out.stdout.strip()) == min(want, scale.LOCAL_PROCESSES, __import__("os").cpu_count() or 1)
