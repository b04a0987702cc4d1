"""Point-to-plane ICP recovers real wrist-bone motion from a perturbed start (Kurihara §3)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.kinematics.transforms import compose, from_rotation_translation, invert, rotation_angle_deg
from registration.icp import icp_point_to_plane


@pytest.fixture(scope="module")
def wrist():
    from workbench.io.wrist_bones import find_wrist_data, load_wrist_study

    if find_wrist_data() is None:
        pytest.skip("../shared/data/wrist-bones-mri is absent")
    return load_wrist_study(1)


def test_icp_recovers_true_bone_motion(wrist):
    from workbench.io.wrist_bones import true_motion

    rng = np.random.default_rng(0)
    base = wrist.poses[0]
    errors = []
    for bone, pose in [(b, p) for b in wrist.bones for p in wrist.poses[1:]]:  # every bone, both motions
        truth = true_motion(wrist, bone, base, pose).transform
        src = bone.positions[base]
        # Target: a different sampling of the posed surface (every other vertex, jittered by
        # 0.05 mm), so ICP cannot match vertex to vertex.
        tgt = bone.positions[pose][::2] + rng.normal(0, 0.05, size=bone.positions[pose][::2].shape)
        # Start 5° and 3 mm off the truth about the bone's centroid.
        c = src.mean(axis=0)
        off = from_rotation_translation(
            Rotation.from_rotvec(np.deg2rad(5) * rng.normal(size=3) / np.sqrt(3)).as_matrix()
        )
        off[:3, 3] = c - off[:3, :3] @ c + rng.normal(0, 3 / np.sqrt(3), size=3)
        r = icp_point_to_plane(src, tgt, init=compose(truth, off))
        assert r.converged, r.message
        err = compose(invert(truth), r.transform)
        moved = np.linalg.norm((src @ err[:3, :3].T + err[:3, 3]) - src, axis=1)
        errors.append((rotation_angle_deg(err), moved.max()))
    # Half sampling and 0.05 mm jitter of the target limit the fit (measured: ≤ 0.13°, ≤ 0.02 mm over the
    # ten bones and two motions).  The issue asks ≤ 0.5° and ≤ 0.3 mm; we hold ICP to 0.2° and 0.05 mm
    # anywhere on the bone, from a 5° / 3 mm start.
    assert len(errors) == 2 * len(wrist.bones) == 20
    for angle, dist in errors:
        assert angle < 0.2 and dist < 0.05, errors


def test_icp_flags_a_hopeless_start(wrist):
    bone = wrist.bones[0]
    src = bone.positions[wrist.poses[0]]
    far = np.eye(4)
    far[:3, 3] = (80.0, 0.0, 0.0)  # 8 cm away: no correspondences within 8 mm
    r = icp_point_to_plane(src, src, init=far)
    assert not r.converged and "initialisation" in r.message


def test_icp_input_errors():
    with pytest.raises(ValueError, match="source_points"):
        icp_point_to_plane(np.zeros((3, 3)), np.zeros((20, 3)))
