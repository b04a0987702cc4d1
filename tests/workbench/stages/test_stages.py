"""The stage mechanism and the manifest writer, on toy stages (no registration): digest, skip, needs,
staleness, atomic outputs, interrupted runs, concurrent writers."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from deformation.geometry import GridGeometry, Volume
from workbench.stages.mechanism import Image, Json, Stage, StageNotReady, execute, stage_status
from workbench.study import read_study, recorded_times


@pytest.fixture()
def study(tmp_path):
    """A minimal study: a template, a skeleton and two scans (anisotropic grid, rotated direction)."""
    from workbench.io.jsonio import write_json
    from workbench.io.volumes import write_volume

    c, s = np.cos(0.3), np.sin(0.3)
    g = GridGeometry((6, 5, 4), (1.5, 0.8, 2.0), (1.0, -2.0, 3.0), (c, -s, 0, s, c, 0, 0, 0, 1))
    root = tmp_path / "study"
    (root / "scans").mkdir(parents=True)
    rng = np.random.default_rng(0)
    write_volume(Volume(rng.random(g.array_shape, dtype=np.float32), g), root / "template.nii.gz")
    for sid in ("a", "b"):
        write_volume(Volume(rng.random(g.array_shape, dtype=np.float32), g), root / "scans" / f"{sid}.nii.gz")
    write_json(
        {
            "format": "avw-skeleton",
            "version": 1,
            "name": "toy",
            "bones": [{"name": "r", "label": 1, "parent": None}],
            "joints": [],
        },
        root / "skeleton.json",
    )
    write_json(
        {
            "format": "avw-study",
            "version": 1,
            "units": "mm",
            "template": "template.nii.gz",
            "skeleton": "skeleton.json",
            "stages": {},
            "scans": [{"id": sid, "image": f"scans/{sid}.nii.gz"} for sid in ("a", "b")],
        },
        root / "study.json",
    )
    return read_study(root)


@dataclass(frozen=True)
class Gain:
    factor: float = 2.0


def _scaled(ctx):
    if ctx.options.get("fail"):
        raise RuntimeError("boom")
    img = ctx.study.scan(ctx.scan)
    return {
        "scaled.nii.gz": Image(Volume(img.data * ctx.settings.factor, img.geometry)),
        "info.json": Json({"factor": ctx.settings.factor}),
    }


def _mean(ctx):
    vals = [float(Path(ctx.study.output("scale", "info.json", sid)).stat().st_size) for sid in ctx.study.scan_ids]
    return {"mean.json": Json({"n": len(vals)})}


SCALE = Stage(
    name="scale",
    folder="scaled",
    per_scan=True,
    settings_type=Gain,
    run=_scaled,
    inputs=lambda study, s, scan: {"scan": study.scan_path(scan)},
)
MEAN = Stage(name="mean", folder="mean", per_scan=False, settings_type=Gain, run=_mean, needs=lambda s: ("scale",))
REG = {"scale": SCALE, "mean": MEAN}


def test_a_stage_runs_skips_and_reruns_on_a_new_setting(study):
    out = execute(study, SCALE, Gain(), registry=REG)
    assert [o.status for o in out] == ["ran", "ran"]
    v = study.scan("a")
    from workbench.io.volumes import read_volume

    got = read_volume(study.output("scale", "scaled.nii.gz", "a"))
    got.geometry.check_same(v.geometry)  # geometry travels with the output
    np.testing.assert_array_equal(got.data, v.data * 2.0)
    e = study.stage_entry("scale", "a")
    assert e["settings"] == {"factor": 2.0} and e["inputs"]["scan"]["path"] == "scans/a.nii.gz"
    assert e["outputs"] == {"scaled.nii.gz": "scaled/a/scaled.nii.gz", "info.json": "scaled/a/info.json"}
    assert [o.status for o in execute(study, SCALE, Gain(), registry=REG)] == ["skipped", "skipped"]
    assert [o.status for o in execute(study, SCALE, Gain(3.0), registry=REG)] == ["ran", "ran"]
    assert [o.status for o in execute(study, SCALE, Gain(3.0), registry=REG, force=True)] == ["ran", "ran"]


def _timed(ctx):
    ctx.timings.update(step=0.25, levels=[0.5, np.float64(0.75)])
    return {"out.json": Json({"n": 1})}


TIMED = Stage(name="timed", folder="timed", per_scan=True, settings_type=Gain, run=_timed)


def test_a_stage_hands_its_step_times_to_its_manifest_entry_not_to_its_files(study):
    execute(study, TIMED, Gain(), registry={"timed": TIMED})
    for sid in ("a", "b"):
        e = study.stage_entry("timed", sid)
        assert e["timings"] == {"step": 0.25, "levels": [0.5, 0.75]} and e["seconds"] >= 0
        assert json.loads((study.root / "timed" / sid / "out.json").read_text(encoding="utf-8")) == {"n": 1}
    execute(study, SCALE, Gain(), registry=REG)
    assert "timings" not in study.stage_entry("scale", "a")  # a stage that hands none has none
    # workbench info's lines: each stage's seconds, its steps' summed over its scans
    lines = recorded_times(read_study(study.root), ("scale", "timed"))
    assert [line.split()[0] for line in lines] == ["scale", "timed"]
    assert "(2 scans)" in lines[1] and "step 0.5 s" in lines[1]


def test_needs_are_checked_before_any_work_and_staleness_is_seen(study):
    with pytest.raises(StageNotReady, match="needs the scale stage of scan 'a'"):
        execute(study, MEAN, Gain(), registry=REG)
    assert not (study.root / "mean").exists()
    execute(study, SCALE, Gain(), registry=REG)
    execute(study, MEAN, Gain(), registry=REG)
    assert stage_status(study, MEAN, registry=REG) == "done"
    # a changed input makes the stage that read it, and the stage after it, out of date
    from workbench.io.volumes import write_volume

    v = study.scan("b")
    write_volume(Volume(v.data + 1, v.geometry), study.scan_path("b"), overwrite=True)
    assert stage_status(study, SCALE, "b", registry=REG) == "stale"
    assert stage_status(study, SCALE, "a", registry=REG) == "done"
    with pytest.raises(StageNotReady, match="out of date"):
        execute(study, MEAN, Gain(), registry=REG)
    assert [o.status for o in execute(study, SCALE, Gain(), registry=REG)] == ["skipped", "ran"]
    # the rerun scan's outputs changed, so the whole-study stage after it must run again
    assert stage_status(study, MEAN, registry=REG) == "stale"
    assert execute(study, MEAN, Gain(), registry=REG)[0].status == "ran"


def test_a_failing_stage_leaves_no_partial_output_and_keeps_the_old_one(study):
    execute(study, SCALE, Gain(), registry=REG)
    before = (study.root / "study.json").read_bytes()
    files = {p: p.read_bytes() for p in sorted((study.root / "scaled").rglob("*")) if p.is_file()}
    with pytest.raises(RuntimeError, match="boom"):
        execute(study, SCALE, Gain(5.0), registry=REG, options={"fail": True})
    # no staging folder left, the old outputs as they were, the manifest untouched
    assert {p: p.read_bytes() for p in sorted((study.root / "scaled").rglob("*")) if p.is_file()} == files
    assert (study.root / "study.json").read_bytes() == before


def test_staging_folders_of_dead_processes_are_removed(study):
    (study.root / "scaled").mkdir()
    import socket

    host = socket.gethostname()
    dead = study.root / "scaled" / f".a.partial-{host}-999999999-abcd"  # no such process on this host
    old = study.root / "scaled" / f".a.old-{host}-999999999-abcd"  # a replaced folder its process left
    alive = study.root / "scaled" / f".b.partial-{host}-{os.getpid()}-abcd"  # this process: kept
    other = study.root / "scaled" / ".b.partial-elsewhere-1-abcd"  # another host's: kept
    for p in (dead, old, alive, other):
        p.mkdir()
    execute(study, SCALE, Gain(), registry=REG)
    assert not dead.exists() and not old.exists() and alive.exists() and other.exists()


def _hammer(root, k, n):
    st = read_study(root)
    for i in range(n):
        st.record("toy", {"digest": f"{k}-{i}", "outputs": {}, "outputs_digest": ""}, f"w{k}-{i}")


def test_concurrent_writers_lose_no_entry(study):
    """Four processes record 25 entries each at once: every one is in the manifest afterwards."""
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_hammer, args=(str(study.root), k, 25)) for k in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
        assert p.exitcode == 0
    m = json.loads((study.root / "study.json").read_text(encoding="utf-8"))
    assert len(m["stages"]["toy"]["scans"]) == 100


def _execute_forced(root):
    st = read_study(root)
    execute(st, SCALE, Gain(4.0), registry=REG, force=True)
    execute(st, MEAN, Gain(), registry=REG, force=True)


def test_concurrent_executions_of_the_same_stages_all_succeed(study):
    """Three processes rerun the same per-scan and whole-study stages at once: each unit runs one at a time
    (a lock per unit), every process succeeds and the study ends complete and consistent."""
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_execute_forced, args=(str(study.root),)) for _ in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
        assert p.exitcode == 0
    st = read_study(study.root)
    assert stage_status(st, MEAN, registry=REG) == "done"
    assert all(stage_status(st, SCALE, sid, registry=REG) == "done" for sid in st.scan_ids)
    assert not [p for p in study.root.rglob("*") if ".partial-" in p.name or ".old-" in p.name]


def _wait_for(path: Path, proc=None) -> None:
    """Until ``path`` exists (or ``proc`` has ended); the cap only ends a broken test."""
    import time

    for _ in range(1200):
        if path.exists() or (proc is not None and not proc.is_alive()):
            return
        time.sleep(0.05)


def _second_while_first_is_paused(root, hold: Path, first, first_in: str, second, second_in: str) -> None:
    """``first(root, hold)`` in a process, until it writes ``hold/first_in`` (it then pauses until ``hold/go``);
    then ``second(root, hold)`` likewise, until ``hold/second_in`` (its imports done), and 3 s more: an unlocked
    second would finish in that time (a 6x5x4 study).  Then the first goes on, and both must end cleanly."""
    ctx = mp.get_context("spawn")
    a = ctx.Process(target=first, args=(str(root), str(hold)))
    a.start()
    _wait_for(hold / first_in, a)
    b = ctx.Process(target=second, args=(str(root), str(hold)))
    b.start()
    _wait_for(hold / second_in, b)
    b.join(3.0)
    (hold / "go").touch()
    for proc in (a, b):
        proc.join(120)
        assert proc.exitcode == 0


def _held_mean(ctx):
    """Reads scan a's scale output twice, across a pause the test controls (files ``hold/in``, ``hold/go``)."""
    from workbench.stages.mechanism import file_digest

    hold = Path(ctx.options["hold"])
    before = file_digest(Path(ctx.study.output("scale", "info.json", "a")))
    (hold / "in").touch()
    _wait_for(hold / "go")
    return {"mean.json": Json({"same": file_digest(Path(ctx.study.output("scale", "info.json", "a"))) == before})}


