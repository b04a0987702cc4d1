"""`workbench` command line: phantom studies on disk, their manifest, errors."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from deformation.kinematics.transforms import apply
from workbench import __version__
from workbench.cli import main
from workbench.io.volumes import read_image_geometry
from workbench.study import read_study


def _digest(folder: Path) -> dict:
    """SHA-256 of every file except the (timing) log."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and "logs" not in p.parts
    }


@pytest.fixture(scope="module")
def knee_study(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "knee"
    assert main(["phantom", "knee", "--out", str(out), "--poses", "2", "--seed", "4", "--quiet"]) == 0
    return out


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and __version__ in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["phantom", "--help"])
    text = capsys.readouterr().out
    assert "--poses-file" in text and "scan-to-template" in text.replace("\n", " ").replace("  ", " ")


def test_the_parser_imports_no_stage_nor_protocol_and_takes_the_protocols_tables_in_their_order():
    """`workbench --help` stays fast: building the whole parser imports the CLI's modules only; `reproduce`'s
    tables are validation.protocols' names, in its order, then 'all'."""
    code = (
        "import sys; from workbench.cli import build_parser; build_parser().format_help(); "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('workbench', 'validation', 'registration', "
        "'deformation', 'numpy') and not m.startswith('workbench.cli')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['workbench']"
    from validation.protocols import PROTOCOLS
    from workbench.cli import build_parser
    from workbench.cli.reproduce import TableNames

    assert list(TableNames()) == [*PROTOCOLS, "all"]
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["reproduce", "table5", "--out", "x"])
    assert e.value.code == 2


def test_python_dash_m_runs():
    r = subprocess.run(
        [sys.executable, "-m", "workbench", "--version"], capture_output=True, text=True, encoding="utf-8", check=True
    )
    assert __version__ in r.stdout


def test_study_manifest_and_geometry(knee_study):
    study = read_study(knee_study)
    m = study.manifest
    assert m["format"] == "avw-study" and len(m["scans"]) == 2
    for key in ("template", "template_labels", "skeleton"):
        assert (knee_study / m[key]).is_file()
    g = read_image_geometry(knee_study / m["template"])
    # Test-size knee grid: 64×64×40 voxels covering Rhee's 318.75×318.75×147.6 mm field of view.
    assert g.size == (64, 64, 40)
    np.testing.assert_allclose(np.array(g.size) * np.array(g.spacing), (318.75, 318.75, 147.6), rtol=1e-6)
    labels = study.template_labels()
    assert set(np.unique(labels.data)) == {0, 1, 2, 3, 4}
    sk = study.skeleton()
    assert [b.name for b in sk.bones] == ["femur", "tibia", "fibula", "patella"]


def test_written_truth_resamples_template_onto_scan(tmp_path):
    out = tmp_path / "clean"
    assert main(["phantom", "knee", "--out", str(out), "--poses", "2", "--noise-free", "--quiet"]) == 0
    study = read_study(out)
    sid = study.scan_ids[-1]
    template = sitk.ReadImage(str(out / study.manifest["template"]))
    scan = sitk.ReadImage(str(out / study.manifest["scans"][-1]["image"]))
    field = sitk.ReadImage(str(out / study.manifest["scans"][-1]["truth"]["correspondence"]))
    assert field.GetPixelID() == sitk.sitkVectorFloat64  # usable by DisplacementFieldTransform as is
    outside = -1e6  # marks scan voxels whose template position lies outside the template's grid
    warped = sitk.GetArrayFromImage(
        sitk.Resample(template, scan, sitk.DisplacementFieldTransform(field), sitk.sitkLinear, outside)
    )
    a = sitk.GetArrayFromImage(scan)
    body = (a > 200) & (warped > outside / 2)  # soft tissue and marrow (MRI air is 0 without noise)
    # Linear interpolation of the template on the 5 mm test grid is the only error source.
    assert np.corrcoef(warped[body], a[body])[0, 1] > 0.99
    # Markers and pose agree with each other through the skeleton.
    pose = study.truth_pose(sid)
    markers = study.truth_markers(sid)
    assert len(markers) >= 8
    femur = study.skeleton().joint("knee")
    np.testing.assert_allclose(pose.joint_centers["knee"], apply(pose.transforms["femur"], femur.center))


def test_same_seed_identical_files_other_seed_different(tmp_path, knee_study):
    again = tmp_path / "again"
    other = tmp_path / "other"
    assert main(["phantom", "knee", "--out", str(again), "--poses", "2", "--seed", "4", "--quiet"]) == 0
    assert main(["phantom", "knee", "--out", str(other), "--poses", "2", "--seed", "5", "--quiet"]) == 0
    assert _digest(knee_study) == _digest(again)
    d1, d2 = _digest(knee_study), _digest(other)
    assert d1["template.nii.gz"] != d2["template.nii.gz"]
    assert d1["skeleton.json"] == d2["skeleton.json"]


def test_refuses_to_overwrite_and_force_replaces(tmp_path, capsys):
    out = tmp_path / "s"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["phantom", "knee", "--out", str(out), "--poses", "1", "--quiet"]) == 1
    assert "--force" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert main(["phantom", "knee", "--out", str(out), "--poses", "1", "--quiet", "--force"]) == 0
    assert (out / "study.json").is_file() and not (out / "keep.txt").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left behind


