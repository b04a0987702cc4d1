"""Unit dual quaternions for blending rigid transforms (dual quaternion skinning).

Kavan, Collins, Žára & O'Sullivan, "Geometric skinning with approximate dual
quaternion blending", ACM TOG 27(4), 2008, doi:10.1145/1409625.1409627.
Blending unit dual quaternions instead of matrices keeps every blended
transform rigid, so soft tissue between two bones turns about the joint
instead of collapsing towards it as linear blending does.  Used by the
phantoms' ``soft`` posing (a deformation that is deliberately *not* VBD).

Quaternions are stored ``(w, x, y, z)``; a dual quaternion is 8 numbers,
real part then dual part.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["from_transforms", "blend_apply", "quat_multiply"]


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions ``(..., 4)`` in ``(w, x, y, z)`` order."""
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def from_transforms(transforms: np.ndarray) -> np.ndarray:
    """Rigid 4x4 transforms ``(k, 4, 4)`` → unit dual quaternions ``(k, 8)``."""
    t = np.asarray(transforms, float)
    xyzw = Rotation.from_matrix(t[:, :3, :3]).as_quat()
    qr = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    tq = np.concatenate([np.zeros((len(t), 1)), t[:, :3, 3]], axis=1)
    return np.concatenate([qr, 0.5 * quat_multiply(tq, qr)], axis=1)


def blend_apply(weights: np.ndarray, dual_quats: np.ndarray, points: np.ndarray):
    """Apply the per-point blended rigid transform ``DLB(w; q)`` to ``points``.

    Parameters
    ----------
    weights : (n, k) rows summing to one
    dual_quats : (k, 8) from :func:`from_transforms`
    points : (n, 3)

    Returns
    -------
    moved : (n, 3)
    rotations : (n, 3, 3) the blended rotation of each point
    """
    # Antipodality: align every quaternion with the point's dominant one.
    sign = np.sign(dual_quats[:, :4] @ dual_quats[:, :4].T)
    sign[sign == 0] = 1.0
    pivot = np.argmax(weights, axis=1)
    b = (weights * sign[pivot]) @ dual_quats
    norm = np.linalg.norm(b[:, :4], axis=1, keepdims=True)
    qr, qd = b[:, :4] / norm, b[:, 4:] / norm
    t = 2.0 * quat_multiply(qd, qr * np.array([1.0, -1.0, -1.0, -1.0]))[:, 1:]
    w, x, y, z = qr.T
    r = np.empty((len(qr), 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - z * w)
    r[:, 0, 2] = 2 * (x * z + y * w)
    r[:, 1, 0] = 2 * (x * y + z * w)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - x * w)
    r[:, 2, 0] = 2 * (x * z - y * w)
    r[:, 2, 1] = 2 * (y * z + x * w)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return np.einsum("nij,nj->ni", r, points) + t, r
