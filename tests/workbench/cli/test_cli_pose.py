"""`workbench pose`: writes estimated poses into a study, names them in study.json, refuses to clobber."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest

from deformation.kinematics.transforms import compose, invert, rotation_angle_deg
from workbench.cli import main
from workbench.study import read_study


@pytest.fixture(scope="module")
def small_ct_study(phantom, tmp_path_factory):
    from workbench.study import write_phantom_study

    return write_phantom_study(
        phantom("knee", size="test", modality="ct", n_poses=2, seed=7),
        tmp_path_factory.mktemp("cli-pose") / "study",
    ).root


def _write_seeds(study, path):
    """A seeds file with one point deep inside each bone of the study's label map."""
    from registration.segmentation import seeds_from_labels

    seeds = seeds_from_labels(study.template_labels(), study.skeleton())
    path.write_text(
        json.dumps(
            {"format": "avw-seeds", "version": 1, "units": "mm", "seeds": {b: p.tolist() for b, p in seeds.items()}}
        )
    )
    return path


def _hashes(root):
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
        and p.relative_to(root).parts[0] not in ("poses", "bones", ".locks")
        and p.name not in ("study.json", ".study.json.lock")
    }


def test_pose_writes_into_the_study(tmp_path, small_ct_study, capsys):
    root = tmp_path / "study"
    shutil.copytree(small_ct_study, root)
    before = _hashes(root)
    assert main(["pose", str(root), "--scan", "pose01", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "workbench validate" in out and "knee" in out  # the pose stage does not read the truth
    st = read_study(root)
    assert st.has_pose("pose01") and not st.has_pose("pose00")
    stage = st.stage_entry("pose")
    assert stage["outputs"]["pose01_pose.json"] == "poses/pose01_pose.json"
    assert stage["settings"]["method"] == "intensity" and stage["settings"]["scans"] == ["pose01"]
    assert st.pose_report()["failures"] == []
    assert "truth" not in json.dumps(stage["inputs"])  # its digest covers images, labels and skeleton only
    # Estimate and truth share a schema, so they compare directly.  3.5° is the worst bone over the test-size
    # knee benchmark (2.9°, the patella; the tibia's worst is 2.1°) plus margin.
    est, truth = st.pose("pose01"), st.truth_pose("pose01")
    err = rotation_angle_deg(compose(invert(truth.transforms["tibia"]), est.transforms["tibia"]))
    assert err < 3.5, err
    assert set(est.joint_angles) == set(truth.joint_angles)
    joints = json.loads((root / "poses" / "joints.json").read_text(encoding="utf-8"))
    assert joints["format"] == "avw-joints" and set(joints["joints"]) == {"knee", "tibiofibular", "patellofemoral"}
    vec = json.loads((root / "poses" / "pose_vectors.json").read_text(encoding="utf-8"))
    assert len(vec["scans"]["pose01"]) == sum(vec["dof"]) == 9
    np.testing.assert_allclose(vec["scans"]["pose01"][:3], est.joint_angles["knee"])
    frames = json.loads((root / "bones" / "bone_frames.json").read_text(encoding="utf-8"))
    assert set(frames["bones"]) == {"femur", "tibia", "fibula", "patella"}
    fits = json.loads((root / "poses" / "fits.json").read_text(encoding="utf-8"))
    assert fits["scans"]["pose01"]["bones"]["tibia"]["status"] == "ok"
    assert 0.0 <= fits["scans"]["pose01"]["bones"]["tibia"]["joint_gap_mm"] < 2.0  # a kept joint (see test_pose)
    assert _hashes(root) == before  # no input file touched

    # The same command again is up to date: skipped, and the study is left as it was.
    manifest = (root / "study.json").read_bytes()
    assert main(["pose", str(root), "--scan", "pose01"]) == 0
    assert "pose: up to date, skipped" in capsys.readouterr().err
    assert (root / "study.json").read_bytes() == manifest

    # Unknown scans are named.
    assert main(["pose", str(root), "--scan", "nope", "--force", "--quiet"]) == 1
    assert "pose00" in capsys.readouterr().err
    assert (root / "study.json").read_bytes() == manifest


def test_pose_with_seeds_segments_the_template(tmp_path, small_ct_study, capsys):
    root = tmp_path / "study"
    shutil.copytree(small_ct_study, root)
    st = read_study(root)
    sf = _write_seeds(st, tmp_path / "seeds.json")
    assert main(["pose", str(root), "--scan", "pose00", "--seeds", str(sf), "--quiet"]) == 0
    capsys.readouterr()
    st = read_study(root)
    assert st.template_labels_path() == root / "bones" / "template_labels.nii.gz"  # what every stage uses now
    assert st.stage_entry("bones")["settings"]["source"] == "seeds"
    seg = json.loads((root / "bones" / "segmentation.json").read_text(encoding="utf-8"))
    assert seg["method"].startswith("ct") and all(v > 0 for v in seg["voxels"].values())
    # pose00 is the straight leg: every bone's true transform is the identity.  Segmented regions differ
    # from the exact labels at the rim only, so the bones stay within 2° and 0.5 mm (at their centroids).
    est = st.pose("pose00")
    lab = st.template_labels()
    for b, t in est.transforms.items():
        k, j, i = np.nonzero(lab.data == st.skeleton().label_of(b))
        c = lab.geometry.index_to_world(np.column_stack([i, j, k]).astype(float)).mean(axis=0)
        assert rotation_angle_deg(t) < 2.0, (b, rotation_angle_deg(t))
        assert np.linalg.norm(t[:3, :3] @ c + t[:3, 3] - c) < 0.5, b


def test_pose_help_teaches_the_schema(capsys):
    with pytest.raises(SystemExit):
        main(["pose", "--help"])
    text = capsys.readouterr().out
    assert "avw-seeds" in text and "--method" in text and "intrinsic XYZ" in text


def test_initial_pose_file_formats(tmp_path, small_ct_study):
    from workbench.errors import InputFileError
    from workbench.io.inputs import read_initial_poses

    st = read_study(small_ct_study)
    sk = st.skeleton()
    t = np.eye(4)
    t[:3, 3] = (5.0, 0.0, -2.0)
    p = tmp_path / "init.json"
    p.write_text(json.dumps({"format": "avw-initial-poses", "version": 1, "scans": {"pose01": t.tolist()}}))
    got = read_initial_poses(p, st.scan_ids, sk)
    assert set(got) == {"pose01"} and np.allclose(got["pose01"], t)
    # An avw-pose file: its root transform serves every scan.
    p.write_text(json.dumps(st.truth_pose("pose01").to_dict()))
    assert set(read_initial_poses(p, st.scan_ids, sk)) == set(st.scan_ids)
    p.write_text(json.dumps({"format": "avw-initial-poses", "version": 1, "scans": {"nope": t.tolist()}}))
    with pytest.raises(InputFileError, match="unknown scans"):
        read_initial_poses(p, st.scan_ids, sk)
    bad = t.copy()
    bad[0, 0] = 2.0
    p.write_text(json.dumps({"format": "avw-initial-poses", "version": 1, "scans": {"pose01": bad.tolist()}}))
    with pytest.raises(InputFileError, match="init.json"):
        read_initial_poses(p, st.scan_ids, sk)
    p.write_text(json.dumps({"scans": {}}))
    with pytest.raises(InputFileError, match="avw-initial-poses"):
        read_initial_poses(p, st.scan_ids, sk)


def test_study_without_labels_and_a_bone_out_of_view(tmp_path, small_ct_study, capsys):
    """A user's study: no label map (so --seeds is required) and a scan that misses the shank; the
    missing bones are reported in fits.json and report.json (metrics that could not be computed are null)."""
    from workbench.io.volumes import write_volume

    root = tmp_path / "study"
    shutil.copytree(small_ct_study, root)
    st = read_study(root)
    sf = _write_seeds(st, tmp_path / "seeds.json")
    manifest = json.loads((root / "study.json").read_text(encoding="utf-8"))
    del manifest["template_labels"]
    (root / "study.json").write_text(json.dumps(manifest))
    (root / "template_labels.nii.gz").unlink()
    scan = st.scan("pose01")
    cut = scan.crop((0, scan.geometry.size[1] // 2 + 4, 0), scan.geometry.size)  # the shank is gone
    (root / "scans" / "pose01.nii.gz").unlink()
    write_volume(cut, root / "scans" / "pose01.nii.gz")

    assert main(["info", str(root)]) == 0
    assert "no label map" in capsys.readouterr().out
    assert main(["pose", str(root), "--scan", "pose01", "--quiet"]) == 1
    assert "--seeds" in capsys.readouterr().err
    assert main(["pose", str(root), "--scan", "pose01", "--seeds", str(sf), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "tibia" in out and "fibula" in out  # named in the problems column
    report = json.loads((root / "poses" / "report.json").read_text(encoding="utf-8"))
    failed = {f["bone"]: f for f in report["failures"]}
    assert {"tibia", "fibula"} <= set(failed) and all(f["scan"] == "pose01" for f in failed.values())
    fits = json.loads((root / "poses" / "fits.json").read_text(encoding="utf-8"))["scans"]["pose01"]["bones"]
    assert fits["femur"]["status"] == "ok" and fits["tibia"]["status"] != "ok"


def test_pose_refuses_a_negative_joint_gap_limit(small_ct_study, capsys):
    manifest = (small_ct_study / "study.json").read_bytes()
    assert main(["pose", str(small_ct_study), "--max-joint-gap-mm", "-1", "--quiet"]) == 1
    assert "--max-joint-gap-mm" in capsys.readouterr().err
    assert (small_ct_study / "study.json").read_bytes() == manifest


@pytest.mark.parametrize("value", ["-1", "0.5"])
def test_pose_refuses_an_outlier_factor_that_is_not_a_multiple_of_the_median(small_ct_study, capsys, value):
    manifest = (small_ct_study / "study.json").read_bytes()
    assert main(["pose", str(small_ct_study), "--outlier-factor", value, "--quiet"]) == 1
    assert "--outlier-factor" in capsys.readouterr().err
    assert (small_ct_study / "study.json").read_bytes() == manifest


# slow: ~30 s; the stages end to end run in the default suite on the MRI study (tests/workbench/test_run.py),
# the CT study's seeded segmentation and pose stage in the tests above
@pytest.mark.slow
def test_a_ct_study_without_labels_goes_from_seeds_to_an_evd_model(tmp_path, small_ct_study, capsys):
    """A user's CT study with no label map and no truth: pose --seeds segments the bones, and weights,
    register, model (from the registrations) and deform (by EVD) all find those labels."""
    root = tmp_path / "study"
    shutil.copytree(small_ct_study, root, ignore=shutil.ignore_patterns("truth"))
    st = read_study(small_ct_study)
    sf = _write_seeds(st, tmp_path / "seeds.json")
    m = json.loads((root / "study.json").read_text(encoding="utf-8"))
    del m["template_labels"]
    for s in m["scans"]:
        s.pop("truth")
    (root / "study.json").write_text(json.dumps(m))
    (root / "template_labels.nii.gz").unlink()
    assert main(["pose", str(root), "--seeds", str(sf), "--quiet"]) == 0
    assert main(["weights", str(root), "--method", "distance", "--quiet"]) == 0
    assert (
        main(["register", str(root), "--method", "adaptive", "--levels", "3", "3", "--max-steps", "4", "--quiet"]) == 0
    )
    assert main(["model", str(root), "--quiet"]) == 0
    assert "registration correspondences of 2 scans" in capsys.readouterr().out
    st = read_study(root)
    assert st.stage_entry("weights")["inputs"]["labels"]["path"] == "bones/template_labels.nii.gz"
    pose = tmp_path / "bend.json"
    pose.write_text(json.dumps({"angles": {"knee": [20, 0, 0]}}))
    assert main(["deform", str(root), "--pose", str(pose), "--out", str(tmp_path / "bent.nii.gz")]) == 0
    assert "posing by EVD" in capsys.readouterr().err
    assert main(["render", str(root), "--bones", "--out", str(tmp_path / "b.png"), "--size", "64x48", "--quiet"]) in (
        0,
        1,
    )  # 1 only where no OpenGL context exists; it must not ask for --seeds
    assert "--seeds" not in capsys.readouterr().err


# slow (~35 s: a knee at twice the test size's voxels per axis); `make test-slow`
@pytest.mark.slow
def test_pose_on_every_other_voxel_of_a_finer_scan(phantom, tmp_path, capsys):
    """`workbench pose --grid-factor 2` (what a template over 60 M voxels gets by default): template and scans
    smoothed and taken on every 2nd voxel, the bones registered there.  On a knee at half the test size's
    spacing (2.5 mm, so the working grid is the test size's 5 mm) the tibia comes out within the bound of the
    test-size pose test above, and the stage records the factor."""
    from workbench.study import write_phantom_study

    ph = phantom("knee", size="test", modality="ct", n_poses=2, seed=7, spacing=(2.49, 2.49, 1.845))
    root = write_phantom_study(ph, tmp_path / "study").root
    assert main(["pose", str(root), "--grid-factor", "2"]) == 0
    assert "bones registered on every 2nd voxel" in capsys.readouterr().err
    st = read_study(root)
    assert st.pose_report()["grid_factor"] == 2 and st.pose_report()["failures"] == []
    assert st.stage_entry("pose")["settings"]["grid_factor"] == 2
    # a factor that leaves a bone without a voxel is one line naming the option, not a label-id puzzle
    assert main(["pose", str(root), "--grid-factor", "12", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--grid-factor" in err[0] and "no voxel" in err[0], err
    est, truth = st.pose("pose01"), st.truth_pose("pose01")
    err = rotation_angle_deg(compose(invert(truth.transforms["tibia"]), est.transforms["tibia"]))
    assert err < 3.5, err
