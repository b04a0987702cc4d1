"""Running stages in order: ``workbench run`` and every single-stage command.

:func:`run_stages` runs the asked-for stages and, before them, every stage
they need (transitively) that has not run or is out of date, each through
:func:`workbench.stages.mechanism.execute`.  Each stage's settings are, in
order of precedence: those given for this call, those recorded in the study
by its last run (so ``workbench register --method adaptive --levels 3 5`` is remembered by a
later ``workbench run``), or the defaults.  A stage that is up to date is
skipped and says so; ``force`` names stages to rerun, and everything after
them that depends on them reruns because their outputs changed.

The commands' options become stage settings here too: :func:`given_settings`
and, per command, :func:`pose_settings`, :func:`bones_settings`,
:func:`weights_settings`, :func:`surface_settings`, :func:`register_settings`
and :func:`run_settings` (``--set`` and ``--seeds``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from workbench.stages import ORDER, STAGES
from workbench.stages.mechanism import Event, Outcome, execute, stage_status
from workbench.stages.settings import setting_value, settings_from_json
from workbench.study import Study, StudyError

__all__ = [
    "run_stages",
    "settings_for",
    "parse_set",
    "dependents",
    "json_value",
    "merged_settings",
    "given_settings",
    "pose_settings",
    "bones_settings",
    "weights_settings",
    "surface_settings",
    "register_settings",
    "dense_options",
    "run_settings",
]


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


# -- the commands' options as stage settings --------------------------------------------------------------------
# ``options`` below are a command's options that were given, by their argparse names (``vars(args)``: an option
# left out is absent, as argparse.SUPPRESS leaves it); each table maps a setting to (option, conversion).


def given_settings(study: Study, stage: str, given: dict, implied: dict | None = None):
    """The stage's settings for a single-stage command: those it last ran with in the study (else the
    defaults), with ``given`` (``{setting: value}``, from the options given on the command line) applied, and
    ``implied`` settings (those the given options imply, e.g. no VBD repair after ``--init none``) for
    whatever was not given itself."""
    over = dict(given)
    for k, v in (implied or {}).items():
        over.setdefault(k, v)
    return dataclasses.replace(settings_for(study, stage), **over)


def _from_options(options: dict, table: dict) -> dict:
    return {k: convert(options[o]) for k, (o, convert) in table.items() if o in options}


def _same(v):
    return v


def _zero_is_none(v):
    return v or None


_POSE_OPTIONS = {
    "method": ("method", _same),
    "init": ("init", str),
    "metric": ("metric", _same),
    "interpolation": ("interpolation", lambda v: 3 if v == "bspline" else 1),
    "prior_deg": ("prior_deg", _zero_is_none),
    "min_ncc": ("min_ncc", _same),
    "bias_correction": ("bias_correction", {"auto": None, "on": True, "off": False}.get),
    "margin_mm": ("margin_mm", _same),
    "max_joint_gap_mm": ("max_joint_gap_mm", _zero_is_none),
    "outlier_factor": ("outlier_factor", _zero_is_none),
    "grid_factor": ("grid_factor", _same),
}


def pose_settings(study: Study, options: dict) -> dict:
    """``{"pose": settings[, "bones": settings]}`` for ``workbench pose``: the pose stage's settings (recorded,
    else default, with the given options; ``scan``: this run's scans only) and, with ``seeds``, the bones
    stage's (:func:`bones_settings`)."""
    ps = given_settings(study, "pose", _from_options(options, _POSE_OPTIONS))
    settings = {"pose": dataclasses.replace(ps, scans=tuple(options["scan"]) if options.get("scan") else None)}
    bs = bones_settings(options)
    if bs is not None:
        settings["bones"] = bs
    return settings


def bones_settings(options: dict):
    """The bones stage's settings that segment the template from ``options["seeds"]`` (with ``modality`` and
    ``threshold``), or ``None`` without seeds (then ``modality`` and ``threshold`` are refused)."""
    from workbench.stages.bones import BonesSettings

    modality, threshold = options.get("modality"), options.get("threshold")
    if options.get("seeds") is None:
        if modality or threshold is not None:
            raise ValueError("--modality and --threshold choose how --seeds segments the bones: pass --seeds FILE")
        return None
    return BonesSettings(source="seeds", seeds=str(options["seeds"]), modality=modality, threshold=threshold)


def weights_settings(study: Study, options: dict):
    """The weights stage's settings for ``workbench weights`` (recorded, else default, with the given options)."""
    names = ("method", "edge_length_mm", "grid_factor")
    return given_settings(study, "weights", _from_options(options, {k: (k, _same) for k in names}))


_SURFACE_OPTIONS = {
    **{k: (k, _same) for k in ("target_triangles", "features", "n_features", "fit", "stiffness")},
    "landmarks": ("landmarks", str),
}


