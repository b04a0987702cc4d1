"""`workbench weights`, `model` and `deform`: weight maps, EVD models and posed volumes of a study."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from deformation.geometry import GridGeometry
from deformation.models.skinning import SkinningWeights
from workbench.cli import main
from workbench.errors import InputFileError, OutputExistsError
from workbench.io.volumes import read_labels, read_volume
from workbench.io.weights import read_voxel_weights, write_voxel_weights
from workbench.study import read_study


@pytest.fixture(scope="module")
def study(phantom, tmp_path_factory):
    """A noise-free CT knee (0°, 35°, 70°) with distance weights and an EVD model from the truth."""
    from workbench.study import write_phantom_study

    root = write_phantom_study(
        phantom("knee", size="test", modality="ct", n_poses=3, seed=2, noise=False),
        tmp_path_factory.mktemp("cli-deform") / "study",
    ).root
    assert main(["weights", str(root), "--method", "distance", "--quiet"]) == 0
    assert main(["model", str(root), "--source", "truth", "--quiet"]) == 0
    return root


def _hashes(root):
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_weight_map_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    rot = Rotation.from_euler("xyz", [10.0, -20.0, 35.0], degrees=True).as_matrix()
    g = GridGeometry((5, 4, 3), (1.5, 0.7, 2.2), (10.0, -3.0, 4.0), tuple(rot.ravel()))
    w = SkinningWeights.from_dense(rng.random((g.n_voxels, 6)) ** 4, list("abcdef"))
    write_voxel_weights(w, g, tmp_path / "w.json", method="test")
    back, g2, meta = read_voxel_weights(tmp_path / "w.json")
    assert g2.is_close(g, rtol=0, atol_mm=0)  # MetaImage stores 17 digits: exact
    np.testing.assert_array_equal(back.index, w.index)
    np.testing.assert_array_equal(back.value, w.value)
    assert back.bones == w.bones and meta["method"] == "test"
    with pytest.raises(OutputExistsError):
        write_voxel_weights(w, g, tmp_path / "w.json")


def test_weights_stage_writes_a_partition_of_unity_on_the_template_grid(study):
    s = read_study(study)
    w, g, meta = read_voxel_weights(study / "skinning" / "weights.json")
    assert g.is_close(s.template().geometry)
    dense = w.dense()
    np.testing.assert_allclose(dense.sum(1), 1.0, atol=1e-6)  # float32 storage
    lab = s.template_labels().data.reshape(-1)
    sk = s.skeleton()
    for b in sk.bone_names:  # bone voxels are one-hot on their bone
        np.testing.assert_array_equal(dense[lab == sk.label_of(b), w.bones.index(b)], 1.0)
    assert s.stage_entry("weights")["outputs"]["weights.json"] == "skinning/weights.json"
    body = read_labels(study / "skinning" / "body_mask.nii.gz").data
    # the segmented body holds every bone
    assert np.all(body[s.template_labels().data > 0] == 1)


def _cc(a, b):
    return float(np.corrcoef(a, b)[0, 1])


def test_deform_at_a_training_pose_reproduces_the_scan(study, tmp_path):
    s = read_study(study)
    out = tmp_path / "p2.nii.gz"
    assert (
        main(
            [
                "deform",
                str(study),
                "--pose",
                str(study / "truth" / "pose02_pose.json"),
                "--out",
                str(out),
                "--field-out",
                str(tmp_path / "p2_field.mha"),
                "--quiet",
            ]
        )
        == 0
    )
    posed = read_volume(out)
    assert posed.geometry.is_close(s.template().geometry)
    labels = read_labels(tmp_path / "p2_labels.nii.gz")
    scan = s.scan("pose02")
    truth = s.truth_correspondence("pose02")
    phi = truth.data.reshape(-1, 3) + truth.geometry.world_coordinates().reshape(-1, 3)
    # compare where the scan shows the body and its template position lies in the template's field of view
    m = (scan.data.reshape(-1) > -500) & truth.geometry.contains_world(phi)
    cc = _cc(posed.data.reshape(-1)[m], scan.data.reshape(-1)[m])
    # EVD at a training pose with the exact correspondences (Rhee's "reproduces the training volume");
    # not 1: bone edges in the scan are blurred in the bones' frames, and ≈1 % of the body folds at 70°.
    assert cc >= 0.98, cc
    # the posed label map puts each bone where the truth does (nearest-neighbour labels)
    t_lab = s.template_labels()
    sampled = sitk.GetArrayFromImage(
        sitk.Resample(
            t_lab.to_sitk(),
            scan.to_sitk(),
            sitk.DisplacementFieldTransform(sitk.Cast(truth.to_sitk(), sitk.sitkVectorFloat64)),
            sitk.sitkNearestNeighbor,
            0,
        )
    )
    bone = sampled.reshape(-1)[m] > 0
    agree = np.mean(labels.data.reshape(-1)[m][bone] == sampled.reshape(-1)[m][bone])
    assert agree > 0.97, agree  # bone voxels: the boundary layer (one voxel) may differ
    # the field written maps the posed grid to the template: resampling the template through it
    # with SimpleITK gives the posed volume back (the same trilinear interpolation)
    field = sitk.ReadImage(str(tmp_path / "p2_field.mha"))
    again = sitk.GetArrayFromImage(
        sitk.Resample(
            s.template().to_sitk(),
            scan.to_sitk(),
            sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64)),
            sitk.sitkLinear,
            0.0,
        )
    )
    assert _cc(again.reshape(-1)[m], posed.data.reshape(-1)[m]) > 0.999


def test_deform_with_joint_angles_and_vbd(study, tmp_path):
    pose = tmp_path / "bend.json"
    pose.write_text(json.dumps({"angles": {"knee": [35, 0, 0]}}))
    before = _hashes(study)
    out = tmp_path / "bend.mha"
    assert main(["deform", str(study), "--pose", str(pose), "--out", str(out), "--method", "vbd", "--quiet"]) == 0
    assert _hashes(study) == before  # inputs are never modified
    v = read_volume(out)
    t = read_study(study).template()
    # the bend moves the shin: the posed volume differs from the template, yet keeps its intensity range
    assert np.mean(np.abs(v.data - t.data) > 100) > 0.01
    assert v.data.min() >= t.data.min() - 1e-3 and v.data.max() <= t.data.max() + 1e-3
    # refuses to overwrite without --force
    assert main(["deform", str(study), "--pose", str(pose), "--out", str(out), "--quiet"]) == 1
    # --map-factor 2: the maps on every other voxel, the template pulled at full resolution, on the same grid;
    # the test knee's 5 mm grid gives a 10 mm map, so only the grid and the bulk agreement are checked here (the
    # accuracy is measured in tests/deformation/models/test_evd.py and benchmarks/bench_deformation.py)
    coarse = tmp_path / "bend2.mha"
    assert (
        main(
            [
                "deform",
                str(study),
                "--pose",
                str(pose),
                "--out",
                str(coarse),
                "--method",
                "vbd",
                "--map-factor",
                "2",
                "--quiet",
            ]
        )
        == 0
    )
    c = read_volume(coarse)
    assert c.geometry.is_close(v.geometry)
    assert not np.array_equal(c.data, v.data)  # the option took effect: a blended map, not the exact one
    assert np.median(np.abs(c.data - v.data)) < 0.05 * np.ptp(t.data)  # yet the bulk is the same volume
    with pytest.raises(SystemExit):
        main(["deform", str(study), "--pose", str(pose), "--out", str(tmp_path / "z.mha"), "--map-factor", "0"])


def test_deform_reports_bad_input(study, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"angles": {"elbow": [10]}}))
    assert main(["deform", str(study), "--pose", str(bad), "--out", str(tmp_path / "x.nii.gz")]) == 1
    err = capsys.readouterr().err
    assert "bad.json" in err and "elbow" in err
    assert not (tmp_path / "x.nii.gz").exists()
    good = study / "truth" / "pose01_pose.json"
    # outputs are checked before any work: a clash with the study's own files, or with each other
    assert (
        main(["deform", str(study), "--pose", str(good), "--out", str(study / "template.nii.gz"), "--force", "--quiet"])
        == 1
    )
    assert "study's own files" in capsys.readouterr().err
    assert (
        main(
            [
                "deform",
                str(study),
                "--pose",
                str(good),
                "--out",
                str(tmp_path / "a.nii.gz"),
                "--labels-out",
                str(tmp_path / "a.nii.gz"),
                "--quiet",
            ]
        )
        == 1
    )
    assert (
        main(
            [
                "deform",
                str(study),
                "--pose",
                str(good),
                "--out",
                str(tmp_path / "a.nii.gz"),
                "--field-out",
                str(tmp_path / "f.xyz"),
                "--quiet",
            ]
        )
        == 1
    )
    assert not (tmp_path / "a.nii.gz").exists()
    # an output into a missing folder: one line naming the option and the fix, before any work, nothing
    # written (the posed volume used to be written first and a rerun then hit "exists")
    for opt in ("--field-out", "--labels-out"):
        capsys.readouterr()
        assert (
            main(
                [
                    "deform",
                    str(study),
                    "--pose",
                    str(good),
                    "--out",
                    str(tmp_path / "b.nii.gz"),
                    opt,
                    str(tmp_path / "missing" / "f.nii.gz"),
                ]
            )
            == 1
        )
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and opt in err[0] and "does not exist" in err[0] and "mkdir -p" in err[0], err
        assert not (tmp_path / "b.nii.gz").exists() and not (tmp_path / "b_labels.nii.gz").exists()
    s = read_study(study)
    with pytest.raises(InputFileError, match="workbench weights"):
        type(s)(s.root, {**s.manifest, "stages": {}}).weights()  # a study whose weights stage has not run


# slow: ~25 s (a phantom, two weights runs and a model); the weights stage's distance path and the harmonic
# solve itself (tests/deformation/models/test_harmonic.py, test_lattice_tetmesh.py) stay in the default suite
@pytest.mark.slow
def test_harmonic_weights_are_the_same_bytes_when_rerun(phantom, tmp_path):
    """The lattice mesh is a function of the body mask and the step: a forced rerun rewrites identical files."""
    from workbench.study import write_phantom_study

    root = write_phantom_study(phantom("knee", size="test", modality="ct", n_poses=1, seed=5), tmp_path / "study").root
    assert main(["weights", str(root), "--edge-length-mm", "14", "--quiet"]) == 0
    files = ("tetmesh.vtu", "weights_index.mha", "weights_value.mha")
    first = {f: hashlib.sha256((root / "skinning" / f).read_bytes()).hexdigest() for f in files}
    assert main(["weights", str(root), "--quiet"]) == 0  # up to date: skipped, nothing rewritten
    assert {f: hashlib.sha256((root / "skinning" / f).read_bytes()).hexdigest() for f in files} == first
    assert main(["weights", str(root), "--force", "--quiet"]) == 0
    again = {f: hashlib.sha256((root / "skinning" / f).read_bytes()).hexdigest() for f in files}
    assert again == first
    w, g, meta = read_voxel_weights(root / "skinning" / "weights.json")
    s = read_study(root)
    lab = s.template_labels().data.reshape(-1)
    dense = w.dense()
    np.testing.assert_allclose(dense.sum(1), 1.0, atol=1e-6)  # float32 storage
    for b in s.skeleton().bone_names:
        np.testing.assert_array_equal(dense[lab == s.skeleton().label_of(b), w.bones.index(b)], 1.0)
    assert meta["method"] == "harmonic"
    assert meta["lattice_step"] == [3, 3, 4]  # 14 mm on the 4.98×4.98×3.69 mm grid: 2.8, 2.8, 3.8 voxels
    # an EVD model is tied to the weights it was built with
    assert main(["model", str(root), "--source", "truth", "--quiet"]) == 0
    # distance weights replace the weights (no tet mesh) ...
    assert main(["weights", str(root), "--method", "distance", "--force", "--quiet"]) == 0
    assert not (root / "skinning" / "tetmesh.vtu").exists()
    # ... and the model built on the harmonic weights is now refused
    with pytest.raises(InputFileError, match="other skinning weights"):
        read_study(root).model()
    # ... and the model stage knows it is out of date
    from workbench.stages import STAGES
    from workbench.stages.mechanism import stage_status

    assert stage_status(read_study(root), STAGES["model"], registry=STAGES) == "stale"


def test_angles_outside_the_range_of_motion_or_as_strings_are_refused(study, tmp_path, capsys):
    """A 1000° knee used to be posed into a mangled volume; an angle given as a string was read silently.
    Both are one line naming the file, the joint and the fix, and nothing is written."""
    for angles, expect in (
        ({"knee": [1000, 0, 0]}, "knee[0] = 1000° outside [-10, 150]"),
        ({"knee": [20, 40, 0]}, "knee[1] = 40° outside [-15, 15]"),
        ({"knee": ["30", 0, 0]}, "needs a list of numbers"),
    ):
        pose = tmp_path / "p.json"
        pose.write_text(json.dumps({"angles": angles}))
        capsys.readouterr()
        assert main(["deform", str(study), "--pose", str(pose), "--out", str(tmp_path / "o.nii.gz")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "p.json" in err[0] and expect in err[0], err
        assert not (tmp_path / "o.nii.gz").exists()
    # the study's skeleton.json carries the limits (an older one without them checks nothing)
    sk = json.loads((study / "skeleton.json").read_text(encoding="utf-8"))
    assert {j["name"]: j["limits"][0] for j in sk["joints"]}["knee"] == [-10.0, 150.0]


def test_a_one_dof_joint_takes_a_number_alone(tmp_path):
    from deformation.kinematics.skeleton import Bone, Joint, Skeleton
    from workbench.io.inputs import read_target_pose

    sk = Skeleton(
        [Bone("upper", 1, None), Bone("fore", 2, "upper")],
        [Joint("elbow", "upper", "fore", 1, (0.0, 0.0, 0.0), limits=((0, 150),))],
        name="arm",
    )
    p = tmp_path / "p.json"
    p.write_text(json.dumps({"angles": {"elbow": 30}}))
    assert read_target_pose(p, sk).joint_angles["elbow"].tolist() == [30.0]
    p.write_text(json.dumps({"angles": {"elbow": 170}}))
    with pytest.raises(InputFileError, match=r"elbow\[0\] = 170° outside \[0, 150\]"):
        read_target_pose(p, sk)


@pytest.mark.slow  # ~14 s: a template at twice the test size's voxels per axis (`make test-slow`)
def test_weights_on_every_other_voxel_pose_the_full_resolution_template(phantom, tmp_path, capsys, monkeypatch):
    """`workbench weights --grid-factor 2` (what a Kurihara-size CT gets by default): the weights and body
    mask on every 2nd template voxel; `deform` solves its maps there and writes the posed volume on the
    template's full grid, close to the exact full-grid deformation; the stages that need full-grid weights
    (init, model) and EVD say so in one line, and so does another --map-factor."""
    from workbench.study import write_phantom_study

    root = write_phantom_study(
        phantom("knee", size="test", modality="ct", n_poses=2, seed=4, noise=False), tmp_path / "study"
    ).root
    pose = tmp_path / "bend.json"
    pose.write_text(json.dumps({"angles": {"knee": [40, 0, 0]}}))
    t = read_study(root).template()
    assert main(["weights", str(root), "--method", "distance", "--quiet"]) == 0
    exact = tmp_path / "exact.nii.gz"
    assert main(["deform", str(root), "--pose", str(pose), "--out", str(exact), "--method", "vbd", "--quiet"]) == 0
    # a model from the full-grid weights stays in the study: the coarse weights pose by VBD all the same
    assert main(["model", str(root), "--source", "truth", "--quiet"]) == 0
    model_json = (root / "model" / "evd.json").read_bytes()
    assert main(["weights", str(root), "--method", "distance", "--grid-factor", "2", "--quiet"]) == 0
    w, g, meta = read_voxel_weights(root / "skinning" / "weights.json")
    assert g.is_close(t.geometry.every(2)) and meta["grid_factor"] == 2 and w.n_points == g.n_voxels
    assert read_labels(root / "skinning" / "body_mask.nii.gz").geometry.is_close(g)
    before = _hashes(root)
    out = tmp_path / "coarse.nii.gz"
    assert main(["deform", str(root), "--pose", str(pose), "--out", str(out)]) == 0
    said = capsys.readouterr()
    assert "every 2nd template voxel: posing by VBD" in said.err + said.out
    assert _hashes(root) == before
    v, e = read_volume(out), read_volume(exact)
    assert v.geometry.is_close(t.geometry)  # the full grid, not the weights'
    # the same posed knee: the coarse distance weights and the blended map move a few voxels by a fraction of
    # a voxel (this 5 mm test grid makes a 10 mm map), so the bulk agrees and the labels almost everywhere
    assert np.median(np.abs(v.data - e.data)) < 0.02 * np.ptp(t.data)
    lv, le = read_labels(tmp_path / "coarse_labels.nii.gz"), read_labels(tmp_path / "exact_labels.nii.gz")
    bone = (lv.data > 0) | (le.data > 0)
    assert (lv.data == le.data)[bone].mean() > 0.85
    for argv, match in (
        (
            ["deform", str(root), "--pose", str(pose), "--out", str(tmp_path / "m.nii.gz"), "--map-factor", "3"],
            "--map-factor",
        ),
        (
            ["deform", str(root), "--pose", str(pose), "--out", str(tmp_path / "e.nii.gz"), "--method", "evd"],
            "--method vbd",
        ),
        (["register", str(root), "--init", "vbd", "--force"], "--grid-factor 1"),
        # every 6th voxel of this 5 mm knee (30 mm) holds none of the fibula's
        (["weights", str(root), "--method", "distance", "--grid-factor", "6"], "fibula"),
        (["model", str(root), "--source", "truth", "--force"], "--grid-factor 1"),
        # VBD has no expected error: refused once the poser is known, before any posing or writing
        (
            [
                "deform",
                str(root),
                "--pose",
                str(pose),
                "--out",
                str(tmp_path / "u.nii.gz"),
                "--uncertainty-out",
                str(tmp_path / "u_sigma.nii.gz"),
            ],
            "--uncertainty-out",
        ),
    ):
        assert main(argv + ["--quiet"]) == 1, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], (argv, err)
    assert (root / "model" / "evd.json").read_bytes() == model_json  # the refused model stage wrote nothing
    assert not (tmp_path / "u.nii.gz").exists() and not (tmp_path / "u_sigma.nii.gz").exists()
    # the VBD start itself takes the coarse weights (register needs full-grid ones, above): its field lies on
    # the scan's full grid, blended up from the maps solved on every 2nd voxel
    st = read_study(root)
    # the refusal comes from the images' headers, before the map's voxels are read
    import workbench.io.weights as weights_io

    with monkeypatch.context() as m:
        m.setattr(weights_io, "read_voxel_weights", lambda *a, **k: pytest.fail("the weight map was read"))
        with pytest.raises(InputFileError, match="--grid-factor 1"):
            st.weights()
    for sid in st.scan_ids:
        f = st.init_field(sid)
        assert f.geometry.is_close(st.scan(sid).geometry) and st.init_info(sid)["backward_map"]["map_factor"] == 2


def test_deform_writes_the_posed_expected_error(study, tmp_path, capsys):
    """Issue R, item 2: ``--uncertainty-out`` writes the model's expected error on the posed grid.  The model
    here is built from the truth (exact maps: no scan error), so σ is the cross-validated pose interpolation's
    alone: at a training pose the poses explain themselves (γ = 1) and σ vanishes over the body (float: 1e-3
    mm); bent past the range (110°) it is larger than between the examples (52°).  Asking for it with VBD is
    refused in one line before any work, and writes nothing."""
    s = read_study(study)
    out = tmp_path / "p2.nii.gz"
    sig = tmp_path / "p2_sigma.nii.gz"
    args = ["deform", str(study), "--pose", str(study / "truth" / "pose02_pose.json"), "--out", str(out)]
    assert main(args + ["--uncertainty-out", str(sig), "--quiet"]) == 0
    sigma = read_volume(sig)
    assert sigma.geometry.is_close(s.template().geometry)
    posed_body = read_labels(tmp_path / "p2_labels.nii.gz").data > 0  # the posed bones: inside the body
    assert float(sigma.data[posed_body].max()) < 1e-3
    med = {}
    for bend in (52, 110):
        pose = tmp_path / f"bend{bend}.json"
        pose.write_text(json.dumps({"angles": {"knee": [bend, 0, 0]}}))
        o = tmp_path / f"b{bend}.nii.gz"
        su = tmp_path / f"b{bend}_sigma.nii.gz"
        assert main(["deform", str(study), "--pose", str(pose), "--out", str(o), "--uncertainty-out", str(su)]) == 0
        lab = read_labels(tmp_path / f"b{bend}_labels.nii.gz").data > 0
        med[bend] = float(np.median(read_volume(su).data[lab]))
        assert "expected error over the posed body" in capsys.readouterr().out
    assert 0 < med[52] < med[110], med
    capsys.readouterr()
    bad = tmp_path / "vbd_sigma.nii.gz"
    assert main(args[:-1] + [str(tmp_path / "v.nii.gz"), "--method", "vbd", "--uncertainty-out", str(bad)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--uncertainty-out" in err[0] and "leave --method vbd out" in err[0], err
    assert not bad.exists() and not (tmp_path / "v.nii.gz").exists()
