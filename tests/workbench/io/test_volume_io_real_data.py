"""workbench.io.volumes on real scans from ../shared/data/io-samples (skipped when absent)."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from workbench.errors import AmbiguousSeriesError, SeriesNotFoundError, UnreadableFileError
from workbench.io.volumes import read_image_geometry, read_volume, write_volume

DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data"
HEAD_MHD = DATA / "io-samples" / "head-mr-mhd" / "HeadMRVolume.mhd"
DICOM_DIR = DATA / "io-samples" / "forearm-mr-dicom-series" / "data"

needs_head = pytest.mark.skipif(not HEAD_MHD.is_file(), reason=f"real data absent: {HEAD_MHD}")
needs_dicom = pytest.mark.skipif(not DICOM_DIR.is_dir(), reason=f"real data absent: {DICOM_DIR}")


def _header_numbers(text: str, key: str) -> tuple[float, ...]:
    m = re.search(rf"^{key}\s*=\s*(.+)$", text, flags=re.MULTILINE)
    return tuple(float(v) for v in m.group(1).split())


@needs_head
def test_head_mr_metaimage(tmp_path):
    text = HEAD_MHD.read_text(encoding="utf-8")
    # What the header states, read independently of ITK.
    assert _header_numbers(text, "DimSize") == (48.0, 62.0, 42.0)
    assert _header_numbers(text, "ElementSpacing") == (4.0, 4.0, 4.0)
    assert "Offset" not in text and "Origin" not in text  # so the origin is (0, 0, 0)
    assert "ElementType = MET_UCHAR" in text

    vol = read_volume(HEAD_MHD)
    assert vol.geometry.size == (48, 62, 42)
    assert vol.data.shape == (42, 62, 48)
    assert vol.geometry.spacing == (4.0, 4.0, 4.0)
    assert vol.geometry.origin == (0.0, 0.0, 0.0)
    assert vol.geometry.direction == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    assert vol.data.dtype == np.uint8
    # The voxels are exactly the raw file's bytes in x-fastest order.
    raw = np.fromfile(HEAD_MHD.with_suffix(".raw"), dtype=np.uint8).reshape(42, 62, 48)
    np.testing.assert_array_equal(vol.data, raw)
    assert read_image_geometry(HEAD_MHD) == vol.geometry
    # Converting to NIfTI keeps voxels and (integer-valued, float32-exact) geometry.
    write_volume(vol, tmp_path / "head.nii.gz")
    back = read_volume(tmp_path / "head.nii.gz")
    np.testing.assert_array_equal(back.data, raw)
    assert back.geometry == vol.geometry


def _slice_metadata(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Image Position Patient and the slice normal of one DICOM file, from its own tags."""
    r = sitk.ImageFileReader()
    r.SetFileName(path)
    r.ReadImageInformation()
    ipp = np.array([float(v) for v in r.GetMetaData("0020|0032").split("\\")])
    iop = np.array([float(v) for v in r.GetMetaData("0020|0037").split("\\")])
    return ipp, np.cross(iop[:3], iop[3:])


