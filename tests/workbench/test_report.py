"""The HTML report's pieces: the overlay's colours, the report of a `workbench reproduce` folder.

A study's report (every table and picture, a study without truth, bad outputs, headless Chromium) is tested
in test_run.py, on the study that module runs once (a second pipeline run here would cost minutes).
"""

from __future__ import annotations

import numpy as np
import pytest

from report_checks import decode, parse
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
