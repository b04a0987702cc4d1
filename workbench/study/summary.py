"""The summary of a study folder that ``workbench info`` and ``workbench phantom`` print."""

from __future__ import annotations

import numpy as np

from workbench.io.jsonio import read_json
from workbench.io.volumes import read_image_geometry

__all__ = ["summarize", "recorded_times"]


def summarize(study, stage_order=()) -> str:
    """A human-readable summary of a study folder (``workbench info``): the template's grid, the skeleton, the
    bones' sizes, each scan's flexion and, for a phantom, its generation statistics, and the stages' recorded
    times (``stage_order`` first: ``workbench.stages.ORDER``)."""
    m = study.manifest
    sk = study.skeleton()
    g = read_image_geometry(study.path(m["template"]))
    lines = [
        f"study: {study.root}  ({m.get('name', '')})",
        f"template: {m['template']}  size {g.size} voxels, spacing "
        f"{tuple(round(s, 4) for s in g.spacing)} mm, extent {tuple(round(e, 1) for e in g.extent_mm)} mm",
        f"skeleton: {sk.name}, {len(sk.bones)} bones, {len(sk.joints)} joints, {sk.n_dof} DOF "
        f"(6-DOF joints: {', '.join(j.name for j in sk.joints if j.dof == 6) or 'none'})",
    ]
    drawn = (m.get("phantom") or {}).get("acquisition_drawn")
    if isinstance(drawn, dict):  # a random-acquisition phantom: what it drew
        from validation.phantoms.generate import describe_acquisition

        lines.append(describe_acquisition(drawn))
    vox_ml = float(np.prod(g.spacing)) / 1000.0
    if study.has_template_labels:
        labels = study.template_labels().data
        counts = np.bincount(labels.ravel(), minlength=max(b.label for b in sk.bones) + 1)
        lines.append(
            "bones (label: voxels, ml): "
            + ", ".join(f"{b.name} ({b.label}: {counts[b.label]}, {counts[b.label] * vox_ml:.1f})" for b in sk.bones)
        )
    else:
        lines.append("bones: no label map yet (segment them with `workbench pose STUDY --seeds FILE`)")
    log_path = study.root / "logs" / "phantom.json"
    stats = {s["id"]: s for s in read_json(log_path)["scans"]} if log_path.exists() else {}
    lines.append(f"scans: {len(m['scans'])}")
    header = f"  {'id':<10}{'joint angles (deg)':<44}{'max |u| body':>13}{'folded':>9}{'inv. resid.':>12}{'markers':>8}"
    lines.append(header)
    poses = {s["id"]: study.truth_pose(s["id"]) for s in m["scans"] if "truth" in s}
    # Show the three joints that flex most over the study (first angle = flexion).
    span = {
        j.name: max(
            (abs(p.joint_angles[j.name][0]) for p in poses.values() if p.joint_angles and j.name in p.joint_angles),
            default=0.0,
        )
        for j in sk.joints
    }
    shown = [j for j in sorted(span, key=span.get, reverse=True)[:3] if span[j] > 0]
    shown.sort(key=[j.name for j in sk.joints].index)
    for s in m["scans"]:
        sid = s["id"]
        angles = ""
        nm = 0
        if sid in poses:
            ja = poses[sid].joint_angles or {}
            angles = " ".join(f"{j}={ja[j][0]:.0f}" if j in ja else f"{j}=?" for j in shown)
            nm = len(study.truth_markers(sid))
        st = stats.get(sid, {})
        lines.append(
            f"  {sid:<10}{angles[:43]:<44}{st.get('max_displacement_mm', float('nan')):>10.1f} mm"
            f"{100 * st.get('folded_fraction_body', float('nan')):>8.2f}%"
            f"{st.get('inverse_residual_body_p99_mm', float('nan')):>9.1e} mm{nm:>8}"
        )
    if stats:
        lines.append(
            "  (max |u|: largest correspondence displacement inside the body; folded: body voxels whose "
            "correspondence has Jacobian determinant ≤ 0; inv. resid.: 99th percentile of |F(φ(x)) − x| "
            "in the body)"
        )
    times = recorded_times(study, stage_order)  # study.json's: the stages' files hold no time
    if times:
        lines.append("stages run (wall-clock seconds, from study.json):")
        lines += times
    return "\n".join(lines)


def recorded_times(study, order=()) -> list[str]:
    """One line per stage recorded in ``study.json`` (``order`` first): its wall-clock seconds (summed over its
    scans) and those of the steps it recorded in ``timings`` — the times no stage writes into its files."""
    stages = study.manifest.get("stages") or {}
    lines = []
    for name in [n for n in order if n in stages] + [n for n in stages if n not in order]:
        e = stages[name]
        units = [
            u
            for u in ((e.get("scans") or {}).values() if "scans" in e else [e])
            if isinstance(u, dict) and "seconds" in u
        ]
        if not units:
            continue
        steps: dict = {}
        per_scan: dict = {}
        for u in units:
            for k, v in (u.get("timings") or {}).items():
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    steps[k] = steps.get(k, 0.0) + v
                elif k == "scans" and isinstance(v, dict):  # a whole-study stage's per-scan work (pose)
                    per_scan.update({s: t["seconds"] for s, t in v.items() if isinstance(t, dict) and "seconds" in t})
        text = f"  {name:<10}{sum(u['seconds'] for u in units):>9.1f} s"
        if "scans" in e:
            text += f"  ({len(units)} scan{'s' if len(units) != 1 else ''})"
        if steps:
            text += "  " + ", ".join(f"{k} {v:.1f} s" for k, v in steps.items())
        if per_scan:
            text += "; per scan: " + ", ".join(f"{s} {v:.1f} s" for s, v in per_scan.items())
        lines.append(text)
    return lines
