"""Faults and odd input (issue Q): a write that does not complete is an error naming the file, with nothing left
half-written and no input changed; input that cannot work is refused before the work, in one line.

Writes are cut short by a file-size limit (``RLIMIT_FSIZE``, set in the child process only: Python ignores the
SIGXFSZ the kernel sends, so each write past the limit fails with EFBIG, as on a full disk).  The children run
with ``python -B``: under the limit, Python's own bytecode cache would be written short (it does not check the
length a write returned) and every later process importing that module would fail reading it.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from workbench.cli import main

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _workbench(*args, limit_bytes: int | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """``workbench ARGS`` in a child process, its written files capped at ``limit_bytes``."""

    def cap():
        if limit_bytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return subprocess.run(
        [sys.executable, "-B", "-m", "workbench", *map(str, args)],
        capture_output=True,
        text=True,
        encoding="utf-8",
        timeout=timeout,
        preexec_fn=cap,
    )


def _tree(root: Path) -> dict:
    """Every file under ``root`` (hidden ones too) with its SHA-256: what a failed command must leave as it was."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and ".locks" not in p.parts and p.name != ".study.json.lock"
    }


def _one_error_line(err: str, command: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.startswith(f"workbench {command}: error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def study(phantom, tmp_path_factory):
    """A noise-free CT knee (0°, 35°) with distance weights and an EVD model from the truth: every writer's input."""
    from workbench.study import write_phantom_study

    root = write_phantom_study(
        phantom("knee", size="test", modality="ct", n_poses=2, seed=2, noise=False),
        tmp_path_factory.mktemp("faults") / "study",
    ).root
    assert main(["weights", str(root), "--method", "distance", "--quiet"]) == 0
    assert main(["model", str(root), "--source", "truth", "--quiet"]) == 0
    return root


# -- 1. a full disk (a file-size limit) is an error naming the file, never a success ---------------------------
# 20 KiB: the headers fit, the data of a 64x64x40 volume (655 kB; 100-200 kB gzipped), a 640x480 PNG and a video
# of 6 frames do not; 5 KiB for the video and 2 KiB for a 320x240 frame (both compress the dark background well)
@pytest.mark.parametrize(
    "command, out, limit",
    [
        (["deform", "{study}", "--pose", str(EXAMPLES / "knee_bend45.json")], "bent.nii.gz", 20_480),
        (["deform", "{study}", "--pose", str(EXAMPLES / "knee_bend45.json")], "bent.nii", 20_480),
        (["deform", "{study}", "--pose", str(EXAMPLES / "knee_bend45.json")], "bent.mha", 20_480),
        (["clean-image", "{study}/template.nii.gz"], "clean.nii.gz", 20_480),
        (["render", "{study}/template.nii.gz"], "picture.png", 20_480),
        (["animate", "{study}", "--frames", "6", "--size", "320x240"], "knee.gif", 20_480),
        (["animate", "{study}", "--frames", "6", "--size", "320x240"], "knee.mp4", 5_120),
        (["animate", "{study}", "--frames", "6", "--size", "320x240"], "frames.png", 2_048),
        # named by its place in the study, not the staging folder; slow (~14 s: a whole phantom study), `make test-slow`
        pytest.param(["phantom", "knee", "--quiet"], "new-study", 20_480, marks=pytest.mark.slow),
    ],
)
def test_a_write_cut_short_is_an_error_naming_the_file(study, tmp_path, command, out, limit):
    before = _tree(study)
    target = tmp_path / out
    args = [a.format(study=study) for a in command] + ["--out", target]
    r = _workbench(*args, limit_bytes=limit)
    assert r.returncode == 1, r.stderr
    line = _one_error_line(r.stderr, command[0])
    assert line.startswith(f"workbench {command[0]}: error: {target}") and ".partial-" not in line, line
    assert "the file could not be written completely" in line and "nothing was left under that name" in line
    assert list(tmp_path.iterdir()) == []  # no output, no temporary file, no frame
    assert _tree(study) == before  # no input changed
    # the same command without the limit writes the file: the failure was the limit's
    ok = _workbench(*args)
    assert ok.returncode == 0, ok.stderr
    assert any(tmp_path.iterdir())


def test_a_stage_output_cut_short_names_its_final_path_and_keeps_the_previous_outputs(study):
    """`workbench weights --force` under a limit: the error names skinning/<file> (not the staging folder), the
    old outputs and the manifest stay as they were, no staging folder is left."""
    before = _tree(study)
    r = _workbench("weights", study, "--method", "harmonic", "--force", limit_bytes=20_480)
    assert r.returncode == 1, r.stderr
    line = _one_error_line(r.stderr, "weights")
    assert f"{study / 'skinning'}/" in line and "could not be written completely" in line, line
    assert ".partial-" not in line
    assert _tree(study) == before
    assert [p for p in study.rglob("*") if ".partial-" in p.name or ".tmp-" in p.name] == []


def test_the_manifest_write_cut_short_names_study_json(study, tmp_path):
    """The manifest (study.json) is rewritten whole by each record; under a limit smaller than it, the error
    names it and the old manifest stays."""
    copy = shutil.copytree(study, tmp_path / "study")
    size = (copy / "study.json").stat().st_size
    code = (
        "from workbench.study import read_study\n"
        f"read_study({str(copy)!r}).update(lambda m: m.setdefault('notes', []).append('x' * 10))\n"
    )

    def cap():
        resource.setrlimit(resource.RLIMIT_FSIZE, (size // 2, size // 2))

    r = subprocess.run(
        [sys.executable, "-B", "-c", code],
        capture_output=True,
        text=True,
        encoding="utf-8",
        preexec_fn=cap,
        timeout=120,
    )
    assert r.returncode != 0
    assert f"{copy / 'study.json'}: the file could not be written completely" in r.stderr, r.stderr
    assert (copy / "study.json").read_bytes() == (study / "study.json").read_bytes()


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".vtp", ".obj", ".vtu"])
def test_mesh_writers_cut_short_raise(tmp_path, suffix):
    """Open3D's PLY/STL writer (RPly) reports a short write only on stderr and VTK's XML writer crashed the
    process (SIGSEGV): each now raises, naming the file, and leaves nothing."""
    code = f"""
import numpy as np, resource
from deformation.meshes.tetmesh import TetMesh
from workbench.io.meshes import SurfaceMesh, write_mesh
from workbench.io.tetmeshes import write_tetmesh
rng = np.random.default_rng(0)
v = rng.random((4000, 3)) * 100
resource.setrlimit(resource.RLIMIT_FSIZE, (20_480, 20_480))
if {suffix!r} == ".vtu":
    t = np.array([[i, i + 1, i + 2, i + 3] for i in range(0, 3996, 4)])
    write_tetmesh(TetMesh(v, t).oriented(), {str(tmp_path / ("m" + suffix))!r},
                  point_data={{"w": rng.random(4000)}})
else:
    t = np.array([[i, i + 1, i + 2] for i in range(0, 3998)])
    write_mesh(SurfaceMesh(v, t), {str(tmp_path / ("m" + suffix))!r})
"""
    r = subprocess.run(
        [sys.executable, "-B", "-c", code], capture_output=True, text=True, encoding="utf-8", timeout=120
    )
    assert r.returncode == 1, (r.returncode, r.stderr)  # 1: a Python exception, not a crash (-11)
    assert "OutputWriteError" in r.stderr and f"m{suffix}: the file could not be written completely" in r.stderr
    assert list(tmp_path.iterdir()) == []


# -- 3. a scan outside the template's space: refused at pose, naming the scan -------------------------------
def _scan_elsewhere(root: Path, sid: str) -> Path:
    """Rewrite scan ``sid`` with another spacing and a permuted, flipped direction, far from the template."""
    path = root / "scans" / f"{sid}.nii.gz"
    im = sitk.ReadImage(str(path))
    a = sitk.GetArrayFromImage(im).transpose(1, 0, 2)[::-1]
    out = sitk.GetImageFromArray(np.ascontiguousarray(a))
    out.SetSpacing((3.0, 2.0, 4.5))
    out.SetDirection((0, 1, 0, 1, 0, 0, 0, 0, -1))
    out.SetOrigin((400.0, 300.0, 200.0))
    sitk.WriteImage(out, str(path))
    return path


def test_a_scan_outside_the_templates_space_is_refused_at_pose(study, tmp_path):
    root = shutil.copytree(study, tmp_path / "study")
    scan = _scan_elsewhere(root, "pose01")
    info = _workbench("info", root, "--check")
    assert info.returncode == 0 and f"{scan}: no bone of the template lies in this scan's field of view" in info.stderr
    before = _tree(root)
    r = _workbench("run", root, "--until", "pose")
    assert r.returncode == 1
    line = _one_error_line(r.stderr, "run")
    assert f"{scan}: no bone of the template lies in this scan's field of view" in line
    assert "no bone could be placed" in line and "--init moments" in line
    assert not (root / "poses").exists()
    after = _tree(root)
    assert all(after[k] == v for k, v in before.items() if k != "study.json")  # the bones stage ran first


def test_a_scan_where_no_bone_can_be_placed_is_refused(study, tmp_path):
    """A scan in the template's space whose image shows nothing (constant): every bone is flagged, and the
    pose stage says so instead of handing on a pose no bone confirmed."""
    root = shutil.copytree(study, tmp_path / "study")
    path = root / "scans" / "pose01.nii.gz"
    im = sitk.ReadImage(str(path))
    flat = sitk.GetImageFromArray(np.full(sitk.GetArrayFromImage(im).shape, -1000.0, np.float32))
    flat.CopyInformation(im)
    sitk.WriteImage(flat, str(path))
    r = _workbench("run", root, "--until", "pose")
    assert r.returncode == 1
    line = _one_error_line(r.stderr, "run")
    assert f"{path}: no bone of scan 'pose01' could be placed (" in line, line
    assert not (root / "poses").exists()


# -- 4. implausible geometry is refused at load ---------------------------------------------------------------
def test_a_scan_with_1000_mm_voxels_is_refused_before_the_work(study, tmp_path):
    root = shutil.copytree(study, tmp_path / "study")
    path = root / "scans" / "pose01.nii.gz"
    im = sitk.ReadImage(str(path))
    im.SetSpacing((1000.0, 1000.0, 1000.0))
    sitk.WriteImage(im, str(path))
    info = _workbench("info", root, "--check")
    assert info.returncode == 1 and f"{path}: voxel spacing x 1000 mm, y 1000 mm, z 1000 mm is outside" in info.stderr
    r = _workbench("run", root)
    assert r.returncode == 1
    line = _one_error_line(r.stderr, "run")
    assert f"{path}: voxel spacing x 1000 mm" in line and "no scan of a body has" in line
    assert not (root / "poses").exists()  # refused as the pose stage loads its scans, before any bone is fitted


@pytest.mark.parametrize(
    "spacing, size, message",
    [
        ((1000.0, 1.0, 1.0), (8, 8, 8), "voxel spacing x 1000 mm is outside 0.001–20 mm"),
        ((0.5, 0.5, 1e-4), (8, 8, 8), "voxel spacing z 0.0001 mm is outside"),
        ((19.0, 1.0, 1.0), (300, 8, 8), "a field of view of 5700 x 8 x 8 mm is longer than 4000 mm"),
    ],
)
def test_readers_refuse_implausible_geometry(tmp_path, spacing, size, message):
    from workbench.errors import ImplausibleGeometryError
    from workbench.io.volumes import read_image_geometry, read_labels, read_volume

    im = sitk.GetImageFromArray(np.zeros(size[::-1], np.uint8))
    im.SetSpacing(spacing)
    path = tmp_path / "odd.nii.gz"
    sitk.WriteImage(im, str(path))
    for reader in (read_volume, read_labels, read_image_geometry):
        with pytest.raises(ImplausibleGeometryError, match=message):
            reader(path)


def test_the_limits_of_plausible_geometry_are_accepted(tmp_path):
    """20 mm (thick slices) and 0.001 mm (micro-CT), 4000 mm of field of view: read."""
    from workbench.io.volumes import read_volume

    im = sitk.GetImageFromArray(np.zeros((4, 200, 5), np.float32))
    im.SetSpacing((0.001, 20.0, 1.0))
    sitk.WriteImage(im, str(tmp_path / "edge.nii.gz"))
    assert read_volume(tmp_path / "edge.nii.gz").geometry.extent_mm[1] == pytest.approx(4000.0)


# -- 5. manifest version ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("version", [99, "1", 1.5, None])
def test_an_unsupported_manifest_version_is_refused(study, tmp_path, version):
    root = shutil.copytree(study, tmp_path / "study")
    m = json.loads((root / "study.json").read_text(encoding="utf-8"))
    m["version"] = version
    (root / "study.json").write_text(json.dumps(m))
    before = _tree(root)
    r = _workbench("run", root)
    assert r.returncode == 1
    line = _one_error_line(r.stderr, "run")
    assert f"unsupported manifest version {json.dumps(version)} (this workbench reads 1)" in line, line
    assert _tree(root) == before


# -- 6. --set values are checked against their declared types -------------------------------------------------
@pytest.mark.parametrize(
    "item, message",
    [
        ('register.seed="abc"', "--set register.seed: the setting is a whole number (int), got the text 'abc'"),
        ('register.fix_bones="yes"', "--set register.fix_bones: the setting is true or false (bool), got the text"),
        (
            "register.max_steps_per_level=1.5",
            "--set register.max_steps_per_level: the setting is a whole number (int) (null for the default), got 1.5",
        ),
        (
            "register.levels=abc",
            "--set register.levels: the setting is a JSON list (tuple), e.g. [3, 5] (null for the "
            "default), got the text 'abc'",
        ),
        (
            "weights.edge_length_mm=true",
            "--set weights.edge_length_mm: the setting is a number (float) (null for the default), got true",
        ),
    ],
)
def test_a_set_value_of_the_wrong_type_is_refused_and_nothing_stored(study, tmp_path, item, message):
    root = shutil.copytree(study, tmp_path / "study")
    before = _tree(root)
    r = _workbench("run", root, "--set", item)
    assert r.returncode == 1
    assert message in _one_error_line(r.stderr, "run")
    assert _tree(root) == before


def test_set_values_of_the_declared_types_are_taken():
    from workbench.stages.run import parse_set

    assert parse_set(
        [
            "register.seed=3",
            "register.levels=[3, 5]",
            "register.fix_bones=false",
            "weights.edge_length_mm=4",
            "weights.grid_factor=null",
            "register.max_steps_per_level=20.0",
            "register.method=adaptive",
        ]
    ) == {
        "register": {"seed": 3, "levels": [3, 5], "fix_bones": False, "max_steps_per_level": 20, "method": "adaptive"},
        "weights": {"edge_length_mm": 4.0, "grid_factor": None},
    }
    assert isinstance(parse_set(["weights.edge_length_mm=4"])["weights"]["edge_length_mm"], float)


# -- 7. the phantom's spacing is refused up front ----------------------------------------------------------------
@pytest.mark.parametrize(
    "spacing, message",
    [
        (
            "1000",
            "leaves the knee's field of view (319 x 319 x 148 mm) only 1 x 1 x 1 voxels; a phantom needs at least "
            "16 along each axis: give a spacing of at most 19.92, 19.92, 9.22 mm",
        ),
        ("0.001", "more than 250,000,000"),
    ],
)
def test_a_phantom_spacing_that_cannot_work_is_refused_up_front(tmp_path, spacing, message):
    r = _workbench("phantom", "knee", "--out", tmp_path / "p", "--spacing", spacing, "--quiet")
    assert r.returncode == 1
    assert message in _one_error_line(r.stderr, "phantom")
    assert list(tmp_path.iterdir()) == []


# -- unclear rows, decided --------------------------------------------------------------------------------------
def test_label_ids_not_in_the_skeleton_are_warned_of(study, tmp_path):
    """Ids 7 and 200 in the label map: taken as soft tissue, said by info --check and by the bones stage (with
    --quiet too), listed in bones.json."""
    root = shutil.copytree(study, tmp_path / "study")
    path = root / "template_labels.nii.gz"
    im = sitk.ReadImage(str(path))
    a = sitk.GetArrayFromImage(im)
    a[0, 0, :3] = 7
    a[0, 1, :5] = 200
    out = sitk.GetImageFromArray(a)
    out.CopyInformation(im)
    sitk.WriteImage(out, str(path))
    info = _workbench("info", root, "--check")
    assert info.returncode == 0
    assert f"{path}: label ids 7 (3 voxels), 200 (5 voxels) are no bone of skeleton.json" in info.stderr
    r = _workbench("bones", root, "--quiet")
    assert r.returncode == 0, r.stderr
    assert f"warning: {path}: label ids 7 (3 voxels), 200 (5 voxels) are not the label of any bone" in r.stderr
    assert json.loads((root / "bones" / "bones.json").read_text(encoding="utf-8"))["unknown_labels"] == {
        "7": 3,
        "200": 5,
    }


def test_an_empty_dicom_folder_is_said_the_same_way_everywhere(study, tmp_path):
    root = shutil.copytree(study, tmp_path / "study")
    (root / "scans" / "pose01_dicom").mkdir()
    m = json.loads((root / "study.json").read_text(encoding="utf-8"))
    m["scans"][1]["image"] = "scans/pose01_dicom"
    (root / "study.json").write_text(json.dumps(m))
    said = f"{root / 'scans' / 'pose01_dicom'}: no DICOM series found in this folder"
    info = _workbench("info", root, "--check")
    assert info.returncode == 1 and said in info.stderr
    r = _workbench("run", root)
    assert r.returncode == 1 and said in _one_error_line(r.stderr, "run")


def test_a_symlink_to_a_scan_outside_the_study_is_followed_and_dotdot_is_refused(study, tmp_path):
    """Decided: the manifest names paths inside the folder (no '..': it stays right when the folder moves); a
    symbolic link inside the folder is the way to use a file kept elsewhere — followed, and info --check says so."""
    root = shutil.copytree(study, tmp_path / "study")
    outside = tmp_path / "elsewhere.nii.gz"
    shutil.move(root / "scans" / "pose01.nii.gz", outside)
    (root / "scans" / "pose01.nii.gz").symlink_to(outside)
    info = _workbench("info", root, "--check")
    assert info.returncode == 0, info.stderr
    assert f"{root / 'scans' / 'pose01.nii.gz'}: a symbolic link to {outside}, outside the study folder" in info.stderr
    from workbench.study import read_study

    assert read_study(root).scan("pose01").data.shape == sitk.GetArrayFromImage(sitk.ReadImage(str(outside))).shape
    m = json.loads((root / "study.json").read_text(encoding="utf-8"))
    m["scans"][1]["image"] = "../elsewhere.nii.gz"
    (root / "study.json").write_text(json.dumps(m))
    r = _workbench("info", root)
    assert r.returncode == 1
    line = _one_error_line(r.stderr, "info")
    assert "'../elsewhere.nii.gz' must be a path inside the study folder" in line and "symbolic link" in line


def test_a_joint_without_limits_takes_rotations_within_half_a_turn(study, tmp_path):
    root = shutil.copytree(study, tmp_path / "study")
    sk = json.loads((root / "skeleton.json").read_text(encoding="utf-8"))
    for j in sk["joints"]:
        j.pop("limits", None)
    (root / "skeleton.json").write_text(json.dumps(sk))
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"angles": {"knee": [1000, 0, 0]}}))
    r = _workbench("deform", root, "--pose", pose, "--out", tmp_path / "bent.nii.gz", "--method", "vbd")
    assert r.returncode == 1
    line = _one_error_line(r.stderr, "deform")
    assert f"{pose}: knee[0] = 1000° is more than half a turn (the joint has no 'limits'" in line, line
    assert not (tmp_path / "bent.nii.gz").exists()
    pose.write_text(json.dumps({"angles": {"knee": [170, 0, 0]}}))  # beyond the phantom's limits, within ±180°
    r = _workbench("deform", root, "--pose", pose, "--out", tmp_path / "bent.nii.gz", "--method", "vbd")
    assert r.returncode == 0, r.stderr
    info = _workbench("info", root, "--check")
    assert "have no 'limits': poses are checked only to keep their rotations within ±180°" in info.stderr


