"""Accuracy of estimated poses and joint centres against ground truth, as numbers and as tables.

Definitions (used in the README, the CLI report and the closing notes):

* **bone rotation error** — the angle of ``T_true⁻¹ T_est`` (degrees);
* **bone translation error** — the distance between where the two transforms
  put the bone's template centroid (mm), independent of the world origin;
* **joint centre error** (joints judged well-conditioned by Eq. 1) — distance
  between the estimated centre and the skeleton's true centre (mm);
* **hinge joints** (Eq. 1 finds only an axis) — the distance from the true
  centre to the estimated axis line (mm) and the angle between the estimated
  axis and the axis that Eq. 1 finds from the *true* motions of the same scans
  (degrees): a 3-DOF joint that moves mostly in flexion has a helical axis a
  few degrees off its flexion axis, and that is the axis the data define.
"""

from __future__ import annotations

import numpy as np

from deformation.skeleton import Pose, Skeleton
from deformation.transforms import rotation_angle_deg

from .joint_centers import estimate_joint_center
from .pose import MOVING_DEG, PoseResult, compare_poses

__all__ = ["accuracy", "format_accuracy", "format_fits", "MOVING_DEG"]


def accuracy(
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


def format_accuracy(acc: dict) -> str:
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
        f"{'axis err °':>12}{'Eq.1 rms mm':>13}{'|cf−it| mm':>12}"
    )
    for j, e in acc["joints"].items():
        hinge = "kept" if not e["estimated"] else "yes" if e["is_hinge"] else "no"
        lines.append(
            f"{j:<18}{e['dof']:>4}{e['max_rotation_deg']:>9.1f}{hinge:>7}"
            f"{_f(e.get('center_error_mm')):>15}{_f(e.get('center_to_axis_mm')):>16}"
            f"{_f(e.get('axis_error_deg')):>12}{e['rms_mm']:>13.2f}"
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


def format_fits(result: PoseResult, *, seconds: bool = False) -> str:
    """Per scan: bones not ``ok`` (with reason and metric), joint-centre residuals; the time of each scan's fits
    too with ``seconds`` (not in the pose stage's report.txt: the same inputs give the same bytes there)."""
    lines = [f"{'scan':<10}{'  seconds' if seconds else ''}{'bones ok':>10}  problems"]
    for s in result.scans:
        n_ok = sum(f.ok for f in s.fits.values())
        probs = "; ".join(f"{f.bone}: {f.status} (ncc {f.ncc:.2f})" for f in s.failures) or "—"
        time = f"{s.seconds:>9.1f}" if seconds else ""
        lines.append(f"{s.scan_id:<10}{time}{n_ok:>6}/{len(s.fits):<3}  {probs}")
    lines.append(
        f"Eq. 1 residual over all joints and scans (RMS): {result.overall_rms_mm():.2f} mm "
        "(Kurihara reports 0.91 mm; the template is the base pose and is not a scan, so it is not counted)"
    )
    return "\n".join(lines)
