"""Accuracy of an estimated pose against ground truth (Rhee §3.1; Kurihara §3, Eq. 1).

Per bone: the rotation error, the angle of ``T_true⁻¹ T_est`` (degrees), and
the translation error, the distance between where the two transforms put the
bone's template centroid (mm; :func:`registration.pose.compare_poses`).  Per
joint: the difference of the joint angles (degrees; 6-DOF joints' last three
values are mm) and the distance between the estimated and the true centre in
the scan (mm), where both poses record them.
"""

from __future__ import annotations

import numpy as np

from registration.pose import compare_poses

__all__ = ["pose_errors"]


def pose_errors(estimate, truth, centroids: dict) -> dict:
    """Bone and joint errors of one scan's estimated :class:`~deformation.skeleton.Pose` (see the module docstring)."""
    bones = compare_poses(estimate, truth, centroids)
    joints = {}
    for name, a_true in (truth.joint_angles or {}).items():
        e = {}
        a_est = (estimate.joint_angles or {}).get(name)
        if a_est is not None:
            d = np.asarray(a_est, float) - np.asarray(a_true, float)
            d[:3] = (d[:3] + 180.0) % 360.0 - 180.0  # angles wrap; a 6-DOF joint's last three values are mm
            e["angle_error_deg"] = np.abs(d).tolist()
        c_true = (truth.joint_centers or {}).get(name)
        c_est = (estimate.joint_centers or {}).get(name)
        if c_true is not None and c_est is not None:
            e["center_error_mm"] = float(np.linalg.norm(np.asarray(c_est, float) - np.asarray(c_true, float)))
        joints[name] = e
    rot = [v["rotation_deg"] for v in bones.values()]
    tr = [v["translation_mm"] for v in bones.values()]
    return {
        "bones": bones,
        "joints": joints,
        "mean_rotation_deg": float(np.mean(rot)) if rot else None,
        "max_rotation_deg": float(np.max(rot)) if rot else None,
        "mean_translation_mm": float(np.mean(tr)) if tr else None,
        "max_translation_mm": float(np.max(tr)) if tr else None,
    }
