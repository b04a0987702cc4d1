"""Reading and writing volumes, label maps, displacement fields and vector images (SimpleITK).

Every reader returns a :class:`deformation.geometry.Volume` — voxels indexed
``[z, y, x]`` (``[z, y, x, c]`` for vectors) together with the grid geometry
in ITK ``(x, y, z)`` order — and every writer takes one.  The formats and
what each keeps of the geometry: :mod:`workbench.io.formats`; NIfTI's
guards: :mod:`workbench.io.nifti`; DICOM folders: :mod:`workbench.io.dicom`.

Readers reject missing files (:class:`~workbench.errors.MissingFileError`), unknown suffixes
(:class:`~workbench.errors.UnknownFormatError`), truncated or corrupt data
(:class:`~workbench.errors.UnreadableFileError`, chaining SimpleITK's ``RuntimeError``), images
that are not 3-D or have the wrong number of components
(:class:`~workbench.errors.DimensionError`), implausible geometry
(:class:`~workbench.errors.ImplausibleGeometryError`) and, unless asked, NaN or infinite
voxels (:class:`~workbench.errors.NonFiniteError`).  The writers (:mod:`workbench.io.volume_writers`)
are re-exported here.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from deformation.geometry import GridGeometry, Volume
from workbench.errors import DimensionError, MissingFileError, PixelTypeError, UnreadableFileError
from workbench.io.dicom import dicom_geometry, read_dicom_series
from workbench.io.formats import (
    DETACHED,
    DICOM,
    IMAGE_IO,
    SUPPORTED_SUFFIXES,
    check_finite,
    detached_data_file,
    image_format,
    require_exists,
    require_plausible_geometry,
    sitk_error_line,
)
from workbench.io.nifti import (
    NiftiLayout,
    NonFinite,
    nifti_read_name,
    restore_nonfinite,
    scan_nifti,
)
from workbench.io.volume_writers import write_displacement, write_labels, write_vector_image, write_volume

__all__ = [
    "SUPPORTED_SUFFIXES",
    "image_format",
    "read_volume",
    "read_labels",
    "read_displacement",
    "read_vector_image",
    "write_vector_image",
    "read_image_geometry",
    "write_volume",
    "write_labels",
    "write_displacement",
]


@dataclass(frozen=True)
class _Loaded:
    image: sitk.Image
    path: Path
    # NIfTI only: NaN/inf values that niftilib zeroed while reading.
    nifti: tuple[NiftiLayout, NonFinite] | None = None

    def voxels(self) -> np.ndarray:
        """The voxels as in the file: ``[z, y, x]`` or ``[z, y, x, c]`` (for NIfTI with the NaN and infinite
        values niftilib replaced by 0 put back, so that every format reports them the same way)."""
        data = sitk.GetArrayFromImage(self.image)
        return data if self.nifti is None else restore_nonfinite(data, *self.nifti)


def _read_sitk(path: str | os.PathLike, *, series_uid: str | None = None) -> _Loaded:
    p = Path(path)
    require_exists(p)
    fmt = image_format(p)
    if fmt == DICOM:
        return _Loaded(read_dicom_series(p, series_uid), p)
    if series_uid is not None:
        raise TypeError(f"{p}: series_uid= applies to DICOM folders only, not to {fmt} files.")
    if not p.is_file():
        raise UnreadableFileError(f"{p}: not a regular file. Give the path of an image file.", p)
    if fmt in DETACHED:
        data = detached_data_file(p, fmt)
        if data is not None and not data.exists():
            raise MissingFileError(
                f"{p}: the header refers to the data file {data.name}, which does not exist in "
                f"{data.parent}. Copy the data file next to the header (keep its name).",
                data,
            )
    nifti = scan_nifti(p) if fmt in (".nii", ".nii.gz") else None
    reader = sitk.ImageFileReader()
    reader.SetImageIO(IMAGE_IO[fmt])
    try:
        with nifti_read_name(p) if nifti is not None else contextlib.nullcontext(p) as name:
            reader.SetFileName(str(name))
            image = reader.Execute()
    except RuntimeError as e:
        raise UnreadableFileError(
            f"{p}: SimpleITK could not read this {fmt} file: it is truncated, corrupt or not "
            f"really {fmt} ({sitk_error_line(e)}). Copy or export it again"
            + (" and check that its data file is complete." if fmt in DETACHED else "."),
            p,
        ) from e
    if image.GetDimension() == 3:
        require_plausible_geometry(image.GetSize(), image.GetSpacing(), p)
    return _Loaded(image, p, nifti)


def _require_3d(image: sitk.Image, path: Path, what: str) -> None:
    dim = image.GetDimension()
    if dim != 3:
        hint = (
            " If this is one slice of a DICOM series, read the folder that holds all slices."
            if dim == 2
            else " Split the extra dimension (e.g. time points) into separate 3-D files."
        )
        raise DimensionError(
            f"{path}: the image is {dim}-D (size {image.GetSize()}), but a 3-D {what} is needed.{hint}",
            path,
        )


_FIX_READ = (
    "Replace these voxels and save the file again: `workbench clean-image FILE --out CLEAN.nii.gz` "
    "fills them (with --value V, default the image's lowest finite value)"
)
_FIX_READ_FIELD = (
    "Replace these vectors (by zero displacement where nothing is known) and save the file again, "
    "or make the field anew"
)


def read_volume(path: str | os.PathLike, *, series_uid: str | None = None, allow_nonfinite: bool = False) -> Volume:
    """Read a scalar 3-D image (intensities) with its geometry.

    Parameters
    ----------
    path : str or os.PathLike
        An image file (see the module docstring for the formats) or a folder
        holding a DICOM series.
    series_uid : str, optional
        SeriesInstanceUID of the series to read when a DICOM folder holds
        several.
    allow_nonfinite : bool, optional
        Accept NaN and infinite voxels.

    Returns
    -------
    Volume
        ``data`` indexed ``[z, y, x]`` in the file's pixel type (integer or
        floating point), ``geometry`` in ITK ``(x, y, z)`` order.

    Raises
    ------
    MissingFileError, UnknownFormatError, UnreadableFileError
        The file is absent, of an unknown format, or truncated/corrupt.
    DimensionError
        The image is not 3-D or has more than one component per voxel.
    PixelTypeError
        Complex voxels.
    NonFiniteError
        NaN or infinite voxels (unless ``allow_nonfinite``).
    AmbiguousSeriesError, SeriesNotFoundError
        DICOM folder with several series and no (or an unknown) ``series_uid``.
    """
    loaded = _read_sitk(path, series_uid=series_uid)
    image, p = loaded.image, loaded.path
    _require_3d(image, p, "volume")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise DimensionError(
            f"{p}: the image has {image.GetNumberOfComponentsPerPixel()} components per voxel "
            f"({image.GetPixelIDTypeAsString()}); a scalar volume is needed. A 3-vector image is "
            "probably a displacement field: read it with read_displacement().",
            p,
        )
    data = loaded.voxels()
    if np.iscomplexobj(data):
        raise PixelTypeError(
            f"{p}: complex voxels ({image.GetPixelIDTypeAsString()}); save the magnitude image instead.", p
        )
    if not allow_nonfinite and data.dtype.kind == "f":
        check_finite(data, p, "volume", _FIX_READ + ".")
    return Volume(data, GridGeometry.from_sitk(image))


def _geometry_of(reference, role: str) -> tuple[GridGeometry, str]:
    if isinstance(reference, Volume):
        return reference.geometry, f"{role} volume"
    if isinstance(reference, GridGeometry):
        return reference, f"{role} geometry"
    if isinstance(reference, (str, os.PathLike)):
        return read_image_geometry(reference), f"{role} {Path(reference)}"
    raise TypeError(f"reference must be a Volume, a GridGeometry or a path, got {type(reference).__name__}")


def read_labels(
    path: str | os.PathLike,
    *,
    reference: Volume | GridGeometry | str | os.PathLike | None = None,
) -> Volume:
    """Read an integer label map, optionally checking it lies on a reference grid.

    Parameters
    ----------
    path : str or os.PathLike
        Label-map file (NIfTI, MetaImage, NRRD) or DICOM folder.
    reference : Volume, GridGeometry, path, optional
        The grid the labels must share (e.g. the scan they segment). A path is
        read header-only.  No resampling is ever done silently.

    Returns
    -------
    Volume
        Integer labels indexed ``[z, y, x]`` in the file's integer type.  A
        floating-point file is accepted when every voxel is a whole number and
        is converted to ``int32``.

    Raises
    ------
    GeometryMismatchError
        The label map's grid differs from ``reference`` (the message prints
        both geometries and the remedy).
    PixelTypeError
        Fractional, NaN or out-of-range values.
    MissingFileError, UnknownFormatError, UnreadableFileError, DimensionError
        As for :func:`read_volume`.
    """
    loaded = _read_sitk(path)
    image, p = loaded.image, loaded.path
    _require_3d(image, p, "label map")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise DimensionError(
            f"{p}: the image has {image.GetNumberOfComponentsPerPixel()} components per voxel; "
            "a label map has one integer label per voxel. Check that this is the right file.",
            p,
        )
    geometry = GridGeometry.from_sitk(image)
    if reference is not None:
        ref_geometry, ref_name = _geometry_of(reference, "reference")
        geometry.check_same(
            ref_geometry,
            names=(f"label map {p}", ref_name),
            remedy=(
                f"the label map {p.name} does not lie on the grid of the volume it should "
                "segment. Check that the two files belong together, or resample the label map "
                "onto the volume's grid with nearest-neighbour interpolation "
                "(SimpleITK.Resample(labels, volume, sitk.Transform(), sitk.sitkNearestNeighbor))"
            ),
        )
    data = loaded.voxels()
    if data.dtype.kind == "f":
        whole = np.isfinite(data) & (data == np.round(data))
        if not whole.all() or (data.size and np.abs(data).max() > np.iinfo(np.int32).max):
            zyx = np.unravel_index(int(np.argmin(whole)), data.shape)
            raise PixelTypeError(
                f"{p}: a label map must hold whole numbers, but voxel (i, j, k) = "
                f"{tuple(int(v) for v in zyx[::-1])} is {data[zyx]!r}. This looks like an "
                "intensity image: read it with read_volume(), or round and save the labels as "
                "an integer type.",
                p,
            )
        data = data.astype(np.int32)
    elif data.dtype.kind not in "iu":
        raise PixelTypeError(f"{p}: label maps need integer voxels, got {data.dtype}.", p)
    return Volume(data, geometry)


def read_displacement(path: str | os.PathLike, *, allow_nonfinite: bool = False) -> Volume:
    """Read a displacement field stored as a 3-component vector image.

    Parameters
    ----------
    path : str or os.PathLike
        Vector image (NIfTI, MetaImage, NRRD) as written by
        :func:`write_displacement` or by ITK tools.
    allow_nonfinite : bool, optional
        Accept NaN and infinite vectors.

    Returns
    -------
    Volume
        ``data`` of shape ``(nz, ny, nx, 3)``, float64, components
        ``(x, y, z)`` in world millimetres.  The direction of the mapping is
        whatever the file's producer states; this reader does not change it.

    Raises
    ------
    DimensionError
        Not 3-D, or not exactly 3 components per voxel.
    NonFiniteError
        NaN or infinite components (unless ``allow_nonfinite``).
    MissingFileError, UnknownFormatError, UnreadableFileError
        As for :func:`read_volume`.
    """
    loaded = _read_sitk(path)
    image, p = loaded.image, loaded.path
    if image.GetDimension() == 4 and image.GetSize()[3] == 3 and image.GetNumberOfComponentsPerPixel() == 1:
        raise DimensionError(
            f"{p}: a 4-D scalar image of size {image.GetSize()}: the three displacement "
            "components are stored as a fourth (time) dimension. Convert it to a 3-D vector "
            "image (e.g. sitk.Compose of the three 3-D components) and save it again.",
            p,
        )
    _require_3d(image, p, "displacement field")
    n = image.GetNumberOfComponentsPerPixel()
    if n != 3:
        raise DimensionError(
            f"{p}: {n} component{'s' if n != 1 else ''} per voxel; a displacement field needs 3 "
            "(x, y, z in mm). A scalar image is a volume or label map: read it with "
            "read_volume() or read_labels().",
            p,
        )
    data = loaded.voxels()
    if data.dtype.kind not in "fiu":
        raise PixelTypeError(f"{p}: displacement components must be real numbers, got {data.dtype}.", p)
    data = data.astype(np.float64, copy=False)
    if not allow_nonfinite:
        check_finite(data, p, "displacement field", _FIX_READ_FIELD + ".")
    return Volume(data, GridGeometry.from_sitk(image))


def read_image_geometry(path: str | os.PathLike, *, series_uid: str | None = None) -> GridGeometry:
    """Read only the grid geometry from an image header (no voxels are read).

    Parameters
    ----------
    path : str or os.PathLike
        Image file or DICOM folder (for DICOM every slice's header is read to
        find the slice spacing, as :func:`read_volume` does).
    series_uid : str, optional
        See :func:`read_volume`.

    Returns
    -------
    GridGeometry
        Size, spacing, origin and direction in ITK ``(x, y, z)`` order.
    """
    p = Path(path)
    require_exists(p)
    fmt = image_format(p)
    if fmt == DICOM:
        return dicom_geometry(p, series_uid)
    reader = sitk.ImageFileReader()
    reader.SetImageIO(IMAGE_IO[fmt])
    reader.SetFileName(str(p))
    try:
        reader.ReadImageInformation()
    except RuntimeError as e:
        raise UnreadableFileError(
            f"{p}: SimpleITK could not read the header of this {fmt} file ({sitk_error_line(e)}). "
            "It is corrupt or not really of this format: export it again.",
            p,
        ) from e
    if reader.GetDimension() != 3:
        raise DimensionError(
            f"{p}: the image is {reader.GetDimension()}-D (size {reader.GetSize()}); a 3-D grid is needed.",
            p,
        )
    require_plausible_geometry(reader.GetSize(), reader.GetSpacing(), p)
    return GridGeometry(
        size=reader.GetSize(), spacing=reader.GetSpacing(), origin=reader.GetOrigin(), direction=reader.GetDirection()
    )


def read_vector_image(path: str | os.PathLike, *, components: int | None = None) -> Volume:
    """Read a 3-D vector image as ``(nz, ny, nx, c)`` in its stored dtype (scalars get ``c = 1``).

    ``components`` checks the number of components per voxel
    (:class:`~workbench.errors.DimensionError` naming the file when it differs).
    """
    loaded = _read_sitk(path)
    image, p = loaded.image, loaded.path
    _require_3d(image, p, "vector image")
    n = image.GetNumberOfComponentsPerPixel()
    if components is not None and n != components:
        raise DimensionError(f"{p}: {n} component(s) per voxel, expected {components}.", p)
    data = loaded.voxels()
    if data.ndim == 3:
        data = data[..., None]
    if data.dtype.kind == "f":
        check_finite(data, p, "vector image", _FIX_READ_FIELD + ".")
    return Volume(data, GridGeometry.from_sitk(image))
