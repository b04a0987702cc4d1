"""Landmark files (Kurihara §4's hand-picked feature points): JSON and CSV, checked before any work."""

from __future__ import annotations

import json

import numpy as np
import pytest

from workbench.errors import InputFileError
from workbench.io.inputs import read_landmarks

PAIRS = {
    "pose01": [
        ([1.0, 2.0, 3.0], [1.5, 2.0, 3.25]),
        ([4.0, 5.0, 6.0], [4.0, 5.5, 6.0]),
        ([7.0, 8.0, 9.5], [7.0, 8.0, 10.0]),
        ([-1.0, 0.0, 2.0], [-1.0, 0.5, 2.0]),
    ]
}


def _json(path, scans):
    path.write_text(
        json.dumps(
            {
                "format": "avw-landmarks",
                "scans": {s: [{"template": a, "scan": b} for a, b in v] for s, v in scans.items()},
            }
        )
    )
    return path


def _csv(path, scans):
    rows = ["scan,template_x,template_y,template_z,scan_x,scan_y,scan_z"]
    rows += [",".join([s, *map(str, a + b)]) for s, v in scans.items() for a, b in v]
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize("writer, name", [(_json, "marks.json"), (_csv, "marks.csv")])
def test_json_and_csv_give_the_same_pairs(tmp_path, writer, name):
    got = read_landmarks(writer(tmp_path / name, PAIRS), ["pose01"])
    assert list(got) == ["pose01"]
    np.testing.assert_array_equal(got["pose01"][0], [a for a, _ in PAIRS["pose01"]])
    np.testing.assert_array_equal(got["pose01"][1], [b for _, b in PAIRS["pose01"]])


@pytest.mark.parametrize(
    "scans, ids, match",
    [
        (PAIRS, ["pose01", "pose02"], "fewer than 4 landmarks"),  # a scan of the study without landmarks
        ({**PAIRS, "pose09": PAIRS["pose01"]}, ["pose01"], "unknown scans"),
        ({"pose01": PAIRS["pose01"][:3]}, ["pose01"], "fewer than 4"),
    ],
)
def test_bad_landmark_sets_are_refused_naming_the_file(tmp_path, scans, ids, match):
    p = _json(tmp_path / "m.json", scans)
    with pytest.raises(InputFileError, match=match) as e:
        read_landmarks(p, ids)
    assert str(p) in str(e.value)


def test_a_subset_of_scans_needs_landmarks_for_those_only(tmp_path):
    """`workbench surface --scan pose01 --landmarks FILE`: the file may cover the whole study, the other scans
    need no landmarks, and a scan the study lacks is still refused."""
    p = _json(tmp_path / "m.json", PAIRS)
    assert list(read_landmarks(p, ["pose01", "pose02"], ["pose01"])) == ["pose01"]
    with pytest.raises(InputFileError, match="fewer than 4"):
        read_landmarks(p, ["pose01", "pose02"], ["pose02"])
    with pytest.raises(InputFileError, match=r"unknown scans \['pose01'\]; the study has \['pose02'\]"):
        read_landmarks(p, ["pose02"], [])


def test_malformed_files_say_what_is_expected(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"scans": {}}))
    with pytest.raises(InputFileError, match="avw-landmarks"):
        read_landmarks(bad)
    for t, sc in (([1, 2], [1, 2, 3]), ([1, 2, 3, 4], [5, 6])):  # 3 numbers each, not 6 in all
        bad.write_text(json.dumps({"format": "avw-landmarks", "scans": {"p": [{"template": t, "scan": sc}]}}))
        with pytest.raises(InputFileError, match=r"landmark 0 of scan 'p'"):
            read_landmarks(bad)
    csv = tmp_path / "bad.csv"
    csv.write_text("scan,x,y,z\n")
    with pytest.raises(InputFileError, match="header"):
        read_landmarks(csv)
    csv.write_text("scan,template_x,template_y,template_z,scan_x,scan_y,scan_z\np,1,2,3,4,5,six\n")
    with pytest.raises(InputFileError, match="line 2"):
        read_landmarks(csv)
    with pytest.raises(InputFileError, match="no such landmarks file"):
        read_landmarks(tmp_path / "missing.csv")
