"""Accuracy of estimated poses against ground truth (Rhee §3.1; Kurihara §3, Kurihara Eq. 1).

Per bone (:func:`compare_poses`): the rotation error, the angle of
``T_true⁻¹ T_est`` (degrees), and the translation error, the distance between
where the two transforms put the bone's template centroid (mm, independent of
the world origin).  Per scan (:func:`pose_errors`): those, and per joint the
difference of the joint angles (degrees; 6-DOF joints' last three values are
mm) and the distance between the estimated and the true centre in the scan
(mm), where both poses record them.  Per study (:func:`pose_accuracy`): the
bones' errors over the scans, and per joint the centre error (joints judged
well-conditioned by Kurihara Eq. 1) or, for a hinge (Kurihara Eq. 1 finds only
an axis), the distance from the true centre to the estimated axis line (mm) and
the angle between the estimated axis and the axis Kurihara Eq. 1 finds from the
*true* motions of the same scans (degrees): a 3-DOF joint that moves mostly in
flexion has a helical axis a few degrees off its flexion axis, and that is the
axis the data define.  :func:`format_pose_accuracy` prints the study's tables.
"""

from __future__ import annotations

import numpy as np

from deformation.kinematics.skeleton import Pose, Skeleton
from deformation.kinematics.transforms import apply, compose, invert, rotation_angle_deg
from registration.joint_centers import estimate_joint_center
from registration.pose import MOVING_DEG, PoseResult

__all__ = ["compare_poses", "pose_errors", "pose_accuracy", "format_pose_accuracy"]


