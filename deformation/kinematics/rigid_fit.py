"""Least-squares rigid fit between corresponding point sets (Kabsch [1]_, Umeyama [2]_).

Convention: a transform is a 4x4 homogeneous matrix mapping
template world → scan world.  :func:`fit_rigid` returns the ``T`` for which
``T @ [source, 1] ≈ [target, 1]``: ``source`` plays the template,
``target`` the scan.

References
----------
.. [1] W. Kabsch, "A solution for the best rotation to relate two sets of
   vectors", Acta Crystallographica A32 (1976) 922-923.
   doi:10.1107/S0567739476001873
.. [2] S. Umeyama, "Least-squares estimation of transformation parameters
   between two point patterns", IEEE TPAMI 13(4) (1991) 376-380.
   doi:10.1109/34.88573
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_rigid", "rigid_residuals"]


def _points(a, name: str) -> np.ndarray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite")
    return p


def fit_rigid(source_points, target_points, *, weights=None) -> np.ndarray:
    """Rotation and translation minimising ``Σ w_i |R s_i + t − d_i|²``.

    Parameters
    ----------
    source_points : (n, 3) array_like
        Points in the source (template) frame, mm.
    target_points : (n, 3) array_like
        Corresponding points in the target (scan) frame, mm.
    weights : (n,) array_like, optional
        Non-negative weight per correspondence; uniform by default.

    Returns
    -------
    (4, 4) ndarray
        ``T = [[R, t], [0, 1]]`` with ``R`` a proper rotation (det +1) and
        ``T @ [s, 1] ≈ [d, 1]``.

    Raises
    ------
    ValueError
        Shapes differ, fewer than 3 points, negative or all-zero weights, or
        the points are collinear (the rotation about their line is then
        undetermined); no NaNs are returned.

    Notes
    -----
    SVD of the weighted cross-covariance ``H = Σ w (s − s̄)(d − d̄)ᵀ = U S Vᵀ``
    gives ``R = V diag(1, 1, sign det(V Uᵀ)) Uᵀ``; the sign term keeps ``R`` a
    rotation when the best orthogonal fit would be a reflection (Umeyama 1991, Eq. 39–40).
    """
    src = _points(source_points, "source_points")
    dst = _points(target_points, "target_points")
    if src.shape != dst.shape:
        raise ValueError(f"source and target point sets differ in shape: {src.shape} vs {dst.shape}")
    n = src.shape[0]
    if n < 3:
        raise ValueError(f"a rigid fit needs at least 3 point pairs, got {n}")
    if weights is None:
        w = np.full(n, 1.0 / n)
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape != (n,) or np.any(w < 0) or not np.all(np.isfinite(w)) or w.sum() <= 0:
            raise ValueError("weights must be n finite non-negative numbers with a positive sum")
        w = w / w.sum()
    src_mean = w @ src
    dst_mean = w @ dst
    s = src - src_mean
    d = dst - dst_mean
    h = (s * w[:, None]).T @ d
    u, sv, vt = np.linalg.svd(h)
    # Rank check: with collinear (or coincident) points the second singular
    # value vanishes and the rotation is not unique.
    scale = max(sv[0], np.finfo(float).tiny)
    if sv[1] <= 1e-12 * scale:
        raise ValueError(
            "the points are collinear or coincident: the rotation about their line is "
            "undetermined; use at least 3 non-collinear points"
        )
    v = vt.T
    sign = np.sign(np.linalg.det(v @ u.T)) or 1.0  # reflection guard, Umeyama Eq. (39)
    r = v @ np.diag([1.0, 1.0, sign]) @ u.T
    t = dst_mean - r @ src_mean
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = t
    return out


def rigid_residuals(transform, source_points, target_points) -> np.ndarray:
    """Distance (mm) between each transformed source point and its target.

    Parameters
    ----------
    transform : (4, 4) array_like
        Homogeneous transform source → target.
    source_points, target_points : (n, 3) array_like
        Corresponding points.

    Returns
    -------
    (n,) ndarray
        ``|T s_i − d_i|``.
    """
    T = np.asarray(transform, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"transform must be 4x4, got {T.shape}")
    src = _points(source_points, "source_points")
    dst = _points(target_points, "target_points")
    moved = src @ T[:3, :3].T + T[:3, 3]
    return np.linalg.norm(moved - dst, axis=1)
