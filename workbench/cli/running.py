"""What the command handlers share: the progress printer, a line printer, running stages on the study."""

from __future__ import annotations

__all__ = ["progress_printer", "line_printer", "run_study_stages", "read_output"]


def progress_printer(args):
    """The stages' progress printer (:class:`workbench.progress.ProgressPrinter`), logging set by -v/--quiet."""
    from workbench.progress import ProgressPrinter, setup_logging

    setup_logging(-1 if args.quiet else args.verbose)
    return ProgressPrinter(quiet=args.quiet)


def line_printer(args):
    """A line printer for the commands that are not stages (deform, render, animate), through the same
    progress printer as the stages' events (``None`` with --quiet)."""
    if args.quiet:
        return None
    from workbench.stages.mechanism import Event

    printer = progress_printer(args)
    return lambda line: printer(Event(args.command, None, 0, 0, line, "message"))


def run_study_stages(args, targets, settings=None, *, force=(), scans=None):
    """Run ``targets`` (and the stages they need) on the study ``args.study``, on the Dask cluster of
    ``--workers``/``--scheduler`` when the command has them; returns ``(study, outcomes)``."""
    from workbench.scale import open_runner
    from workbench.stages.run import run_stages
    from workbench.study import read_study

    study = read_study(args.study)
    printer = progress_printer(args)
    try:
        with open_runner(getattr(args, "workers", None), getattr(args, "scheduler", None)) as runner:
            outcomes = run_stages(
                study, targets, settings=settings or {}, force=force, scans=scans, progress=printer, runner=runner
            )
    finally:
        printer.close()
    return study.reload(), outcomes


def read_output(study, stage, name, scan=None):
    """A stage's JSON output file, read."""
    from workbench.io.jsonio import read_json

    return read_json(study.output(stage, name, scan))