def compare_poses(estimate: Pose, truth: Pose, centroids: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per-bone error of an estimated pose against the truth.

    Rotation error: the angle of ``T_true⁻¹ T_est`` (degrees).  Translation
    error: the distance between where the two transforms put the bone's
    template centroid (mm) — independent of where the world origin is.
    """
    out = {}
    for b, t_true in truth.transforms.items():
        if b not in estimate.transforms:
            continue
        t_est = estimate.transforms[b]
        c = np.asarray(centroids[b], float)
        out[b] = {
            "rotation_deg": rotation_angle_deg(compose(invert(t_true), t_est)),
            "translation_mm": float(np.linalg.norm(apply(t_est, c) - apply(t_true, c))),
        }
    return out


def pose_errors(estimate, truth, centroids: dict) -> dict:
    """Bone and joint errors of one scan's estimated :class:`~deformation.kinematics.skeleton.Pose`
    (see the module docstring)."""
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


def pose_accuracy(
    result: PoseResult, truth: dict[str, Pose], true_skeleton: Skeleton, centroids: dict[str, np.ndarray]
) -> dict:
    """Per-bone and per-joint errors of ``result`` against ``truth`` (scan id → true pose)."""
    bones = {}
    rot, tr, rot_ok, tr_ok = [], [], [], []
    for s in result.scans:
        if s.scan_id not in truth:
            continue
        e = compare_poses(s.pose, truth[s.scan_id], centroids)
        bones[s.scan_id] = e
        rot += [v["rotation_deg"] for v in e.values()]
        tr += [v["translation_mm"] for v in e.values()]
        rot_ok += [v["rotation_deg"] for b, v in e.items() if s.fits[b].ok]
        tr_ok += [v["translation_mm"] for b, v in e.items() if s.fits[b].ok]
    joints = {}
    for name, r in result.joints.items():
        tj = true_skeleton.joint(name)
        true_motions = [
            true_skeleton.relative_motion(truth[s.scan_id].transforms, name) for s in result.scans if s.scan_id in truth
        ]
        max_rot = max((rotation_angle_deg(m) for m in true_motions), default=0.0)
        c_true = np.asarray(tj.center)
        e = {
            "dof": tj.dof,
            "is_hinge": bool(r.is_hinge),
            "max_rotation_deg": float(max_rot),
            "moving": bool(max_rot >= MOVING_DEG),
            "estimated": bool(r.estimated),
            "rms_mm": float(r.rms_mm),
            "closed_form_vs_iterative_mm": (
                None if r.iterative_center is None else float(np.linalg.norm(r.iterative_center - r.center))
            ),
        }
        if r.is_hinge:
            d = c_true - r.center
            e["center_to_axis_mm"] = float(np.linalg.norm(d - r.axis * (r.axis @ d)))
            try:
                ref = estimate_joint_center(true_motions, cross_check=False).axis
                e["axis_error_deg"] = float(np.degrees(np.arccos(min(1.0, abs(float(ref @ r.axis))))))
            except ValueError:
                e["axis_error_deg"] = None
        else:
            e["center_error_mm"] = float(np.linalg.norm(r.center - c_true))
        joints[name] = e

    def stats(v):
        v = np.asarray(v, float)
        return {
            "n": int(v.size),
            "median": float(np.median(v)) if v.size else None,
            "max": float(v.max()) if v.size else None,
        }

    centre_ok = [
        e["center_error_mm"]
        for e in joints.values()
        if "center_error_mm" in e and e["dof"] in (2, 3) and e["moving"] and e["estimated"]
    ]  # a centre kept from the input skeleton is not an estimate
    return {
        "bones": bones,
        "joints": joints,
        "summary": {
            "rotation_deg": stats(rot),
            "translation_mm": stats(tr),
            # The same over the bones not flagged (flagged ones are reported, not accepted).
            "rotation_deg_unflagged": stats(rot_ok),
            "translation_mm_unflagged": stats(tr_ok),
            "center_error_mm_2_3_dof_moving": stats(centre_ok),
            "center_error_mm_all": stats([e["center_error_mm"] for e in joints.values() if "center_error_mm" in e]),
            "hinge_center_to_axis_mm": stats([e["center_to_axis_mm"] for e in joints.values() if e["is_hinge"]]),
            "hinge_axis_error_deg": stats(
                [e["axis_error_deg"] for e in joints.values() if e["is_hinge"] and e.get("axis_error_deg") is not None]
            ),
        },
    }


def _f(v, fmt="{:.2f}"):
    return "—" if v is None else fmt.format(v)


def format_pose_accuracy(acc: dict) -> str:
    """Tables: per-bone errors (worst scan) and per-joint errors."""
    lines = []
    per_bone = {}
    for e in acc["bones"].values():
        for b, v in e.items():
            w = per_bone.setdefault(b, {"rot": [], "tr": []})
            w["rot"].append(v["rotation_deg"])
            w["tr"].append(v["translation_mm"])
    lines.append(f"{'bone':<20}{'rot median °':>13}{'rot max °':>11}{'trans median mm':>17}{'trans max mm':>14}")
    for b, w in per_bone.items():
        lines.append(
            f"{b:<20}{np.median(w['rot']):>13.2f}{max(w['rot']):>11.2f}{np.median(w['tr']):>17.2f}{max(w['tr']):>14.2f}"
        )
    s = acc["summary"]
    lines.append(
        f"{'all bones':<20}{_f(s['rotation_deg']['median']):>13}{_f(s['rotation_deg']['max']):>11}"
        f"{_f(s['translation_mm']['median']):>17}{_f(s['translation_mm']['max']):>14}"
    )
    u, t = s["rotation_deg_unflagged"], s["translation_mm_unflagged"]
    if u["n"] != s["rotation_deg"]["n"]:
        lines.append(
            f"{'unflagged bones':<20}{_f(u['median']):>13}{_f(u['max']):>11}{_f(t['median']):>17}"
            f"{_f(t['max']):>14}   ({s['rotation_deg']['n'] - u['n']} flagged bone fits left out)"
        )
    lines.append("")
    lines.append(
        f"{'joint':<18}{'dof':>4}{'moves °':>9}{'hinge':>7}{'centre err mm':>15}{'true c→axis mm':>16}"
        f"{'axis err °':>12}{'Kurihara Eq. 1 rms mm':>23}{'|cf−it| mm':>12}"
    )
    for j, e in acc["joints"].items():
        hinge = "kept" if not e["estimated"] else "yes" if e["is_hinge"] else "no"
        lines.append(
            f"{j:<18}{e['dof']:>4}{e['max_rotation_deg']:>9.1f}{hinge:>7}"
            f"{_f(e.get('center_error_mm')):>15}{_f(e.get('center_to_axis_mm')):>16}"
            f"{_f(e.get('axis_error_deg')):>12}{e['rms_mm']:>23.2f}"
            f"{_f(e['closed_form_vs_iterative_mm'], '{:.1e}'):>12}"
        )
    c = s["center_error_mm_2_3_dof_moving"]
    lines.append(
        f"centre error, 2-3 DOF joints moving ≥ {MOVING_DEG:.0f}° (n={c['n']}): median {_f(c['median'])} mm, "
        f"max {_f(c['max'])} mm"
        + (
            ""
            if all(e["estimated"] for e in acc["joints"].values())
            else f"  ('kept': estimated motion < {MOVING_DEG:.0f}°, the skeleton's centre was kept, not counted)"
        )
    )
    h = s["hinge_center_to_axis_mm"]
    a = s["hinge_axis_error_deg"]
    lines.append(
        f"hinge joints (n={h['n']}): true centre to axis median {_f(h['median'])} mm, max {_f(h['max'])} mm; "
        f"axis error median {_f(a['median'])}°, max {_f(a['max'])}°"
    )
    return "\n".join(lines)
