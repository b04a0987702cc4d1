"""Keyframe animation: interpolation, keyframe files, and rendered MP4 / GIF / PNG output of a bending knee."""

from __future__ import annotations

import json

import numpy as np
import pytest

from workbench.cli import main
from workbench.errors import InputFileError, OutputExistsError
from workbench.viz.animate import Keyframes, animate_study, builtin_keyframes, read_keyframes
from workbench.viz.render import offscreen_available

_skip_no_gl = pytest.mark.skipif(not offscreen_available(), reason="no off-screen OpenGL (EGL or OSMesa) here")


def needs_gl(test):
    """Rendering tests: marked ``render`` and skipped where no off-screen OpenGL context exists."""
    return pytest.mark.render(_skip_no_gl(test))


@pytest.fixture(scope="module")
def study(phantom, tmp_path_factory):
    """A noise-free test-size knee with distance weights (VBD animation; no model)."""
    from workbench.study import write_phantom_study

    root = write_phantom_study(
        phantom("knee", size="test", n_poses=2, seed=3, noise=False), tmp_path_factory.mktemp("animate") / "study"
    ).root
    assert main(["weights", str(root), "--method", "distance", "--quiet"]) == 0
    return root


@pytest.fixture(scope="module")
def skeleton(study):
    from workbench.study import read_study

    return read_study(study).skeleton()


