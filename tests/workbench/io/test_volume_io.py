"""Round trips and error paths of workbench.io.volumes on small synthetic volumes.

Every grid is anisotropic (0.7, 1.3, 2.1) mm with a rotated direction and a
non-zero origin, so that an x/z swap, a lost direction or a lost origin shows.
"""

from __future__ import annotations

import gzip
import os

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from deformation.geometry import GeometryMismatchError, GridGeometry, Volume
from workbench.errors import (
    DimensionError,
    MissingFileError,
    NonFiniteError,
    OutputExistsError,
    OutputWriteError,
    PixelTypeError,
    UnknownFormatError,
    UnreadableFileError,
)
from workbench.io import volumes as volume_io
from workbench.io.volumes import (
    read_displacement,
    read_image_geometry,
    read_labels,
    read_volume,
    write_displacement,
    write_labels,
    write_volume,
)

SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")
EPS32 = float(np.finfo(np.float32).eps)  # 2**-23
EPS64 = float(np.finfo(np.float64).eps)

ROTATION = Rotation.from_euler("xyz", [20.0, -35.0, 50.0], degrees=True).as_matrix()
GEOMETRY = GridGeometry(
    size=(13, 11, 7),  # nx, ny, nz: all different, so an axis swap changes shapes
    spacing=(0.7, 1.3, 2.1),
    origin=(-12.345, 67.891, 3.14159),
    direction=ROTATION.ravel(),
)


def _listing(folder) -> list[str]:
    return sorted(os.listdir(folder))


def assert_geometry_round_trip(got: GridGeometry, want: GridGeometry, suffix: str) -> None:
    """Geometry after a write/read cycle through ``suffix``.

    * MetaImage writes 17 significant digits: exact.
    * NRRD stores spacing × direction ('space directions'); ITK recovers the
      spacing as a column norm and the direction as the normalised column,
      which costs a couple of float64 ulps; the origin is exact.
    * NIfTI stores pixdim and the qform offset as float32, so spacing and
      origin come back as exactly the float32-rounded values.  The direction
      comes from a float32 quaternion; each matrix entry is a quadratic form
      of its components, measured ≤ 0.53 float32 eps over 300 random
      rotations: 2 eps is the bound.
    """
    assert got.size == want.size
    if suffix in (".mha", ".mhd"):
        assert got.spacing == want.spacing
        assert got.origin == want.origin
        assert got.direction == want.direction
    elif suffix in (".nrrd", ".nhdr"):
        assert got.origin == want.origin
        np.testing.assert_allclose(got.spacing, want.spacing, rtol=4 * EPS64, atol=0)
        np.testing.assert_allclose(got.direction, want.direction, rtol=0, atol=4 * EPS64)
    else:
        as_float32 = lambda v: tuple(float(x) for x in np.asarray(v, dtype=np.float32))  # noqa: E731
        assert got.spacing == as_float32(want.spacing)
        assert got.origin == as_float32(want.origin)
        np.testing.assert_allclose(got.direction, want.direction, rtol=0, atol=2 * EPS32)


def _volume(dtype, rng) -> Volume:
    if np.dtype(dtype).kind == "f":
        data = rng.normal(100.0, 30.0, size=GEOMETRY.array_shape).astype(dtype)
    else:
        info = np.iinfo(dtype)
        data = rng.integers(info.min, info.max, size=GEOMETRY.array_shape, endpoint=True, dtype=dtype)
    return Volume(data, GEOMETRY)


# ---------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", SUFFIXES)
@pytest.mark.parametrize("dtype", [np.float32, np.int16])
def test_volume_round_trip(tmp_path, suffix, dtype):
    rng = np.random.default_rng(1)
    vol = _volume(dtype, rng)
    before = vol.data.copy()
    path = write_volume(vol, tmp_path / f"scan{suffix}")
    back = read_volume(path)
    assert back.data.dtype == np.dtype(dtype)
    assert back.data.shape == (7, 11, 13)
    np.testing.assert_array_equal(back.data, vol.data)
    assert_geometry_round_trip(back.geometry, GEOMETRY, suffix)
    np.testing.assert_array_equal(vol.data, before)  # input untouched
    # Header-only geometry agrees with the full read.
    assert read_image_geometry(path) == back.geometry


