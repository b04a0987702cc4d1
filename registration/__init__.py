"""From images to transforms and fields: bone segmentation and rigid registration, joint centres, similarity
measures, the dense registration, Rhee's Algorithm 1, the B-spline baselines, surface fitting."""

import deformation  # noqa: F401  (numba's threading layer: deformation/__init__.py)
