"""Joints, skeletons, forward kinematics and poses (deformation.kinematics.skeleton)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.kinematics.skeleton import Bone, Joint, Pose, Skeleton, SkeletonError
from deformation.kinematics.transforms import apply, compose, from_rotation_translation, invert, rotation_about_point
from validation.phantoms import hand, knee
from workbench.io.jsonio import read_json, write_json

# Transforms act on ~100 mm coordinates and chains are ≤ 6 products deep: float64
# rounding stays below 1e-12 mm (and 1e-12 in the rotation entries).
ATOL = 1e-12


def _rx(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _random_frame(rng) -> np.ndarray:
    return Rotation.random(random_state=rng).as_matrix()


def _random_values(rng, dof: int, *, max_deg: float = 80.0) -> np.ndarray:
    v = rng.uniform(-max_deg, max_deg, dof)
    if dof == 6:
        v[3:] = rng.normal(0.0, 10.0, 3)
    return v


def _random_angles(skel: Skeleton, rng, *, max_deg: float = 60.0) -> dict:
    return {j.name: _random_values(rng, j.dof, max_deg=max_deg) for j in skel.joints}


def _random_root(rng) -> np.ndarray:
    return from_rotation_translation(_random_frame(rng), rng.normal(0.0, 50.0, 3))


@pytest.fixture(scope="module")
def hand_skeleton() -> Skeleton:
    return hand.skeleton()


@pytest.fixture(scope="module")
def knee_skeleton() -> Skeleton:
    return knee.skeleton()


# -- Joint.motion: the convention of the module docstring ------------------------------------------


@pytest.mark.parametrize("dof", [1, 2, 3])
def test_rotational_joint_fixes_its_centre(dof):
    rng = np.random.default_rng(100 + dof)
    for _ in range(20):
        j = Joint("j", "p", "c", dof, rng.normal(0.0, 100.0, 3), _random_frame(rng))
        m = j.motion(_random_values(rng, dof, max_deg=170.0))
        np.testing.assert_allclose(apply(m, j.center), j.center, rtol=0, atol=ATOL)
        np.testing.assert_allclose(m[3], [0, 0, 0, 1], rtol=0, atol=0)
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), rtol=0, atol=1e-14)
        assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0, abs=1e-14)


def test_zero_angles_give_the_identity():
    rng = np.random.default_rng(104)
    for dof in (1, 2, 3, 6):
        j = Joint("j", "p", "c", dof, rng.normal(0.0, 100.0, 3), _random_frame(rng))
        np.testing.assert_allclose(j.motion(np.zeros(dof)), np.eye(4), rtol=0, atol=ATOL)


@pytest.mark.parametrize("theta", [30.0, 90.0, -45.0])
def test_flexion_turns_the_z_axis_towards_minus_y(theta):
    rng = np.random.default_rng(105)
    a = _random_frame(rng)
    x_ax, y_ax, z_ax = a.T
    c = np.array([12.0, -40.0, 7.0])
    j = Joint("j", "p", "c", 1, c, a)
    m = j.motion([theta])
    th = np.radians(theta)
    # A point one unit along the joint's z axis ends at cos θ z − sin θ y (about c);
    # the flexion axis x itself does not move.
    np.testing.assert_allclose(apply(m, c + z_ax), c + np.cos(th) * z_ax - np.sin(th) * y_ax, rtol=0, atol=ATOL)
    np.testing.assert_allclose(apply(m, c + y_ax), c + np.cos(th) * y_ax + np.sin(th) * z_ax, rtol=0, atol=ATOL)
    np.testing.assert_allclose(apply(m, c + 5.0 * x_ax), c + 5.0 * x_ax, rtol=0, atol=ATOL)
    # Cross-check against the matrix built by hand in the joint frame: A Rx(θ) Aᵀ about c.
    np.testing.assert_allclose(m, rotation_about_point(a @ _rx(theta) @ a.T, c), rtol=0, atol=ATOL)


def test_90_degree_flexion_in_the_identity_frame_maps_z_to_minus_y():
    j = Joint("j", "p", "c", 1, (0.0, 0.0, 0.0))
    np.testing.assert_allclose(j.motion([90.0])[:3, :3] @ [0.0, 0.0, 1.0], [0.0, -1.0, 0.0], rtol=0, atol=1e-15)


def test_intrinsic_xyz_equals_rx_ry_rz_composed_by_hand():
    rng = np.random.default_rng(106)
    for _ in range(20):
        a = _random_frame(rng)
        c = rng.normal(0.0, 100.0, 3)
        fx, ab, tw = rng.uniform(-80.0, 80.0, 3)
        j3 = Joint("j", "p", "c", 3, c, a)
        r = _rx(fx) @ _ry(ab) @ _rz(tw)
        np.testing.assert_allclose(j3.local_rotation([fx, ab, tw]), r, rtol=0, atol=1e-14)
        np.testing.assert_allclose(j3.motion([fx, ab, tw]), rotation_about_point(a @ r @ a.T, c), rtol=0, atol=ATOL)
        j2 = Joint("j", "p", "c", 2, c, a)
        np.testing.assert_allclose(
            j2.motion([fx, ab]), rotation_about_point(a @ _rx(fx) @ _ry(ab) @ a.T, c), rtol=0, atol=ATOL
        )


def test_intrinsic_order_on_an_explicit_case():
    # Flex 90° then abduct 90° about the *moved* y axis: Rx(90) Ry(90) sends z → x.
    # The extrinsic reading of the same angles, Ry(90) Rx(90), would send z → −y.
    j = Joint("j", "p", "c", 2, (0.0, 0.0, 0.0))
    np.testing.assert_allclose(j.motion([90.0, 90.0])[:3, :3] @ [0, 0, 1.0], [1.0, 0.0, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose((_ry(90.0) @ _rx(90.0)) @ [0, 0, 1.0], [0.0, -1.0, 0.0], rtol=0, atol=1e-15)


def test_six_dof_translation_moves_the_centre_by_a_t():
    rng = np.random.default_rng(107)
    for _ in range(20):
        a = _random_frame(rng)
        c = rng.normal(0.0, 100.0, 3)
        j = Joint("j", "p", "c", 6, c, a)
        rot = rng.uniform(-80.0, 80.0, 3)
        t = rng.normal(0.0, 10.0, 3)
        m = j.motion(np.concatenate([rot, t]))
        np.testing.assert_allclose(apply(m, c), c + a @ t, rtol=0, atol=ATOL)
        # Module doc: M p = c + A (R Aᵀ (p − c) + t).
        r = _rx(rot[0]) @ _ry(rot[1]) @ _rz(rot[2])
        p = rng.normal(0.0, 100.0, size=(8, 3))
        expected = c + ((p - c) @ a @ r.T + t) @ a.T
        np.testing.assert_allclose(apply(m, p), expected, rtol=0, atol=ATOL)
        # Pure translation: every point moves by A t.
        np.testing.assert_allclose(
            j.motion(np.r_[0.0, 0.0, 0.0, t]), from_rotation_translation(np.eye(3), a @ t), rtol=0, atol=ATOL
        )


@pytest.mark.parametrize("dof", [1, 2, 3, 6])
def test_angles_from_motion_inverts_motion(dof):
    rng = np.random.default_rng(200 + dof)
    worst = 0.0
    for _ in range(100):
        j = Joint("j", "p", "c", dof, rng.normal(0.0, 100.0, 3), _random_frame(rng))
        values = _random_values(rng, dof, max_deg=80.0)
        recovered = j.angles_from_motion(j.motion(values))
        assert recovered.shape == (dof,)
        worst = max(worst, np.abs(recovered - values).max())
    # Degrees and mm; the Euler extraction is well conditioned within ±80° of the middle angle.
    assert worst < 1e-9


def test_full_angles_layout_and_errors():
    j6 = Joint("j6", "p", "c", 6, (0.0, 0.0, 0.0))
    np.testing.assert_array_equal(j6.full_angles([1, 2, 3, 4, 5, 6]), [1, 2, 3, 4, 5, 6])
    j2 = Joint("j2", "p", "c", 2, (0.0, 0.0, 0.0))
    np.testing.assert_array_equal(j2.full_angles([1, 2]), [1, 2, 0, 0, 0, 0])
    assert j2.n_rotations == 2 and j6.n_rotations == 3
    with pytest.raises(SkeletonError, match=r"'j2' has 2 DOF but got 3 values"):
        j2.motion([1.0, 2.0, 3.0])
    with pytest.raises(SkeletonError, match=r"'j6' has 6 DOF but got 3 values"):
        j6.motion([1.0, 2.0, 3.0])
    with pytest.raises(SkeletonError, match="finite"):
        j2.motion([np.nan, 0.0])


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"dof": 4}, r"dof must be one of \(1, 2, 3, 6\), got 4"),
        ({"dof": 0}, "dof must be one of"),
        ({"axes": np.diag([1.0, 1.0, 1.1])}, "orthonormal"),
        ({"axes": np.array([[1.0, 0.3, 0], [0, 1, 0], [0, 0, 1]])}, "orthonormal"),
        ({"axes": np.diag([1.0, 1.0, -1.0])}, "right-handed"),
        ({"axes": np.eye(2)}, "orthonormal"),
        ({"center": (1.0, 2.0)}, "center must be 3 finite numbers"),
        ({"center": (1.0, np.nan, 2.0)}, "center must be 3 finite numbers"),
    ],
)
def test_joint_rejects_bad_definitions(kwargs, fragment):
    args = {"name": "elbow", "parent": "p", "child": "c", "dof": 3, "center": (0.0, 0.0, 0.0)}
    args.update(kwargs)
    with pytest.raises(SkeletonError, match=fragment) as info:
        Joint(**args)
    assert "'elbow'" in str(info.value)


def test_joint_axes_are_copied_and_read_only():
    a = np.eye(3)
    j = Joint("j", "p", "c", 3, (0.0, 0.0, 0.0), a)
    a[0, 0] = -1.0
    assert j.axes[0, 0] == 1.0
    with pytest.raises(ValueError):
        j.axes[0, 0] = 5.0


# -- the phantom skeletons ------------------------------------------------------------------------------


def test_hand_skeleton_structure(hand_skeleton):
    s = hand_skeleton
    assert len(s.bones) == 21 and len(s.joints) == 20
    assert s.root == "radius"
    assert s.joint("wrist").dof == 6 and s.joint("thumb_cmc").dof == 6
    assert sorted(j.dof for j in s.joints) == [3] * 18 + [6] * 2
    assert s.n_dof == 66
    assert s.joint_of("index_distal").name == "index_dip" and s.joint_of("radius") is None
    # Topological order: every parent comes before its children.
    pos = {n: i for i, n in enumerate(s.order)}
    for b in s.bones:
        if b.parent is not None:
            assert pos[b.parent] < pos[b.name]
    assert s.label_of("radius") == 1
    with pytest.raises(SkeletonError, match="no bone 'ulna'"):
        s.bone("ulna")
    with pytest.raises(SkeletonError, match="no joint 'elbow'"):
        s.joint("elbow")


def test_forward_kinematics_at_zero_is_the_root_transform(hand_skeleton, knee_skeleton):
    rng = np.random.default_rng(300)
    root = _random_root(rng)
    for s in (hand_skeleton, knee_skeleton):
        for name, t in s.forward_kinematics().items():
            np.testing.assert_allclose(t, np.eye(4), rtol=0, atol=ATOL, err_msg=name)
        for name, t in s.forward_kinematics(root_transform=root).items():
            np.testing.assert_allclose(t, root, rtol=0, atol=ATOL, err_msg=name)


@pytest.mark.parametrize("with_root", [False, True])
def test_index_finger_chain_composes_by_hand(hand_skeleton, with_root):
    s = hand_skeleton
    rng = np.random.default_rng(301)
    angles = _random_angles(s, rng)
    root = _random_root(rng) if with_root else np.eye(4)
    fk = s.forward_kinematics(angles, root_transform=root if with_root else None)
    m = {n: s.joint(n).motion(angles[n]) for n in ("wrist", "index_cmc", "index_mcp", "index_pip", "index_dip")}
    np.testing.assert_allclose(fk["radius"], root, rtol=0, atol=0)
    np.testing.assert_allclose(fk["capitate"], root @ m["wrist"], rtol=0, atol=ATOL)
    np.testing.assert_allclose(fk["index_metacarpal"], root @ m["wrist"] @ m["index_cmc"], rtol=0, atol=ATOL)
    t_distal = root @ m["wrist"] @ m["index_cmc"] @ m["index_mcp"] @ m["index_pip"] @ m["index_dip"]
    np.testing.assert_allclose(fk["index_distal"], t_distal, rtol=0, atol=ATOL)
    # The thumb hangs from the capitate through the second 6-DOF joint.
    t_thumb = root @ m["wrist"] @ s.joint("thumb_cmc").motion(angles["thumb_cmc"])
    np.testing.assert_allclose(fk["thumb_metacarpal"], t_thumb, rtol=0, atol=ATOL)


def test_every_bone_is_its_parent_times_its_joint_motion(hand_skeleton, knee_skeleton):
    rng = np.random.default_rng(302)
    for s in (hand_skeleton, knee_skeleton):
        angles = _random_angles(s, rng)
        fk = s.forward_kinematics(angles, root_transform=_random_root(rng))
        assert set(fk) == set(s.bone_names)
        for j in s.joints:
            np.testing.assert_allclose(fk[j.child], fk[j.parent] @ j.motion(angles[j.name]), rtol=0, atol=ATOL)


def test_missing_joints_stay_at_zero(hand_skeleton):
    s = hand_skeleton
    fk = s.forward_kinematics({"index_mcp": [40.0, 0.0, 0.0]})
    # Zero angles give A I Aᵀ about c: the identity up to rounding, not bit for bit.
    np.testing.assert_allclose(fk["index_metacarpal"], np.eye(4), rtol=0, atol=ATOL)
    np.testing.assert_allclose(fk["index_distal"], s.joint("index_mcp").motion([40.0, 0.0, 0.0]), rtol=0, atol=ATOL)
    np.testing.assert_allclose(fk["middle_distal"], np.eye(4), rtol=0, atol=ATOL)


def test_relative_motion_recovers_each_joint_motion_and_angles(hand_skeleton, knee_skeleton):
    rng = np.random.default_rng(303)
    for s in (hand_skeleton, knee_skeleton):
        angles = _random_angles(s, rng)
        fk = s.forward_kinematics(angles, root_transform=_random_root(rng))
        for j in s.joints:
            m = s.relative_motion(fk, j.name)
            np.testing.assert_allclose(m, j.motion(angles[j.name]), rtol=0, atol=ATOL, err_msg=j.name)
            # Through a root and up to five products of ~100 mm transforms: ~1e-13 deg / mm.
            np.testing.assert_allclose(j.angles_from_motion(m), angles[j.name], rtol=0, atol=1e-9, err_msg=j.name)


def test_pose_joint_centres(hand_skeleton):
    s = hand_skeleton
    rng = np.random.default_rng(304)
    angles = _random_angles(s, rng)
    root = _random_root(rng)
    pose = s.pose(angles, root_transform=root)
    assert pose.skeleton == "hand"
    assert set(pose.joint_centers) == set(s.joint_names)
    for j in s.joints:
        centre = pose.joint_centers[j.name]
        np.testing.assert_allclose(centre, apply(pose[j.parent], j.center), rtol=0, atol=ATOL)
        if j.dof == 6:
            # The child's copy of the centre is displaced by the joint translation A t.
            t = angles[j.name][3:]
            np.testing.assert_allclose(
                apply(pose[j.child], j.center), apply(pose[j.parent], j.center + j.axes @ t), rtol=0, atol=ATOL
            )
        else:
            np.testing.assert_allclose(centre, apply(pose[j.child], j.center), rtol=0, atol=ATOL)
        np.testing.assert_array_equal(pose.joint_angles[j.name], angles[j.name])


def test_pose_fills_in_zero_angles_for_missing_joints(knee_skeleton):
    pose = knee_skeleton.pose({"knee": [30.0, 0.0, 0.0]})
    np.testing.assert_array_equal(pose.joint_angles["knee"], [30.0, 0.0, 0.0])
    np.testing.assert_array_equal(pose.joint_angles["patellofemoral"], np.zeros(3))
    np.testing.assert_allclose(pose.joint_centers["knee"], knee.KNEE_CENTER, rtol=0, atol=0)


def test_forward_kinematics_errors(hand_skeleton):
    s = hand_skeleton
    with pytest.raises(SkeletonError, match=r"unknown joints \['elbow', 'knee'\]"):
        s.forward_kinematics({"knee": [0, 0, 0], "elbow": [0.0], "wrist": np.zeros(6)})
    with pytest.raises(SkeletonError, match=r"'wrist' has 6 DOF but got 3 values"):
        s.forward_kinematics({"wrist": [1.0, 2.0, 3.0]})
    with pytest.raises(SkeletonError, match=r"'index_pip' has 3 DOF but got 1 values"):
        s.pose({"index_pip": [10.0]})
    with pytest.raises(ValueError, match="root_transform is not rigid"):
        s.forward_kinematics(root_transform=np.diag([1.0, 1.0, -1.0, 1.0]))


# -- skeleton validation ----------------------------------------------------------------------------------


def _chain_bones():
    return [Bone("a", 1, None), Bone("b", 2, "a"), Bone("c", 3, "b")]


def _chain_joints():
    return [Joint("ab", "a", "b", 1, (0.0, 0.0, 0.0)), Joint("bc", "b", "c", 3, (0.0, 10.0, 0.0))]


def test_a_valid_chain():
    s = Skeleton(_chain_bones(), _chain_joints(), name="chain")
    assert s.order == ("a", "b", "c") and s.root == "a" and s.n_dof == 4
    assert repr(s) == "Skeleton('chain', 3 bones, 2 joints, 4 DOF)"


@pytest.mark.parametrize(
    "bones, joints, fragment",
    [
        (_chain_bones() + [Bone("b", 4, "a")], _chain_joints(), "bone names must be unique"),
        ([Bone("a", 1, None), Bone("b", 1, "a"), Bone("c", 3, "b")], _chain_joints(), "labels must be unique"),
        ([Bone("a", 0, None), Bone("b", 2, "a"), Bone("c", 3, "b")], _chain_joints(), "positive integers"),
        (
            [Bone("a", 1, None), Bone("b", 2, None), Bone("c", 3, "b")],
            _chain_joints()[1:],
            r"exactly one root bone .* got \['a', 'b'\]",
        ),
        ([Bone("a", 1, "c"), Bone("b", 2, "a"), Bone("c", 3, "b")], _chain_joints(), r"exactly one root .* got \[\]"),
        ([], [], "exactly one root"),
        (
            [Bone("a", 1, None), Bone("b", 2, "a"), Bone("c", 3, "x")],
            _chain_joints(),
            r"bone 'c': parent 'x' is not a bone",
        ),
        (
            _chain_bones(),
            [Joint("ab", "a", "b", 1, (0, 0, 0)), Joint("bc", "a", "c", 3, (0, 0, 0))],
            r"joint 'bc' links 'a' → 'c', but bone 'c' has parent 'b'",
        ),
        (_chain_bones(), _chain_joints()[:1], r"bone 'c' must hang from its parent by exactly one joint, found 0"),
        (_chain_bones(), _chain_joints() + [Joint("bc2", "b", "c", 1, (0, 0, 0))], "exactly one joint, found 2"),
        (_chain_bones(), _chain_joints() + [Joint("ab", "a", "b", 1, (0, 0, 0))], "joint names must be unique"),
        (_chain_bones(), _chain_joints() + [Joint("xd", "a", "d", 1, (0, 0, 0))], r"child 'd' is not a bone"),
        (_chain_bones(), _chain_joints() + [Joint("ba", "b", "a", 1, (0, 0, 0))], r"bone 'a' has parent None"),
        # b and c hang from each other: a cycle not connected to the root a.
        (
            [Bone("a", 1, None), Bone("b", 2, "c"), Bone("c", 3, "b")],
            [Joint("cb", "c", "b", 1, (0, 0, 0)), Joint("bc", "b", "c", 1, (0, 0, 0))],
            r"bones \['b', 'c'\] are not connected to the root \(cycle\?\)",
        ),
        ([Bone("a", 1, None), Bone("b", 2, "b")], [Joint("bb", "b", "b", 1, (0, 0, 0))], "cycle"),
    ],
)
def test_skeleton_validation_errors(bones, joints, fragment):
    with pytest.raises(SkeletonError, match=fragment):
        Skeleton(bones, joints, name="broken")


# -- JSON round trips -----------------------------------------------------------------------------------


@pytest.mark.parametrize("make", [knee.skeleton, hand.skeleton], ids=["knee", "hand"])
def test_skeleton_json_round_trip_is_exact(make, tmp_path):
    s = make()
    path = write_json(s.to_dict(), tmp_path / "skeleton.json")
    d = read_json(path)
    assert d["format"] == "avw-skeleton" and d["version"] == 1 and d["units"] == "mm"
    back = Skeleton.from_dict(d)
    assert back == s
    assert back is not s and back.order == s.order
    for j0, j1 in zip(s.joints, back.joints):
        assert j1.center == j0.center  # tuples of floats, bit for bit
        np.testing.assert_array_equal(j1.axes, j0.axes)
    # Writing again gives the same text: the format is stable.
    again = write_json(back.to_dict(), tmp_path / "again.json")
    assert again.read_text(encoding="utf-8") == path.read_text(encoding="utf-8")


def test_skeleton_equality_sees_a_changed_centre(knee_skeleton):
    d = knee_skeleton.to_dict()
    d["joints"][0]["center"][1] += 1e-12
    assert Skeleton.from_dict(d) != knee_skeleton


@pytest.mark.parametrize("make", [knee.skeleton, hand.skeleton], ids=["knee", "hand"])
def test_pose_json_round_trip_is_exact(make, tmp_path):
    s = make()
    rng = np.random.default_rng(305)
    pose = s.pose(_random_angles(s, rng), root_transform=_random_root(rng))
    back = Pose.from_dict(read_json(write_json(pose.to_dict(), tmp_path / "pose.json")))
    assert back.skeleton == s.name
    assert set(back.transforms) == set(pose.transforms)
    for bone, t in pose.transforms.items():
        np.testing.assert_array_equal(back[bone], t)
        assert back[bone].dtype == np.float64
    assert set(back.joint_angles) == set(pose.joint_angles) == set(s.joint_names)
    for name in s.joint_names:
        np.testing.assert_array_equal(back.joint_angles[name], pose.joint_angles[name])
        np.testing.assert_array_equal(back.joint_centers[name], pose.joint_centers[name])


def test_pose_without_joint_extras_round_trips_to_none(tmp_path):
    fk = knee.skeleton().forward_kinematics({"knee": [20.0, 1.0, -2.0]})
    bare = Pose.from_dict(read_json(write_json(Pose(fk, skeleton="knee").to_dict(), tmp_path / "bare.json")))
    assert bare.joint_angles is None and bare.joint_centers is None
    only_angles = Pose(fk, joint_angles={"knee": [20.0, 1.0, -2.0]})
    back = Pose.from_dict(read_json(write_json(only_angles.to_dict(), tmp_path / "angles.json")))
    np.testing.assert_array_equal(back.joint_angles["knee"], [20.0, 1.0, -2.0])
    assert back.joint_centers is None


def test_pose_rejects_a_non_rigid_transform():
    with pytest.raises(ValueError, match="transform of bone 'tibia' is not rigid"):
        Pose({"femur": np.eye(4), "tibia": np.diag([1.0, 1.0, 2.0, 1.0])})


@pytest.mark.parametrize(
    "change, fragment",
    [
        ({"format": "avw-pose"}, r"not a skeleton description: 'format' is 'avw-pose'"),
        ({"format": None}, "not a skeleton description"),
        ({"version": 2}, r"unsupported skeleton version 2"),
        ({"version": 1.5}, r"unsupported skeleton version 1.5"),
        ({"version": "1"}, r"unsupported skeleton version '1'"),
        ({"version": True}, r"unsupported skeleton version True"),
        ({"version": None}, r"unsupported skeleton version None"),
    ],
)
def test_skeleton_from_dict_rejects_wrong_format_or_version(knee_skeleton, change, fragment):
    d = knee_skeleton.to_dict()
    d.update(change)
    with pytest.raises(SkeletonError, match=fragment):
        Skeleton.from_dict(d)


def test_skeleton_from_dict_rejects_a_missing_version_and_missing_keys(knee_skeleton):
    d = knee_skeleton.to_dict()
    del d["version"]
    with pytest.raises(SkeletonError, match="unsupported skeleton version None"):
        Skeleton.from_dict(d)
    d = knee_skeleton.to_dict()
    del d["bones"][1]["label"]
    with pytest.raises(SkeletonError, match="a bone entry lacks the key 'label'"):
        Skeleton.from_dict(d)
    d = knee_skeleton.to_dict()
    del d["joints"][0]["center"]
    with pytest.raises(SkeletonError, match="lacks the key 'center'"):
        Skeleton.from_dict(d)


@pytest.mark.parametrize(
    "change, fragment",
    [
        ({"format": "avw-skeleton"}, r"not a pose: 'format' is 'avw-skeleton'"),
        ({"version": 2}, r"unsupported pose version 2"),
        ({"version": 1.5}, r"unsupported pose version 1.5"),
        ({"version": None}, r"unsupported pose version None"),
    ],
)
def test_pose_from_dict_rejects_wrong_format_or_version(knee_skeleton, change, fragment):
    d = knee_skeleton.pose().to_dict()
    d.update(change)
    with pytest.raises(SkeletonError, match=fragment):
        Pose.from_dict(d)


def test_pose_from_dict_rejects_missing_bones(knee_skeleton):
    d = knee_skeleton.pose().to_dict()
    del d["bones"]
    with pytest.raises(SkeletonError, match="lacks the key 'bones'"):
        Pose.from_dict(d)


def test_relative_motion_of_a_recorded_pose_matches_inverse_composition(knee_skeleton):
    rng = np.random.default_rng(306)
    pose = knee_skeleton.pose(_random_angles(knee_skeleton, rng), root_transform=_random_root(rng))
    m = knee_skeleton.relative_motion(pose.transforms, "knee")
    np.testing.assert_allclose(m, compose(invert(pose["femur"]), pose["tibia"]), rtol=0, atol=0)


def test_joint_limits_round_trip_and_name_what_is_outside():
    from deformation.kinematics.skeleton import Bone, Joint, Skeleton, SkeletonError

    j = Joint("knee", "femur", "tibia", 3, (0.0, 0.0, 0.0), limits=((-10, 150), (-15, 15), (-30, 30)))
    sk = Skeleton([Bone("femur", 1, None), Bone("tibia", 2, "femur")], [j], name="k")
    again = Skeleton.from_dict(sk.to_dict())
    assert again.joint("knee").limits == ((-10.0, 150.0), (-15.0, 15.0), (-30.0, 30.0))
    assert sk.limit_problems({"knee": [20, 0, 0]}) == []
    assert sk.limit_problems({"knee": [200, -20, 0]}) == [
        "knee[0] = 200° outside [-10, 150]",
        "knee[1] = -20° outside [-15, 15]",
    ]
    six = Joint("w", "femur", "tibia", 6, (0.0, 0.0, 0.0), limits=((-5, 5),) * 3 + ((-10, 10),) * 3)
    assert six.outside_limits([0, 0, 0, 0, 12, 0]) == ["w[4] = 12 mm outside [-10, 10]"]
    for bad in (
        ((-10, 150), (-15, 15)),
        ((10, -10), (0, 1), (0, 1)),
        ((0, np.inf), (0, 1), (0, 1)),
        ((0, "x"), (0, 1), (0, 1)),
        ((0, 1), (0,), (0, 1)),
    ):
        with pytest.raises(SkeletonError, match="limits must be 3"):
            Joint("knee", "femur", "tibia", 3, (0.0, 0.0, 0.0), limits=bad)
    no_limits = Skeleton.from_dict(
        {**sk.to_dict(), "joints": [{k: v for k, v in j.to_dict().items() if k != "limits"}]}
    )
    # a joint without limits (an older skeleton.json) takes rotations within ±180°: more is a slip
    assert no_limits.limit_problems({"knee": [170, -180, 180]}) == []
    assert no_limits.limit_problems({"knee": [1000, 0, -181]}) == [
        "knee[0] = 1000° is more than half a turn (the joint has no 'limits' in the skeleton; its rotations are "
        "taken within ±180°)",
        "knee[2] = -181° is more than half a turn (the joint has no 'limits' in the skeleton; its rotations are "
        "taken within ±180°)",
    ]
    six_free = Joint("w", "femur", "tibia", 6, (0.0, 0.0, 0.0))
    assert six_free.outside_limits([0, 0, 0, 500, 0, 0]) == []  # translations (mm) are not checked


@pytest.mark.parametrize("region", ["knee", "hand"])
def test_the_phantoms_own_poses_lie_within_their_skeletons_range_of_motion(region):
    """The phantoms' seeded default poses (their jitter around a straight joint included) are poses a user
    could give back (a truth pose file, keyframes): none outside the limits their skeleton.json carries."""
    mod = {"knee": knee, "hand": hand}[region]
    sk = mod.skeleton()
    for seed in range(30):
        for n in (4, 5, 10):
            for a in mod.default_poses(n, np.random.default_rng(seed)):
                assert sk.limit_problems(mod.complete_angles(a)) == [], (seed, n)