@pytest.mark.parametrize("suffix", SUFFIXES)
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_labels_round_trip(tmp_path, suffix, dtype):
    rng = np.random.default_rng(2)
    labels = Volume(rng.integers(0, 12, size=GEOMETRY.array_shape).astype(dtype), GEOMETRY)
    labels.data[0, 0, 0] = np.iinfo(dtype).max
    path = write_labels(labels, tmp_path / f"labels{suffix}")
    back = read_labels(path, reference=GEOMETRY)
    assert back.data.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(back.data, labels.data)
    assert int(back.data[0, 0, 0]) == np.iinfo(dtype).max
    assert_geometry_round_trip(back.geometry, GEOMETRY, suffix)


@pytest.mark.parametrize("suffix", SUFFIXES)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_displacement_round_trip(tmp_path, suffix, dtype):
    rng = np.random.default_rng(3)
    field = Volume(rng.normal(0.0, 2.0, size=GEOMETRY.array_shape + (3,)).astype(dtype), GEOMETRY)
    path = write_displacement(field, tmp_path / f"field{suffix}")
    image = sitk.ReadImage(str(path))
    expected_id = sitk.sitkVectorFloat32 if dtype == np.float32 else sitk.sitkVectorFloat64
    assert image.GetPixelID() == expected_id
    assert image.GetNumberOfComponentsPerPixel() == 3
    back = read_displacement(path)
    assert back.data.dtype == np.float64
    assert back.data.shape == (7, 11, 13, 3)
    np.testing.assert_array_equal(back.data, field.data.astype(np.float64))
    assert_geometry_round_trip(back.geometry, GEOMETRY, suffix)


def test_detached_headers_write_their_data_files(tmp_path):
    vol = _volume(np.float32, np.random.default_rng(4))
    write_volume(vol, tmp_path / "a.mhd", compress=False)
    write_volume(vol, tmp_path / "b.mhd", compress=True)
    write_volume(vol, tmp_path / "c.nhdr", compress=True)
    assert _listing(tmp_path) == ["a.mhd", "a.raw", "b.mhd", "b.zraw", "c.nhdr", "c.raw.gz"]
    assert "ElementDataFile = a.raw" in (tmp_path / "a.mhd").read_text(encoding="utf-8")
    assert (tmp_path / "a.raw").stat().st_size == vol.data.nbytes == 7 * 11 * 13 * 4


def test_constant_displacement_moves_points_through_sitk_transform(tmp_path):
    shift = np.array([1.5, -2.25, 0.75])  # exact in float32
    for dtype, suffix in [(np.float32, ".nii.gz"), (np.float64, ".mha")]:
        data = np.broadcast_to(shift.astype(dtype), GEOMETRY.array_shape + (3,)).copy()
        path = write_displacement(Volume(data, GEOMETRY), tmp_path / f"const{suffix}")
        tx = sitk.DisplacementFieldTransform(sitk.Cast(sitk.ReadImage(str(path)), sitk.sitkVectorFloat64))
        inside = GEOMETRY.index_to_world([[6.0, 5.0, 3.0], [2.3, 7.9, 4.4], [10.5, 1.25, 1.5]])
        for p in inside:
            moved = np.array(tx.TransformPoint(tuple(p)))
            np.testing.assert_allclose(moved - p, shift, rtol=0, atol=1e-12)


def test_linear_displacement_components_are_x_y_z_in_world_mm(tmp_path):
    # d(p) = A p + b in world mm: trilinear interpolation of a linear field is
    # exact, so any axis or component mix-up shows as an error ≫ 1e-9 mm.
    a = np.array([[0.01, -0.02, 0.03], [0.015, 0.005, -0.01], [-0.02, 0.01, 0.025]])
    b = np.array([0.5, -1.0, 2.0])
    world = GEOMETRY.world_coordinates()
    data = world @ a.T + b
    path = write_displacement(Volume(data, GEOMETRY), tmp_path / "linear.mha")
    tx = sitk.DisplacementFieldTransform(sitk.Cast(sitk.ReadImage(str(path)), sitk.sitkVectorFloat64))
    for ijk in ([3.25, 4.5, 2.75], [9.1, 2.2, 5.9], [1.0, 9.0, 1.0]):
        p = GEOMETRY.index_to_world(ijk)
        moved = np.array(tx.TransformPoint(tuple(p)))
        np.testing.assert_allclose(moved, p + a @ p + b, rtol=0, atol=1e-9)


