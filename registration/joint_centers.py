"""Joint centres of rotation from bone motions (Kurihara & Miyata 2004, §3, Kurihara Eq. 1).

For a joint, let ``M_i`` be the child bone's motion relative to its parent in
scan ``i`` (``M_i = T_parent,i⁻¹ T_child,i``, Kurihara's ``M_{i,k}``).  The
centre of rotation ``c`` is the point that moves least::

    E(c) = Σ_i |M_i c − c|²                                   (Kurihara Eq. 1)

With ``M_i c = R_i c + t_i`` this is linear least squares,
``[R_i − I] c = −t_i`` stacked over the scans, solved here in closed form by
SVD (:func:`estimate_joint_center`).  Kurihara minimised it with
Davidon–Fletcher–Powell; a quasi-Newton minimisation (SciPy's BFGS, DFP's dual
update) is kept as a cross-check.

Near-hinge joints (knee, finger PIP/DIP) rotate about nearly one axis, so
``E`` fixes the centre only up to a line.  This is detected from the stacked
matrix's conditioning: its smallest / largest singular value below
``hinge_ratio``, or the centre's standard error along the weakest direction
(``σ̂ / s_min``, ``σ̂`` the residual's standard deviation per row) above
``hinge_sd_mm`` (a knee whose 8° of screw-home rotation sits beside 70° of
flexion has a ratio of 0.05: the ratio alone would decide by a coin flip).
The axis is reported and the centre is the point on it closest to the
``reference`` the caller passes (the bones' contact region), where the joint
physically is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

__all__ = ["JointCenterResult", "estimate_joint_center", "eq1_energy", "HINGE_SD_MM"]

HINGE_SD_MM = 1.0  # centre's standard error along the weakest direction above which a joint is a hinge


@dataclass
class JointCenterResult:
    """Centre (world mm), its fit, and whether the joint is hinge-like.

    ``rms_mm`` is ``sqrt(E(c) / n)`` over the ``n`` motions used (Kurihara's
    "square root of the mean error in Equation 1", Kurihara Eq. 1); ``per_motion_mm`` the
    individual ``|M_i c − c|``.  ``singular_values`` of the stacked
    ``[R_i − I]`` (descending) show the conditioning; ``axis`` is the weakest
    direction (the hinge axis when ``is_hinge``) and ``axis_sd_mm`` the
    standard error of the unconstrained centre along it (NaN with a single
    motion, which has no residual degrees of freedom).
    """

    center: np.ndarray
    rms_mm: float
    per_motion_mm: np.ndarray
    singular_values: np.ndarray
    is_hinge: bool
    axis: np.ndarray
    n_motions: int
    axis_sd_mm: float = float("nan")
    estimated: bool = True  # False: Kurihara Eq. 1 was not solved and the given centre was kept (see ``message``)
    iterative_center: np.ndarray | None = None
    message: str = ""


def eq1_energy(center, motions) -> float:
    """Kurihara Eq. 1: ``Σ_i |M_i c − c|²``."""
    c = np.asarray(center, float)
    return float(sum(np.sum((m[:3, :3] @ c + m[:3, 3] - c) ** 2) for m in motions))  # Kurihara Eq. 1: Σ_i ‖M_i c − c‖²


def estimate_joint_center(
    motions,
    *,
    reference=None,
    hinge_ratio: float = 0.05,
    hinge_sd_mm: float | None = HINGE_SD_MM,
    cross_check: bool = True,
) -> JointCenterResult:
    """Closed-form joint centre from relative motions (Kurihara Eq. 1), with hinge handling.

    Parameters
    ----------
    motions : sequence of 4x4
        Child-relative-to-parent motions, one per scan.  Identity motions (the
        base pose) add nothing to Kurihara Eq. 1 and are dropped from the RMS, so the
        RMS is over the moving scans only.
    reference : (3,), optional
        A point near the joint (the bones' contact region).  Required to pin
        the centre on a hinge axis; otherwise the minimum-norm solution is used.
    hinge_ratio : float
        Smallest/largest singular value below which the joint counts as a hinge.
    hinge_sd_mm : float or None
        Standard error of the centre along the weakest direction above which
        the joint counts as a hinge too (None: the ratio alone decides).
    cross_check : bool
        Also minimise Kurihara Eq. 1 with BFGS from the reference (or the origin) —
        for a hinge, on the plane through the reference perpendicular to the
        axis, the problem the closed form solves there.
    """
    ms = [np.asarray(m, float) for m in motions]
    moving = [m for m in ms if not np.allclose(m, np.eye(4), atol=1e-12)]
    if len(moving) < 1:
        raise ValueError("joint centre needs at least one scan in which the joint moves; all motions are identity")
    a = np.concatenate([m[:3, :3] - np.eye(3) for m in moving])  # Kurihara Eq. 1 as A c = b
    b = np.concatenate([-m[:3, 3] for m in moving])
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    axis = vt[-1]
    dof = a.shape[0] - 3
    c_full = vt.T @ ((u.T @ b) / s) if s[-1] > 0 else None  # Kurihara Eq. 1's minimiser, closed form (SVD)
    axis_sd = (
        float(np.linalg.norm(a @ c_full - b) / np.sqrt(dof) / s[-1]) if dof > 0 and c_full is not None else float("nan")
    )
    is_hinge = bool(s[-1] < hinge_ratio * s[0]) or (hinge_sd_mm is not None and axis_sd > hinge_sd_mm)
    if is_hinge:
        # Solve in the well-determined 2-D subspace, then slide along the axis to the reference.
        c = vt[:2].T @ ((u[:, :2].T @ b) / s[:2])
        if reference is not None:
            r = np.asarray(reference, float)
            c = c + axis * float(axis @ (r - c))
        msg = (
            f"near-hinge joint (singular-value ratio {s[-1] / s[0]:.3f}, centre sd along the axis "
            f"{axis_sd:.2f} mm): the centre is fixed only up to the axis; "
            + (
                "placed at the point of the axis closest to the reference"
                if reference is not None
                else "minimum-norm point of the axis (pass reference= to place it at the bones' contact)"
            )
        )
    else:
        c = c_full
        msg = "well-conditioned"
    per = np.array([np.linalg.norm(m[:3, :3] @ c + m[:3, 3] - c) for m in moving])  # Kurihara Eq. 1's ‖M_i c − c‖
    it = None
    if cross_check:
        x0 = np.zeros(3) if reference is None else np.asarray(reference, float)
        if is_hinge:
            # The same problem on the plane through the start point perpendicular to the axis: Kurihara Eq. 1 is nearly
            # flat along the axis, so an unconstrained descent stops anywhere along it.
            basis = vt[:2].T
            p0 = x0 if reference is not None else c
            y = minimize(
                lambda y: eq1_energy(p0 + basis @ y, moving), np.zeros(2), method="BFGS", options={"gtol": 1e-10}
            ).x
            it = p0 + basis @ y
        else:
            it = minimize(eq1_energy, x0, args=(moving,), method="BFGS", options={"gtol": 1e-10}).x
    return JointCenterResult(
        center=c,
        rms_mm=float(np.sqrt(np.mean(per**2))),
        per_motion_mm=per,
        singular_values=s,
        is_hinge=is_hinge,
        axis=axis,
        n_motions=len(moving),
        axis_sd_mm=axis_sd,
        iterative_center=it,
        message=msg,
    )
