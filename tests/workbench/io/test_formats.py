"""Image formats by suffix and the checks every reader makes first (workbench.io.formats)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from workbench.errors import ImplausibleGeometryError, MissingFileError, NonFiniteError, UnknownFormatError
from workbench.io.formats import (
    DETACHED,
    DICOM,
    IMAGE_IO,
    MAX_EXTENT_MM,
    SPACING_RANGE_MM,
    SUPPORTED_SUFFIXES,
    check_finite,
    detached_data_file,
    image_format,
    require_exists,
    require_plausible_geometry,
    sitk_error_line,
)


@pytest.mark.parametrize(
    "name, fmt",
    [
        ("scan.nii", ".nii"),
        ("scan.nii.gz", ".nii.gz"),
        ("SCAN.NII.GZ", ".nii.gz"),  # case-insensitive
        ("scan.v2.nii.gz", ".nii.gz"),  # only a compression suffix joins the one before it
        ("knee.mha", ".mha"),
        ("knee.Mhd", ".mhd"),
        ("knee.nrrd", ".nrrd"),
        ("knee.nhdr", ".nhdr"),
    ],
)
def test_the_suffix_chooses_the_format_for_reading_and_writing(tmp_path, name, fmt):
    assert image_format(tmp_path / name) == fmt
    assert image_format(str(tmp_path / name), for_writing=True) == fmt


def test_every_supported_suffix_has_an_image_io_and_the_detached_ones_are_headers():
    assert set(SUPPORTED_SUFFIXES) == set(IMAGE_IO)
    assert DETACHED == {".mhd", ".nhdr"} and DETACHED <= set(IMAGE_IO)


def test_a_folder_is_a_dicom_series_for_reading_only(tmp_path):
    series = tmp_path / "series.nii"  # a folder's name does not make it a file format
    series.mkdir()
    assert image_format(series) == DICOM == "dicom"
    with pytest.raises(UnknownFormatError, match=r"suffix '\(none\)'\. Supported suffixes: .*Rename the output"):
        image_format(tmp_path, for_writing=True)


@pytest.mark.parametrize(
    "name, said", [("scan.gz", "'.gz'"), ("scan.png", "'.png'"), ("scan", "'(none)'"), ("scan.nii.bz2", "'.nii.bz2'")]
)
def test_an_unknown_suffix_names_the_file_the_suffix_and_the_fix(tmp_path, name, said):
    p = tmp_path / name
    with pytest.raises(UnknownFormatError) as e:
        image_format(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: cannot tell the image format from the suffix {said}. ")
    assert ".nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd, or a folder holding one DICOM series" in msg
    assert "Convert the file" in msg and e.value.path == p
    with pytest.raises(UnknownFormatError) as e:
        image_format(p, for_writing=True)
    assert "Supported suffixes: .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd. Rename the output accordingly." in str(e.value)
    assert "DICOM" not in str(e.value)


def test_require_exists_names_the_working_folder_for_a_relative_path(tmp_path, monkeypatch):
    require_exists(tmp_path)  # a folder exists too
    with pytest.raises(
        MissingFileError, match=rf"^{re.escape(str(tmp_path))}/no\.nii: no such file or folder\. Check the path"
    ):
        require_exists(tmp_path / "no.nii")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(
        MissingFileError,
        match=rf"^no\.nii: no such file or folder \(relative to the working folder "
        rf"{re.escape(str(tmp_path))}\)\.",
    ):
        require_exists(type(tmp_path)("no.nii"))


def test_sitk_error_line_is_the_last_informative_line():
    e = RuntimeError(
        "Exception thrown in SimpleITK ImageFileReader_Execute:\n  itk::ERROR: \n  File is truncated  \n\n"
    )
    assert sitk_error_line(e) == "File is truncated"
    assert sitk_error_line(RuntimeError("")) == "RuntimeError"


@pytest.mark.parametrize(
    "header, fmt, data",
    [
        ("NDims = 3\nElementType = MET_FLOAT\nElementDataFile = scan.raw\n", ".mhd", "scan.raw"),
        ("ndims=3\nelementdatafile=scan.zraw\n", ".mhd", "scan.zraw"),
        ("ElementDataFile = LOCAL\n", ".mhd", None),
        ("ElementDataFile = LIST\n", ".mhd", None),
        ("ElementDataFile = slice%03d.raw 1 10 1\n", ".mhd", None),
        ("NDims = 3\n", ".mhd", None),
        ("NRRD0004\ntype: float\ndata file: scan.raw.gz\n", ".nhdr", "scan.raw.gz"),
        ("NRRD0004\ndatafile: scan.raw\n", ".nhdr", "scan.raw"),
        ("NRRD0004\ndata file: LIST\n", ".nhdr", None),
    ],
)
def test_detached_data_file_is_the_single_file_the_header_names(tmp_path, header, fmt, data):
    p = tmp_path / f"h{fmt}"
    p.write_text(header, encoding="latin-1")
    assert detached_data_file(p, fmt) == (None if data is None else tmp_path / data)


def test_detached_data_file_of_an_unreadable_header_is_none(tmp_path):
    assert detached_data_file(tmp_path / "missing.mhd", ".mhd") is None


def test_plausible_geometry_bounds_are_inclusive():
    lo, hi = SPACING_RANGE_MM
    require_plausible_geometry((10, 10, 10), (lo, 1.0, hi), "x.nii")
    n = int(MAX_EXTENT_MM / 20.0)
    require_plausible_geometry((n, 1, 1), (20.0, 1.0, 1.0), "x.nii")  # exactly MAX_EXTENT_MM long


@pytest.mark.parametrize(
    "spacing, said",
    [((1.0, 1.0, 1000.0), "z 1000 mm"), ((0.0005, 1.0, 25.0), "x 0.0005 mm, z 25 mm"), ((1.0, -1.0, 1.0), "y -1 mm")],
)
def test_implausible_spacing_names_each_axis_and_the_fix(tmp_path, spacing, said):
    p = tmp_path / "ct.nii.gz"
    with pytest.raises(ImplausibleGeometryError) as e:
        require_plausible_geometry((8, 8, 8), spacing, p)
    assert str(e.value).startswith(f"{p}: voxel spacing {said} is outside 0.001–20 mm")
    assert "SetSpacing" in str(e.value) and e.value.path == p


def test_a_field_of_view_too_long_gives_its_extent(tmp_path):
    with pytest.raises(ImplausibleGeometryError, match=r"field of view of 10 x 4001 x 10 mm is longer than 4000 mm"):
        require_plausible_geometry((10, 4001, 10), (1.0, 1.0, 1.0), tmp_path / "x.mha")


def test_check_finite_passes_finite_data():
    check_finite(np.zeros((2, 3, 4), np.float32), "x.nii", "volume", "Fix it.")
    check_finite(np.zeros((2, 3, 4), np.int16), "x.nii", "volume", "Fix it.")


def test_check_finite_counts_and_locates_the_first_bad_voxel(tmp_path):
    data = np.zeros((2, 3, 4), np.float32)  # [z, y, x]
    data[1, 2, 3] = np.inf
    data[0, 1, 2] = np.nan
    data[1, 0, 0] = -np.inf
    p = tmp_path / "scan.mha"
    with pytest.raises(NonFiniteError) as e:
        check_finite(data, p, "volume", "Replace them.")
    assert str(e.value) == (
        f"{p}: 3 of 24 voxels of this volume are not finite (1 NaN, 2 infinite); the first is at voxel index "
        "(i, j, k) = (2, 1, 0) (array [z, y, x] = (0, 1, 2)), value nan. Replace them."
    )


def test_check_finite_of_a_vector_image_counts_voxels_not_components(tmp_path):
    data = np.zeros((2, 2, 2, 3))
    data[0, 0, 1] = [np.nan, np.nan, 0.0]
    data[1, 1, 1] = [0.0, np.inf, 1.0]
    with pytest.raises(
        NonFiniteError,
        match=r"2 of 8 voxels of this field are not finite \(1 NaN, 1 infinite\); "
        r"the first is at voxel index \(i, j, k\) = \(1, 0, 0\)",
    ):
        check_finite(data, tmp_path / "f.mha", "field", "")