def test_label_map_on_nifti_grid_matches_exact_volume_grid(tmp_path):
    # NIfTI rounds the geometry to float32; the geometry check's tolerances
    # (origin 1e-4 mm, spacing 1e-6 relative) accept that, as they must.
    vol = _volume(np.float32, np.random.default_rng(5))
    write_volume(vol, tmp_path / "scan.mha")
    labels = Volume(np.ones(GEOMETRY.array_shape, np.uint8), GEOMETRY)
    write_labels(labels, tmp_path / "labels.nii.gz")
    back = read_labels(tmp_path / "labels.nii.gz", reference=tmp_path / "scan.mha")
    assert int(back.data.sum()) == 7 * 11 * 13


def test_nifti_gz_is_read_from_itself_when_a_plain_nii_sibling_exists(tmp_path):
    # niftilib would read the voxels of scan.nii.gz from scan.nii.
    ones = Volume(np.ones(GEOMETRY.array_shape, np.float32), GEOMETRY)
    twos = Volume(np.full(GEOMETRY.array_shape, 2.0, np.float32), GEOMETRY)
    write_volume(ones, tmp_path / "scan.nii.gz")
    write_volume(twos, tmp_path / "scan.nii")
    assert float(read_volume(tmp_path / "scan.nii.gz").data.mean()) == 1.0
    assert float(read_volume(tmp_path / "scan.nii").data.mean()) == 2.0
    assert _listing(tmp_path) == ["scan.nii", "scan.nii.gz"]


def test_float_label_map_with_whole_numbers_becomes_int32(tmp_path):
    data = np.arange(7 * 11 * 13, dtype=np.float32).reshape(GEOMETRY.array_shape) % 5
    write_volume(Volume(data, GEOMETRY), tmp_path / "labels.mha")
    back = read_labels(tmp_path / "labels.mha")
    assert back.data.dtype == np.int32
    np.testing.assert_array_equal(back.data, data.astype(np.int32))


# ---------------------------------------------------------------------------
# Bad inputs: documented error, nothing written
# ---------------------------------------------------------------------------


def _write_raw_sitk(image: sitk.Image, path) -> None:
    sitk.WriteImage(image, str(path))


def test_missing_file(tmp_path):
    with pytest.raises(MissingFileError) as err:
        read_volume(tmp_path / "nope.nii.gz")
    assert err.value.path == tmp_path / "nope.nii.gz"
    assert "nope.nii.gz" in str(err.value)
    assert isinstance(err.value, FileNotFoundError)
    assert _listing(tmp_path) == []