def _read_mp4(path) -> np.ndarray:
    """Every decoded frame of a video, through imageio-ffmpeg's own ffmpeg binary.

    The stream's size is read from ffmpeg's description of the file, the frames as raw RGB (one
    subprocess, closed; imageio's frame readers leave pipes open, an error under our warning filters).
    """
    import re
    import subprocess

    import imageio_ffmpeg

    exe = imageio_ffmpeg.get_ffmpeg_exe()
    info = subprocess.run(
        [exe, "-hide_banner", "-i", str(path)], capture_output=True, text=True, encoding="utf-8"
    ).stderr
    w, h = (int(v) for v in re.search(r"Video: .*?, (\d+)x(\d+)", info).groups())
    raw = subprocess.run(
        [exe, "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "rgb24", "-"],
        capture_output=True,
        check=True,
    ).stdout
    assert len(raw) % (w * h * 3) == 0
    return np.frombuffer(raw, np.uint8).reshape(-1, h, w, 3)


def _keys(tmp_path, doc, name="keys.json"):
    p = tmp_path / name
    p.write_text(json.dumps(doc))
    return p


def _bend(t1=1.0, deg=40.0, interpolation="smooth"):
    return {
        "format": "avw-keyframes",
        "version": 1,
        "skeleton": "knee",
        "interpolation": interpolation,
        "keyframes": [
            {"time": 0.0, "angles": {"knee": [0, 0, 0]}},
            {
                "time": t1,
                "angles": {"knee": [deg, 0, 0], "tibiofibular": [deg, 0, 0], "patellofemoral": [0.7 * deg, 0, 0]},
            },
        ],
    }  # the phantom's couplings


def test_interpolation_is_smoothstep_or_linear_between_keyframes(tmp_path, skeleton):
    kf = read_keyframes(_keys(tmp_path, _bend(2.0, 40.0)), skeleton)
    # smoothstep s(u) = u²(3 − 2u): s(0.25) = 0.15625, s(0.5) = 0.5; clamped outside [0, 2] s
    assert kf.at(0.5)["knee"][0] == pytest.approx(40.0 * 0.15625)
    assert kf.at(1.0)["knee"][0] == pytest.approx(20.0)
    assert kf.at(-1.0)["knee"][0] == 0.0 and kf.at(5.0)["knee"][0] == pytest.approx(40.0)
    assert kf.at(1.0)["patellofemoral"][0] == pytest.approx(14.0)
    one = _bend(2.0, 40.0)
    del one["keyframes"][1]["angles"]["patellofemoral"]
    assert read_keyframes(_keys(tmp_path, one, "one.json"), skeleton).at(1.0)["patellofemoral"][0] == 0.0  # left out: 0
    lin = read_keyframes(_keys(tmp_path, _bend(2.0, 40.0, "linear"), "lin.json"), skeleton)
    assert lin.at(0.5)["knee"][0] == pytest.approx(10.0)
    assert np.allclose(kf.frame_times(5), [0.0, 0.5, 1.0, 1.5, 2.0])


def test_bad_keyframe_files_name_the_problem(tmp_path, skeleton):
    bad = _bend()
    bad["keyframes"][1]["angles"]["elbow"] = [1, 2, 3]
    with pytest.raises(InputFileError, match="keyframe 1: unknown joint 'elbow'"):
        read_keyframes(_keys(tmp_path, bad), skeleton)
    bad = _bend()
    bad["keyframes"][1]["angles"]["knee"] = [10, 0]
    with pytest.raises(InputFileError, match="takes 3 values"):
        read_keyframes(_keys(tmp_path, bad), skeleton)
    bad = _bend()
    bad["keyframes"][1]["time"] = 0.0
    with pytest.raises(InputFileError, match="increase strictly"):
        read_keyframes(_keys(tmp_path, bad), skeleton)
    bad = _bend()
    bad["skeleton"] = "hand"
    with pytest.raises(InputFileError, match="skeleton is 'knee'"):
        read_keyframes(_keys(tmp_path, bad), skeleton)
    with pytest.raises(InputFileError, match="not a keyframe file"):
        read_keyframes(_keys(tmp_path, {"angles": {}}), skeleton)
    for key, value, message in (("time", None, "'time' must be a number"), ("time", "a", "'time' must be a number")):
        bad = _bend()
        bad["keyframes"][0][key] = value
        with pytest.raises(InputFileError, match=message):
            read_keyframes(_keys(tmp_path, bad), skeleton)
    bad = _bend()
    bad["keyframes"][1]["angles"]["knee"] = ["x", 0, 0]
    with pytest.raises(InputFileError, match="list of numbers"):
        read_keyframes(_keys(tmp_path, bad), skeleton)
    for camera, message in (
        ({"zoom": None}, "zoom must be a number"),
        ({"view": "side"}, "camera view"),
        ({"zoom": -1}, "zoom must be > 0"),
        ({"spin": 1}, "unknown keys"),
    ):
        bad = _bend()
        bad["camera"] = camera
        with pytest.raises(InputFileError, match=message) as e:
            read_keyframes(_keys(tmp_path, bad), skeleton)
        assert "keys.json" in str(e.value)  # the message names the file
    bad = _bend()
    bad["fps"] = True
    with pytest.raises(InputFileError, match="fps must be a positive number"):
        read_keyframes(_keys(tmp_path, bad), skeleton)
    bad = _bend()
    bad["keyframes"][1]["angles"]["knee"] = [1000, 0, 0]  # a 1000° knee: outside the skeleton's range of motion
    with pytest.raises(InputFileError, match=r"keyframe 1: knee\[0\] = 1000° outside \[-10, 150\]"):
        read_keyframes(_keys(tmp_path, bad), skeleton)


def test_ready_keyframes_fit_the_phantom_skeletons():
    from validation.phantoms.hand import skeleton as hand_skeleton
    from validation.phantoms.knee import complete_angles
    from validation.phantoms.knee import skeleton as knee_skeleton

    knee = builtin_keyframes(knee_skeleton())
    assert knee.angles[0]["knee"][0] == 0 and max(a["knee"][0] for a in knee.angles) == 60  # bend, straighten
    for a in knee.angles:  # the phantom's couplings: fibula with the tibia, patella 70 % of the flexion
        want = complete_angles({"knee": a["knee"]})
        assert np.allclose(a["tibiofibular"], want["tibiofibular"]) and np.allclose(
            a["patellofemoral"], want["patellofemoral"]
        )
    hand = builtin_keyframes(hand_skeleton())
    names = hand.names
    assert names[0] == "open" and "fist" in names and "point" in names
    point = hand.angles[names.index("point")]
    assert np.all(point["index_pip"] == 0) and all(point[f"{f}_pip"][0] > 45 for f in ("middle", "ring", "little"))


@needs_gl
def test_animate_writes_an_mp4_of_differing_frames(tmp_path, study):
    keys = _keys(tmp_path, _bend(1.0, 40.0, "linear"))
    out = tmp_path / "bend.mp4"
    s = animate_study(study, out, keyframes=keys, size=(160, 120), n_frames=6)
    assert s["frames"] == 6 and s["method"] == "vbd"
    frames = _read_mp4(out)
    assert frames.shape == (6, 120, 160, 3)
    # 8° of flexion between frames moves the shank by ~1.4 voxels per 10 cm: consecutive frames differ
    # well above H.264's quantisation noise (a still scene decodes to < 0.5 grey levels of difference)
    d = [np.abs(frames[i + 1].astype(int) - frames[i]).mean() for i in range(5)]
    assert min(d) > 0.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bend.mp4", "keys.json"]  # no temporaries left
    with pytest.raises(OutputExistsError):
        animate_study(study, out, keyframes=keys, size=(160, 120), n_frames=6)


@needs_gl
def test_animate_gif_and_numbered_png_frames(tmp_path, study):
    import imageio.v3 as iio

    keys = _keys(tmp_path, _bend(1.0, 30.0))
    gif = tmp_path / "bend.gif"
    animate_study(study, gif, keyframes=keys, size=(96, 72), n_frames=4, fps=10)
    g = np.stack(list(iio.imiter(gif)))
    assert g.shape[:3] == (4, 72, 96)
    pngs = tmp_path / "frames"
    pngs.mkdir()
    s = animate_study(study, pngs / "k.png", keyframes=keys, size=(96, 72), n_frames=3)
    files = sorted(p.name for p in pngs.iterdir())
    assert files == ["k_0000.png", "k_0001.png", "k_0002.png"] and s["files"] == 3
    first, last = iio.imread(pngs / files[0]), iio.imread(pngs / files[-1])
    assert first.shape == (72, 96, 3) and np.abs(first.astype(int) - last).mean() > 0.5
    with pytest.raises(OutputExistsError):
        animate_study(study, pngs / "k.png", keyframes=keys, size=(96, 72), n_frames=3)
    with pytest.raises(ValueError, match="extension"):
        animate_study(study, tmp_path / "bend.avi", keyframes=keys)


@needs_gl
def test_cli_render_and_animate(tmp_path, study, capsys):
    import imageio.v3 as iio

    png = tmp_path / "t.png"
    assert (
        main(["render", str(study), "--out", str(png), "--size", "160x120", "--clip", "z:0.5", "--bones", "--quiet"])
        == 0
    )
    img = iio.imread(png)
    assert img.shape == (120, 160, 3) and (img.max(axis=2) > 12).mean() > 0.02
    assert main(["render", str(study), "--out", str(png), "--quiet"]) == 1  # exists, no --force
    assert "--force" in capsys.readouterr().err
    assert main(["render", str(study), "--out", str(tmp_path / "o.png"), "--size", "161x120"]) == 1
    assert "even" in capsys.readouterr().err
    assert (
        main(
            [
                "render",
                str(study),
                "--scan",
                "pose01",
                "--overlay",
                "pose00",
                "--out",
                str(tmp_path / "ov.png"),
                "--size",
                "160x120",
                "--quiet",
            ]
        )
        == 0
    )
    assert main(["render", str(study), "--scan", "nope", "--out", str(tmp_path / "x.png"), "--quiet"]) == 1
    assert "no scan 'nope'" in capsys.readouterr().err
    assert main(["render", str(study), "--overlay", "pose01", "--bones", "--out", str(tmp_path / "y.png")]) == 1
    assert "leave them out" in capsys.readouterr().err
    assert main(["render", str(study), "--control-points", "--out", str(tmp_path / "c.png")]) == 1
    assert "pass --registered ID" in capsys.readouterr().err
    plain, marked = tmp_path / "p.png", tmp_path / "m.png"
    assert main(["render", str(study), "--scan", "pose01", "--out", str(plain), "--size", "160x120", "--quiet"]) == 0
    assert (
        main(
            [
                "render",
                str(study),
                "--scan",
                "pose01",
                "--markers",
                "--out",
                str(marked),
                "--size",
                "160x120",
                "--quiet",
            ]
        )
        == 0
    )
    a, b = iio.imread(plain).astype(int), iio.imread(marked).astype(int)
    white = (b.min(axis=2) > 150) & (np.abs(b - a).sum(axis=2) > 60)  # the markers are white spheres
    assert white.sum() > 3
    mp4 = tmp_path / "a.mp4"
    assert (
        main(
            ["animate", str(study), "--out", str(mp4), "--frames", "4", "--size", "96x72", "--quiet", "--mapper", "gpu"]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "4 frames 96x72" in out and "gpu mapper" in out  # --mapper reaches the renderer
    assert _read_mp4(mp4).shape == (4, 72, 96, 3)


def test_animate_into_a_folder_it_cannot_write_says_so_before_any_frame(tmp_path, study, capsys, monkeypatch):
    """An MP4 or GIF into a read-only or missing folder: one line naming --out, no "Broken pipe" from ffmpeg
    after the frames were made, no traceback, nothing left."""
    import errno
    import tempfile

    def refuse(*a, **k):  # a read-only file system (as root os.access cannot see it): the probe write fails
        raise OSError(errno.EROFS, "Read-only file system")

    for name in ("a.mp4", "a.gif"):
        monkeypatch.setattr(tempfile, "mkstemp", refuse)
        capsys.readouterr()
        assert main(["animate", str(study), "--out", str(tmp_path / name), "--frames", "4", "--size", "96x72"]) == 1
        monkeypatch.undo()
        err = capsys.readouterr().err.strip().splitlines()
        assert "frame" not in " ".join(err) and any("--out" in e and "Read-only file system" in e for e in err), err
        assert not any("Traceback" in e or "Broken pipe" in e for e in err)
    assert main(["animate", str(study), "--out", str(tmp_path / "missing" / "a.gif"), "--frames", "4"]) == 1
    assert "mkdir -p" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_keyframes_dataclass_needs_two_frames():
    kf = Keyframes(np.array([0.0, 1.0]), [{"knee": np.zeros(3)}, {"knee": np.ones(3)}])
    with pytest.raises(ValueError, match="at least 2 frames"):
        kf.frame_times(1)


def test_covering_grid_extends_the_grid_by_whole_voxels():
    from deformation.geometry import GridGeometry, covering_grid

    g = GridGeometry(
        (10, 8, 6), (2.0, 1.5, 3.0), (-9.0, -5.25, 0.0), ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    )
    w = g.index_to_world(np.array([[0, 0, 0], [9, 7, 5]], float))
    lo, hi = w.min(axis=0), w.max(axis=0)
    # a box 4 mm beyond the grid in -z and 2.9 mm beyond in +y (world), inside elsewhere
    box = (lo[0] + 1, hi[0] - 1, lo[1] + 1, hi[1] + 2.9, lo[2] - 4.0, hi[2] - 1)
    big = covering_grid(g, box)
    ijk = big.world_to_index(g.index_to_world(np.array([[0, 0, 0]], float)))[0]
    assert np.allclose(ijk, np.round(ijk))  # the old voxel centres are voxel centres of the new grid
    # world +y is index axis i (column 0 of the direction): 2.9 mm / 2.0 mm spacing -> 2 more voxels;
    # world -z is axis k: 4 mm / 3 mm -> 2 more voxels below; the rest unchanged
    assert big.size == (12, 8, 8)
    corners = big.index_to_world(np.array([[0, 0, 0], [11, 7, 7]], float))
    assert corners.min(axis=0)[2] <= box[4] and corners.max(axis=0)[1] >= box[3]
    assert covering_grid(g, box, max_growth=1.0).size == g.size  # growth capped
