"""Pose weights (Kurihara Eq. 12–15), PSD (Kurihara Eq. 6–8) and WPSD (Kurihara Eq. 16)."""

from __future__ import annotations

import numpy as np
import pytest

from deformation.models.posespace import (
    PoseSpace,
    pose_vector,
    pose_weights,
    psd_deform,
    psd_training,
    skin,
    wpsd_deform,
)
from deformation.models.skinning import SkinningWeights, lbs, stack_transforms
from validation.phantoms import hand


@pytest.fixture(scope="module")
def hand_setup():
    """The phantom hand's skeleton, 5 training poses and skin-like points with smooth weights."""
    rng = np.random.default_rng(7)
    sk = hand.skeleton()
    poses = [sk.pose(a) for a in hand.default_poses(5, rng)]
    bones = tuple(sk.bone_names)
    # points scattered around the bones, weighted by a smooth function of distance to bone origins
    origins = np.stack([np.asarray(sk.joint_of(b).center) if sk.joint_of(b) else np.zeros(3) for b in bones])
    p = origins[rng.integers(0, len(bones), 3000)] + rng.normal(scale=8.0, size=(3000, 3))
    d = np.linalg.norm(p[:, None] - origins[None], axis=2)
    w = SkinningWeights.from_dense(np.exp(-((d / 15.0) ** 2)) + 1e-12, bones)
    return sk, poses, bones, p, w, rng


def test_pose_weights_interpolate_the_training_poses_and_sum_to_one():
    rng = np.random.default_rng(3)
    train = rng.normal(scale=30.0, size=(7, 5))
    # Kurihara Eq. 10 at the training poses; the 7×7 Gaussian system is solved in float64 (cond < 1e4 here).
    np.testing.assert_allclose(pose_weights(train, train), np.eye(7), atol=1e-9)
    q = rng.normal(scale=30.0, size=(50, 5))
    np.testing.assert_allclose(pose_weights(train, q).sum(1), 1.0, atol=1e-12)  # Kurihara Eq. 11
    # the width is the nearest-neighbour distance: scaling every distance leaves the weights unchanged
    np.testing.assert_allclose(pose_weights(train, q), pose_weights(3.0 * train, 3.0 * q), atol=1e-9)
    # per-point DOF weights (Kurihara Eq. 16) that are uniform give the PSD weights
    np.testing.assert_allclose(pose_weights(train, q, dof_weights=np.full(5, 0.2)), pose_weights(train, q), atol=1e-9)


def test_pose_weights_are_continuous():
    rng = np.random.default_rng(4)
    train = rng.normal(scale=30.0, size=(6, 4))
    a = rng.normal(scale=30.0, size=4)
    step = rng.normal(size=4) * 1e-4
    # a 1e-4° step moves the weights by O(1e-4 · |∇s|); |∇s| ~ 1/σ ≈ 1/20 per degree here.
    assert np.abs(pose_weights(train, a + step) - pose_weights(train, a)).max() < 1e-4


def test_weights_far_from_every_example_are_the_nearest_examples(hand_setup):
    """Kurihara Eq. 14 normalises the φ of Kurihara Eq. 12: far from every example each φ underflows to 0, and the
    weights must still be those of the limit (the nearest example's), not 0 / 0."""
    sk, poses, bones, p, w, rng = hand_setup
    space = PoseSpace(sk, poses)
    far = space.train[2] + 400.0 * (space.train[2] - space.train.mean(axis=0))  # ~100 widths away, past pose 2
    s = pose_weights(space.train, far)
    assert np.all(np.isfinite(s)) and np.isclose(s.sum(), 1.0)
    assert np.argmax(s) == int(np.argmin(((space.train - far) ** 2).sum(axis=1)))
    # the per-point weights of WPSD (Kurihara Eq. 16) at that pose vector: finite, summing to one at every point
    pw = space.point_space(w).weights(far)
    assert np.all(np.isfinite(pw)) and np.allclose(pw.sum(axis=1), 1.0)