def test_unknown_suffix(tmp_path):
    (tmp_path / "scan.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(UnknownFormatError) as err:
        read_volume(tmp_path / "scan.png")
    message = str(err.value)
    assert "scan.png" in message
    for suffix in (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd"):
        assert suffix in message
    with pytest.raises(UnknownFormatError):
        write_volume(_volume(np.float32, np.random.default_rng(0)), tmp_path / "out.png")
    assert _listing(tmp_path) == ["scan.png"]


@pytest.mark.parametrize("suffix", [".nii.gz", ".nii"])
@pytest.mark.parametrize("fraction", [0.5, 0.98])
def test_truncated_nifti(tmp_path, suffix, fraction):
    # ITK itself pads a truncated NIfTI with zeros and reports success.
    write_volume(_volume(np.float32, np.random.default_rng(6)), tmp_path / f"full{suffix}")
    data = (tmp_path / f"full{suffix}").read_bytes()
    (tmp_path / f"cut{suffix}").write_bytes(data[: int(len(data) * fraction)])
    before = _listing(tmp_path)
    with pytest.raises(UnreadableFileError) as err:
        read_volume(tmp_path / f"cut{suffix}")
    assert f"cut{suffix}" in str(err.value)
    assert "truncated" in str(err.value)
    assert _listing(tmp_path) == before


def test_corrupt_gzip_crc(tmp_path):
    write_volume(_volume(np.float32, np.random.default_rng(7)), tmp_path / "full.nii.gz")
    raw = bytearray(gzip.decompress((tmp_path / "full.nii.gz").read_bytes()))
    good = gzip.compress(bytes(raw))
    bad = bytearray(good)
    bad[-8] ^= 0xFF  # flip CRC32 bits: decompressed length still right
    (tmp_path / "bad.nii.gz").write_bytes(bytes(bad))
    with pytest.raises(UnreadableFileError) as err:
        read_volume(tmp_path / "bad.nii.gz")
    assert isinstance(err.value.__cause__, gzip.BadGzipFile)


def test_truncated_mhd_raw(tmp_path):
    write_volume(_volume(np.int16, np.random.default_rng(8)), tmp_path / "scan.mhd", compress=False)
    raw = (tmp_path / "scan.raw").read_bytes()
    assert len(raw) == 7 * 11 * 13 * 2
    (tmp_path / "scan.raw").write_bytes(raw[:1000])
    before = _listing(tmp_path)
    with pytest.raises(UnreadableFileError) as err:
        read_volume(tmp_path / "scan.mhd")
    assert isinstance(err.value.__cause__, RuntimeError)  # SimpleITK's error, chained
    assert "scan.mhd" in str(err.value)
    assert _listing(tmp_path) == before


def test_mhd_without_its_raw(tmp_path):
    write_volume(_volume(np.int16, np.random.default_rng(9)), tmp_path / "scan.mhd", compress=False)
    (tmp_path / "scan.raw").unlink()
    with pytest.raises(MissingFileError) as err:
        read_volume(tmp_path / "scan.mhd")
    assert err.value.path == tmp_path / "scan.raw"
    assert "scan.raw" in str(err.value) and "scan.mhd" in str(err.value)


@pytest.mark.parametrize("suffix", [".nii", ".nrrd", ".mha"])
def test_garbage_bytes(tmp_path, suffix):
    rng = np.random.default_rng(10)
    (tmp_path / f"junk{suffix}").write_bytes(rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(UnreadableFileError) as err:
        read_volume(tmp_path / f"junk{suffix}")
    assert f"junk{suffix}" in str(err.value)
    assert _listing(tmp_path) == [f"junk{suffix}"]


def test_empty_file(tmp_path):
    (tmp_path / "empty.mha").write_bytes(b"")
    with pytest.raises(UnreadableFileError):
        read_volume(tmp_path / "empty.mha")


def test_two_dimensional_image(tmp_path):
    _write_raw_sitk(sitk.GetImageFromArray(np.zeros((5, 6), np.float32)), tmp_path / "slice.nii.gz")
    before = _listing(tmp_path)
    with pytest.raises(DimensionError) as err:
        read_volume(tmp_path / "slice.nii.gz")
    assert "2-D" in str(err.value) and "(6, 5)" in str(err.value)
    with pytest.raises(DimensionError):
        read_image_geometry(tmp_path / "slice.nii.gz")
    with pytest.raises(DimensionError):
        read_labels(tmp_path / "slice.nii.gz")
    assert _listing(tmp_path) == before


def test_wrong_number_of_components(tmp_path):
    two = sitk.GetImageFromArray(np.zeros((4, 5, 6, 2), np.float32), isVector=True)
    _write_raw_sitk(two, tmp_path / "two.mha")
    with pytest.raises(DimensionError) as err:
        read_displacement(tmp_path / "two.mha")
    assert "2 components" in str(err.value)
    write_volume(_volume(np.float32, np.random.default_rng(11)), tmp_path / "scalar.mha")
    with pytest.raises(DimensionError) as err:
        read_displacement(tmp_path / "scalar.mha")
    assert "1 component " in str(err.value)
    three = sitk.GetImageFromArray(np.zeros((4, 5, 6, 3), np.float32), isVector=True)
    _write_raw_sitk(three, tmp_path / "three.mha")
    with pytest.raises(DimensionError):
        read_volume(tmp_path / "three.mha")


@pytest.mark.parametrize("suffix", [".nii.gz", ".nii", ".mha", ".nrrd"])
@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf])
def test_non_finite_voxels(tmp_path, suffix, bad_value):
    # niftilib replaces NaN/inf by 0 while reading; the reader must still see them.
    data = np.ones(GEOMETRY.array_shape, np.float32)
    data[2, 3, 4] = bad_value  # [z, y, x] → (i, j, k) = (4, 3, 2)
    data[5, 6, 7] = bad_value
    image = sitk.GetImageFromArray(data)
    GEOMETRY.apply_to_sitk(image)
    _write_raw_sitk(image, tmp_path / f"scan{suffix}")
    before = _listing(tmp_path)
    with pytest.raises(NonFiniteError) as err:
        read_volume(tmp_path / f"scan{suffix}")
    message = str(err.value)
    assert f"scan{suffix}" in message
    assert "2 of 1001 voxels" in message
    assert ("(2 NaN, 0 infinite)" if np.isnan(bad_value) else "(0 NaN, 2 infinite)") in message
    assert "(i, j, k) = (4, 3, 2)" in message
    assert "workbench clean-image" in message and "allow_nonfinite" not in message  # the CLI's fix
    vol = read_volume(tmp_path / f"scan{suffix}", allow_nonfinite=True)
    expected = data.copy()
    np.testing.assert_array_equal(vol.data, expected)  # NaN == NaN here; inf signs kept
    assert int((~np.isfinite(vol.data)).sum()) == 2
    with pytest.raises(PixelTypeError):
        read_labels(tmp_path / f"scan{suffix}")
    assert _listing(tmp_path) == before


@pytest.mark.parametrize("suffix", [".nii.gz", ".mha"])
def test_non_finite_displacement(tmp_path, suffix):
    data = np.zeros(GEOMETRY.array_shape + (3,), np.float64)
    data[1, 2, 3, 1] = np.nan
    data[4, 0, 9, 2] = -np.inf
    image = sitk.GetImageFromArray(data, isVector=True)
    _write_raw_sitk(image, tmp_path / f"field{suffix}")
    with pytest.raises(NonFiniteError) as err:
        read_displacement(tmp_path / f"field{suffix}")
    assert "2 of 1001 voxels" in str(err.value) and "(i, j, k) = (3, 2, 1)" in str(err.value)
    back = read_displacement(tmp_path / f"field{suffix}", allow_nonfinite=True)
    np.testing.assert_array_equal(back.data, data)  # each value back in its own component
    # The writer refuses too, and writes nothing.
    with pytest.raises(NonFiniteError):
        write_displacement(Volume(data, GEOMETRY), tmp_path / "out.mha")
    assert _listing(tmp_path) == [f"field{suffix}"]


def test_label_map_with_other_geometry_than_its_volume(tmp_path):
    write_volume(_volume(np.float32, np.random.default_rng(12)), tmp_path / "scan.mha")
    shifted = GridGeometry(GEOMETRY.size, GEOMETRY.spacing, np.add(GEOMETRY.origin, (0.5, 0, 0)), GEOMETRY.direction)
    write_labels(Volume(np.zeros(GEOMETRY.array_shape, np.uint8), shifted), tmp_path / "labels.mha")
    before = _listing(tmp_path)
    with pytest.raises(GeometryMismatchError) as err:
        read_labels(tmp_path / "labels.mha", reference=tmp_path / "scan.mha")
    message = str(err.value)
    assert "labels.mha" in message and "scan.mha" in message
    assert "origin=(-12.345, 67.891, 3.1416)" in message and "origin=(-11.845, 67.891, 3.1416)" in message
    assert "Remedy" in message and "resample" in message
    vol = read_volume(tmp_path / "scan.mha")
    with pytest.raises(GeometryMismatchError):
        read_labels(tmp_path / "labels.mha", reference=vol)
    with pytest.raises(GeometryMismatchError):
        read_labels(tmp_path / "labels.mha", reference=vol.geometry)
    assert _listing(tmp_path) == before


def test_fractional_label_map(tmp_path):
    write_volume(_volume(np.float32, np.random.default_rng(13)), tmp_path / "scan.mha")
    with pytest.raises(PixelTypeError) as err:
        read_labels(tmp_path / "scan.mha")
    assert "read_volume" in str(err.value)


# ---------------------------------------------------------------------------
# Writers: overwrite refused, failures leave nothing behind
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".nii.gz", ".mha", ".mhd"])
def test_overwrite_refused_and_existing_bytes_unchanged(tmp_path, suffix):
    rng = np.random.default_rng(14)
    write_volume(_volume(np.float32, rng), tmp_path / f"scan{suffix}")
    before = {name: (tmp_path / name).read_bytes() for name in _listing(tmp_path)}
    other = _volume(np.float32, rng)
    with pytest.raises(OutputExistsError) as err:
        write_volume(other, tmp_path / f"scan{suffix}")
    assert f"scan{suffix}" in str(err.value) and "overwrite=True" in str(err.value) and "--force" in str(err.value)
    assert isinstance(err.value, FileExistsError)
    assert {name: (tmp_path / name).read_bytes() for name in _listing(tmp_path)} == before
    write_volume(other, tmp_path / f"scan{suffix}", overwrite=True)
    np.testing.assert_array_equal(read_volume(tmp_path / f"scan{suffix}").data, other.data)
    assert _listing(tmp_path) == sorted(before)


