"""Running stages in order: ``workbench run`` and every single-stage command.

:func:`run_stages` runs the asked-for stages and, before them, every stage
they need (transitively) that has not run or is out of date, each through
:func:`workbench.stages.mechanism.execute`.  Each stage's settings are, in
order of precedence: those given for this call, those recorded in the study
by its last run (so ``workbench register --method adaptive --levels 3 5`` is remembered by a
later ``workbench run``), or the defaults.  A stage that is up to date is
skipped and says so; ``force`` names stages to rerun, and everything after
them that depends on them reruns because their outputs changed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from workbench.stages import ORDER, STAGES
from workbench.stages.mechanism import Event, Outcome, execute, stage_status
from workbench.stages.settings import setting_value, settings_from_json
from workbench.study import Study, StudyError

__all__ = ["run_stages", "settings_for", "parse_set", "dependents", "json_value"]


def settings_for(study: Study, name: str, given: dict | None = None):
    """The settings a stage runs with: ``given[name]``, else the study's recorded ones, else the defaults."""
    stage = STAGES[name]
    if given and name in given:
        return given[name]
    recorded = study.recorded_settings(name)
    if recorded:
        try:
            return stage.settings_type(**settings_from_json(stage.settings_type, recorded))
        except (TypeError, ValueError):
            pass  # settings of an older version: the defaults
    return stage.settings_type()


def _closure(targets, settings: dict) -> list[str]:
    want = set()

    def add(n):
        if n in want:
            return
        want.add(n)
        for m in STAGES[n].needs(settings[n]):
            add(m)

    for t in targets:
        add(t)
    return [n for n in ORDER if n in want]


def dependents(names) -> set[str]:
    """Stages that need any of ``names``, directly or not (by their default settings' needs)."""
    out = set(names)
    changed = True
    while changed:
        changed = False
        for n, st in STAGES.items():
            needs = set(st.needs(st.settings_type()))
            if n not in out and needs & out:
                out.add(n)
                changed = True
    return out


def run_stages(
    study: Study,
    targets,
    *,
    settings: dict | None = None,
    force=(),
    scans=None,
    progress: Callable | None = None,
    options: dict | None = None,
    runner=None,
) -> list[Outcome]:
    """Run ``targets`` (stage names) and what they need; see the module docstring.

    ``settings``: ``{stage: settings}`` for this call (a stage given settings
    runs with them — and is skipped only when up to date with them — even
    when it is not a target); ``force``: stage names
    to rerun even when up to date; ``scans``: per-scan stages only for these
    (whole-study stages still cover every scan they are set to);
    ``options``: ``{stage: {option: value}}`` (:func:`~workbench.stages.mechanism.execute`);
    ``runner``: a :class:`workbench.scale.Runner` with a Dask cluster runs the per-scan work as tasks.
    """
    unknown = [t for t in list(targets) + list(force) if t not in STAGES]
    if unknown:
        raise ValueError(f"unknown stage {unknown}; the stages are {list(ORDER)}")
    resolved = {n: settings_for(study, n, settings) for n in ORDER}
    order = _closure(targets, resolved)
    study.check_writable()
    emit = progress or (lambda e: None)
    outcomes = []
    scan_ids = study.check_scan_ids(scans)
    for name in order:
        stage = STAGES[name]
        if name not in targets and name not in force and name not in (settings or {}):
            units = scan_ids if stage.per_scan else [None]
            if all(stage_status(study, stage, u, registry=STAGES) == "done" for u in units):
                emit(Event(name, None, len(units), len(units), f"{name}: up to date, skipped", "skip"))
                continue
        outcomes += execute(
            study,
            stage,
            resolved[name],
            registry=STAGES,
            scans=scan_ids,
            force=name in force,
            progress=emit,
            options=(options or {}).get(name),
            runner=runner,
        )
    return outcomes


def parse_set(items) -> dict:
    """``["register.max_steps_per_level=50", ...]`` → ``{"register": {"max_steps_per_level": 50}}`` (JSON values).

    Each value is checked against the type its stage's settings dataclass declares (``int``, ``float``,
    ``bool``, ``str``, ``tuple`` — a JSON list —, optionally ``| None`` — JSON ``null``), so that a wrong one is
    one clear line before anything runs or is recorded.  A whole-number float is taken for an ``int`` and a
    whole number for a ``float``.
    """
    out: dict = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        stage, dot, field = key.partition(".")
        if not sep or not dot or stage not in STAGES:
            raise ValueError(f"--set {item!r}: expected STAGE.SETTING=VALUE with STAGE one of {list(ORDER)}")
        names = [f.name for f in dataclasses.fields(STAGES[stage].settings_type)]
        if field not in names:
            raise ValueError(f"--set {item!r}: the {stage} stage has no setting {field!r}; its settings are {names}")
        out.setdefault(stage, {})[field] = setting_value(
            f"{stage}.{field}", json_value(value), _declared_type(stage, field)
        )
    return out


def json_value(text: str):
    """A command line's setting value: JSON (``true``, ``4``, ``[3, 5]``, ``null``), else the text itself."""
    import json

    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _declared_type(stage: str, field: str):
    import typing

    return typing.get_type_hints(STAGES[stage].settings_type)[field]


def merged_settings(study: Study, overrides: dict) -> dict:
    """``{stage: settings}`` with ``overrides`` (from :func:`parse_set`) applied over the study's settings."""
    out = {}
    for stage, fields in overrides.items():
        base = settings_for(study, stage)
        try:
            out[stage] = dataclasses.replace(
                base, **{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}
            )
        except (TypeError, ValueError) as e:
            raise StudyError(f"--set {stage}: {e}", study.manifest_path) from e
    return out
