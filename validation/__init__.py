"""Ground truth: phantoms, error measures, leave one out, and the papers' protocols as tables."""

import deformation  # noqa: F401  (numba's threading layer: deformation/__init__.py)
