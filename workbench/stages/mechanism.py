"""The one stage mechanism: digest, skip, staging folder, atomic swap, manifest entry, progress.

A :class:`Stage` (:mod:`workbench.stages.stage`) declares its name, folder, needs, settings dataclass and
input files, and a ``run`` that *returns* its outputs (:mod:`workbench.stages.outputs`).  :func:`execute`
does the rest, the same way for every stage:

1. **needs** — each needed stage must be recorded and up to date, else one clear line: "run
   ``workbench X STUDY`` first" or "... is out of date";
2. **digest** — a unit whose recorded digest (:mod:`workbench.stages.digests`) matches and whose outputs
   exist is skipped, and says so;
3. **staging** — the outputs are written into a private staging folder beside the final one, then swapped
   in atomically; an exception, Ctrl-C or SIGTERM removes the staging folder, and the next run removes
   those of processes that died (SIGKILL);
4. **manifest** — one entry per stage (per scan for per-scan stages) through
   :meth:`workbench.study.Study.record`: inputs, settings, needs, outputs and their digest, seed, timings,
   versions.  Times, dates and hosts go there only, so the same inputs and settings give the same bytes in
   the stage folders.  Per-scan stages commit each scan as it finishes (an interrupted run resumes);
5. **scale-out** — with a Dask cluster (:mod:`workbench.scale`), a per-scan stage's scans run as tasks that
   do step 3 for their scan, and this process alone does step 4 as each arrives, inside
   :func:`workbench.scale.same_bits`: the same bits on any machine, for any number of workers.

Progress: stages report :class:`Event` records to one callback (:mod:`workbench.progress` draws them);
everything else goes to ``logging.getLogger("workbench")``.  The names of the modules above are
re-exported here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import secrets
import shutil
import socket
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from workbench import __version__
from workbench.io.atomic import naming_staged, replace_dir
from workbench.io.jsonio import to_jsonable
from workbench.stages.digests import (
    digests_of_needs,
    dir_digest,
    file_digest,
    input_digests,
    need_units,
    outputs_exist,
    stage_status,
    unit_digest,
)
from workbench.stages.outputs import (
    CopyFile,
    Field,
    Image,
    Json,
    Labels,
    MeshFile,
    TetMeshFile,
    Text,
    VectorImage,
    WeightMap,
    write_output,
)
from workbench.stages.settings import settings_dict, settings_from_json
from workbench.stages.stage import (
    WORKING_VOXELS,
    Event,
    Outcome,
    Stage,
    StageContext,
    StageNotReady,
    working_factor,
    working_labels,
)
from workbench.study import Study

__all__ = [
    "Stage",
    "Event",
    "Outcome",
    "StageNotReady",
    "execute",
    "stage_status",
    "file_digest",
    "Image",
    "Labels",
    "Field",
    "VectorImage",
    "Json",
    "Text",
    "WeightMap",
    "TetMeshFile",
    "MeshFile",
    "CopyFile",
    "settings_dict",
    "WORKING_VOXELS",
    "working_factor",
    "working_labels",
]

log = logging.getLogger("workbench")

_HOST = socket.gethostname()


def _clean_dead_staging(folder: Path) -> None:
    """Remove staging (``.partial-``) and replaced (``.old-``) folders left by processes of this host that no
    longer run (killed with SIGKILL, power loss).  Another host's folders are left alone: its processes may
    still be writing them (a shared file system)."""
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        if not p.name.startswith("."):
            continue
        for marker in (".partial-", ".old-"):
            if marker in p.name:
                tail = p.name.split(marker, 1)[1].rsplit("-", 2)  # host (may hold '-'), pid, random
                if len(tail) == 3 and tail[0] == _HOST and tail[1].isdigit():
                    try:
                        os.kill(int(tail[1]), 0)
                    except ProcessLookupError:
                        shutil.rmtree(p, ignore_errors=True)
                    except PermissionError:
                        pass


def execute(
    study: Study,
    stage: Stage,
    settings,
    *,
    registry: dict,
    scans=None,
    force: bool = False,
    progress: Callable | None = None,
    options: dict | None = None,
    runner=None,
) -> list[Outcome]:
    """Run ``stage`` on ``study`` with ``settings`` (every scan, or ``scans``); see the module docstring.

    ``registry`` maps stage names to :class:`Stage` objects (for ``needs``);
    ``options`` reach the stage's ``run`` as ``ctx.options`` and stay out of
    the digest (run-time choices that do not change what the outputs mean).
    ``runner`` (:class:`workbench.scale.Runner`): a distributed one runs a per-scan stage's scans as Dask
    tasks, and reaches a whole-study stage's ``run`` as ``ctx.runner`` (its per-scan work).
    Returns one :class:`Outcome` per unit (the study, or each scan).
    """
    if not isinstance(settings, stage.settings_type):
        raise TypeError(f"{stage.name}: settings must be {stage.settings_type.__name__}, got {type(settings).__name__}")
    emit = progress or (lambda event: None)
    scans = study.check_scan_ids(scans)
    units = list(scans) if stage.per_scan else [None]
    settings_json = settings_dict(settings)
    need_scans = scans if stage.per_scan else study.check_scan_ids(stage.uses(study, settings))
    with _needs_held(study, stage, settings, units, registry):
        study.reload()
        # every need is checked before any work, so that a missing stage is reported at once
        need_digests = {u: digests_of_needs(study, stage, settings, u, need_scans, registry) for u in units}
        root = study.root
        folder = root / stage.folder
        _clean_dead_staging(folder if stage.per_scan else root)
        if stage.per_scan and runner is not None and runner.distributed:
            return _execute_distributed(
                study, stage, settings, settings_json, units, need_digests, force, emit, options, runner
            )
        outcomes = []
        n = len(units)
        for i, unit in enumerate(units):
            # One process at a time per unit: a second one waits, then finds the work done (and skips it).
            with _unit_lock(root, stage.name, unit):
                study.reload()
                outcomes.append(
                    _execute_unit(
                        study,
                        stage,
                        settings,
                        settings_json,
                        unit,
                        i,
                        n,
                        need_digests[unit],
                        force,
                        emit,
                        options,
                        runner,
                    )
                )
        return outcomes


def _upstream_units(study: Study, stage: Stage, settings, units, registry) -> list:
    """``(stage name, unit)`` of every unit upstream of ``stage``'s ``units``: its needs, their needs (which
    :func:`stage_status` reads to tell whether a need is up to date), and so on.  A need's own needs are taken
    under its recorded settings and its defaults both (an over-estimate costs a writer a wait, no more)."""
    out, todo = set(), [(name, u) for name in stage.needs(settings) for u in units]
    while todo:
        name, u = todo.pop()
        need = registry[name]
        for unit in need_units(need, u, study.scan_ids):  # a whole-study unit: every scan (an over-estimate)
            if (name, unit or "") in out:
                continue
            out.add((name, unit or ""))
            recorded = (study.stage_entry(name, unit) or {}).get("settings") or {}
            sets = []
            for make in (
                lambda: need.settings_type(**settings_from_json(need.settings_type, recorded)),
                need.settings_type,
            ):
                try:
                    sets.append(make())
                except (TypeError, ValueError):
                    pass
            todo += [(m, unit) for st in sets for m in need.needs(st)]
    return sorted(out)


@contextlib.contextmanager
def _needs_held(study: Study, stage: Stage, settings, units, registry):
    """Shared locks on every unit upstream of the stage (:func:`_upstream_units`), held while it runs: another
    process may read them too, but not rerun them (forget their entries, swap their folders) under it.  The set
    is made again under the locks until no unit is added (a need rerun meanwhile with other settings may need
    other stages).  A process holding a unit's exclusive lock takes no other lock (a Dask coordinator holds no
    exclusive one while its tasks run; each task takes its own scan's), so this cannot deadlock."""
    held: set = set()
    with contextlib.ExitStack() as stack:
        while True:
            study.reload()
            new = [u for u in _upstream_units(study, stage, settings, units, registry) if u not in held]
            if not new:
                break
            for name, unit in new:
                stack.enter_context(_unit_lock(study.root, name, unit or None, shared=True))
                held.add((name, unit))
        yield