def test_companion_data_file_conflict_is_refused(tmp_path):
    vol = _volume(np.float32, np.random.default_rng(15))
    write_volume(vol, tmp_path / "scan.mhd", compress=False)  # scan.mhd + scan.raw
    raw_before = (tmp_path / "scan.raw").read_bytes()
    with pytest.raises(OutputExistsError) as err:
        write_volume(vol, tmp_path / "scan.nhdr", compress=False)  # would write scan.raw too
    assert err.value.path == tmp_path / "scan.raw"
    assert _listing(tmp_path) == ["scan.mhd", "scan.raw"]
    assert (tmp_path / "scan.raw").read_bytes() == raw_before


@pytest.mark.parametrize("suffix", [".nii.gz", ".mhd"])
def test_failing_write_leaves_no_temporary_file(tmp_path, monkeypatch, suffix):
    (tmp_path / "other.txt").write_text("keep")

    def half_write_then_fail(self, image):
        # Leave a partial file where SimpleITK was told to write, then fail.
        with open(self.GetFileName(), "wb") as f:
            f.write(b"partial")
        raise RuntimeError("disk full (simulated)")

    monkeypatch.setattr(sitk.ImageFileWriter, "Execute", half_write_then_fail)
    with pytest.raises(
        OutputWriteError,
        match=rf"scan\{suffix}: the file could not be written completely "
        r"\(SimpleITK could not write the file \(disk full \(simulated\)\)",
    ):
        write_volume(_volume(np.float32, np.random.default_rng(16)), tmp_path / f"scan{suffix}")
    assert _listing(tmp_path) == ["other.txt"]