@needs_dicom
def test_dicom_series_is_ordered_along_the_slice_normal():
    files = sorted(str(p) for p in DICOM_DIR.glob("*.dcm"))
    assert len(files) == 3
    # Position of each file along the normal, computed from its own header.
    meta = {f: _slice_metadata(f) for f in files}
    normal = meta[files[0]][1]
    along = {Path(f).name: float(meta[f][0] @ normal) for f in files}
    # File-name order is *not* position order in this series.
    assert along == {"1-1.dcm": 12.0, "1-2.dcm": 0.0, "1-3.dcm": -12.0}

    vol = read_volume(DICOM_DIR)
    g = vol.geometry
    assert g.size == (512, 512, 3)
    assert vol.data.shape == (3, 512, 512)
    assert vol.data.dtype == np.uint16
    assert g.spacing == (0.9765625, 0.9765625, 12.0)  # in-plane from Pixel Spacing; slices 12 mm apart
    assert g.origin == (-250.0, -250.0, -12.0)  # the lowest slice along the normal
    np.testing.assert_array_equal(g.direction_matrix[:, 2], normal)
    # Slice k of the volume sits at origin + k * spacing_z * normal, increasing along the normal.
    slice_positions = [float(g.index_to_world([0, 0, k]) @ normal) for k in range(3)]
    assert slice_positions == [-12.0, 0.0, 12.0]
    assert np.all(np.diff(slice_positions) > 0)
    # And each slice holds the pixels of the file at that position.
    for k, name in enumerate(sorted(along, key=along.get)):
        pixels = sitk.GetArrayFromImage(sitk.ReadImage(str(DICOM_DIR / name)))[0]
        np.testing.assert_array_equal(vol.data[k], pixels)
    assert read_image_geometry(DICOM_DIR) == g


def _copy_as_new_series(files: list[Path], folder: Path, uid: str, description: str) -> None:
    for f in files:
        image = sitk.ReadImage(str(f))
        image.SetMetaData("0020|000e", uid)  # SeriesInstanceUID
        image.SetMetaData("0008|103e", description)  # SeriesDescription
        writer = sitk.ImageFileWriter()
        writer.KeepOriginalImageUIDOn()
        writer.SetFileName(str(folder / f"copy-{f.name}"))
        writer.Execute(image)


@needs_dicom
def test_folder_with_two_series(tmp_path):
    folder = tmp_path / "dicom"
    folder.mkdir()
    originals = sorted(DICOM_DIR.glob("*.dcm"))
    for f in originals:
        shutil.copy(f, folder)
    new_uid = "1.2.826.0.1.3680043.2.1125.1.4242"
    _copy_as_new_series(originals[:2], folder, new_uid, "COPY OF TWO")  # slices at +12 and 0
    before = sorted(os.listdir(folder))
    assert len(before) == 5

    original_uid = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(DICOM_DIR))[0]
    with pytest.raises(AmbiguousSeriesError) as err:
        read_volume(folder)
    message = str(err.value)
    assert str(folder) in message
    assert f"{original_uid}  'AX SCOUT'  3 slices" in message
    assert f"{new_uid}  'COPY OF TWO'  2 slices" in message
    assert "series_uid=" in message

    vol = read_volume(folder, series_uid=new_uid)
    assert vol.geometry.size == (512, 512, 2)
    assert vol.geometry.spacing[2] == 12.0
    assert vol.geometry.origin == (-250.0, -250.0, 0.0)
    full = read_volume(folder, series_uid=original_uid)
    assert full.geometry.size == (512, 512, 3)
    np.testing.assert_array_equal(vol.data, full.data[1:])  # same pixels at the same positions

    with pytest.raises(SeriesNotFoundError) as err:
        read_volume(folder, series_uid="1.2.3")
    assert new_uid in str(err.value) and original_uid in str(err.value)
    assert sorted(os.listdir(folder)) == before


@needs_dicom
def test_series_with_a_missing_slice_is_refused(tmp_path):
    # Slices at -12 and +12 plus one moved to +30: gaps 24 and 18 mm.
    folder = tmp_path / "gappy"
    folder.mkdir()
    files = sorted(DICOM_DIR.glob("*.dcm"))
    shutil.copy(files[0], folder)  # +12
    shutil.copy(files[2], folder)  # -12
    image = sitk.ReadImage(str(files[1]))
    image.SetMetaData("0020|0032", "-250\\-250\\30")
    image.SetOrigin((-250.0, -250.0, 30.0))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    writer.SetFileName(str(folder / "moved.dcm"))
    writer.Execute(image)
    with pytest.raises(UnreadableFileError) as err:
        read_volume(folder)
    assert "not equally spaced" in str(err.value) and "[24.0, 18.0]" in str(err.value)