def test_psd_and_wpsd_reproduce_every_training_example(hand_setup):
    sk, poses, bones, p, w, rng = hand_setup
    space = PoseSpace(sk, poses)
    # training surfaces: SSD plus a pose-dependent offset that SSD cannot produce
    samples = []
    for k, pose in enumerate(poses):
        offset = 2.0 * np.sin(p / 17.0 + k)
        samples.append(lbs(p + offset, w, pose.transforms))
    base = psd_training(samples, w, [q.transforms for q in poses])  # Kurihara Eq. 6
    per_point = np.ascontiguousarray(base.transpose(1, 0, 2))
    pts = space.point_space(w)
    for k, pose in enumerate(poses):
        s = space.weights(pose)
        # Kurihara Eq. 10: s = e_k at a training pose; Kurihara Eq. 7–8 then give the sample back.  The inverse
        # blend and the Gaussian solve cost ≤ 1e-8 mm on ~100 mm coordinates.
        np.testing.assert_allclose(psd_deform(base, w, s, pose.transforms), samples[k], atol=1e-6)
        np.testing.assert_allclose(skin(per_point, w, pose.transforms, s), samples[k], atol=1e-6)
        sw = pts.weights(pose)
        np.testing.assert_allclose(sw.sum(1), 1.0, atol=1e-9)
        np.testing.assert_allclose(sw, np.eye(len(poses))[np.full(len(p), k)], atol=1e-6)
        np.testing.assert_allclose(skin(per_point, w, pose.transforms, sw), samples[k], atol=1e-5)
        np.testing.assert_allclose(wpsd_deform(per_point, w, pts, pose, pose.transforms), samples[k], atol=1e-5)
    # away from the training poses the fused kernel equals the two-step evaluation (round-off only)
    q = space.train.mean(axis=0)
    two_step = skin(per_point, w, poses[0].transforms, pts.weights(q))
    np.testing.assert_allclose(wpsd_deform(per_point, w, pts, q, poses[0].transforms), two_step, atol=1e-9)
    # the coefficients folded with the samples once by the caller (PointPoseSpace.fold: Σ φ Cᵀbase / Σ φ Cᵀ1
    # rearranges Kurihara Eq. 14 and 7) give the two-step surface too (round-off only)
    folded = pts.fold(per_point)
    np.testing.assert_allclose(
        wpsd_deform(per_point, w, pts, q, poses[0].transforms, folded=folded), two_step, atol=1e-9
    )
    with pytest.raises(ValueError, match="PointPoseSpace.fold"):
        wpsd_deform(per_point, w, pts, q, poses[0].transforms, folded=folded[:, :, :3])


def test_wpsd_follows_only_the_dofs_that_move_the_points_bone(hand_setup):
    sk, poses, bones, p, w, rng = hand_setup
    space = PoseSpace(sk, poses)
    pts = space.point_space(w)
    # a new pose that copies training pose 2 except at one finger's joints
    vec = space.train[2].copy()
    finger = [j for j in sk.joints if j.child in ("index_proximal", "index_middle", "index_distal")]
    assert finger, [j.child for j in sk.joints]
    names = [j.name for j in sk.joints]
    offs = np.cumsum([0] + [j.dof for j in sk.joints])
    moved = set()
    for j in finger:
        i = names.index(j.name)
        vec[offs[i] : offs[i + 1]] = space.train[4, offs[i] : offs[i + 1]]
        moved.add(bones.index(j.child))
    sw = pts.weights(vec)
    # points off the moved finger (and mostly off the root bone, which no DOF moves, so that its
    # points fall back to the PSD weights) still see pose 2 ... up to the U_FLOOR leak
    dense = w.dense()
    far = (dense[:, sorted(moved)].sum(1) < 1e-9) & (dense[:, bones.index(sk.root)] < 0.5)
    assert far.sum() > 500
    # the floor u ≥ 1e-6 lets the moved DOFs leak in: d² grows by 1e-6·Σ Δ² ≈ 1e-3 deg², far below σ²
    # (≈ 4 deg² for the least-moved bone here); measured 4e-4
    assert np.abs(sw[far, 2] - 1.0).max() < 2e-2
    # points on the moved finger's bones are drawn towards pose 4
    on = dense[:, sorted(moved)].sum(1) > 0.99
    assert on.sum() > 50
    assert np.median(sw[on, 4]) > 0.3
    # PSD instead mixes the poses for every point alike
    s = space.weights(vec)
    assert s[2] < 0.95


def test_pose_vector_recovers_angles_from_transforms(hand_setup):
    sk, poses, *_ = hand_setup
    from deformation.kinematics.skeleton import Pose

    bare = Pose(poses[1].transforms)  # no recorded angles
    # Euler angles recovered from 4×4 products of ≤ 6 matrices: ≤ 1e-9° round-off.
    np.testing.assert_allclose(pose_vector(sk, bare), pose_vector(sk, poses[1]), atol=1e-9)


def test_identical_training_poses_are_refused(hand_setup):
    sk, poses, *_ = hand_setup
    with pytest.raises(ValueError, match="identical"):
        PoseSpace(sk, [poses[0], poses[1], poses[0]])


def test_stack_transforms_order(hand_setup):
    sk, poses, bones, *_ = hand_setup
    t = stack_transforms(poses[0].transforms, bones)
    assert t.shape == (len(bones), 4, 4)
    np.testing.assert_array_equal(t[3], poses[0].transforms[bones[3]])
