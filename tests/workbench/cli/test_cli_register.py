"""`workbench register`: files, conventions, manifest, skips and reruns, refusals (a tiny budget: this checks
plumbing, the accuracy is tested in tests/registration/test_adaptive.py and test_dense.py).  Starts use the
phantom's true pose (--pose truth) so that these tests need no pose stage; tests/workbench/test_run.py runs the
estimated one.  FAST is Rhee's Algorithm 1 on a tiny budget; the default (polyrigid start, dense) has its own
test below."""

import json
import shutil

import numpy as np
import pytest

from deformation.fields.interpolate import sample_displaced_array
from workbench.cli import main
from workbench.io.volumes import read_displacement, read_volume
from workbench.study import read_study

FAST = ["--method", "adaptive", "--levels", "3", "3", "--max-steps", "4", "--pose", "truth"]
VBD = ["--init", "vbd"]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("reg") / "knee"
    assert main(["phantom", "knee", "--out", str(root), "--size", "test", "--poses", "2", "--quiet"]) == 0
    assert main(["weights", str(root), "--method", "distance", "--quiet"]) == 0
    return root


def _unregistered_copy(study, d, *, keep_init: bool = False):
    """``study`` copied to ``d`` as if never registered: no register or validate outputs nor recorded settings
    (the defaults apply, not the settings an earlier test ran with), and no init either unless ``keep_init``."""
    drop = ("registration", "validation") if keep_init else ("registration", "init", "validation")
    shutil.copytree(study, d, ignore=shutil.ignore_patterns(*drop))
    m = json.loads((d / "study.json").read_text(encoding="utf-8"))
    for stage in ("register", "validate") if keep_init else ("init", "register", "validate"):
        m.get("stages", {}).pop(stage, None)
    (d / "study.json").write_text(json.dumps(m))