HELD_MEAN = Stage(
    name="mean", folder="mean", per_scan=False, settings_type=Gain, run=_held_mean, needs=lambda s: ("scale",)
)


def _execute_held_mean(root, hold):
    execute(read_study(root), HELD_MEAN, Gain(), registry={"scale": SCALE, "mean": HELD_MEAN}, options={"hold": hold})


def _rerun_scale_a(root, hold):
    st = read_study(root)
    (Path(hold) / "started").touch()  # imports done: what is left is the rerun itself
    execute(st, SCALE, Gain(4.0), registry=REG, scans=["a"], force=True)


def test_a_stage_is_not_rerun_under_a_stage_reading_it(study, tmp_path):
    """While a whole-study stage runs, a forced rerun of a stage it reads (in another process) waits for it:
    the outputs it read do not change under it (a shared lock on each unit it reads). Without the lock the
    rerun would finish during the pause; with it, the rerun ends after the reader, and the reader is stale."""
    execute(study, SCALE, Gain(), registry=REG)
    hold = tmp_path / "hold"
    hold.mkdir()
    # the reader pauses inside mean's run; the writer's rerun of scale a gets 3 s to happen under it
    _second_while_first_is_paused(study.root, hold, _execute_held_mean, "in", _rerun_scale_a, "started")
    st = read_study(study.root)
    assert json.loads(Path(st.output("mean", "mean.json")).read_text(encoding="utf-8"))["same"]
    assert st.stage_entry("scale", "a")["settings"] == {"factor": 4.0}  # the rerun did happen, after the reader
    assert stage_status(st, HELD_MEAN, registry={"scale": SCALE, "mean": HELD_MEAN}) == "stale"