@contextlib.contextmanager
def _unit_lock(root: Path, stage: str, unit, *, shared: bool = False):
    """A unit's lock: exclusive to run (or record) it, shared to read its outputs while another stage runs."""
    import fcntl

    locks = root / ".locks"
    locks.mkdir(exist_ok=True)
    with open(locks / (f"{stage}-{unit}.lock" if unit else f"{stage}.lock"), "a+") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_SH if shared else fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _prepare_unit(
    study: Study, stage: Stage, settings, settings_json, unit, i: int, n: int, need_digests: dict, force: bool, emit
):
    """An :class:`Outcome` when the unit has nothing to do or is up to date (recorded, reported), else
    ``(digest, inputs)`` for the work."""
    label = f"{stage.name}" + (f" {unit}" if unit else "")
    old = study.stage_entry(stage.name, unit)
    reason = stage.applies(study, settings, unit)
    if reason:
        entry = {
            "digest": "",
            "skipped": reason,
            "outputs": {},
            "outputs_digest": "",
            "settings": settings_json,
            "finished": _now(),
        }
        if old is None or old.get("skipped") != reason or old.get("settings") != settings_json:
            study.record(stage.name, entry, unit, stage_info={"folder": stage.folder})
        emit(Event(stage.name, unit, i + 1, n, f"{label}: nothing to do ({reason})", "skip"))
        return Outcome(stage.name, unit, "skipped", 0.0, entry)
    inputs = input_digests(study, stage, settings, unit)
    digest = unit_digest(stage, settings_json, inputs, need_digests)
    if not force and old is not None and old.get("digest") == digest and outputs_exist(study, old):
        emit(Event(stage.name, unit, i + 1, n, f"{label}: up to date, skipped", "skip"))
        return Outcome(stage.name, unit, "skipped", 0.0, old)
    return digest, inputs


