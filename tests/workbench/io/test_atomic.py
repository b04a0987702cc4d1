"""Atomic output (workbench.io.atomic) and the error hierarchy (workbench.errors)."""

from __future__ import annotations

import os

import pytest

from deformation.geometry import GeometryMismatchError as GeometryMismatchFromGeometry
from workbench import errors
from workbench.errors import OutputExistsError
from workbench.io.atomic import atomic_file_group, atomic_path, split_suffix, write_text_atomic


@pytest.mark.parametrize(
    "name, stem, suffix",
    [
        ("scan.nii.gz", "scan", ".nii.gz"),
        ("scan.v2.nii.gz", "scan.v2", ".nii.gz"),
        ("bones.ply", "bones", ".ply"),
        ("field.raw.gz", "field", ".raw.gz"),
        ("README", "README", ""),
    ],
)
def test_split_suffix(name, stem, suffix):
    assert split_suffix(name) == (stem, suffix)


def test_temporary_name_keeps_compound_suffix_and_folder(tmp_path):
    final = tmp_path / "scan.nii.gz"
    with atomic_path(final) as tmp:
        assert tmp.parent == tmp_path
        assert tmp.name.startswith(".scan.tmp-") and tmp.name.endswith(".nii.gz")
        assert len(tmp.name) == len(".scan.tmp-") + 8 + len(".nii.gz")
        tmp.write_bytes(b"abc")
        assert not final.exists()  # nothing at the final name before success
    assert final.read_bytes() == b"abc"
    assert os.listdir(tmp_path) == ["scan.nii.gz"]


def test_failure_removes_temporary_file_and_leaves_target(tmp_path):
    final = tmp_path / "out.json"
    final.write_text("old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_path(final, overwrite=True) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert final.read_text(encoding="utf-8") == "old"
    assert os.listdir(tmp_path) == ["out.json"]


def test_existing_target_refused_before_anything_happens(tmp_path):
    final = tmp_path / "out.txt"
    final.write_text("old")
    entered = []
    with pytest.raises(OutputExistsError) as err:
        with atomic_path(final):
            entered.append(True)
    assert entered == []
    assert err.value.path == final
    assert "out.txt" in str(err.value) and "overwrite=True" in str(err.value) and "--force" in str(err.value)
    assert final.read_text(encoding="utf-8") == "old"


def test_target_created_meanwhile_is_not_clobbered(tmp_path):
    final = tmp_path / "out.txt"
    with pytest.raises(OutputExistsError):
        with atomic_path(final) as tmp:
            tmp.write_text("new")
            final.write_text("someone else")
    assert final.read_text(encoding="utf-8") == "someone else"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_body_that_writes_nothing_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError):
        with atomic_path(tmp_path / "out.txt"):
            pass
    assert os.listdir(tmp_path) == []


def test_missing_output_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        with atomic_path(tmp_path / "no" / "out.txt"):
            pass


def test_write_text_atomic(tmp_path):
    path = write_text_atomic(tmp_path / "notes.md", "é\n")
    assert path.read_bytes() == "é\n".encode()
    with pytest.raises(OutputExistsError):
        write_text_atomic(tmp_path / "notes.md", "x")
    write_text_atomic(tmp_path / "notes.md", "x", overwrite=True)
    assert path.read_text(encoding="utf-8") == "x"
    assert os.listdir(tmp_path) == ["notes.md"]


def test_file_group_moves_companions_and_header(tmp_path):
    final = tmp_path / "scan.mhd"
    with atomic_file_group(final) as tmp:
        assert tmp.name == "scan.mhd" and tmp.parent.parent == tmp_path
        tmp.write_text("ElementDataFile = scan.raw\n")
        (tmp.parent / "scan.raw").write_bytes(b"\x00" * 10)
    assert sorted(os.listdir(tmp_path)) == ["scan.mhd", "scan.raw"]
    assert (tmp_path / "scan.raw").stat().st_size == 10


def test_file_group_failure_and_conflicts_leave_nothing(tmp_path):
    with pytest.raises(ValueError):
        with atomic_file_group(tmp_path / "a.mhd") as tmp:
            tmp.write_text("x")
            raise ValueError("writer failed")
    assert os.listdir(tmp_path) == []
    (tmp_path / "a.raw").write_bytes(b"old")
    with pytest.raises(OutputExistsError) as err:
        with atomic_file_group(tmp_path / "a.mhd") as tmp:
            tmp.write_text("x")
            (tmp.parent / "a.raw").write_bytes(b"new")
    assert err.value.path == tmp_path / "a.raw"
    assert os.listdir(tmp_path) == ["a.raw"]
    assert (tmp_path / "a.raw").read_bytes() == b"old"


def test_error_hierarchy():
    e = errors.MissingFileError("x.nii: no such file. Check the path.", "x.nii")
    assert isinstance(e, errors.InputFileError) and isinstance(e, FileNotFoundError)
    assert isinstance(e, ValueError) and isinstance(e, errors.WorkbenchError)
    assert str(e) == "x.nii: no such file. Check the path." and str(e.path) == "x.nii"
    for cls in (
        errors.UnknownFormatError,
        errors.UnreadableFileError,
        errors.DimensionError,
        errors.NonFiniteError,
        errors.AmbiguousSeriesError,
        errors.PixelTypeError,
        errors.SeriesNotFoundError,
    ):
        assert issubclass(cls, errors.InputFileError) and issubclass(cls, ValueError)
    out = OutputExistsError("out/scan.nii.gz")
    assert isinstance(out, FileExistsError) and isinstance(out, errors.WorkbenchError)
    assert not isinstance(out, ValueError)
    assert errors.GeometryMismatchError is GeometryMismatchFromGeometry
