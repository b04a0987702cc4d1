"""Rigid transforms as 4x4 homogeneous matrices in world millimetres.

Convention: a transform maps *template* world points to *scan* world points,
``p_scan = T @ [p_template, 1]``.  Composition follows matrix products:
``compose(A, B)`` applies ``B`` first, then ``A`` (``A @ B``).

Rotation angles are in degrees at every public boundary (files, CLI) and
radians nowhere outside this module's internals.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

__all__ = [
    "identity",
    "from_rotation_translation",
    "rotation_about_point",
    "axis_angle_matrix",
    "compose",
    "invert",
    "apply",
    "interpolate",
    "is_rigid",
    "rotation_angle_deg",
    "check_rigid",
]


def identity() -> np.ndarray:
    return np.eye(4)


def check_rigid(t, *, name: str = "transform", atol: float = 1e-6) -> np.ndarray:
    """Validate a 4x4 rigid transform and return it as a float64 array."""
    t = np.asarray(t, dtype=float)
    if t.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} contains NaN or inf:\n{t}")
    if not is_rigid(t, atol=atol):
        raise ValueError(f"{name} is not rigid (rotation part must be orthonormal with det +1, last row 0 0 0 1):\n{t}")
    return t


def is_rigid(t, *, atol: float = 1e-6) -> bool:
    t = np.asarray(t, dtype=float)
    # Shape first (slicing a wrong shape would raise), and finiteness of all 16
    # entries: the rotation tests below never look at the translation column.
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        return False
    r = t[:3, :3]
    return bool(
        np.allclose(t[3], [0, 0, 0, 1], atol=atol)
        and np.allclose(r.T @ r, np.eye(3), atol=atol)
        and np.linalg.det(r) > 0
    )


def from_rotation_translation(rotation, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = np.asarray(rotation, dtype=float)
    t[:3, 3] = np.asarray(translation, dtype=float)
    return t


def axis_angle_matrix(axis, angle_deg: float) -> np.ndarray:
    """3x3 rotation by ``angle_deg`` degrees about unit vector ``axis`` (right-hand rule)."""
    axis = np.asarray(axis, dtype=float)
    n = np.linalg.norm(axis)
    if n == 0:
        raise ValueError("rotation axis must be non-zero")
    return Rotation.from_rotvec(axis / n * np.deg2rad(angle_deg)).as_matrix()


def rotation_about_point(rotation, center) -> np.ndarray:
    """4x4 transform rotating by the 3x3 ``rotation`` about the world point ``center``.

    ``p' = R (p - c) + c``: the centre is the fixed point.
    """
    r = np.asarray(rotation, dtype=float)
    c = np.asarray(center, dtype=float)
    return from_rotation_translation(r, c - r @ c)


def compose(*transforms) -> np.ndarray:
    """``compose(A, B, C) = A @ B @ C``: C is applied first."""
    out = np.eye(4)
    for t in transforms:
        out = out @ np.asarray(t, dtype=float)
    return out


def invert(t) -> np.ndarray:
    """Exact inverse of a rigid transform (``R^T``, ``-R^T t``), not a general matrix inverse."""
    t = np.asarray(t, dtype=float)
    r = t[:3, :3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ t[:3, 3]
    return out


def apply(t, points) -> np.ndarray:
    """Apply a 4x4 transform to points ``(..., 3)``."""
    t = np.asarray(t, dtype=float)
    p = np.asarray(points, dtype=float)
    return p @ t[:3, :3].T + t[:3, 3]


def interpolate(t0, t1, alpha: float, *, center=None) -> np.ndarray:
    """Interpolate between two rigid transforms.

    The rotation is interpolated along the geodesic (slerp); the translation
    is interpolated linearly *for the point* ``center`` (default: the world
    origin), so that a joint centre moves on a straight line while the bone
    turns about it.  ``alpha = 0`` gives ``t0``, ``alpha = 1`` gives ``t1``.
    """
    t0 = check_rigid(t0, name="t0")
    t1 = check_rigid(t1, name="t1")
    # The keyframes themselves are returned bit for bit: a matrix → quaternion
    # → matrix round trip through Slerp would move them by ~1e-14 mm.
    if alpha == 0:
        return t0.copy()
    if alpha == 1:
        return t1.copy()
    c = np.zeros(3) if center is None else np.asarray(center, dtype=float)
    rots = Rotation.from_matrix(np.stack([t0[:3, :3], t1[:3, :3]]))
    r = Slerp([0.0, 1.0], rots)([alpha]).as_matrix()[0]
    c0 = apply(t0, c)
    c1 = apply(t1, c)
    ca = (1 - alpha) * c0 + alpha * c1
    return from_rotation_translation(r, ca - r @ c)


def rotation_angle_deg(t) -> float:
    """Rotation angle of the transform's rotation part, in degrees (0..180)."""
    r = np.asarray(t, dtype=float)[:3, :3]
    cos = np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)
    return float(np.rad2deg(np.arccos(cos)))
