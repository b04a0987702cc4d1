"""`workbench reproduce`: tables written as CSV, Markdown and JSON, and the protocols run through the stages."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from validation.protocols import Column, Table
from workbench.cli import main
from workbench.reproduce import format_csv, format_markdown, write_table


def _table():
    t = Table(
        "demo",
        "A demo table",
        [Column("med_mm", "MED", "mm"), Column("cc", "CC", "", 3), Column("n", "scans", "", 0)],
        definitions={"med_mm": "mean distance"},
        notes=["a note"],
    )
    t.add("ours", "ours", {"med_mm": 1.0 / 3.0, "cc": 0.91234, "n": 3})
    t.add("paper", "paper", {"med_mm": 3.5, "cc": None, "n": None})
    return t


def test_markdown_has_units_in_headings_rounded_cells_definitions_and_notes():
    md = format_markdown(_table())
    assert "| MED (mm) | CC | scans |" in md
    assert "| ours | 0.33 | 0.912 | 3 |" in md
    assert "| paper | 3.50 |  |  |" in md
    assert "- **med_mm**: mean distance" in md and "- a note" in md


def test_csv_keeps_full_precision():
    rows = list(csv.DictReader(format_csv(_table()).splitlines()))
    assert float(rows[0]["med_mm"]) == 1.0 / 3.0  # repr round-trips the float exactly
    assert rows[1]["cc"] == "" and rows[1]["kind"] == "paper"


def test_write_table_writes_all_three_files_or_none(tmp_path):
    paths = write_table(_table(), tmp_path)
    assert sorted(p.name for p in paths) == ["demo.csv", "demo.json", "demo.md"]
    assert Table.from_dict(json.loads((tmp_path / "demo.json").read_text(encoding="utf-8"))).value("ours", "n") == 3
    bad = _table()
    bad.id = "bad"
    bad.meta = {1: "an integer key JSON cannot hold"}
    with pytest.raises(TypeError):
        write_table(bad, tmp_path)
    assert not list(tmp_path.glob("bad.*"))  # nothing half-written


def test_reproduce_eigenposes_from_the_command_line(tmp_path, capsys):
    assert main(["reproduce", "eigenposes", "--out", str(tmp_path), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "Eigenposes of a hand pose library" in out
    doc = json.loads((tmp_path / "eigenposes.json").read_text(encoding="utf-8"))
    ours = next(r for r in doc["rows"] if r["kind"] == "ours")
    cum = np.asarray(doc["meta"]["cumulative_variance"])
    assert ours["variance_10"] == pytest.approx(cum[9]) and 0.9 <= cum[9] <= 1.0
    assert (tmp_path / "eigenposes.csv").exists() and (tmp_path / "eigenposes.md").exists()


def test_unknown_table_is_refused_by_the_parser(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["reproduce", "table9", "--out", str(tmp_path)])
    assert "invalid choice: 'table9'" in capsys.readouterr().err


# slow: ~50 s from nothing here (phantom and stages ~15 s, Rhee's Algorithm 1 ~35 s), then ~35 s again for the
# rerun (Algorithm 1's row is not a stage's, so nothing caches it)
@pytest.mark.slow
def test_reproduce_table2_through_the_stages(tmp_path, capsys):
    """Rhee Table 2 at test size through the stages: a phantom study is written and run, then reused; beside the
    pipeline's registration, Rhee's Algorithm 1 as implemented here from the same (identity) start."""
    from validation.protocols.registration import ALGORITHM1_ROW

    assert main(["reproduce", "table2", "--out", str(tmp_path), "--quiet"]) == 0
    t = Table.from_dict(json.loads((tmp_path / "table2.json").read_text(encoding="utf-8")))
    src, reg = t.row("source (no deformation)"), t.row("registered (ours)")
    # Rhee's own reduction was 5.5 -> 3.5 mm; a registration that works removes at least half of the start's MED
    assert reg["med_mm"] < 0.5 * src["med_mm"]
    assert reg["cc"] > src["cc"]
    alg1 = t.row(ALGORITHM1_ROW)
    assert alg1["kind"] == "ours" and alg1["n_scans"] == 1
    assert all(np.isfinite(alg1[k]) for k in ("med_mm", "cc", "seconds"))
    # Algorithm 1 must improve on no deformation by at least the reduction Rhee reported for it on this
    # protocol (5.5 -> 3.5 mm, -36 %: bound 0.64 x the source's MED).  Measured here: 7.17 -> 2.48 mm (-65 %),
    # so the bound leaves room for the phantom's or the defaults' drift, while a registration that barely
    # moves (ratio ~1) fails it
    assert alg1["med_mm"] < 0.64 * src["med_mm"]
    assert alg1["cc"] > src["cc"]
    for doc in (
        (tmp_path / "table2.md").read_text(encoding="utf-8"),
        (tmp_path / "table2.csv").read_text(encoding="utf-8"),
    ):
        assert ALGORITHM1_ROW in doc  # in every format written (JSON above; the HTML report draws every row)
    assert (tmp_path / "studies" / "table2-test" / "study.json").exists()
    capsys.readouterr()
    manifest = (tmp_path / "studies" / "table2-test" / "study.json").read_bytes()
    assert main(["reproduce", "table2", "--out", str(tmp_path), "--quiet"]) == 0
    # every stage reused: the manifest (finish times, digests) is untouched, the table the same
    assert (tmp_path / "studies" / "table2-test" / "study.json").read_bytes() == manifest
    again = Table.from_dict(json.loads((tmp_path / "table2.json").read_text(encoding="utf-8")))
    assert again.row("registered (ours)")["med_mm"] == reg["med_mm"]
    assert again.row(ALGORITHM1_ROW)["med_mm"] == alg1["med_mm"]  # run again, from the same start: the same bits


@pytest.mark.slow
def test_two_workers_give_the_same_tables(tmp_path, capsys):
    """`--workers 2` runs table2's study and the eigenposes in two Dask processes: the same numbers as one
    process (the second folder starts from a copy of the first's studies with their stage outputs, so only the
    registration and the tables are redone)."""
    one = tmp_path / "one"
    assert main(["reproduce", "table2", "eigenposes", "--out", str(one), "--quiet"]) == 0
    two = tmp_path / "two"
    two.mkdir()
    import shutil

    shutil.copytree(one / "studies", two / "studies")
    st = two / "studies" / "table2-test"
    shutil.rmtree(st / "registration")
    shutil.rmtree(st / "validation")
    m = json.loads((st / "study.json").read_text(encoding="utf-8"))
    for k in ("init", "register", "validate"):
        m["stages"].pop(k, None)
    (st / "study.json").write_text(json.dumps(m))
    capsys.readouterr()
    assert main(["reproduce", "table2", "eigenposes", "--out", str(two), "--workers", "2"]) == 0
    err = capsys.readouterr().err
    assert "side by side on a local Dask cluster of 2 worker processes" in err
    a = Table.from_dict(json.loads((one / "eigenposes.json").read_text(encoding="utf-8")))
    b = Table.from_dict(json.loads((two / "eigenposes.json").read_text(encoding="utf-8")))
    assert [r for r in a.rows if r["kind"] == "ours"] == [r for r in b.rows if r["kind"] == "ours"]
    # the registration again, in a worker process: the same bits (its time aside)
    ra = Table.from_dict(json.loads((one / "table2.json").read_text(encoding="utf-8"))).row("registered (ours)")
    rb = Table.from_dict(json.loads((two / "table2.json").read_text(encoding="utf-8"))).row("registered (ours)")
    assert {k: v for k, v in ra.items() if k != "seconds"} == {k: v for k, v in rb.items() if k != "seconds"}
    from validation.protocols.registration import ALGORITHM1_ROW

    aa = Table.from_dict(json.loads((one / "table2.json").read_text(encoding="utf-8"))).row(ALGORITHM1_ROW)
    ab = Table.from_dict(json.loads((two / "table2.json").read_text(encoding="utf-8"))).row(ALGORITHM1_ROW)
    assert {k: v for k, v in aa.items() if k != "seconds"} == {k: v for k, v in ab.items() if k != "seconds"}
    assert main(["reproduce", "eigenposes", "--out", str(two), "--workers", "0"]) == 1
    assert "--workers must be at least 1" in capsys.readouterr().err


def test_a_study_of_other_explicit_poses_is_not_reused():
    """The runner reuses a protocol's study only when its recorded phantom poses are the wanted ones: every
    DOF compared (the phantom records all of them; a wanted joint given with fewer values has zeros after)."""
    from workbench.reproduce import same_poses

    rec = [{"id": "a", "angles_deg": {"knee": [10.0, 0.0, 0.0]}}]
    assert same_poses(rec, (("a", {"knee": [10.0, 0.0, 0.0]}),))
    assert same_poses(rec, (("a", {"knee": [10.0]}),))
    assert not same_poses(rec, (("a", {"knee": [12.0, 0.0, 0.0]}),))
    assert not same_poses([{"id": "a", "angles_deg": {"knee": [10.0, 5.0, 0.0]}}], (("a", {"knee": [10.0]}),))
    assert not same_poses([{"id": "a", "angles_deg": {"knee": [10.0]}}], (("a", {"knee": [10.0, 0.0, 1.0]}),))
    assert not same_poses(rec, (("b", {"knee": [10.0, 0.0, 0.0]}),))
    assert not same_poses(None, (("a", {"knee": [10.0]}),))