def test_writers_reject_bad_data_and_write_nothing(tmp_path):
    with pytest.raises(TypeError):
        write_labels(Volume(np.zeros(GEOMETRY.array_shape, np.float32), GEOMETRY), tmp_path / "l.nii.gz")
    with pytest.raises(TypeError):
        write_volume(Volume(np.zeros(GEOMETRY.array_shape, np.float16), GEOMETRY), tmp_path / "v.nii.gz")
    with pytest.raises(ValueError):
        write_displacement(Volume(np.zeros(GEOMETRY.array_shape + (2,)), GEOMETRY), tmp_path / "d.mha")
    nan_volume = Volume(np.full(GEOMETRY.array_shape, np.nan, np.float32), GEOMETRY)
    with pytest.raises(NonFiniteError):
        write_volume(nan_volume, tmp_path / "v.mha")
    assert _listing(tmp_path) == []
    write_volume(nan_volume, tmp_path / "v.mha", allow_nonfinite=True)
    assert int(np.isnan(read_volume(tmp_path / "v.mha", allow_nonfinite=True).data).sum()) == 1001


def test_bool_labels_are_written_as_uint8(tmp_path):
    mask = np.zeros(GEOMETRY.array_shape, bool)
    mask[3:5, 2:8, 4:9] = True
    write_labels(Volume(mask, GEOMETRY), tmp_path / "mask.nrrd")
    back = read_labels(tmp_path / "mask.nrrd")
    assert back.data.dtype == np.uint8
    assert int(back.data.sum()) == 2 * 6 * 5


def test_supported_suffix_list_is_the_documented_one():
    assert volume_io.SUPPORTED_SUFFIXES == SUFFIXES


def test_folder_without_dicom_series(tmp_path):
    folder = tmp_path / "empty"
    folder.mkdir()
    (folder / "notes.txt").write_text("not DICOM")
    with pytest.raises(UnreadableFileError) as err:
        read_volume(folder)
    assert "no DICOM series" in str(err.value) and str(folder) in str(err.value)
    with pytest.raises(UnknownFormatError):  # folders are not written
        write_volume(_volume(np.float32, np.random.default_rng(0)), folder)


def test_writer_checks_the_suffix_before_the_data(tmp_path):
    nan_volume = Volume(np.full(GEOMETRY.array_shape, np.nan, np.float32), GEOMETRY)
    with pytest.raises(UnknownFormatError):
        write_volume(nan_volume, tmp_path / "scan.tiff")
    with pytest.raises(TypeError, match="expected a Volume"):
        write_volume(np.zeros((2, 2, 2)), tmp_path / "scan.mha")
    assert _listing(tmp_path) == []
