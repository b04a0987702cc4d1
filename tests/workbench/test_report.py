"""The HTML validation report (`workbench report`, the report stage): every table and picture present, and the
page drawn by a real browser (headless Chromium) is not blank.

One test-size knee study runs once for the module, with the small configuration of test_run.py (distance
weights, a short registration budget): the report's plumbing is under test, not the registration's accuracy.
"""

from __future__ import annotations

import base64
import io
import json
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from workbench.cli import main

SETTINGS = ["--set", "weights.method=\"distance\"", "--set", "register.max_steps_per_level=20"]
MAX_BYTES = 5 * 2**20  # issue J: a test-size report stays under ~5 MB


class _Parse(HTMLParser):
    """Tables (rows of cell texts), images (src), toggles, section headings and scripts of a page."""

    def __init__(self):
        super().__init__()
        self.tables, self.images, self.toggles, self.headings, self.external = [], [], 0, [], []
        self._cell = None
        self._h2 = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = ""
        elif tag == "img":
            self.images.append(a.get("src", ""))
        elif tag == "div" and a.get("class") == "toggle":
            self.toggles += 1
        elif tag == "h2":
            self._h2 = True
            self.headings.append("")
        for k in ("src", "href"):
            v = a.get(k)
            if v and not v.startswith(("data:", "#")):
                self.external.append(v)

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append(self._cell.strip())
            self._cell = None
        elif tag == "h2":
            self._h2 = False

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data
        if self._h2:
            self.headings[-1] += data


def _parse(path: Path) -> _Parse:
    p = _Parse()
    p.feed(path.read_text(encoding="utf-8"))
    return p


def _decode(src: str):
    from PIL import Image

    assert src.startswith("data:image/"), src[:40]
    data = base64.b64decode(src.split(",", 1)[1], validate=True)
    img = Image.open(io.BytesIO(data))
    img.load()  # decodes every pixel (verify() checks only the structure)
    return img


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("report") / "knee"
    assert main(["phantom", "knee", "--out", str(root), "--quiet"]) == 0
    proc = subprocess.run([sys.executable, "-m", "workbench", "run", str(root), *SETTINGS, "--quiet"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return root


@pytest.fixture(scope="module")
def report(study, tmp_path_factory):
    out = tmp_path_factory.mktemp("report-out") / "knee.html"
    assert main(["report", str(study), "--out", str(out), "--quiet"]) == 0
    return out


def test_run_ends_with_the_report_stage(study):
    m = json.loads((study / "study.json").read_text())
    assert "report" in m["stages"]
    assert (study / "report" / "report.html").exists()


def test_every_table_and_picture_of_a_study_with_truth(study, report):
    p = _parse(report)
    scans = json.loads((study / "study.json").read_text())["scans"]
    assert report.stat().st_size < MAX_BYTES
    assert not p.external  # self-contained: nothing fetched
    assert p.headings[:2] == ["Bone poses and joints", "Registration"] and p.headings[-1].startswith("Software")
    # the pose tables: one row per joint; the angle table a column per scan
    joints = next(t for t in p.tables if t[0][:2] == ["joint", "DOF"])
    angles = next(t for t in p.tables if t[0][0] == "joint" and len(t[0]) == len(scans) + 1)
    assert len(joints) == len(angles) > 1
    # the similarity table: one row per scan, every cell filled
    sim = next(t for t in p.tables if t[0][:2] == ["scan", "start"])
    assert len(sim) == len(scans) + 1 and all(c != "" for row in sim[1:] for c in row[2:8])
    # with truth: source / initialised / registered per scan, MED a number
    truth_tables = [t for t in p.tables if t[0][:2] == ["volume", "MED (mm)"]]
    assert len(truth_tables) == len(scans)
    for t in truth_tables:
        assert [r[0] for r in t[1:]] == ["source", "initialised", "registered"]
        assert all(float(r[1]) >= 0 for r in t[1:])
    # every embedded picture decodes, with real content (not one flat colour)
    assert len(p.images) >= len(scans) * 10
    for src in p.images:
        a = np.asarray(_decode(src).convert("L"), float)
        assert a.size > 100 and a.std() > 1.0
    assert p.toggles == 3 * len(scans)  # three planes per scan
    text = report.read_text(encoding="utf-8")
    assert "Study digest" in text and "SimpleITK" in text


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


def test_a_study_without_truth_reports_similarity_and_no_med(study, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(study, bare, ignore=shutil.ignore_patterns("truth", "validation", "report", ".locks"))
    m = json.loads((bare / "study.json").read_text())
    for s in m["scans"]:
        s.pop("truth", None)
    m["stages"].pop("validate", None)
    m["stages"].pop("report", None)
    (bare / "study.json").write_text(json.dumps(m))
    out = tmp_path / "bare.html"
    assert main(["report", str(bare), "--out", str(out), "--quiet"]) == 0
    p = _parse(out)
    assert not [t for t in p.tables if t[0][:2] == ["volume", "MED (mm)"]]
    assert len(next(t for t in p.tables if t[0][:2] == ["scan", "start"])) == len(m["scans"]) + 1
    assert "without ground truth" in out.read_text(encoding="utf-8")


def test_report_refuses_bad_outputs_and_sources_before_any_work(study, report, tmp_path, capsys):
    before = report.read_bytes()
    assert main(["report", str(study), "--out", str(report)]) == 1
    assert "already exists" in capsys.readouterr().err and report.read_bytes() == before
    assert main(["report", str(study), "--out", str(tmp_path / "r.pdf")]) == 1
    assert "ending in .html" in capsys.readouterr().err
    assert main(["report", str(study), "--out", str(tmp_path / "missing" / "r.html")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert main(["report", str(tmp_path), "--out", str(tmp_path / "r.html")]) == 1
    assert "neither a study folder" in capsys.readouterr().err
    assert not (tmp_path / "r.html").exists()


def test_report_of_a_reproduce_folder_has_every_table(tmp_path):
    tables = tmp_path / "tables"
    assert main(["reproduce", "eigenposes", "--out", str(tables), "--quiet"]) == 0
    out = tmp_path / "tables.html"
    assert main(["report", str(tables), "--out", str(out), "--quiet"]) == 0
    p = _parse(out)
    assert any(h.startswith("Eigenposes") for h in p.headings)
    t = next(t for t in p.tables if t[0][1:3] == ["poses", "joint rotations"])
    assert [r[0] for r in t[1:]] == ["ours", "paper (Rhee §6.2, Poser poses)"]
    for src in p.images:
        _decode(src)


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def test_report_opens_in_headless_chromium(report, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip("headless Chromium is not installed (make test installs Debian's chromium when run as root; "
                    "else: sudo apt-get install chromium)")
    shot = tmp_path / "shot.png"
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={tmp_path / 'profile'}", "--hide-scrollbars", "--window-size=1280,2400",
           f"--screenshot={shot}", report.resolve().as_uri()]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert shot.exists(), proc.stderr[-2000:]
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB"), float)
    assert img.shape[:2] == (2400, 1280)
    # not blank: the header's dark band is drawn, and the page holds many colours (tables, plots, slices)
    header = img[5:60, 5:600]
    assert np.abs(header - np.array([0x2B, 0x25, 0x40])).mean() < 25
    colours = np.unique((img[::4, ::4] // 8).reshape(-1, 3), axis=0)
    assert len(colours) > 200
    assert (np.abs(img - img[-1, -1]).sum(axis=-1) > 30).mean() > 0.2  # a fifth of the page differs from its corner
