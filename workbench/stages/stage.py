"""What a stage is: its declaration (:class:`~workbench.stages.stage.Stage`), what its ``run`` gets
(:class:`~workbench.stages.stage.StageContext`), its progress (:class:`~workbench.stages.stage.Event`) and results
(:class:`~workbench.stages.stage.Outcome`), and the working grid of the stages that thin the template.

:mod:`workbench.stages.mechanism` runs stages; these names are re-exported there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from deformation.geometry import every_nth
from workbench.study import Study, StudyError

__all__ = [
    "Stage",
    "StageContext",
    "Event",
    "Outcome",
    "StageNotReady",
    "WORKING_VOXELS",
    "working_factor",
    "working_labels",
]

#: the most template voxels the pose and weights stages work on, to stay within 8 GiB (see
#: docs/measurements/workbench.md); a template up to this size keeps full-grid weights (which register, model and
#: validate need), a bigger one (Kurihara's CT: 197 M voxels) is worked on every f-th voxel (``--grid-factor``)
WORKING_VOXELS = 60_000_000


def working_factor(setting, geometry) -> int:
    """The ``--grid-factor`` of a stage: the setting, or (None) the smallest that leaves at most
    :data:`~workbench.stages.stage.WORKING_VOXELS` of the template's grid."""
    return geometry.factor_within(WORKING_VOXELS) if setting is None else int(setting)


def working_labels(study, labels, f: int):
    """The template's bone labels on every ``f``-th voxel; a bone left with no voxel there is one clear error
    naming ``--grid-factor``."""
    if f == 1:
        return labels
    sk = study.skeleton()
    coarse = labels.every(f)
    gone = [
        b for b in sk.bone_names if (labels.data == sk.label_of(b)).any() and not (coarse.data == sk.label_of(b)).any()
    ]
    if gone:
        path = study.template_labels_path()
        raise StudyError(
            f"{path}: bone(s) {', '.join(gone)} have no voxel on {every_nth(f)} voxel of the template; "
            "give a smaller --grid-factor (1 keeps the full grid)",
            path,
        )
    return coarse


class StageNotReady(StudyError):
    """A stage cannot run: a stage it needs has not run (or is out of date)."""


@dataclass(frozen=True)
class Event:
    """One progress report: ``stage``, ``scan`` (or None), ``done`` of ``total`` units, a message.

    ``kind`` is ``"progress"`` (work inside a unit: ``done`` of ``total``,
    ``total`` 0 when unknown; shown as a bar or a rate-limited line),
    ``"message"`` (a line always shown), ``"start"``, ``"done"`` or ``"skip"``
    (a unit begun, finished or skipped).
    """

    stage: str
    scan: str | None
    done: int
    total: int
    message: str = ""
    kind: str = "progress"


@dataclass(frozen=True)
class Outcome:
    """What :func:`~workbench.stages.mechanism.execute` did with one unit (the study, or one scan)."""

    stage: str
    scan: str | None
    status: str  #: "ran" or "skipped"
    seconds: float
    entry: dict


@dataclass(frozen=True)
class StageContext:
    """What a stage's ``run`` gets: the study, its settings, the scan, the previous outputs, progress."""

    study: Study
    settings: object
    scan: str | None
    previous: dict  #: file name → path of the outputs of the previous run, if any
    report: Callable  #: report(done, total, message="")
    options: dict = field(default_factory=dict)  #: run-time options that do not change the result's meaning
    stage_name: str = ""
    emit: Callable = lambda event: None
    runner: object = None  #: a :class:`workbench.scale.Runner` for per-scan work inside a whole-study stage, or None
    #: wall-clock seconds of the stage's steps (JSON: numbers, lists, dicts), recorded under the unit's manifest
    #: entry's ``timings``: a stage's files hold no time, so the same inputs and settings give the same bytes
    timings: dict = field(default_factory=dict)

    def map_scans(self, fn, items, *, shared=None, on_result=None, processes: int = 1) -> list:
        """``fn`` over ``items`` here (over ``processes`` processes of this machine), or as Dask tasks when the
        run has a cluster (:mod:`workbench.scale`)."""
        from workbench.scale import Runner

        return (self.runner or Runner()).map(
            fn, items, shared=shared, name=self.stage_name, on_result=on_result, processes=processes
        )

    def say(self, message: str) -> None:
        """A message worth every line (always shown, unlike ``report``'s rate-limited progress)."""
        self.emit(Event(self.stage_name, self.scan, 0, 0, message, "message"))


@dataclass(frozen=True)
class Stage:
    """A pipeline stage (see the module docstring).

    ``needs(settings)`` names the stages whose outputs it reads; ``inputs(study,
    settings, scan)`` maps names to the input files it reads (their content
    goes into the digest); ``applies(study, settings, scan)`` returns ``None``
    when the stage has work for that unit, else the reason it has none (e.g.
    validate without ground truth); ``run(ctx)`` returns ``{file name:
    output}``.  Bump ``version`` when the stage's results change for the same
    inputs and settings.
    """

    name: str
    folder: str
    per_scan: bool
    settings_type: type
    run: Callable
    needs: Callable = lambda settings: ()
    inputs: Callable = lambda study, settings, scan: {}
    applies: Callable = lambda study, settings, scan: None
    uses: Callable = lambda study, settings: None  #: scans a whole-study stage reads of per-scan needs (None: all)
    version: int = 1
