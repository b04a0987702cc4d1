"""The HTML report's pieces: the overlay's colours, the report of a `workbench reproduce` folder.

A study's report (every table and picture, a study without truth, bad outputs, headless Chromium) is tested
in test_run.py, on the study that module runs once (a second pipeline run here would cost minutes).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.workbench.report_checks import decode, parse
from workbench.cli import main


def test_overlay_uses_the_papers_colours():
    """Target magenta, template green (Rhee Figs. 8-9): a square only in the target is magenta, one only in the
    template green, their overlap grey; an anisotropic plane is drawn to its millimetre aspect."""
    from workbench.report import figures as F

    target = np.zeros((10, 20))
    template = np.zeros((10, 20))
    target[2:5, 2:8] = 1.0
    template[2:5, 12:18] = 1.0
    target[6:9, 8:12] = template[6:9, 8:12] = 1.0
    img = np.asarray(F.overlay(target, template, (2.0, 1.0), ((0.0, 1.0), (0.0, 1.0))), float)
    assert img.shape[0] == img.shape[1]  # 10 rows of 2 mm, 20 columns of 1 mm: a square picture
    h, w = img.shape[:2]

    def at(r, c):  # the picture's pixel at array row r, column c (cell centres)
        return img[int((r + 0.5) * h / 10), int((c + 0.5) * w / 20)]

    assert at(3, 4) == pytest.approx([255, 0, 255], abs=2)  # target only: magenta
    assert at(3, 15) == pytest.approx([0, 255, 0], abs=2)  # template only: green
    assert at(7, 10) == pytest.approx([255, 255, 255], abs=2)  # both: white/grey
    assert at(0, 0) == pytest.approx([0, 0, 0], abs=2)


def test_report_of_a_reproduce_folder_has_every_table(tmp_path):
    tables = tmp_path / "tables"
    assert main(["reproduce", "eigenposes", "--out", str(tables), "--quiet"]) == 0
    out = tmp_path / "tables.html"
    assert main(["report", str(tables), "--out", str(out), "--quiet"]) == 0
    p = parse(out)
    assert any(h.startswith("Eigenposes") for h in p.headings)
    t = next(t for t in p.tables if t[0][1:3] == ["poses", "joint rotations"])
    assert [r[0] for r in t[1:]] == ["ours", "paper (Rhee §6.2, Poser poses)"]
    for src in p.images:
        decode(src)
    # a JSON file cut short beside the tables is named in the report, the tables still there
    (tables / "table3.json").write_text('{"format": "avw-table", "id": "tab', encoding="utf-8")
    out2 = tmp_path / "tables2.html"
    assert main(["report", str(tables), "--out", str(out2), "--quiet"]) == 0
    p2 = parse(out2)
    assert p2.headings[0] == "Files not read" and "table3.json" in out2.read_text(encoding="utf-8")
    assert any(h.startswith("Eigenposes") for h in p2.headings)


def test_control_point_map_of_rhee_algorithm_1():
    """The adaptive method's accepted steps drawn per block level (Rhee Fig. 9), projected on the scan's yz
    plane: the projection is the plane's own mm frame, both levels appear in their colours, the dense method
    has no such map."""
    import io

    from PIL import Image

    from deformation.geometry import GridGeometry, Volume
    from workbench.report import control_points
    from workbench.report import figures as F

    c, s = np.cos(0.3), np.sin(0.3)
    g = GridGeometry((32, 24, 20), (1.5, 1.0, 2.0), (-3.0, 4.0, 5.0), (c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0))
    data = np.zeros(g.array_shape, np.float32)
    data[4:16, 4:20, 6:26] = 100.0  # a body in air
    scan = Volume(data, g)
    log = {
        "summary": {},
        "log": {
            "settings": {"inset": 0.25, "min_block_voxels": 4},
            "steps": [
                {"level": 2, "block": [1, 2, 0], "accepted": True},
                {"level": 2, "block": [0, 0, 0], "accepted": False},
                {"level": 3, "block": [2, 1, 1], "accepted": True},
            ],
        },
    }

    class Study:
        def registration_log(self, sid):
            return log

        def scan(self, sid):
            return scan

    png, caption = control_points(Study(), "s1")
    assert "(2 steps)" in caption
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), int)
    for colour in ((31, 119, 180), (255, 127, 14)):  # matplotlib's C0 (level 2) and C1 (level 3)
        assert np.sum(np.abs(img - colour).sum(-1) < 40) > 5, colour
    # index (i, j, k) → the yz picture's (column, row) mm: voxel centres, rows counted up from k = 0
    p = np.array([[3.0, 5.0, 7.0]])
    assert F.plane_point_coordinates(p, (1.5, 1.0, 2.0), "yz")[0] == pytest.approx([5.5 * 1.0, 7.5 * 2.0])
    assert F.plane_point_coordinates(p, (1.5, 1.0, 2.0), "xy")[0] == pytest.approx([3.5 * 1.5, 5.5 * 1.0])
    log = {"summary": {"levels": [{"level": 0, "shrink": 4, "lncc": [0.1, 0.2]}]}}  # the dense method's log
    assert control_points(Study(), "s1") is None


def test_renders_embed_pictures_and_mp4_videos(tmp_path):
    """An animation in renders/ (workbench animate's MP4) is embedded whole as a looping video; a file that is
    neither a picture nor a video is named in the report, not fatal."""
    import base64

    import imageio_ffmpeg

    from workbench.report import renders_section
    from workbench.report.html import Page

    renders = tmp_path / "renders"
    renders.mkdir()
    w = imageio_ffmpeg.write_frames(str(renders / "bend.mp4"), (64, 48), fps=5, macro_block_size=16)
    w.send(None)
    for k in range(5):
        w.send(np.full((48, 64, 3), 40 * k, np.uint8).tobytes())
    w.close()
    (renders / "broken.png").write_bytes(b"not a picture")

    class Study:
        root = tmp_path

    page = Page("t")
    renders_section(page, Study())
    html = page.html()
    src = html.split('<video src="', 1)[1].split('"', 1)[0]
    assert src.startswith("data:video/mp4;base64,")
    assert base64.b64decode(src.split(",", 1)[1]) == (renders / "bend.mp4").read_bytes()
    assert "broken.png" in html and "not embedded" in html
