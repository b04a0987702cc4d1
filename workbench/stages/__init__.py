"""The pipeline's stages, each a small module on one mechanism (:mod:`workbench.stages.mechanism`).

In order: ``bones`` → ``pose`` → ``weights`` → ``init`` (per scan) →
``register`` (per scan) → ``model`` → ``surface`` → ``validate`` (per scan, with truth) → ``report``.
:func:`workbench.stages.run.run_stages` orders and runs them.
"""

from workbench.stages import bones, init, model, pose, register, report, surface, validate, weights

STAGES = {m.STAGE.name: m.STAGE for m in (bones, pose, weights, init, register, model, surface, validate, report)}
ORDER = tuple(STAGES)

__all__ = ["STAGES", "ORDER"]
