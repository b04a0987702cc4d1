"""The pose stage's report of its fits (registration.report.format_fits) on constructed fits."""

from __future__ import annotations

import math

import numpy as np

from registration.joint_centers import JointCenterResult
from registration.pose import PoseResult, ScanPose
from registration.report import format_fits
from registration.rigid import BoneFit


def _fit(bone, status="ok", ncc=0.95):
    return BoneFit(bone, np.eye(4), "intensity", status, ssd_before=2.0, ssd_after=1.0, ncc=ncc, inside_fraction=1.0)


def _joint(per_motion_mm):
    r = np.asarray(per_motion_mm, float)
    return JointCenterResult(
        center=np.zeros(3),
        rms_mm=float(np.sqrt(np.mean(r**2))),
        per_motion_mm=r,
        singular_values=np.ones(3),
        is_hinge=False,
        axis=np.array([0.0, 0.0, 1.0]),
        n_motions=len(r),
    )


def _result(joints) -> PoseResult:
    # the pose and skeleton are not part of the report
    scans = [
        ScanPose("pose00", None, {b: _fit(b) for b in ("femur", "tibia", "patella")}, seconds=12.34),
        ScanPose(
            "pose01",
            None,
            {
                "femur": _fit("femur"),
                "tibia": _fit("tibia", "poor_match", 0.4321),
                "patella": _fit("patella", "outside_field_of_view", 0.0),
            },
            seconds=7.06,
        ),
    ]
    return PoseResult("intensity", scans, joints, skeleton=None)


def test_one_line_per_scan_with_the_bones_ok_and_each_problem():
    lines = format_fits(_result({"knee": _joint([1.0, 1.0])})).splitlines()
    assert lines[0] == "scan        bones ok  problems"
    assert lines[1] == "pose00         3/3    —"
    assert lines[2] == "pose01         1/3    tibia: poor_match (ncc 0.43); patella: outside_field_of_view (ncc 0.00)"
    assert len(lines) == 4


def test_the_residual_is_the_rms_over_all_joints_and_motions():
    # joints with 2 and 1 motions: RMS of (3, 4) and (12) is sqrt((9 + 16 + 144) / 3) = sqrt(169 / 3) = 7.5056 mm
    text = format_fits(_result({"knee": _joint([3.0, 4.0]), "ankle": _joint([12.0])}))
    assert math.isclose(math.sqrt(169 / 3), 7.50555, rel_tol=1e-5)
    assert text.splitlines()[-1] == (
        "Kurihara Eq. 1 residual over all joints and scans (RMS): 7.51 mm (Kurihara reports 0.91 mm; the template "
        "is the base pose and is not a scan, so it is not counted)"
    )


def test_no_joint_residual_is_nan():
    assert "(RMS): nan mm" in format_fits(_result({}))


def test_seconds_add_a_column_only_when_asked():
    lines = format_fits(_result({"knee": _joint([1.0])}), seconds=True).splitlines()
    assert lines[0] == "scan        seconds  bones ok  problems"
    assert lines[1] == "pose00         12.3     3/3    —"
    assert lines[2].startswith("pose01          7.1     1/3    tibia: poor_match")
    assert "seconds" not in format_fits(_result({"knee": _joint([1.0])}))