def _held_scaled(ctx):
    hold = Path(ctx.options["hold"])
    (hold / "in").touch()
    _wait_for(hold / "go")
    return _scaled(ctx)


def _per_scan_b(ctx):
    return {"b.json": Json({"size": Path(ctx.study.output("scale", "info.json", ctx.scan)).stat().st_size})}


def _whole_c(ctx):
    return {"c.json": Json({"n": len(ctx.study.scan_ids)})}


B = Stage(name="b", folder="b", per_scan=True, settings_type=Gain, run=_per_scan_b, needs=lambda s: ("scale",))
C = Stage(name="c", folder="c", per_scan=False, settings_type=Gain, run=_whole_c, needs=lambda s: ("b",))
CHAIN = {"scale": SCALE, "b": B, "c": C}


def _rerun_scale_a_held(root, hold):
    held = Stage(
        name="scale", folder="scaled", per_scan=True, settings_type=Gain, run=_held_scaled, inputs=SCALE.inputs
    )
    execute(
        read_study(root), held, Gain(4.0), registry={"scale": held}, scans=["a"], force=True, options={"hold": hold}
    )


def _execute_c(root, hold):
    st = read_study(root)
    (Path(hold) / "reader").touch()  # imports done
    try:
        execute(st, C, Gain(), registry=CHAIN)
        (Path(hold) / "ran").touch()
    except StageNotReady as e:
        (Path(hold) / "stale").write_text(str(e))