def test_poses_file_and_its_errors(tmp_path, capsys):
    pf = tmp_path / "bend10.json"
    pf.write_text(json.dumps({"poses": [{"id": "bend10", "angles": {"knee": [10, 0, 0]}}]}))
    out = tmp_path / "bend"
    assert main(["phantom", "knee", "--out", str(out), "--poses-file", str(pf), "--posing", "vbd", "--quiet"]) == 0
    study = read_study(out)
    assert study.scan_ids == ["bend10"]
    pose = study.truth_pose("bend10")
    assert pose.joint_angles["knee"][0] == 10.0
    assert pose.joint_angles["tibiofibular"][0] == 10.0  # the fibula follows the tibia
    assert pose.joint_angles["patellofemoral"][0] == pytest.approx(7.0)

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"poses": [{"id": "x", "angles": {"elbow": [10]}}]}))
    assert main(["phantom", "knee", "--out", str(tmp_path / "x"), "--poses-file", str(bad), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "bad.json" in err and "elbow" in err
    assert not (tmp_path / "x").exists()
    wrong_dof = tmp_path / "dof.json"
    wrong_dof.write_text(json.dumps({"poses": [{"id": "x", "angles": {"knee": [10]}}]}))
    assert main(["phantom", "knee", "--out", str(tmp_path / "y"), "--poses-file", str(wrong_dof), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "3 DOF" in err and "dof.json" in err
    assert not (tmp_path / "y").exists()


def test_info_prints_summary(knee_study, capsys):
    assert main(["info", str(knee_study)]) == 0
    out = capsys.readouterr().out
    assert "femur" in out and "pose01" in out and "64, 64, 40" in out


def test_info_on_missing_study(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nothing")]) == 1
    assert "no such study folder" in capsys.readouterr().err


def test_poses_file_with_a_number_instead_of_a_list(tmp_path, capsys):
    pf = tmp_path / "scalar.json"
    pf.write_text(json.dumps({"poses": [{"id": "x", "angles": {"knee": 10}}]}))
    assert main(["phantom", "knee", "--out", str(tmp_path / "s"), "--poses-file", str(pf), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "scalar.json" in err and "list of numbers" in err


def test_info_on_manifest_with_bad_truth(knee_study, tmp_path, capsys):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(knee_study, copy)
    m = json.loads((copy / "study.json").read_text(encoding="utf-8"))
    m["scans"][0]["truth"] = "not an object"
    (copy / "study.json").write_text(json.dumps(m))
    assert main(["info", str(copy)]) == 1
    assert "['truth'] must name" in capsys.readouterr().err


def test_a_hand_written_manifest_without_format_is_told_what_to_add(tmp_path, capsys):
    d = tmp_path / "mine"
    d.mkdir()
    (d / "study.json").write_text(json.dumps({"template": "t.nii.gz", "skeleton": "s.json", "scans": []}))
    assert main(["info", str(d)]) == 1
    err = capsys.readouterr().err
    assert '"format": "avw-study"' in err and "study.json" in err


def test_info_check_reads_every_image_and_clean_image_repairs_a_nan_scan(knee_study, tmp_path, capsys):
    """A scan with NaN voxels: `info` alone reads no image and says nothing; `info --check` names the file and
    the command that repairs it; `clean-image` writes a copy (input kept) that passes."""
    import shutil

    import numpy as np

    from workbench.io.volumes import read_volume, write_volume

    copy = tmp_path / "copy"
    shutil.copytree(knee_study, copy)
    m = json.loads((copy / "study.json").read_text(encoding="utf-8"))
    scan = copy / m["scans"][1]["image"]
    v = read_volume(scan)
    data = np.array(v.data)
    data[3, 4, 5] = np.nan
    data[0, 0, 0] = np.inf
    write_volume(type(v)(data, v.geometry), scan, overwrite=True, allow_nonfinite=True)
    assert main(["info", str(copy)]) == 0
    capsys.readouterr()
    assert main(["info", str(copy), "--check"]) == 1
    err = capsys.readouterr().err
    assert "1 problem" in err and str(scan) in err and "2 of" in err and "workbench clean-image" in err
    assert "allow_nonfinite" not in err  # no Python argument offered on the command line
    # the pose stage reads every scan before fitting any bone: the NaN scan (the second) is said first
    assert main(["pose", str(copy)]) == 1
    err = capsys.readouterr().err
    assert str(scan) in err and "workbench clean-image" in err and "bone 1/" not in err, err
    fixed = tmp_path / "fixed.nii.gz"
    assert main(["clean-image", str(scan), "--out", str(fixed)]) == 0
    assert "2 of" in capsys.readouterr().out
    c = read_volume(fixed)
    finite = data[np.isfinite(data)]
    assert c.data[3, 4, 5] == finite.min() and c.data[0, 0, 0] == finite.min()
    assert c.geometry.is_close(v.geometry)
    np.testing.assert_array_equal(c.data[np.isfinite(data)], finite)
    assert not np.isfinite(read_volume(scan, allow_nonfinite=True).data).all()  # the input is kept as it was
    shutil.copyfile(fixed, scan)
    assert main(["info", str(copy), "--check"]) == 0
    assert "no problem found" in capsys.readouterr().out


def test_poses_file_outside_the_range_of_motion_or_with_strings(tmp_path, capsys):
    for angles, expect in (
        ({"knee": [1000, 0, 0]}, "knee[0] = 1000° outside [-10, 150]"),
        ({"knee": ["30", 0, 0]}, "list of numbers"),
    ):
        pf = tmp_path / "poses.json"
        pf.write_text(json.dumps({"poses": [{"id": "x", "angles": angles}]}))
        capsys.readouterr()
        assert main(["phantom", "knee", "--out", str(tmp_path / "s"), "--poses-file", str(pf), "--quiet"]) == 1
        err = capsys.readouterr().err
        assert expect in err and "poses.json" in err and not (tmp_path / "s").exists(), err
