"""`workbench register`: files, conventions, manifest, refusals (a tiny budget: this checks plumbing, the
accuracy is tested in tests/registration/test_adaptive.py)."""

import json
import shutil

import numpy as np
import pytest

from deformation.interpolate import sample_displaced_array
from workbench.cli import main
from workbench.study import read_study
from workbench.io.volumes import read_displacement, read_volume

FAST = ["--levels", "3", "3", "--max-steps", "4"]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("reg") / "knee"
    assert main(["phantom", "knee", "--out", str(root), "--size", "test", "--poses", "2", "--quiet"]) == 0
    assert main(["weights", str(root), "--method", "distance", "--quiet"]) == 0
    return root


def test_register_writes_fields_in_the_truth_convention(study, capsys):
    assert main(["register", str(study), "--scan", "pose01", *FAST, "--quiet"]) == 0
    table = capsys.readouterr().out
    assert "| pose01 | registered |" in table and "| pose01 | initialised |" in table
    st = read_study(study)
    entry = next(s for s in st.manifest["scans"] if s["id"] == "pose01")["registration"]
    assert entry["init"] == "vbd" and entry["control_points"] % 8 == 0
    corr = read_displacement(study / entry["correspondence"])
    scan = st.scan("pose01")
    corr.geometry.check_same(scan.geometry)
    inv = read_displacement(study / entry["template_to_scan"])
    inv.geometry.check_same(st.template().geometry)
    # registered.nii.gz is the template pulled through the written field (no other definition)
    reg = read_volume(study / entry["registered"])
    t = st.template()
    again = sample_displaced_array(t.data, t.geometry.world_to_index_matrix, corr.geometry, corr.data, 1, 0.0)
    body = again > 0.1 * float(t.data.max())
    assert np.allclose(reg.data[body], again[body], rtol=1e-4, atol=1e-2)
    # MED in the log is one subtraction against the truth field
    log = json.loads((study / entry["log"]).read_text())
    rows = log["summary"]["validation"]
    from validation.registration_measures import body_on_scan, med
    from workbench.io.volumes import read_labels

    body = body_on_scan(st.truth_correspondence("pose01"), read_labels(study / "skinning" / "body_mask.nii.gz"))
    # the written float32 field against the in-memory one the log used: float32 rounding only
    assert med(corr, st.truth_correspondence("pose01"), body) == pytest.approx(rows["registered"]["med_mm"],
                                                                                abs=1e-4)
    assert rows["registered"]["med_mm"] < rows["source"]["med_mm"]  # VBD + registration beats nothing
    # the inverse undoes the field where both are defined (body voxels): |F(G(y)) − y| small
    y = t.geometry.world_coordinates()
    fwd = y + inv.data  # template voxel → scan position
    back = fwd + sample_displaced_array(corr.data, corr.geometry.world_to_index_matrix, t.geometry, inv.data, 1,
                                        0.0)
    tbody = t.data > 0.1 * float(t.data.max())
    resid = np.linalg.norm(back - y, axis=-1)[tbody]
    assert np.median(resid) < 0.5  # mm, a tenth of a voxel (5 mm); folds of VBD leave a few outliers


def test_register_refuses_to_overwrite_and_names_bad_scans(study, capsys):
    if not (study / "registration" / "pose01").exists():
        assert main(["register", str(study), "--scan", "pose01", *FAST, "--quiet"]) == 0
    before = (study / "registration" / "pose01" / "log.json").read_bytes()
    assert main(["register", str(study), "--scan", "pose01", *FAST, "--quiet"]) == 1
    assert "--force" in capsys.readouterr().err
    assert (study / "registration" / "pose01" / "log.json").read_bytes() == before
    assert main(["register", str(study), "--scan", "nope", *FAST, "--quiet"]) == 1
    assert "no scan 'nope'" in capsys.readouterr().err


def test_register_without_weights_says_what_to_run(tmp_path, study, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(study, bare, ignore=shutil.ignore_patterns("skinning", "registration"))
    assert main(["register", str(bare), "--scan", "pose01", *FAST, "--quiet"]) == 1
    assert "workbench weights" in capsys.readouterr().err


def test_register_init_none_is_deterministic(tmp_path, study):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        shutil.copytree(study, d, ignore=shutil.ignore_patterns("registration"))
        assert main(["register", str(d), "--scan", "pose01", "--init", "none", *FAST, "--seed", "7",
                     "--quiet"]) == 0
    fa = read_displacement(a / "registration" / "pose01" / "correspondence.mha").data
    fb = read_displacement(b / "registration" / "pose01" / "correspondence.mha").data
    assert np.array_equal(fa, fb)


def test_register_unfold_init_gives_a_one_to_one_field(tmp_path, study, capsys):
    from deformation.fields import folding_statistics

    d = tmp_path / "u"
    shutil.copytree(study, d, ignore=shutil.ignore_patterns("registration"))
    assert main(["register", str(d), "--scan", "pose01", "--unfold-init", *FAST, "--quiet"]) == 0
    st = read_study(d)
    entry = next(s for s in st.manifest["scans"] if s["id"] == "pose01")["registration"]
    log = json.loads((d / entry["log"]).read_text())
    repair = log["summary"]["backward_map"]["unfold"]
    assert repair["n_folded_before"] > 0 and repair["n_folded_after"] == 0  # VBD folds in the crease
    corr = read_displacement(d / entry["correspondence"])
    # the registration's steps are guarded, so a fold-free start stays fold-free on every voxel
    assert folding_statistics(corr)["n_folded"] == 0
    assert main(["register", str(d), "--scan", "pose01", "--init", "none", "--unfold-init", "--force", *FAST,
                 "--quiet"]) == 1
    assert "--init vbd" in capsys.readouterr().err
