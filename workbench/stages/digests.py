"""Whether a stage's unit (the study, or one scan) is up to date: the digest of its inputs and settings.

A unit's digest is the SHA-256 of the stage's name and version, the workbench
version, the settings (canonical JSON), the content of its input files and
the ``outputs_digest`` of every needed stage's entry (``unit_digest``).
A stage whose recorded digest matches and whose outputs exist is up to date
(:func:`stage_status`); a need that has not run or is out of date raises
:class:`~workbench.stages.stage.StageNotReady` (:func:`digests_of_needs`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from workbench import __version__
from workbench.errors import WorkbenchError
from workbench.stages.settings import settings_from_json
from workbench.stages.stage import Stage, StageNotReady
from workbench.study import STAGE_COMMANDS, Study, StudyError

__all__ = [
    "file_digest",
    "dir_digest",
    "input_digests",
    "need_units",
    "digests_of_needs",
    "unit_digest",
    "outputs_exist",
    "stage_status",
]

_DIGESTS: dict = {}


def file_digest(path: Path) -> str:
    """SHA-256 of a file's content (cached per process by path, size and modification time); of a folder (a
    DICOM series), of the names and contents of the files in it."""
    path = Path(path)
    if path.is_dir():
        h = hashlib.sha256()
        for p in sorted(q for q in path.iterdir() if q.is_file()):
            h.update(p.name.encode() + b"\0" + file_digest(p).encode())
        return h.hexdigest()
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 22), b""):
                h.update(chunk)
        _DIGESTS[key] = h.hexdigest()
    return _DIGESTS[key]


def input_digests(study: Study, stage: Stage, settings, scan) -> dict:
    files = stage.inputs(study, settings, scan)
    out = {}
    for k, p in sorted(files.items()):
        if p is None:
            continue
        p = Path(p)
        if not p.exists():
            raise StudyError(f"{p}: an input of the {stage.name} stage is missing.", p)
        try:
            rel = str(p.resolve().relative_to(study.root.resolve()))
        except ValueError:
            rel = str(p)
        out[k] = {"path": rel, "sha256": file_digest(p)}
    return out


def need_units(need: Stage, scan, scans) -> list:
    """The units of ``need`` a unit reads: the study, the same scan, or (for a whole-study stage) ``scans``."""
    if not need.per_scan:
        return [None]
    return [scan] if scan is not None else list(scans)


def digests_of_needs(study: Study, stage: Stage, settings, scan, scans, registry) -> dict:
    """``{need: outputs_digest}`` (per-scan needs: ``{need/scan: ...}``); raises
    :class:`~workbench.stages.stage.StageNotReady`."""
    out = {}
    for name in stage.needs(settings):
        need = registry[name]
        for unit in need_units(need, scan, scans):
            e = study.stage_entry(name, unit)  # the caller holds the unit's shared lock (_needs_held)
            what = f"the {name} stage" + (f" of scan {unit!r}" if unit else "")
            cmd = f"`{STAGE_COMMANDS.get(name, 'workbench run')} {study.root}`"
            if e is not None and e.get("skipped"):
                continue  # the need had no work for this unit (e.g. validate without truth)
            if e is None:
                raise StageNotReady(
                    f"{study.manifest_path}: {stage.name} needs {what}; run {cmd} (or `workbench "
                    f"run {study.root}`) first.",
                    study.manifest_path,
                )
            if stage_status(study, need, unit, registry=registry) != "done":
                raise StageNotReady(
                    f"{study.manifest_path}: {what} is out of date (its inputs or a stage before "
                    f"it changed since it ran); run {cmd} or `workbench run {study.root}` first.",
                    study.manifest_path,
                )
            out[name if unit is None else f"{name}/{unit}"] = e["outputs_digest"]
    return out


def unit_digest(stage: Stage, settings_json, inputs: dict, needs: dict) -> str:
    doc = {
        "stage": stage.name,
        "stage_version": stage.version,
        "workbench_version": __version__,
        "settings": settings_json,
        "inputs": {k: v["sha256"] for k, v in inputs.items()},
        "needs": needs,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def outputs_exist(study: Study, entry: dict) -> bool:
    return all(study.path(p).exists() for p in (entry.get("outputs") or {}).values())


def stage_status(study: Study, stage: Stage, scan=None, *, registry: dict) -> str:
    """``"missing"``, ``"stale"`` (its inputs or needs changed since it ran) or ``"done"``, from its recorded settings.

    A unit recorded as having nothing to do (validate without truth) is done
    while that still holds, and missing once it has work.
    """
    e = study.stage_entry(stage.name, scan)
    if e is None:
        return "missing"
    try:
        settings = stage.settings_type(**settings_from_json(stage.settings_type, e.get("settings") or {}))
        if e.get("skipped"):
            return "done" if stage.applies(study, settings, scan) else "missing"
        if not outputs_exist(study, e):
            return "missing"
        inputs = input_digests(study, stage, settings, scan)
        scans = None if stage.per_scan else study.check_scan_ids(stage.uses(study, settings))
        needs = {}
        for name in stage.needs(settings):
            for unit in need_units(registry[name], scan, scans or []):
                ne = study.stage_entry(name, unit)
                if ne is None:
                    return "stale"
                if not ne.get("skipped"):
                    needs[name if unit is None else f"{name}/{unit}"] = ne["outputs_digest"]
    except (WorkbenchError, OSError, TypeError, ValueError):
        return "stale"
    return "done" if unit_digest(stage, e.get("settings"), inputs, needs) == e["digest"] else "stale"


def dir_digest(files: list[Path], base: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(files):
        h.update(str(p.relative_to(base)).encode())
        h.update(file_digest(p).encode())
    return h.hexdigest()
