"""JSON files (workbench.io.jsonio): exact floats, stable text, clear errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from workbench.errors import MissingFileError, OutputExistsError, UnreadableFileError
from workbench.io.jsonio import read_json, write_json


def test_exact_round_trip_of_floats_and_arrays(tmp_path):
    transform = np.eye(4)
    transform[:3, 3] = [0.1, -2.0 / 3.0, 1e300]
    data = {
        "sum": 0.1 + 0.2,
        "tiny": 1e-17,
        "third": 1.0 / 3.0,
        "float32": np.float32(0.1),
        "int64": np.int64(2**53 + 1),
        "one": 1.0,
        "transform": transform,
        "labels": np.array([3, 1, 2], dtype=np.uint8),
        "nested": {"b": [1, 2.5, None, True], "a": (np.float64(5e-324), "é")},
        "path": Path("bones") / "radius.ply",
    }
    path = write_json(data, tmp_path / "pose.json")
    back = read_json(path)
    assert back["sum"] == 0.30000000000000004 == 0.1 + 0.2
    assert back["tiny"] == 1e-17
    assert back["third"] == 1.0 / 3.0
    assert back["float32"] == float(np.float32(0.1)) == 0.10000000149011612
    assert back["int64"] == 2**53 + 1 and isinstance(back["int64"], int)
    assert back["one"] == 1.0 and isinstance(back["one"], float)
    np.testing.assert_array_equal(np.array(back["transform"]), transform)
    assert back["labels"] == [3, 1, 2]
    assert back["nested"] == {"a": [5e-324, "é"], "b": [1, 2.5, None, True]}
    assert back["path"] == "bones/radius.ply"


def test_text_is_sorted_indented_and_stable(tmp_path):
    write_json({"b": 1, "a": {"d": [1.5, 2], "c": 0.1}}, tmp_path / "x.json")
    text = (tmp_path / "x.json").read_text(encoding="utf-8")
    assert text == '{\n  "a": {\n    "c": 0.1,\n    "d": [\n      1.5,\n      2\n    ]\n  },\n  "b": 1\n}\n'
    write_json({"a": {"c": 0.1, "d": [1.5, 2]}, "b": 1}, tmp_path / "y.json")
    assert (tmp_path / "y.json").read_bytes() == (tmp_path / "x.json").read_bytes()


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), np.float32("nan"), np.array([1.0, np.inf])])
def test_nan_and_inf_refused_and_nothing_written(tmp_path, bad):
    with pytest.raises(ValueError) as err:
        write_json({"joint": {"centre": [0.0, bad]}}, tmp_path / "j.json")
    message = str(err.value)
    assert "j.json" in message and "$.joint.centre[1]" in message
    assert os.listdir(tmp_path) == []


def test_unsupported_keys_and_objects(tmp_path):
    with pytest.raises(TypeError, match=r"key 1 of type int"):
        write_json({1: "a"}, tmp_path / "k.json")
    with pytest.raises(TypeError, match=r"\$\.x is a set"):
        write_json({"x": {1, 2}}, tmp_path / "k.json")
    assert os.listdir(tmp_path) == []


def test_syntax_error_names_line_and_column(tmp_path):
    (tmp_path / "bad.json").write_text('{\n  "a": 1,\n  "b": [1, 2,, 3]\n}\n')
    with pytest.raises(UnreadableFileError) as err:
        read_json(tmp_path / "bad.json")
    assert "bad.json" in str(err.value) and "line 3, column 14" in str(err.value)
    assert err.value.__cause__ is not None


@pytest.mark.parametrize(
    "text, fragment",
    [
        ('{"a": NaN}', "NaN"),
        ('{"a": -Infinity}', "-Infinity"),
        ('{"a": 1, "a": 2}', "'a' appears twice"),
        ("[1, 2]", "top level is a JSON list"),
    ],
)
def test_invalid_content(tmp_path, text, fragment):
    (tmp_path / "x.json").write_text(text)
    with pytest.raises(UnreadableFileError) as err:
        read_json(tmp_path / "x.json")
    assert fragment in str(err.value) and "x.json" in str(err.value)


def test_missing_file_and_overwrite(tmp_path):
    with pytest.raises(MissingFileError):
        read_json(tmp_path / "none.json")
    write_json({"a": 1}, tmp_path / "a.json")
    with pytest.raises(OutputExistsError):
        write_json({"a": 2}, tmp_path / "a.json")
    assert read_json(tmp_path / "a.json") == {"a": 1}
    write_json({"a": 2}, tmp_path / "a.json", overwrite=True)
    assert read_json(tmp_path / "a.json") == {"a": 2}
    assert os.listdir(tmp_path) == ["a.json"]


def test_input_not_modified(tmp_path):
    arr = np.arange(3.0)
    data = {"x": arr, "t": (1, 2)}
    write_json(data, tmp_path / "d.json")
    assert data["t"] == (1, 2) and data["x"] is arr
    np.testing.assert_array_equal(arr, [0.0, 1.0, 2.0])