def test_a_stage_waits_for_a_rerun_two_stages_upstream(study, tmp_path):
    """c needs b, b needs scale. While another process reruns scale on scan a with a new setting, c waits for
    it (a shared lock on every unit upstream, not only on b's: c's check of b reads scale's entry), then finds
    b out of date and says so; it does not run on b's outputs while scale's are being replaced."""
    execute(study, SCALE, Gain(), registry=REG)
    execute(study, B, Gain(), registry=CHAIN)
    hold = tmp_path / "hold"
    hold.mkdir()
    # the writer pauses inside scale's run on scan a (its lock held, b's entries still recorded); c gets 3 s
    _second_while_first_is_paused(study.root, hold, _rerun_scale_a_held, "in", _execute_c, "reader")
    assert not (hold / "ran").exists()
    assert "the b stage of scan 'a' is out of date" in (hold / "stale").read_text(encoding="utf-8")


def test_the_cli_names_the_stages_in_the_pipeline_order():
    from workbench.cli.options import STAGE_NAMES
    from workbench.stages import ORDER

    assert list(STAGE_NAMES) == list(ORDER)


def _caught_signals() -> int:
    """The process's caught-signal mask (``SigCgt`` of /proc/self/status): bit n−1 is set while signal n has a
    handler — what the kernel will do, which Python's ``signal.getsignal`` does not see when C code changed it."""
    for line in Path("/proc/self/status").read_text(encoding="utf-8").splitlines():
        if line.startswith("SigCgt:"):
            return int(line.split()[1], 16)
    pytest.skip("no /proc/self/status")


def _drops_sigint(ctx):
    import ctypes
    import signal

    ctypes.CDLL(None).signal(signal.SIGINT, 0)  # SIG_DFL from C, as pytetwild's fTetWild did
    return {"x.json": Json({})}


def test_a_stage_that_replaces_the_sigint_handler_in_c_gets_python_s_back(study):
    """After a stage whose library reset SIGINT in C, Python's handler is installed again (else Ctrl-C kills the
    process without a message and leaves staging folders)."""
    import signal

    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("SIGINT is not Python's default handler in this process (ignored by the test runner's parent)")
    sigint = 1 << (signal.SIGINT - 1)
    assert _caught_signals() & sigint
    drop = Stage(name="drop", folder="drop", per_scan=False, settings_type=Gain, run=_drops_sigint)
    try:
        execute(study, drop, Gain(), registry={"drop": drop})
        assert _caught_signals() & sigint
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