def surface_settings(study: Study, options: dict):
    """The surface stage's settings for ``workbench surface`` (recorded, else default, with the given options;
    ``scan``: this run's scans only).  Landmarks imply ``features="landmarks"``, other features drop recorded
    landmarks; a landmarks file is read here, so that a bad one is reported before the stages it needs run."""
    if "landmarks" in options:
        implied = {"features": "landmarks"}
    elif options.get("features", "landmarks") != "landmarks":
        implied = {"landmarks": None}
    else:
        implied = None
    ss = given_settings(study, "surface", _from_options(options, _SURFACE_OPTIONS), implied)
    ss = dataclasses.replace(ss, scans=tuple(options["scan"]) if options.get("scan") else None)
    if ss.landmarks is not None:
        from workbench.io.inputs import read_landmarks

        read_landmarks(ss.landmarks, study.scan_ids, study.check_scan_ids(ss.scans))
    return ss


def dense_options(items) -> tuple:
    """``--dense NAME=VALUE`` options as ``(name, value)`` pairs (values JSON, else text); ``default`` alone: none.
    The names and types are checked by :class:`workbench.stages.register.RegisterSettings`."""
    if list(items) == ["default"]:
        return ()
    out = []
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"--dense {item!r}: expected NAME=VALUE (e.g. --dense window_mm=4), or 'default' alone")
        out.append((name.strip(), json_value(value)))
    return tuple(out)


_INIT_OPTIONS = {
    "method": ("init", lambda v: "identity" if v == "none" else v),
    "pose": ("pose_source", _same),
    "unfold": ("unfold_init", _same),
    "map_factor": ("map_factor", _same),
}
_REGISTER_OPTIONS = {
    "method": ("method", _same),
    "preset": ("preset", lambda v: "paper" if v == "paper" else "auto"),
    "levels": ("levels", tuple),
    "optimizer": ("optimizer", _same),
    "metric": ("metric", _same),
    "max_steps_per_level": ("max_steps", _same),
    "fix_bones": ("no_fix_bones", lambda v: not v),
    "seed": ("seed", _same),
    "dense_settings": ("dense", dense_options),
}
#: Rhee's Algorithm 1's own options (option, name): refused with the dense method, which would ignore them.
_ADAPTIVE_ONLY = (
    ("--levels", "levels"),
    ("--optimizer", "optimizer"),
    ("--metric", "metric"),
    ("--max-steps", "max_steps"),
)


def register_settings(study: Study, options: dict) -> dict:
    """``{"init": settings, "register": settings}`` for ``workbench register``: recorded (else default), with
    the given options.  A recorded setting that a given option contradicts gives way to it: an earlier
    ``--unfold-init`` repaired a VBD start (not another), ``--preset paper`` is Rhee's method, ``--method
    dense`` has no preset nor Algorithm 1's options; Algorithm 1's options with the dense method are refused."""
    init_implied = {"unfold": False} if options.get("init", "vbd") != "vbd" else {}
    if options.get("init", "polyrigid") != "polyrigid":
        init_implied["map_factor"] = None  # the polyrigid start's
    reg_implied = {}
    if options.get("preset") == "paper":
        reg_implied["method"] = "auto"
    if options.get("preset") == "paper" or options.get("method") == "adaptive":
        reg_implied["dense_settings"] = ()  # the dense registration's, recorded by an earlier run
    if options.get("method") == "dense":  # nor Algorithm 1's options recorded by an earlier run
        reg_implied.update(preset="auto", levels=None, optimizer=None, metric=None, max_steps_per_level=None)
    init = given_settings(study, "init", _from_options(options, _INIT_OPTIONS), init_implied)
    reg = given_settings(study, "register", _from_options(options, _REGISTER_OPTIONS), reg_implied)
    given = [opt for opt, name in _ADAPTIVE_ONLY if name in options]
    if given and reg.resolved_method == "dense":
        raise ValueError(
            f"{', '.join(given)} {'is a setting' if len(given) == 1 else 'are settings'} of Rhee's "
            "Algorithm 1, not of the dense registration: add --method adaptive, or leave "
            f"{'it' if len(given) == 1 else 'them'} out"
        )
    return {"init": init, "register": reg}


def run_settings(study: Study, set_items, seeds=None) -> dict:
    """``{stage: settings}`` for ``workbench run``: ``--set`` items (:func:`parse_set`) over the study's
    settings and, with ``seeds`` (a seeds file), the bones segmented from it."""
    settings = merged_settings(study, parse_set(set_items))
    if seeds is not None:
        settings["bones"] = dataclasses.replace(
            settings.get("bones") or settings_for(study, "bones"), source="seeds", seeds=str(seeds)
        )
    return settings
