"""Bone poses, joint centres and angles of a phantom study against its ground truth (Rhee §3.1, Kurihara §3)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from deformation.geometry import GridGeometry, Volume
from registration.pose import contact_point, estimate_poses, pose_scans
from registration.rigid import bone_regions
from validation.pose_measures import pose_accuracy


def cut_above_knee(scan):
    """The proximal part of a knee scan (y index beyond the middle + 4): the femur stays, the shank is gone."""
    g = scan.geometry
    return scan.crop((0, g.size[1] // 2 + 4, 0), g.size)


@pytest.fixture(scope="module")
def knee_fits(knee_ct_study):
    """Every bone of every scan (the first half of estimate_poses), for the tests to reuse; copy before use
    (estimate_poses places each scan's pose on its ScanPose)."""
    st = knee_ct_study
    return pose_scans(
        st.template(), st.template_labels(), {s: (lambda s=s: st.scan(s)) for s in st.scan_ids}, st.skeleton()
    )


@pytest.fixture(scope="module")
def knee_result(knee_ct_study, knee_fits):
    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    res = estimate_poses(
        tpl, lab, {s: (lambda s=s: st.scan(s)) for s in st.scan_ids}, sk, scan_poses=copy.deepcopy(knee_fits)
    )
    centroids = {k: r.centroid for k, r in bone_regions(tpl, lab, sk).items()}
    acc = pose_accuracy(res, {s: st.truth_pose(s) for s in st.scan_ids}, sk, centroids)
    return res, acc


def test_bone_transforms_match_the_truth(knee_result):
    res, acc = knee_result
    assert all(f.ok for s in res.scans for f in s.fits.values()), res.failures()
    s = acc["summary"]
    # CT-like knee, 5 mm voxels, 3 scans up to 70° flexion: the required bounds (median ≤ 0.5° / 0.5 mm, worst
    # bone ≤ 2° / 2 mm).  Measured: median 0.08° / 0.05 mm, worst 1.15° (the patella, whose Cramér–Rao bound
    # on the benchmark's 4-scan CT knee is 0.46° rms) and 0.24 mm.  Before the phantom rendered bone edges rigidly
    # and the polish became
    # robust, the worst was 2.4° (the tibia) and the patella 2.2°.
    assert s["rotation_deg"]["median"] <= 0.5 and s["translation_mm"]["median"] <= 0.5, s
    assert s["rotation_deg"]["max"] <= 2.0 and s["translation_mm"]["max"] <= 2.0, s


def test_joint_centres_and_hinge_axes(knee_result):
    res, acc = knee_result
    # Every joint flexes (70°, or 49° for the patella) with only a few degrees of varus and twist: Kurihara Eq. 1 sees
    # near-hinges.  The required bounds: the true centre within 1 mm of the estimated axis, the axis within 2°
    # of the one the true motions define.  Measured: knee 0.04 mm / 0.64°, tibiofibular 0.17 mm / 0.13°,
    # patellofemoral 0.65 mm / 0.47°.
    for name, e in acc["joints"].items():
        assert e["is_hinge"], (name, e)
        assert e["center_to_axis_mm"] <= 1.0 and e["axis_error_deg"] <= 2.0, (name, e)
        # Closed form and the quasi-Newton cross-check agree (measured ≤ 1e-7 mm; the issue asks 0.01 mm).
        assert e["closed_form_vs_iterative_mm"] <= 0.01, (name, e)
    # Kurihara's Eq. 1 residual over all joints and scans (measured 0.30 mm; the paper's hand: 0.91 mm).
    assert np.isfinite(res.overall_rms_mm()) and res.overall_rms_mm() < 1.0


def test_angles_and_centres_are_recorded_per_scan(knee_result, knee_ct_study):
    res, _ = knee_result
    sk = knee_ct_study.skeleton()
    for s in res.scans:
        truth = knee_ct_study.truth_pose(s.scan_id)
        assert set(s.pose.joint_angles) == set(sk.joint_names)
        # Flexion (intrinsic XYZ, first angle) within 2.5° of the truth: the tibia's whole rotation error is
        # ≤ 2.4° here (measured), and flexion is one component of it.
        assert abs(s.pose.joint_angles["knee"][0] - truth.joint_angles["knee"][0]) < 2.5
        # The joint centre in the scan is the estimated centre carried by the parent (the femur).
        j = res.skeleton.joint("knee")
        np.testing.assert_allclose(
            s.pose.joint_centers["knee"],
            s.pose.transforms["femur"][:3, :3] @ np.asarray(j.center) + s.pose.transforms["femur"][:3, 3],
        )


@pytest.mark.slow  # ~12 s; the CLI's bone-out-of-view test stays in the default suite (`make test-slow`)
def test_a_bone_outside_the_field_of_view_is_reported(knee_ct_study):
    """Cut the scan above the knee: the tibia and fibula are missing and must be reported, not accepted.

    The joint search may still find a place for a missing bone inside the cut field (turned up by 100°+);
    it then fails the correlation check instead of the field-of-view check — either way it is reported,
    with the scan, the bone and the metric."""
    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    cut = cut_above_knee(st.scan("pose01"))
    res = estimate_poses(tpl, lab, {"cut": cut}, sk)
    fits = res.scans[0].fits
    assert fits["femur"].ok
    failed = {f["bone"]: f for f in res.failures()}
    for bone in ("tibia", "fibula"):
        assert fits[bone].status in ("outside_field_of_view", "poor_match"), (bone, fits[bone].status)
        assert failed[bone]["scan"] == "cut"
        assert failed[bone]["status"] == fits[bone].status
        assert fits[bone].inside_fraction < 0.5 or fits[bone].ncc < 0.5


def test_erased_bone_is_reported(knee_ct_study):
    """Replace the patella by soft tissue in the scan: it cannot be found, and the report says so.

    With squares the fit ended with NCC < 0.5 (``poor_match``).  The robust polish discounts the erased
    voxels and fits what is left of the region's rim (measured NCC 0.57), sliding 10+ mm off the joint:
    ``joint_detached``.  Either way the bone is flagged and listed with the scan and its metric."""
    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    scan = st.scan("pose00")  # the template's own pose: the patella's voxels are where the labels say
    data = scan.data.copy()
    near = np.asarray(bone_regions(tpl, lab, sk, margin_mm=6.0)["patella"].points)
    ijk = np.rint(scan.geometry.world_to_index(near)).astype(int)
    data[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = 40.0  # muscle-like HU, no texture
    res = estimate_poses(tpl, lab, {"erased": Volume(data, scan.geometry)}, sk, min_ncc=0.5)
    f = res.scans[0].fits["patella"]
    assert f.status in ("poor_match", "joint_detached"), (f.status, f.ncc)
    fail = [x for x in res.failures() if x["bone"] == "patella"]
    assert fail and fail[0]["scan"] == "erased" and fail[0]["status"] == f.status
    # The metric is reported, and it is far below a found patella's (0.9 and more on this study).
    assert fail[0]["ncc"] < 0.7
    assert all(x.ok for b, x in res.scans[0].fits.items() if b != "patella")


def test_contact_point_lies_between_the_bones():
    g = GridGeometry((20, 20, 20), (1.0, 1.0, 2.0))
    lab = np.zeros(g.array_shape, np.uint8)
    lab[:, :, :8] = 1
    lab[:, :, 11:] = 2
    p = contact_point(Volume(lab, g), 1, 2)
    # Closest pairs span the whole facing planes x = 7 and x = 11: their midpoints average to x = 9, mid-plane.
    assert abs(p[0] - 9.0) < 1e-9
    np.testing.assert_allclose(p[1:], [9.5, 19.0], atol=1e-9)


def test_root_from_image_moments_follows_a_shifted_scan(knee_ct_study):
    """The whole scan shifted by 12 mm (its origin moved): started from the images' centres of mass, the root
    and every other bone carry the shift; the straight-leg scan otherwise has identity transforms."""
    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    scan = st.scan("pose00")
    shift = np.array([12.0, -7.0, 4.0])
    g = scan.geometry
    moved = Volume(scan.data, GridGeometry(g.size, g.spacing, tuple(np.asarray(g.origin) + shift), g.direction))
    res = estimate_poses(tpl, lab, {"moved": moved}, sk, root_init="moments")
    centroids = {k: r.centroid for k, r in bone_regions(tpl, lab, sk).items()}
    for b, t in res.scans[0].pose.transforms.items():
        c = centroids[b]
        # Translation of each bone's centroid equals the shift within 0.5 mm (the test-size accuracy above).
        np.testing.assert_allclose(t[:3, :3] @ c + t[:3, 3] - c, shift, atol=0.5, err_msg=b)


def test_flagged_bones_do_not_feed_joint_centres_or_angles(knee_ct_study, knee_fits):
    """A scan missing the shank: its knee motion is not used for the knee's centre and gets no angles."""
    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    scans = {s: st.scan(s) for s in st.scan_ids}
    scans["pose02"] = cut_above_knee(scans["pose02"])
    # the other scans' fits are the module's (the same arguments); the cut scan's bones are fitted here
    fits = [copy.deepcopy(f) for f in knee_fits if f.scan_id != "pose02"]
    fits += pose_scans(tpl, lab, {"pose02": scans["pose02"]}, sk)
    res = estimate_poses(tpl, lab, scans, sk, scan_poses=fits)
    cut = next(s for s in res.scans if s.scan_id == "pose02")
    assert not cut.fits["tibia"].ok
    for j in sk.joints:  # angles exactly for the joints whose two bones were found
        assert (j.name in cut.pose.joint_angles) == (cut.fits[j.parent].ok and cut.fits[j.child].ok), j.name
    assert "knee" not in cut.pose.joint_angles
    # The knee's centre comes from the two other scans only (the estimated straight leg is not exactly the
    # identity, so it counts).
    assert res.joints["knee"].n_motions == 2
    # The pose of a flagged bone is its nearest placed ancestor's (the fit itself stays in fits); the placed
    # bones keep their fits
    for b in sk.order:
        f, parent = cut.fits[b], sk.bone(b).parent
        if f.ok or parent is None:
            assert np.array_equal(cut.pose.transforms[b], f.transform), b
        else:
            a = parent
            while not cut.fits[a].ok and sk.bone(a).parent is not None:
                a = sk.bone(a).parent
            assert np.array_equal(cut.pose.transforms[b], cut.fits[a].transform), (b, a)
    assert not np.array_equal(cut.pose.transforms["tibia"], cut.fits["tibia"].transform)


def test_released_labels_drop_only_the_flagged_bones(knee_ct_study):
    from registration.pose import released_labels

    st = knee_ct_study
    sk, lab = st.skeleton(), st.template_labels()
    assert released_labels(lab, sk, []) is lab
    out = released_labels(lab, sk, ["tibia", "fibula"])
    gone = np.isin(lab.data, [sk.label_of("tibia"), sk.label_of("fibula")])
    assert gone.any() and not np.isin(out.data, [sk.label_of("tibia"), sk.label_of("fibula")]).any()
    assert np.array_equal(out.data[~gone], lab.data[~gone]) and np.all(out.data[gone] == 0)
    assert out.geometry == lab.geometry and out.data.dtype == lab.data.dtype


def test_a_joint_that_barely_moves_keeps_the_skeleton_centre_and_is_not_scored(knee_ct_study, knee_fits):
    """The straight-leg scan alone: no joint turns 5°, so Kurihara Eq. 1 is not solved; the skeleton's centres are
    kept, marked as not estimated, and left out of the centre-error statistics (they would score 0 mm)."""
    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    # the scan's bone fits are the module's (pose_scans fits each scan on its own, with the same arguments)
    fits = [copy.deepcopy(f) for f in knee_fits if f.scan_id == "pose00"]
    res = estimate_poses(tpl, lab, {"pose00": st.scan("pose00")}, sk, scan_poses=fits)
    for j in sk.joints:
        r = res.joints[j.name]
        assert not r.estimated and not res.joints_dict()[j.name]["estimated"]
        np.testing.assert_array_equal(r.center, j.center)
    centroids = {k: r.centroid for k, r in bone_regions(tpl, lab, sk).items()}
    acc = pose_accuracy(res, {"pose00": st.truth_pose("pose00")}, sk, centroids)
    assert acc["summary"]["center_error_mm_2_3_dof_moving"]["n"] == 0
    assert all(not e["estimated"] for e in acc["joints"].values())


@pytest.mark.slow  # ~11 s each; the flagged bones' test above stays in the default suite (`make test-slow`)
def test_a_bone_that_leaves_its_joint_is_flagged(knee_ct_study):
    """Each fit records how far the joint centre lands from where the parent puts it; past the limit the
    bone is 'joint_detached' and reported, however well it correlates."""
    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    scan = {"pose01": st.scan("pose01")}
    res = estimate_poses(tpl, lab, scan, sk)
    fits = res.scans[0].fits
    assert "joint_gap_mm" not in fits["femur"].extra  # the root has no joint
    gaps = {b: fits[b].extra["joint_gap_mm"] for b in ("tibia", "fibula", "patella")}
    # Correct fits keep their joints: the truth's gap is 0 (3-DOF joints), and a bone a degree or two off
    # moves it by about a millimetre at most (measured ≤ 0.6 mm in this scan, ≤ 1.6 mm over the
    # 4-scan CT study of the benchmark, the patella).
    assert all(f.ok for f in fits.values()) and max(gaps.values()) < 2.0, gaps
    strict = estimate_poses(tpl, lab, scan, sk, max_joint_gap_mm=1e-3).scans[0].fits
    for b, g in gaps.items():
        assert (strict[b].status == "joint_detached") == (g > 1e-3), (b, g)
        if strict[b].status == "joint_detached":
            assert "left joint" in strict[b].stop and strict[b].extra["joint_gap_mm"] == pytest.approx(g, abs=1e-6)
    assert strict["femur"].ok


@pytest.mark.slow  # ~11 s each; the flagged bones' test above stays in the default suite (`make test-slow`)
def test_a_child_of_a_flagged_bone_is_flagged_too(knee_ct_study):
    """A bone is fitted from its parent's result, so once the parent is flagged the child is not
    trusted, however well it correlates: a chain that moved together (a finger registered onto its
    neighbour) must not pass below its first wrong bone.  Here the fibula hangs from the tibia, and
    the tibia is flagged by a joint-gap limit no real fit meets."""
    from dataclasses import replace

    from deformation.kinematics.skeleton import Skeleton

    st = knee_ct_study
    sk, tpl, lab = st.skeleton(), st.template(), st.template_labels()
    bones = [replace(b, parent="tibia") if b.name == "fibula" else b for b in sk.bones]
    joints = [replace(j, parent="tibia") if j.child == "fibula" else j for j in sk.joints]
    chain = Skeleton(bones, joints, name=sk.name)
    scan = {"pose01": st.scan("pose01")}
    fits = estimate_poses(tpl, lab, scan, chain).scans[0].fits
    assert all(f.ok for f in fits.values()), {b: f.status for b, f in fits.items()}
    strict = estimate_poses(tpl, lab, scan, chain, max_joint_gap_mm=1e-3).scans[0].fits
    assert strict["tibia"].status == "joint_detached"
    assert strict["fibula"].status == "parent_flagged" and "'tibia' was flagged" in strict["fibula"].stop
    # The flag is a judgement, not a different fit: the fibula's transform is the same as before.
    np.testing.assert_allclose(strict["fibula"].transform, fits["fibula"].transform, atol=1e-9)


def _chain_results(rng, n_scans, outlier=None, offset_mm=3.0):
    """Synthetic fits of a three-bone chain a → b → c turning about known centres, with 0.1 mm noise."""
    from scipy.spatial.transform import Rotation

    from deformation.kinematics.skeleton import Bone, Joint, Pose, Skeleton
    from deformation.kinematics.transforms import compose, rotation_about_point
    from registration.pose import ScanPose
    from registration.rigid import BoneFit

    c1, c2 = np.array([0.0, 30.0, 0.0]), np.array([0.0, 60.0, 0.0])
    sk = Skeleton(
        [Bone("a", 1, None), Bone("b", 2, "a"), Bone("c", 3, "b")],
        [Joint("j1", "a", "b", 3, tuple(c1)), Joint("j2", "b", "c", 3, tuple(c2))],
        name="chain",
    )
    results = []
    for i in range(n_scans):
        r1 = Rotation.from_rotvec(np.deg2rad(rng.uniform(-30, 30, 3))).as_matrix()
        r2 = Rotation.from_rotvec(np.deg2rad(rng.uniform(-30, 30, 3))).as_matrix()
        tb = rotation_about_point(r1, c1)
        tb[:3, 3] += rng.normal(0, 0.1, 3)
        if i == outlier:
            tb[:3, 3] += offset_mm * np.array([1.0, 0.0, 0.0])  # b slid off its joint
        tc = compose(tb, rotation_about_point(r2, c2))
        transforms = {"a": np.eye(4), "b": tb, "c": tc}
        fits = {k: BoneFit(k, v, "intensity", "ok", 0.0, 0.0, 1.0, 1.0) for k, v in transforms.items()}
        results.append(ScanPose(f"s{i}", Pose(transforms, skeleton="chain"), fits, 0.0))
    contacts = {"j1": c1, "j2": c2}
    return sk, results, contacts


def test_a_motion_inconsistent_with_its_joint_centre_is_flagged():
    """Kurihara Eq. 1 over all scans fixes each joint's centre; a bone whose motion misses it by far more than the
    others (here 3 mm beside 0.1 mm noise) is flagged joint_outlier, and the bone below it parent_flagged.
    Bones that are right are left alone; so is a scan set without an outlier."""
    from registration.pose import flag_joint_outliers

    rng = np.random.default_rng(4)
    sk, results, contacts = _chain_results(rng, 8, outlier=5)
    voxel = {s.scan_id: 1.0 for s in results}  # 1 mm voxels: the floor is 0.5 mm
    flagged = flag_joint_outliers(results, sk, contacts, voxel)
    assert flagged == [("s5", "b")]
    f = results[5].fits["b"]
    assert f.status == "joint_outlier" and f.extra["eq1_miss_mm"] > 2.0 and "j1" in f.stop
    assert results[5].fits["c"].status == "parent_flagged"
    assert all(x.ok for s in results if s.scan_id != "s5" for x in s.fits.values())
    # No outlier: nothing flagged (the misses are noise, a few tenths of a millimetre).
    sk, clean, contacts = _chain_results(np.random.default_rng(4), 8)
    assert flag_joint_outliers(clean, sk, contacts, voxel) == []
    # A miss below half a voxel is never an outlier, whatever the ratio to the median (5 mm voxels here).
    sk, small, contacts = _chain_results(np.random.default_rng(4), 8, outlier=5, offset_mm=2.0)
    assert flag_joint_outliers(small, sk, contacts, {s.scan_id: 5.0 for s in small}) == []
    # Too few scans to tell (3 motions for 3 unknowns): left alone.
    sk, few, contacts = _chain_results(np.random.default_rng(4), 3, outlier=1)
    assert flag_joint_outliers(few, sk, contacts, voxel) == []
