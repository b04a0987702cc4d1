"""Fields: dense displacement fields, sampling volumes at world points, resampling a deformed volume, splines.

* :mod:`~deformation.fields.displacement` — positions, composition, inversion, Jacobians, folds;
* :mod:`~deformation.fields.interpolate` — compiled trilinear / nearest sampling and warping;
* :mod:`~deformation.fields.resample` — the backward map of a forward-deformed volume;
* :mod:`~deformation.fields.splines` — the clamped plate spline and Kurihara's RBF (Rhee §4, Kurihara Eq. 4–5).
"""
