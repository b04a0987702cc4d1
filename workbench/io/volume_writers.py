"""Writing volumes, label maps, displacement fields and vector images with their geometry (SimpleITK).

Writers never modify their input, write atomically (:mod:`workbench.io.atomic`),
refuse to overwrite unless ``overwrite=True``, and refuse NaN or infinite
voxels (:class:`~workbench.errors.NonFiniteError`) unless asked.  What each format keeps of the
geometry: :mod:`workbench.io.formats`.  All are re-exported by
:mod:`workbench.io.volumes`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from deformation.geometry import Volume, slabs
from workbench.io.atomic import atomic_file_group, atomic_path
from workbench.io.formats import DETACHED, IMAGE_IO, check_finite, image_format, sitk_error_line
from workbench.io.nifti import check_nifti_written

__all__ = ["write_volume", "write_labels", "write_displacement", "write_vector_image"]

_WRITABLE_DTYPES = {
    np.dtype(t)
    for t in (
        np.uint8,
        np.int8,
        np.uint16,
        np.int16,
        np.uint32,
        np.int32,
        np.uint64,
        np.int64,
        np.float32,
        np.float64,
    )
}

_FIX_WRITE = "Nothing was written. Replace or mask these voxels first (e.g. numpy.nan_to_num)"


def _output_path(volume, path: str | os.PathLike) -> Path:
    """Check the arguments common to all writers before looking at the data."""
    p = Path(path)
    if not isinstance(volume, Volume):
        raise TypeError(f"{p}: expected a Volume (data with its geometry), got {type(volume).__name__}")
    image_format(p, for_writing=True)
    return p


def _all_finite(data: np.ndarray) -> bool:
    """Whether every value is finite, a block of slices at a time (a 197 M-voxel field's whole-array mask
    would be another 0.6 GiB)."""
    return all(np.isfinite(data[k0:k1]).all() for k0, k1 in slabs(len(data), data[:1].size, 1 << 24))


def _writable_array(data: np.ndarray, path: Path, what: str) -> np.ndarray:
    dtype = data.dtype
    if dtype.byteorder not in ("=", "|"):
        data = data.astype(dtype.newbyteorder("="))
    if data.dtype not in _WRITABLE_DTYPES:
        raise TypeError(
            f"{path}: cannot write a {what} of dtype {dtype}; supported: "
            f"{', '.join(sorted(str(t) for t in _WRITABLE_DTYPES))}. Cast it first "
            "(e.g. volume.data.astype(numpy.float32))."
        )
    return data


def _write_sitk(image: sitk.Image, path: Path, *, overwrite: bool, compress: bool) -> Path:
    fmt = image_format(path, for_writing=True)
    group = atomic_file_group if fmt in DETACHED else atomic_path
    with group(path, overwrite=overwrite) as tmp:
        writer = sitk.ImageFileWriter()
        writer.SetImageIO(IMAGE_IO[fmt])
        writer.SetFileName(str(tmp))
        # NIfTI compression follows the suffix (.nii.gz); the flag would be ignored.
        writer.SetUseCompression(bool(compress) or fmt == ".nii.gz")
        try:
            writer.Execute(image)
        except RuntimeError as e:
            raise OSError(f"{path}: SimpleITK could not write the file ({sitk_error_line(e)}).") from e
        if fmt in (".nii", ".nii.gz"):
            check_nifti_written(tmp)
    return path


def _image_from(volume: Volume, data: np.ndarray, *, is_vector: bool) -> sitk.Image:
    image = sitk.GetImageFromArray(data, isVector=is_vector)  # copies: input untouched
    volume.geometry.apply_to_sitk(image)
    return image


def write_volume(
    volume: Volume,
    path: str | os.PathLike,
    *,
    overwrite: bool = False,
    compress: bool = True,
    allow_nonfinite: bool = False,
) -> Path:
    """Write a scalar volume with its geometry, atomically.

    Parameters
    ----------
    volume : Volume
        Scalar data ``[z, y, x]`` of an integer or float type; not modified.
    path : str or os.PathLike
        Output file; the suffix chooses the format (``.nii``, ``.nii.gz``,
        ``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``).  NIfTI keeps the geometry to
        float32 precision only (see the module docstring).
    overwrite : bool, optional
        Replace an existing file; otherwise :class:`~workbench.errors.OutputExistsError`.
    compress : bool, optional
        zlib/gzip compression for MetaImage and NRRD.  NIfTI follows its
        suffix (``.nii.gz`` compressed, ``.nii`` not).
    allow_nonfinite : bool, optional
        Write NaN/inf voxels (the default refuses, because :func:`~workbench.io.volumes.read_volume`
        would refuse them too).

    Returns
    -------
    pathlib.Path
        The path written.
    """
    p = _output_path(volume, path)
    if volume.is_vector:
        raise ValueError(f"{p}: write_volume takes a scalar volume; use write_displacement for vector images.")
    data = _writable_array(volume.data, p, "volume")
    if not allow_nonfinite and data.dtype.kind == "f" and not _all_finite(data):
        check_finite(data, p, "volume", _FIX_WRITE + ", or pass allow_nonfinite=True.")
    return _write_sitk(_image_from(volume, data, is_vector=False), p, overwrite=overwrite, compress=compress)


def write_labels(volume: Volume, path: str | os.PathLike, *, overwrite: bool = False, compress: bool = True) -> Path:
    """Write an integer label map with its geometry, atomically.

    Parameters
    ----------
    volume : Volume
        Integer (or boolean, written as uint8) labels ``[z, y, x]``; not modified.
    path : str or os.PathLike
        Output file; formats as for :func:`write_volume`.
    overwrite, compress : bool, optional
        As for :func:`write_volume`.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    p = _output_path(volume, path)
    if volume.is_vector:
        raise ValueError(f"{p}: a label map has one label per voxel; got a vector image.")
    data = volume.data
    if data.dtype == np.bool_:
        data = data.astype(np.uint8)
    if data.dtype.kind not in "iu":
        raise TypeError(
            f"{p}: a label map must have an integer dtype, got {data.dtype}. Round and cast "
            "the labels (e.g. numpy.rint(a).astype(numpy.uint16)), or use write_volume for intensities."
        )
    data = _writable_array(data, p, "label map")
    return _write_sitk(_image_from(volume, data, is_vector=False), p, overwrite=overwrite, compress=compress)


