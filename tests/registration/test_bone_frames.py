"""Rhee §3.1 bone frames (OBB from principal axes, origin at the base) on phantom label maps."""

from __future__ import annotations

import numpy as np
import pytest

from deformation.geometry import GridGeometry, Volume
from deformation.kinematics.skeleton import Bone, Joint, Skeleton
from registration.bone_frames import bone_frames


def test_box_of_a_known_block_with_anisotropic_rotated_grid():
    """A 20x4x3-voxel block of label 2 under a rotated, anisotropic grid: exact OBB."""
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    g = GridGeometry((30, 12, 10), (0.5, 1.5, 2.0), (10.0, -5.0, 3.0), rot.ravel())
    data = np.zeros(g.array_shape, np.uint8)
    data[2:5, 3:7, 4:24] = 2  # k 2..4, j 3..6, i 4..23
    data[2:5, 3:7, 1:3] = 1  # the parent, at lower i
    sk = Skeleton([Bone("a", 1), Bone("b", 2, "a")], [Joint("j", "a", "b", 3, (0.0, 0.0, 0.0))])
    f = bone_frames(Volume(data, g), sk)["b"]
    # Longest extent: 20 voxels × 0.5 mm along i, whose world direction is rot[:, 0] = +y.
    np.testing.assert_allclose(np.sort(2 * f.half_extents), np.sort([20 * 0.5, 4 * 1.5, 3 * 2.0]), atol=1e-9)
    z = f.axes[:, 2]
    np.testing.assert_allclose(abs(z @ rot[:, 0]), 1.0, atol=1e-9)
    assert z @ rot[:, 0] > 0  # from the parent (lower i) into the bone
    # Base centre: at the block's low-i face, i = 3.5, centred in j and k.
    np.testing.assert_allclose(f.frame[:3, 3], g.index_to_world([3.5, 4.5, 3.0]), atol=1e-9)
    assert np.isclose(np.linalg.det(f.axes), 1.0)


def test_phantom_knee_frames_follow_the_bones(phantom):
    ph = phantom("knee", size="test", noise=False, n_poses=1)
    _, labels = ph.template()
    frames = bone_frames(labels, ph.skeleton)
    # Tibia: long axis along -y (distal), base at its proximal (plateau) end, near y ≈ -5 mm.
    t = frames["tibia"]
    assert t.axes[:, 2] @ np.array([0.0, -1.0, 0.0]) > 0.99
    assert -15.0 < t.frame[1, 3] < 5.0
    # Femur (root): long axis along +y, base at the proximal end of the field of view.
    f = frames["femur"]
    assert f.axes[:, 2] @ np.array([0.0, 1.0, 0.0]) > 0.99


def test_missing_label_names_the_bone():
    g = GridGeometry((8, 8, 8), (1.0, 1.0, 1.0))
    data = np.zeros(g.array_shape, np.uint8)
    data[1:4, 1:4, 1:4] = 1
    sk = Skeleton([Bone("a", 1), Bone("b", 7, "a")], [Joint("j", "a", "b", 1, (0.0, 0.0, 0.0))])
    with pytest.raises(ValueError, match="'b' \\(label 7\\)"):
        bone_frames(Volume(data, g), sk)