def _unit_folder(study: Study, stage: Stage, unit) -> Path:
    """Where a unit's outputs live: the stage's folder, or its scan's subfolder."""
    return study.root / stage.folder / unit if unit else study.root / stage.folder


def _run_unit(study: Study, stage: Stage, settings, unit, emit, options, runner=None, forget=None) -> dict:
    """Run the stage on one unit and swap its outputs into place: ``{"names", "outputs_digest", "seconds",
    "timings"}`` (``timings``: what the stage put in ``ctx.timings``, plain JSON: it crosses Dask too).

    ``forget()`` is called once the outputs are written and before they replace the old ones (the sync path
    forgets the old manifest entry there; a Dask task leaves the manifest to its coordinator)."""
    t0 = time.perf_counter()
    final = _unit_folder(study, stage, unit)
    final.parent.mkdir(parents=True, exist_ok=True)
    previous = {p.name: p for p in final.iterdir()} if final.is_dir() else {}

    def report(done, total, message=""):
        emit(Event(stage.name, unit, done, total, message))

    ctx = StageContext(study, settings, unit, previous, report, dict(options or {}), stage.name, emit, runner)
    staging = final.parent / f".{final.name}.partial-{_HOST}-{os.getpid()}-{secrets.token_hex(4)}"
    try:
        # made inside the try: a Ctrl-C handled just after mkdir returns (Python runs its handler at the next
        # bytecode) must still remove it
        staging.mkdir()
        from workbench.scale import same_bits

        with same_bits(), _keeping_sigint():  # the same bits on any machine, for any number of workers
            outputs = stage.run(ctx)
        files = []
        for name, obj in outputs.items():
            with naming_staged(staging, final):  # a full disk or a file-size limit: named by the final path
                files += write_output(obj, staging / name)
        out_digest = dir_digest(files, staging)
        timings = to_jsonable(ctx.timings, where=f"{stage.name} timings")  # refused before the swap, not after
        if forget is not None:
            forget()
        replace_dir(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return {
        "names": list(outputs),
        "outputs_digest": out_digest,
        "seconds": time.perf_counter() - t0,
        "timings": timings,
    }


@contextlib.contextmanager
def _keeping_sigint():
    """Install Python's SIGINT handler again after a stage: a library that replaces it in C (as pytetwild did;
    Python's own record, ``signal.getsignal``, does not see that) would leave Ctrl-C in the later stages of the
    same process killing it with no message and staging folders behind."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handler = signal.getsignal(signal.SIGINT)
    try:
        yield
    finally:
        if handler is not None:
            signal.signal(signal.SIGINT, handler)


def _record_unit(
    study: Study,
    stage: Stage,
    settings_json,
    unit,
    i: int,
    n: int,
    digest: str,
    inputs: dict,
    need_digests: dict,
    done: dict,
    emit,
) -> Outcome:
    rel = _unit_folder(study, stage, unit).relative_to(study.root)
    seconds = done["seconds"]
    entry = {
        "digest": digest,
        "settings": settings_json,
        "inputs": inputs,
        "needs": need_digests,
        "outputs": {name: str(rel / name) for name in done["names"]},
        "outputs_digest": done["outputs_digest"],
        "seconds": round(seconds, 3),
        "finished": _now(),
        "workbench_version": __version__,
        "stage_version": stage.version,
    }
    if done.get("timings"):  # the stage's own per-step seconds (its files hold no time)
        entry["timings"] = done["timings"]
    if "seed" in settings_json:
        entry["seed"] = settings_json["seed"]
    study.record(stage.name, entry, unit, stage_info={"folder": stage.folder})
    label = f"{stage.name}" + (f" {unit}" if unit else "")
    emit(Event(stage.name, unit, i + 1, n, f"{label}: done in {seconds:.1f} s", "done"))
    log.info("%s: done in %.1f s", label, seconds)
    return Outcome(stage.name, unit, "ran", seconds, entry)


def _execute_unit(
    study: Study,
    stage: Stage,
    settings,
    settings_json,
    unit,
    i: int,
    n: int,
    need_digests: dict,
    force: bool,
    emit,
    options,
    runner=None,
) -> Outcome:
    prep = _prepare_unit(study, stage, settings, settings_json, unit, i, n, need_digests, force, emit)
    if isinstance(prep, Outcome):
        return prep
    digest, inputs = prep
    label = f"{stage.name}" + (f" {unit}" if unit else "")
    emit(Event(stage.name, unit, i, n, f"{label}: running", "start"))
    # Forget the old entry before its files go: interrupted between the swap and the record, the unit is then
    # missing (and reruns), never recorded with another run's files.
    forget = (lambda: study.forget(stage.name, unit)) if study.stage_entry(stage.name, unit) is not None else None
    done = _run_unit(study, stage, settings, unit, emit, options, runner, forget)
    return _record_unit(study, stage, settings_json, unit, i, n, digest, inputs, need_digests, done, emit)


def _unit_task(job: tuple) -> dict:
    """One scan of a per-scan stage, on a Dask worker: the stage, paths and JSON in, file names and digest out."""
    from workbench.scale import task_reporter
    from workbench.study import read_study

    root, stage, settings_json, unit, options, topic = job
    study = read_study(root)
    settings = stage.settings_type(**settings_from_json(stage.settings_type, settings_json))
    send = task_reporter(topic)  # the stage's progress, back to the coordinator's progress bars

    def emit(event: Event) -> None:
        if event.kind in ("progress", "message"):
            send(dataclasses.asdict(event))

    with _unit_lock(study.root, stage.name, unit):
        done = _run_unit(study, stage, settings, unit, emit, options)
        done["stats"] = _file_stats(_unit_folder(study, stage, unit), done["names"])
        return done


def _file_stats(folder: Path, names) -> dict | None:
    """``{name: (size, mtime_ns)}`` of a unit's files (None when one is missing): which run's files they are."""
    try:
        return {n: ((st := (folder / n).stat()).st_size, st.st_mtime_ns) for n in names}
    except OSError:
        return None


def _execute_distributed(
    study: Study, stage: Stage, settings, settings_json, units, need_digests, force, emit, options, runner
) -> list[Outcome]:
    """The scans of a per-scan stage as Dask tasks (:mod:`workbench.scale`); the manifest is written here only.

    Each scan's old entry is forgotten before its task is sent (a task swaps its folder itself), so a run
    that fails or is interrupted reruns every scan it had sent, finished ones excepted: they are recorded as
    they arrive.  A scan another process ran meanwhile keeps that process's record.
    """
    n = len(units)
    outcomes: dict = {}
    jobs = []
    for i, unit in enumerate(units):
        with _unit_lock(study.root, stage.name, unit):
            study.reload()
            prep = _prepare_unit(study, stage, settings, settings_json, unit, i, n, need_digests[unit], force, emit)
            if isinstance(prep, Outcome):
                outcomes[i] = prep
                continue
            if study.stage_entry(stage.name, unit) is not None:
                # forgotten before the task swaps its folder: a run interrupted in between reruns the scan
                study.forget(stage.name, unit)
        jobs.append((i, unit, prep))
    if jobs:
        emit(
            Event(
                stage.name,
                None,
                0,
                0,
                f"{stage.name}: {len(jobs)} scan(s) as Dask tasks on {runner.description}",
                "message",
            )
        )
        for i, unit, _ in jobs:
            emit(Event(stage.name, unit, i, n, f"{stage.name} {unit}: running", "start"))

        def recorded(k, done):
            i, unit, (digest, inputs) = jobs[k]
            with _unit_lock(study.root, stage.name, unit):
                study.reload()
                if _file_stats(_unit_folder(study, stage, unit), done["names"]) != done["stats"]:
                    # another process ran this scan between our task's swap and now (the lock is not held
                    # across the task): the folder is its run's, and so is the manifest entry it recorded
                    entry = study.stage_entry(stage.name, unit) or {}
                    emit(
                        Event(
                            stage.name,
                            unit,
                            i + 1,
                            n,
                            f"{stage.name} {unit}: done by another process meanwhile; its result kept",
                            "done",
                        )
                    )
                    outcomes[i] = Outcome(stage.name, unit, "skipped", 0.0, entry)
                    return
                outcomes[i] = _record_unit(
                    study, stage, settings_json, unit, i, n, digest, inputs, need_digests[unit], done, emit
                )

        fields = {f.name for f in dataclasses.fields(Event)}  # Dask adds the sender ('worker') to each message

        def forwarded(message: dict) -> None:
            emit(Event(**{k: v for k, v in message.items() if k in fields}))

        with runner.forwarding(forwarded) as topic:
            runner.map(
                _unit_task,
                [
                    (str(study.root.resolve()), stage, settings_json, unit, dict(options or {}), topic)
                    for _, unit, _ in jobs
                ],
                name=f"{stage.name}",
                on_result=recorded,
            )
    return [outcomes[i] for i in range(n)]


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")
