"""The pose stage's report of its fits: per scan, the bones not ``ok`` and the joint-centre residual.

Nothing here needs the truth: the accuracy of poses against ground truth is
:mod:`validation.pose_measures`.  The residual is that of Kurihara Eq. 1, the
joint centre's least-squares fit over the scans
(:func:`registration.joint_centers.estimate_joint_center`).
"""

from __future__ import annotations

from .pose import PoseResult

__all__ = ["format_fits"]


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
        f"Kurihara Eq. 1 residual over all joints and scans (RMS): {result.overall_rms_mm():.2f} mm "
        "(Kurihara reports 0.91 mm; the template is the base pose and is not a scan, so it is not counted)"
    )
    return "\n".join(lines)