def _chattr(flag: str, path: Path) -> bool:
    return (
        shutil.which("chattr") is not None
        and subprocess.run(["chattr", flag, str(path)], capture_output=True).returncode == 0
    )


@pytest.mark.parametrize("what", ["folder", "manifest"])
def test_a_study_that_cannot_be_written_is_refused_before_any_work(study, tmp_path, what):
    """An immutable study folder (as a read-only mount: no new file) or an immutable study.json: one line naming
    it before any stage runs (it was '[Errno 30] ... .locks/bones.lock', or a failure after the weights' work)."""
    root = shutil.copytree(study, tmp_path / "study")
    shutil.rmtree(root / "skinning")
    target = root if what == "folder" else root / "study.json"
    if os.geteuid() != 0 or not _chattr("+i", target):
        pytest.skip("needs root and a file system with chattr +i (immutable files) to make an unwritable study")
    try:
        before = _tree(root)
        r = _workbench("weights", root)
        assert r.returncode == 1
        line = _one_error_line(r.stderr, "weights")
        assert f"{target}: cannot write there (Operation not permitted)" in line, line
        assert "chmod -R u+w" in line
        assert "weights: running" not in r.stderr
        assert _tree(root) == before
    finally:
        _chattr("-i", target)


# -- 2. Ctrl-C after the weights stage ran in the same process -------------------------------------------------
def test_ctrl_c_during_register_after_a_real_weights_stage_is_clean(study, tmp_path):
    """A fresh `workbench run` (harmonic weights: the tet mesh and its solve run in this process), SIGINT while
    the first registration's staging folder exists: rc 130, the message, no staging folder left.  A library that
    replaced Python's SIGINT handler (pytetwild did) made this a silent kill that left registration/.pose00.partial-…"""
    import signal
    import threading
    import time

    root = shutil.copytree(study, tmp_path / "study", ignore=shutil.ignore_patterns("skinning", "model"))
    m = json.loads((root / "study.json").read_text(encoding="utf-8"))
    m["stages"] = {}
    (root / "study.json").write_text(json.dumps(m))
    # SIGINT at its default in the child: a background job of a non-interactive shell ignores it, and a child
    # inherits that (see tests/workbench/test_run.py)
    # the start on every other voxel: a faster init stage (the signal is sent in register)
    proc = subprocess.Popen(
        [sys.executable, "-m", "workbench", "run", str(root), "--set", "init.map_factor=2"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        encoding="utf-8",
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    lines = []
    watchdog = threading.Timer(600, proc.kill)
    watchdog.start()
    try:
        for line in proc.stderr:
            lines.append(line)
            if "register pose00: running" in line:
                break
        deadline = time.monotonic() + 60
        while not list((root / "registration").glob(".pose00.partial-*")) and time.monotonic() < deadline:
            time.sleep(0.05)
        staged = list((root / "registration").glob(".pose00.partial-*"))
        proc.send_signal(signal.SIGINT)
        with proc.stderr:
            err = "".join(lines) + proc.stderr.read()
        rc = proc.wait(timeout=120)
    finally:
        watchdog.cancel()
    assert "weights: done" in err and "harmonic" in json.dumps(
        json.loads((root / "study.json").read_text(encoding="utf-8"))["stages"]["weights"]["settings"]
    )
    assert staged, err  # the signal came while the registration's outputs were being made
    assert rc == 130, err
    assert "workbench run: interrupted; nothing was left half-written" in err
    assert [p for p in root.rglob("*") if ".partial-" in p.name or ".tmp-" in p.name] == []