def _tree(root):
    """Every file under ``root`` with its bytes (what a refused command must leave as it was)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def default_registered(study, tmp_path_factory):
    """``study`` after the default `workbench register --scan pose01 --pose truth` (the polyrigid start, dense
    steps), run once: its test checks it, and the --dense test starts from its init stage's output (the same
    default start, up to date, so it is not made a second time)."""
    d = tmp_path_factory.mktemp("reg-default") / "knee"
    _unregistered_copy(study, d)
    assert main(["register", str(d), "--scan", "pose01", "--pose", "truth", "--quiet"]) == 0
    return d


def test_register_writes_fields_in_the_truth_convention(study, capsys):
    assert main(["register", str(study), "--scan", "pose01", *FAST, *VBD, "--quiet"]) == 0
    table = capsys.readouterr().out
    assert "| pose01 | registered |" in table and "| pose01 | before |" in table  # similarity: no truth read
    st = read_study(study)
    entry = st.stage_entry("register", "pose01")
    assert entry["settings"]["max_steps_per_level"] == 4 and entry["settings"]["levels"] == [3, 3]
    assert st.stage_entry("init", "pose01")["settings"] == {
        "method": "vbd",
        "pose": "truth",
        "unfold": False,
        "map_factor": None,
    }
    entry = {
        k: f"registration/pose01/{n}"
        for k, n in (
            ("correspondence", "correspondence.mha"),
            ("template_to_scan", "template_to_scan.mha"),
            ("registered", "registered.nii.gz"),
            ("log", "log.json"),
        )
    }
    assert all(st.stage_entry("register", "pose01")["outputs"][p.split("/")[-1]] == p for p in entry.values())
    assert st.registration_log("pose01")["summary"]["control_points"] % 8 == 0
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
    # MED of the validate stage is one subtraction against the truth field
    assert main(["validate", str(study), "--scan", "pose01", "--quiet"]) == 0
    assert "| pose01 | initialised |" in capsys.readouterr().out
    rows = read_study(study).validation("pose01")["rows"]
    from validation.registration_measures import body_on_scan, med
    from workbench.io.volumes import read_labels

    body = body_on_scan(st.truth_correspondence("pose01"), read_labels(study / "skinning" / "body_mask.nii.gz"))
    # the written float32 field against the in-memory one the log used: float32 rounding only
    assert med(corr, st.truth_correspondence("pose01"), body) == pytest.approx(rows["registered"]["med_mm"], abs=1e-4)
    assert rows["registered"]["med_mm"] < rows["source"]["med_mm"]  # VBD + registration beats nothing
    # the inverse undoes the field where both are defined (body voxels): |F(G(y)) − y| small
    y = t.geometry.world_coordinates()
    fwd = y + inv.data  # template voxel → scan position
    back = fwd + sample_displaced_array(corr.data, corr.geometry.world_to_index_matrix, t.geometry, inv.data, 1, 0.0)
    tbody = t.data > 0.1 * float(t.data.max())
    resid = np.linalg.norm(back - y, axis=-1)[tbody]
    assert np.median(resid) < 0.5  # mm, a tenth of a voxel (5 mm); folds of VBD leave a few outliers


def test_register_skips_what_is_up_to_date_and_names_bad_scans(tmp_path, study, capsys):
    d = tmp_path / "s"
    shutil.copytree(study, d)
    if not (d / "registration" / "pose01").exists():
        assert main(["register", str(d), "--scan", "pose01", *FAST, *VBD, "--quiet"]) == 0
    before = (d / "registration" / "pose01" / "log.json").read_bytes()
    manifest = (d / "study.json").read_bytes()
    assert main(["register", str(d), "--scan", "pose01", *FAST, *VBD]) == 0
    assert "register pose01: up to date, skipped" in capsys.readouterr().err
    assert (d / "registration" / "pose01" / "log.json").read_bytes() == before
    assert (d / "study.json").read_bytes() == manifest
    # options left out keep the settings the scan was registered with: still up to date
    assert main(["register", str(d), "--scan", "pose01"]) == 0
    assert "register pose01: up to date, skipped" in capsys.readouterr().err
    # --force reruns it: the same settings give the same field to the bit (deterministic)
    field = (d / "registration" / "pose01" / "correspondence.mha").read_bytes()
    assert main(["register", str(d), "--scan", "pose01", *FAST, "--force", "--quiet"]) == 0
    assert (d / "registration" / "pose01" / "correspondence.mha").read_bytes() == field
    assert main(["register", str(d), "--scan", "nope", *FAST, "--quiet"]) == 1
    assert "no scan ['nope']" in capsys.readouterr().err


def test_register_on_a_study_without_bones_says_what_to_run(tmp_path, study, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(study, bare, ignore=shutil.ignore_patterns("skinning", "registration", "init", "bones"))
    m = json.loads((bare / "study.json").read_text(encoding="utf-8"))
    del m["template_labels"]
    m["stages"] = {}
    (bare / "study.json").write_text(json.dumps(m))
    assert main(["register", str(bare), "--scan", "pose01", *FAST, "--quiet"]) == 1
    assert "--seeds FILE" in capsys.readouterr().err
    assert not (bare / "registration").exists() and not (bare / "skinning").exists()


def test_register_init_none_is_deterministic(tmp_path, study):
    """Rhee's Algorithm 1 in this process and in another: the same bytes in every file, its per-level and
    per-step log.json included — the times are the manifest entry's ``timings``, not the log's."""
    import subprocess
    import sys

    a, b = tmp_path / "a", tmp_path / "b"
    args = ["register", "--scan", "pose01", "--init", "none", *FAST, "--seed", "7", "--quiet"]
    for d in (a, b):
        shutil.copytree(study, d, ignore=shutil.ignore_patterns("registration"))
    assert main([args[0], str(a), *args[1:]]) == 0
    proc = subprocess.run(
        [sys.executable, "-m", "workbench", args[0], str(b), *args[1:]],
        capture_output=True,
        text=True,
        encoding="utf-8",
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    fa = read_displacement(a / "registration" / "pose01" / "correspondence.mha").data
    fb = read_displacement(b / "registration" / "pose01" / "correspondence.mha").data
    assert np.array_equal(fa, fb)
    names = sorted(p.name for p in (a / "registration" / "pose01").iterdir())
    assert "log.json" in names and names == sorted(p.name for p in (b / "registration" / "pose01").iterdir())
    for n in names:
        assert (a / "registration" / "pose01" / n).read_bytes() == (b / "registration" / "pose01" / n).read_bytes(), n
    log = read_study(a).registration_log("pose01")
    assert "seconds" not in json.dumps(log)
    t = read_study(a).stage_entry("register", "pose01")["timings"]
    assert len(t["levels"]) == len(log["log"]["levels"]) == 1 and len(t["steps"]) == len(log["log"]["steps"]) > 0
    assert t["registration"] > 0 and all(v >= 0 for v in t["steps"])


def test_register_unfold_init_repairs_the_folds_of_the_map(tmp_path, study, capsys):
    from deformation.fields.displacement import jacobian_determinant
    from deformation.fields.resample import backward_map
    from deformation.models.evd import vbd_forward
    from deformation.models.skinning import stack_transforms
    from registration.initialise import mapped_voxels as _mapped
    from validation.registration_measures import body_on_scan
    from workbench.io.volumes import read_image_geometry

    d = tmp_path / "u"
    shutil.copytree(study, d, ignore=shutil.ignore_patterns("registration"))
    assert main(["register", str(d), "--scan", "pose01", "--unfold-init", *FAST, *VBD, "--quiet"]) == 0
    init = json.loads((d / "init" / "pose01" / "init.json").read_text(encoding="utf-8"))
    repair = init["backward_map"]["unfold"]
    assert repair["n_folded_before"] > 0 and repair["n_folded_after"] == 0  # VBD folds in the crease
    corr = read_displacement(d / "registration" / "pose01" / "correspondence.mha")
    # the registration's steps are guarded, so a start without folds stays so.  The repair checks the voxels
    # the map sends into the template (_mapped, from the same VBD map as the init stage's): the rest keep a
    # clamped position, det ~0 without a fold (most of this grid's "folded" voxels before the repair, at its
    # faces, some in the body where the leg leaves the grid)
    st = read_study(d)
    weights, body_t = st.weights()
    g_s = read_image_geometry(st.scan_path("pose01"))
    t = stack_transforms(st.truth_pose("pose01").transforms, weights.bones)
    bm = backward_map(
        vbd_forward(body_t.geometry, weights, t), body_t.geometry, g_s, transforms=t, prefer=body_t.data.astype(bool)
    )
    mapped = _mapped(bm, 1, g_s)
    raw = jacobian_determinant(bm.scan_to_template()) <= 0  # the VBD start before the repair
    assert repair["n_folded_before"] == np.count_nonzero(raw & mapped) < np.count_nonzero(raw)
    body = body_on_scan(read_displacement(d / "truth" / "pose01_correspondence.mha"), body_t)
    det = jacobian_determinant(corr)
    assert np.count_nonzero((det <= 0) & body & mapped) == 0 < np.count_nonzero(body & mapped)
    assert (
        main(["register", str(d), "--scan", "pose01", *FAST, "--init", "none", "--unfold-init", "--force", "--quiet"])
        == 1
    )
    assert "--init vbd" in capsys.readouterr().err


def test_default_registration_is_the_polyrigid_start_and_dense_steps(tmp_path, default_registered, capsys):
    """The default: a one-to-one polyrigid start, dense LNCC steps with the bones held; no fold anywhere, the
    bones where the start put them, MED below the start's, and the inverse through the start's forward map."""
    from deformation.fields.displacement import folding_statistics
    from validation.registration_measures import body_on_scan, med
    from workbench.io.volumes import read_labels

    d = tmp_path / "dense"
    shutil.copytree(default_registered, d)  # the module's default registration (validate below writes into it)
    st = read_study(d)
    assert st.stage_entry("init", "pose01")["settings"]["method"] == "polyrigid"
    assert st.stage_entry("register", "pose01")["settings"]["method"] == "auto"
    log = st.registration_log("pose01")
    assert log["method"].startswith("dense") and log["dense_settings"]["bones"] == "fixed"
    init = st.init_field("pose01")
    corr = st.registration_correspondence("pose01")
    assert folding_statistics(corr)["n_folded"] == 0 == log["summary"]["folding"]["n_folded"]
    assert main(["validate", str(d), "--scan", "pose01", "--quiet"]) == 0
    rows = read_study(d).validation("pose01")["rows"]
    assert rows["registered"]["med_mm"] < rows["initialised"]["med_mm"]
    # bones fixed: on the scan's bone voxels (the template's labels pulled through the start) the result is
    # the start to float32 rounding and the fade's edge (trilinear label sampling moves the edge by < 1 voxel)
    labels = st.template_labels()
    from deformation.fields.interpolate import sample_displaced_array

    lab = sample_displaced_array(labels.data, labels.geometry.world_to_index_matrix, init.geometry, init.data, 0, 0)
    inner = ndimage_erode(lab > 0)
    assert inner.sum() > 100
    moved = np.abs(corr.data[inner] - init.data[inner]).max(axis=-1) > 1e-3
    # all of them, except where the final fold repair smoothed a crease fold that touches a bone (1 of 499
    # measured; the repair is logged)
    repair = log["summary"]["unfold"]
    assert moved.sum() <= max(1, repair["n_changed"] if repair and repair["taken"] else 0)
    assert moved.mean() < 0.01
    # the inverse went through the start's exact forward map: template → scan → template returns
    inv, status = st.registration_inverse("pose01")
    t = st.template()
    y = t.geometry.world_coordinates()
    back = (
        y
        + inv.data
        + sample_displaced_array(corr.data, corr.geometry.world_to_index_matrix, t.geometry, inv.data, 1, 0.0)
    )
    tbody = read_labels(d / "skinning" / "body_mask.nii.gz").data > 0
    ok = tbody & (status.data == 0)
    assert ok.mean() > 0.9 * tbody.mean()  # found for the body (the rest leaves the scan's field of view)
    assert np.median(np.linalg.norm(back - y, axis=-1)[ok]) < 0.1  # mm, 1/50 of the 5 mm voxel
    assert (d / "init" / "pose01" / "forward.mha").exists()
    body = body_on_scan(st.truth_correspondence("pose01"), read_labels(d / "skinning" / "body_mask.nii.gz"))
    assert med(corr, st.truth_correspondence("pose01"), body) == pytest.approx(rows["registered"]["med_mm"], abs=1e-4)


def test_polyrigid_start_on_every_other_voxel(tmp_path, study, capsys):
    """--map-factor 2 (what a grid of more than 16 M voxels gets by itself): the start integrated on every 2nd
    voxel and blended up, recorded in init.json, on the scan's and template's full grids; it stays close to
    the exact start (the blend's accuracy is tested in tests/deformation/models/test_polyrigid.py: this checks the
    plumbing, where a wrong factor or frame would be tens of mm off).  A map factor with VBD, below 1 or
    leaving a grid less than 2 voxels along an axis is one line naming the option, and nothing is written;
    --init vbd afterwards drops the recorded factor."""
    from registration.initialise import polyrigid_initial_field

    d = tmp_path / "mf"
    _unregistered_copy(study, d)
    for argv, match in (
        (["--init", "vbd", "--map-factor", "2"], "--init polyrigid"),
        (["--map-factor", "0"], "--map-factor must be a whole number"),
        (["--map-factor", "99"], "--map-factor 99 leaves the scan's"),
    ):
        assert main(["register", str(d), "--scan", "pose01", *FAST, *argv, "--quiet"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], err
        assert not (d / "init").exists() and not (d / "registration").exists()
    assert main(["register", str(d), "--scan", "pose01", *FAST, "--map-factor", "2", "--quiet"]) == 0
    st = read_study(d)
    info = st.init_info("pose01")
    assert info["method"] == "polyrigid" and info["map_factor"] == {"scan": 2, "template": 2}
    assert st.stage_entry("init", "pose01")["settings"]["map_factor"] == 2
    field, scan = st.init_field("pose01"), st.scan("pose01")
    field.geometry.check_same(scan.geometry)
    st.init_forward("pose01").geometry.check_same(st.template().geometry)
    sk, labels = st.skeleton(), st.template_labels()
    exact, _ = polyrigid_initial_field(
        labels,
        {b: sk.label_of(b) for b in sk.bone_names},
        {b: sk.bone(b).parent for b in sk.bone_names},
        st.truth_pose("pose01").transforms,
        scan.geometry,
    )
    body = scan.data > 0.1 * float(scan.data.max())
    dev = np.linalg.norm(field.data - exact.data, axis=-1)[body]
    assert dev.mean() < 0.25 * min(scan.geometry.spacing)  # a quarter voxel: the blend's second-order error
    # a recorded map factor gives way to --init vbd (it is the polyrigid start's)
    assert main(["register", str(d), "--scan", "pose01", *FAST, *VBD, "--quiet"]) == 0
    assert read_study(d).stage_entry("init", "pose01")["settings"]["map_factor"] is None


def ndimage_erode(mask):
    from scipy import ndimage

    return ndimage.binary_erosion(mask, iterations=2)


def test_register_refuses_paper_preset_with_dense(tmp_path, study, capsys):
    d = tmp_path / "p"
    shutil.copytree(study, d, ignore=shutil.ignore_patterns("registration", "init"))
    assert main(["register", str(d), "--scan", "pose01", "--method", "dense", "--preset", "paper", "--quiet"]) == 1
    assert "--method adaptive" in capsys.readouterr().err
    assert not (d / "registration").exists()


def test_register_refuses_algorithm_1_options_with_dense(tmp_path, study, capsys):
    # --levels / --max-steps are Rhee's Algorithm 1's; the dense method would ignore them without a word
    d = tmp_path / "a"
    _unregistered_copy(study, d)
    assert main(["register", str(d), "--scan", "pose01", "--levels", "3", "4", "--max-steps", "9", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "--levels, --max-steps are settings of Rhee's Algorithm 1" in err and "--method adaptive" in err
    assert len(err.strip().splitlines()) == 1
    assert not (d / "registration").exists() and not (d / "init").exists()


def test_recorded_settings_give_way_to_the_options_that_contradict_them(tmp_path, study, capsys):
    # a study last registered with VBD + --unfold-init and Rhee's paper preset: --init none and --method dense
    # must not inherit the repair or the preset (both would be refused)
    from workbench.cli import build_parser
    from workbench.stages.run import register_settings

    d = tmp_path / "r"
    shutil.copytree(study, d, ignore=shutil.ignore_patterns("registration", "init", "validation"))
    m = json.loads((d / "study.json").read_text(encoding="utf-8"))
    m.setdefault("stages", {})
    m["stages"]["init"] = {"digest": "recorded", "settings": {"method": "vbd", "pose": "truth", "unfold": True}}
    m["stages"]["register"] = {
        "digest": "recorded",
        "settings": {"method": "auto", "preset": "paper", "levels": [3, 4], "optimizer": "sbplx"},
    }
    (d / "study.json").write_text(json.dumps(m))
    args = build_parser().parse_args(["register", str(d), "--init", "none", "--method", "dense"])
    s = register_settings(read_study(d), vars(args))
    assert s["init"].method == "identity" and s["init"].unfold is False
    assert s["register"].method == "dense" and s["register"].preset == "auto"
    assert s["register"].levels is None and s["register"].optimizer is None  # Algorithm 1's: dropped
    args = build_parser().parse_args(["register", str(d), "--preset", "paper"])
    assert register_settings(read_study(d), vars(args))["register"].resolved_method == "adaptive"


def test_dense_settings_reach_the_registration_and_bad_ones_are_refused_first(tmp_path, default_registered, capsys):
    """``--dense NAME=VALUE`` sets a DenseSettings field (JSON value), recorded with the stage's settings so that
    a rerun with the same ones is skipped; a wrong name, type, range, the bones' own option or Algorithm 1 get
    one line naming the option, before anything is written."""
    # from the default start (the module's default registration's init, up to date for these options too:
    # --dense changes the register stage's settings only), nothing registered
    d = tmp_path / "ds"
    _unregistered_copy(default_registered, d, keep_init=True)
    init_before, manifest = _tree(d / "init"), (d / "study.json").read_bytes()
    bad = [
        (["--dense", "window=4"], "no setting 'window'"),
        (["--dense", "window_mm=four"], "--dense window_mm: the setting is a number (float), got the text 'four'"),
        (["--dense", "window_mm=-1"], "window_mm > 0"),
        (["--dense", "bones=free"], "--no-fix-bones"),
        (["--dense", "window_mm"], "expected NAME=VALUE"),
        (["--dense", "tolerance=1e-3", "--dense", "tolerance=1e-2"], "given twice"),
        (["--dense", "holdout=true", "--method", "adaptive"], "do not apply to Rhee's Algorithm 1"),
        (["--dense", "shrink=[null, 1, 1]"], "--dense shrink: the setting is a list of whole numbers ≥ 1"),
        (["--dense", "iterations=[2.5, 2, 2]"], "--dense iterations: the setting is a list of whole numbers"),
        (["--dense", "window_mm=NaN"], "--dense window_mm: the setting must be a finite number"),
        (["--dense", "iterations=[200, 200]"], "--dense: shrink and iterations need one entry per level"),
    ]
    for extra, words in bad:
        assert main(["register", str(d), "--scan", "pose01", "--pose", "truth", *extra, "--quiet"]) == 1, extra
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1, (extra, err)
        assert not (d / "registration").exists() and _tree(d / "init") == init_before
        assert (d / "study.json").read_bytes() == manifest
    # three short levels (2 trials each: a fast run) and a wider window, given as JSON
    opts = ["--dense", "iterations=[2, 2, 2]", "--dense", "window_mm=4", "--dense", "refine_bones=false"]
    init_entry = read_study(d).stage_entry("init", "pose01")
    assert main(["register", str(d), "--scan", "pose01", "--pose", "truth", *opts, "--quiet"]) == 0
    st = read_study(d)
    assert st.stage_entry("init", "pose01") == init_entry and _tree(d / "init") == init_before  # the start: reused
    ds = st.registration_log("pose01")["dense_settings"]
    assert ds["iterations"] == [2, 2, 2] and ds["window_mm"] == 4.0 and ds["refine_bones"] is False
    assert ds["bones"] == "fixed" and ds["fluid_voxels"] == 3.0  # the rest: the defaults
    assert all(lv["iterations"] + lv["rejected"] <= 2 for lv in st.registration_log("pose01")["summary"]["levels"])
    digest = st.stage_entry("register", "pose01")["digest"]
    log_time = (d / "registration" / "pose01" / "log.json").stat().st_mtime_ns
    assert main(["register", str(d), "--scan", "pose01", "--quiet"]) == 0  # options left out: the recorded ones
    st = read_study(d)
    assert st.stage_entry("register", "pose01")["digest"] == digest  # up to date: not run again
    assert (d / "registration" / "pose01" / "log.json").stat().st_mtime_ns == log_time
    assert st.stage_entry("register", "pose01")["settings"]["dense_settings"] == [  # sorted: one digest
        ["iterations", [2, 2, 2]],
        ["refine_bones", False],
        ["window_mm", 4.0],
    ]
    from workbench.stages.register import RegisterSettings

    assert RegisterSettings(dense_settings=(("window_mm", 4), ("iterations", [2.0, 2, 2]))).dense_settings == (
        ("iterations", (2, 2, 2)),
        ("window_mm", 4.0),
    )
    from workbench.cli import build_parser
    from workbench.stages.run import register_settings

    args = build_parser().parse_args(["register", str(d), "--dense", "default"])
    assert register_settings(read_study(d), vars(args))["register"].dense_settings == ()
    args = build_parser().parse_args(["register", str(d), "--preset", "paper"])  # Algorithm 1: theirs dropped
    assert register_settings(read_study(d), vars(args))["register"].dense_settings == ()