def write_displacement(
    volume: Volume, path: str | os.PathLike, *, overwrite: bool = False, compress: bool = True
) -> Path:
    """Write a displacement field as an ITK vector image, atomically.

    The file is a 3-D image of 3-component vectors (``sitkVectorFloat32`` or
    ``sitkVectorFloat64``, following the data's dtype), components ``(x, y,
    z)`` in world mm — the layout ``sitk.DisplacementFieldTransform`` expects
    (after ``sitk.Cast(image, sitk.sitkVectorFloat64)``) and 3D Slicer and
    ITK-SNAP read as a vector field.

    In NIfTI files ITK stores the vectors as they are (components in ITK's
    LPS world frame, one 3-D volume per component along dim 5, intent code
    ``NIFTI_INTENT_VECTOR``), which ITK-based tools read correctly; tools that
    assume RAS components (FSL, nibabel-based code) must negate x and y.
    Prefer ``.mha`` or ``.nrrd`` for fields, whose geometry is also exact.

    Parameters
    ----------
    volume : Volume
        Vector data ``(nz, ny, nx, 3)``, float32 or float64, finite; not modified.
    path : str or os.PathLike
        Output file; formats as for :func:`write_volume`.
    overwrite, compress : bool, optional
        As for :func:`write_volume`.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    p = _output_path(volume, path)
    data = volume.data
    if data.ndim != 4 or data.shape[3] != 3:
        raise ValueError(f"{p}: a displacement field needs data of shape (nz, ny, nx, 3), got {data.shape}.")
    if data.dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise TypeError(f"{p}: displacement fields are float32 or float64, got {data.dtype}; cast first.")
    data = _writable_array(data, p, "displacement field")
    if not _all_finite(data):
        check_finite(data, p, "displacement field", _FIX_WRITE + ".")
    return _write_sitk(_image_from(volume, data, is_vector=True), p, overwrite=overwrite, compress=compress)


def write_vector_image(
    volume: Volume, path: str | os.PathLike, *, overwrite: bool = False, compress: bool = True
) -> Path:
    """Write a vector image of any number of components per voxel (e.g. skinning weights), atomically.

    ``volume.data`` is ``(nz, ny, nx, c)`` of an integer or float type, finite.
    Use :func:`write_displacement` for displacement fields (3 components in
    mm), whose layout tools recognise.  MetaImage (``.mha``) and NRRD keep
    the geometry exact.
    """
    p = _output_path(volume, path)
    data = volume.data
    if data.ndim != 4:
        raise ValueError(f"{p}: a vector image needs data of shape (nz, ny, nx, c), got {data.shape}.")
    data = _writable_array(data, p, "vector image")
    if data.dtype.kind == "f" and not _all_finite(data):
        check_finite(data, p, "vector image", _FIX_WRITE + ".")
    return _write_sitk(_image_from(volume, data, is_vector=True), p, overwrite=overwrite, compress=compress)
