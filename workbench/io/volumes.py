"""Reading and writing volumes, label maps and displacement fields (SimpleITK).

Every reader returns a :class:`deformation.geometry.Volume` — voxels indexed
``[z, y, x]`` (``[z, y, x, c]`` for vectors) together with the grid geometry
in ITK ``(x, y, z)`` order — and every writer takes one.

Formats, chosen by suffix (case-insensitive)
--------------------------------------------
``.nii``, ``.nii.gz``
    NIfTI-1.  **Geometry is float32-exact only**: the header stores the
    spacing (``pixdim``), the origin (``qoffset``/``srow``) and the direction
    (a float32 quaternion / ``srow`` matrix) in single precision.  After a
    round trip spacing and origin are exactly the float32-rounded values
    (relative error ≤ 2**-24), and direction entries differ by at most about
    one float32 ulp (measured ≤ 6.3e-8 = 0.53 × float32 eps over 300 random
    rotations).  Integer-valued geometry (e.g. 1 mm spacing, origin 0) is
    therefore exact.  Voxels are exact.
``.mha``, ``.mhd`` (+ ``.raw``/``.zraw``)
    MetaImage.  Geometry is written as decimal text with 17 significant
    digits: exact round trip of every float64.
``.nrrd``, ``.nhdr`` (+ ``.raw``/``.raw.gz``)
    NRRD.  The origin is exact; spacing and direction are stored as their
    product (``space directions``) and recovered by ITK as the column norm and
    the normalised column, which costs up to about two float64 ulps
    (relative error ≤ 4.5e-16).
a folder
    A DICOM series, read with ``SimpleITK.ImageSeriesReader``: GDCM orders the
    slices by their position along the slice normal (Image Position Patient
    projected on the normal from Image Orientation Patient), not by file name
    or instance number; the slice spacing is the distance between slice
    positions.  Reading only.

Readers reject missing files (:class:`MissingFileError`), unknown suffixes
(:class:`UnknownFormatError`), truncated or corrupt data
(:class:`UnreadableFileError`, chaining SimpleITK's ``RuntimeError``), images
that are not 3-D or have the wrong number of components
(:class:`DimensionError`), geometry no scan of a body has
(:class:`ImplausibleGeometryError`: a voxel spacing outside
:data:`SPACING_RANGE_MM` or a field of view longer than
:data:`MAX_EXTENT_MM` along an axis) and, unless asked, NaN or infinite
voxels (:class:`NonFiniteError`).  Writers never modify their input, write atomically
(:mod:`workbench.io.atomic`) and refuse to overwrite unless ``overwrite=True``.

Three behaviours of ITK's NIfTI reader (niftilib) this module guards against:

* It pads a **truncated** ``.nii``/``.nii.gz`` with zeros and reports
  success.  Before reading, the data length in the file is checked against
  the header (``vox_offset + voxels × bitpix/8``); a gzip stream is
  decompressed once to check that it is complete and its CRC is right.
* It **replaces every NaN and infinity by 0** (``nifti_read_buffer``),
  silently.  The same pass over the data records the non-finite values and
  their positions; they are put back into the array, so NIfTI reports them
  like the other formats do (:class:`NonFiniteError`, or the values
  themselves with ``allow_nonfinite=True``).
* When asked for ``scan.nii.gz``, ITK's NIfTI library (``nifti_findimgname``)
  takes the header from ``scan.nii.gz`` but the **voxels from** ``scan.nii`` if
  that file exists beside it.  Such files are read through a private
  symbolic link, so the voxels come from the file asked for.
"""

from __future__ import annotations

import contextlib
import gzip
import os
import shutil
import struct
import tempfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from deformation.geometry import GridGeometry, Volume, slabs
from workbench.errors import (
    AmbiguousSeriesError,
    DimensionError,
    ImplausibleGeometryError,
    MissingFileError,
    NonFiniteError,
    PixelTypeError,
    SeriesNotFoundError,
    UnknownFormatError,
    UnreadableFileError,
)
from workbench.io.atomic import atomic_file_group, atomic_path, split_suffix

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

#: File suffixes understood by the readers and writers (a folder is read as DICOM).
SUPPORTED_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")

_IMAGE_IO = {
    ".nii": "NiftiImageIO",
    ".nii.gz": "NiftiImageIO",
    ".nrrd": "NrrdImageIO",
    ".nhdr": "NrrdImageIO",
    ".mha": "MetaImageIO",
    ".mhd": "MetaImageIO",
}
# Header formats whose voxels live in a companion file named in the header.
_DETACHED = {".mhd", ".nhdr"}

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

DICOM = "dicom"

#: Voxel spacings (mm) of scans of a body: from synchrotron micro-CT (about a micrometre) to thick-slice CT or MRI
#: (10 mm); beyond this range the header is wrong (a unit slip: metres or micrometres for millimetres).
SPACING_RANGE_MM = (1e-3, 20.0)
#: A field of view longer than this along an axis (mm) holds no scan of a body (a whole body is about 2 m).
MAX_EXTENT_MM = 4000.0


# ---------------------------------------------------------------------------
# Formats and paths
# ---------------------------------------------------------------------------


def _supported_list() -> str:
    return ", ".join(SUPPORTED_SUFFIXES) + ", or a folder holding one DICOM series"


def image_format(path: str | os.PathLike, *, for_writing: bool = False) -> str:
    """The format key of ``path``: its lower-case suffix (``".nii.gz"``, ...) or ``"dicom"``.

    Parameters
    ----------
    path : str or os.PathLike
        A file, or (for reading) a folder holding a DICOM series.
    for_writing : bool, optional
        Folders (DICOM) are not accepted for writing.

    Raises
    ------
    UnknownFormatError
        The suffix is not one of :data:`SUPPORTED_SUFFIXES`.
    """
    p = Path(path)
    if not for_writing and p.is_dir():
        return DICOM
    _, suffix = split_suffix(p.name)
    suffix = suffix.lower()
    if suffix in _IMAGE_IO:
        return suffix
    if for_writing:
        supported = ", ".join(SUPPORTED_SUFFIXES)
        raise UnknownFormatError(
            f"{p}: cannot tell the image format from the suffix {suffix or '(none)'!r}. "
            f"Supported suffixes: {supported}. Rename the output accordingly.",
            p,
        )
    raise UnknownFormatError(
        f"{p}: cannot tell the image format from the suffix {suffix or '(none)'!r}. "
        f"Supported: {_supported_list()}. Convert the file (e.g. with 3D Slicer or "
        "SimpleITK) or rename it if the suffix is wrong.",
        p,
    )


def _require_exists(path: Path) -> None:
    if not path.exists():
        where = "" if path.is_absolute() else f" (relative to the working folder {Path.cwd()})"
        raise MissingFileError(f"{path}: no such file or folder{where}. Check the path and the file name.", path)


def _first_line(e: BaseException) -> str:
    """The informative line of a SimpleITK error (the last non-empty one)."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return lines[-1] if lines else type(e).__name__


# ---------------------------------------------------------------------------
# Pre-read checks: companions of detached headers, complete NIfTI data
# ---------------------------------------------------------------------------


def _detached_data_file(path: Path, fmt: str) -> Path | None:
    """Data file named by a ``.mhd``/``.nhdr`` header, or None if not a single plain file."""
    key = "elementdatafile" if fmt == ".mhd" else None
    try:
        with open(path, "rb") as f:
            head = f.read(65536).decode("latin-1")
    except OSError:
        return None
    for line in head.splitlines():
        if fmt == ".mhd":
            name, sep, value = line.partition("=")
            if sep and name.strip().lower() == key:
                value = value.strip()
                if value.upper() in ("LOCAL", "LIST") or "%" in value or " " in value:
                    return None
                return path.parent / value
        else:
            name, sep, value = line.partition(":")
            if sep and name.strip().lower() in ("data file", "datafile"):
                value = value.strip()
                if value.upper().startswith("LIST") or "%" in value or " " in value:
                    return None
                return path.parent / value
    return None


@dataclass(frozen=True)
class _NiftiLayout:
    dims: tuple[int, ...]  # dim[1 .. dim[0]]
    datatype: int
    bitpix: int
    vox_offset: int
    endian: str
    scl_slope: float
    scl_inter: float

    @property
    def n_values(self) -> int:
        return int(np.prod([max(d, 1) for d in self.dims], dtype=np.int64))

    @property
    def n_bytes(self) -> int:
        return self.n_values * (self.bitpix // 8)

    @property
    def float_dtype(self) -> np.dtype | None:
        """Dtype of the float numbers in the data (complex as pairs), None for integers."""
        code = {16: "f4", 32: "f4", 64: "f8", 1792: "f8"}.get(self.datatype)
        return np.dtype(self.endian + code) if code else None


@dataclass(frozen=True)
class _NonFinite:
    """Non-finite numbers found in a file's data, by flat index in file order."""

    index: np.ndarray
    value: np.ndarray


def _nifti_layout(header: bytes, path: Path) -> _NiftiLayout:
    """Data layout from a NIfTI-1 or NIfTI-2 header."""
    if len(header) < 348:
        raise UnreadableFileError(
            f"{path}: only {len(header)} bytes, shorter than a NIfTI header (348 bytes); "
            "the file is truncated or not NIfTI. Re-export or re-copy it.",
            path,
        )
    for endian in "<>":
        (sizeof_hdr,) = struct.unpack(endian + "i", header[:4])
        if sizeof_hdr in (348, 540):
            break
    else:
        raise UnreadableFileError(
            f"{path}: not a NIfTI file (header size field is {sizeof_hdr}, expected 348 or 540). "
            "Check the file, or give it the suffix of its real format.",
            path,
        )
    if sizeof_hdr == 348:
        dims = struct.unpack(endian + "8h", header[40:56])
        datatype, bitpix = struct.unpack(endian + "hh", header[70:74])
        vox_offset, slope, inter = struct.unpack(endian + "fff", header[108:120])
    else:
        if len(header) < 540:
            raise UnreadableFileError(f"{path}: truncated NIfTI-2 header. Re-export the file.", path)
        datatype, bitpix = struct.unpack(endian + "hh", header[12:16])
        dims = struct.unpack(endian + "8q", header[16:80])
        vox_offset, slope, inter = struct.unpack(endian + "qdd", header[168:192])
    ndim = dims[0]
    if not 1 <= ndim <= 7 or bitpix <= 0 or bitpix % 8:
        raise UnreadableFileError(
            f"{path}: corrupt NIfTI header (dim[0]={ndim}, bitpix={bitpix}). Re-export the file.", path
        )
    return _NiftiLayout(
        dims=tuple(int(d) for d in dims[1 : ndim + 1]),
        datatype=int(datatype),
        bitpix=int(bitpix),
        vox_offset=int(vox_offset),
        endian=endian,
        scl_slope=float(slope),
        scl_inter=float(inter),
    )


def _scan_nifti(path: Path) -> tuple[_NiftiLayout, _NonFinite]:
    """Check a NIfTI file is complete, and find its NaN/inf values.

    Both checks are needed because niftilib (inside ITK) pads a truncated
    file with zeros and replaces every NaN and infinity by 0 while reading,
    without reporting either.  A gzip stream is decompressed in full, which
    also checks its CRC.
    """
    none = _NonFinite(np.zeros(0, np.int64), np.zeros(0))
    try:
        with open(path, "rb") as f:
            is_gzip = f.read(2) == b"\x1f\x8b"
        opener = gzip.open if is_gzip else open
        with opener(path, "rb") as f:
            layout = _nifti_layout(f.read(540), path)
            dtype = layout.float_dtype
            if dtype is None and not is_gzip:
                # Integer voxels cannot be non-finite: only the length matters.
                available = max(path.stat().st_size - layout.vox_offset, 0)
                found = none
            else:
                f.seek(layout.vox_offset)  # a gzip stream seeks forward by reading
                available, found = _scan_data_section(f, dtype, layout.n_bytes, drain=is_gzip)
    except (EOFError, gzip.BadGzipFile, zlib.error) as e:
        raise UnreadableFileError(
            f"{path}: the gzip stream is truncated or corrupt ({e}). The file was cut short "
            "(interrupted copy or download?): copy or export it again.",
            path,
        ) from e
    if available < layout.n_bytes:
        raise UnreadableFileError(
            f"{path}: truncated NIfTI file: the header promises {layout.n_bytes} bytes of voxels "
            f"from byte {layout.vox_offset}, but the {'decompressed ' if is_gzip else ''}file holds "
            f"only {available} of them. Copy or export it again.",
            path,
        )
    return layout, found


def _scan_data_section(
    f, dtype: np.dtype | None, n_bytes: int, *, drain: bool, chunk: int = 1 << 22
) -> tuple[int, _NonFinite]:
    """Read up to ``n_bytes`` of data from ``f``; return the count read and the non-finite floats."""
    item = dtype.itemsize if dtype is not None else 1
    n_read, carry = 0, b""
    indices, values = [], []
    while n_read + len(carry) < n_bytes:
        block = f.read(min(chunk, n_bytes - n_read - len(carry)))
        if not block:
            break
        data = carry + block
        usable = len(data) - len(data) % item
        if dtype is not None and usable:
            arr = np.frombuffer(data, dtype=dtype, count=usable // item)
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                indices.append(bad + n_read // item)
                values.append(arr[bad].astype(np.float64))
        n_read += usable
        carry = data[usable:]
    n_read += len(carry)
    if drain:  # read a gzip stream to its end so that its CRC is checked
        while f.read(chunk):
            pass
    found = _NonFinite(
        np.concatenate(indices) if indices else np.zeros(0, np.int64),
        np.concatenate(values) if values else np.zeros(0),
    )
    return n_read, found


@contextlib.contextmanager
def _nifti_read_name(path: Path) -> Iterator[Path]:
    """A name under which ITK reads the voxels of ``path`` itself.

    niftilib looks for the data of ``x.nii.gz`` in ``x.nii`` first; when that
    sibling exists, read through a symbolic link (or copy) in a private folder.
    """
    stem, suffix = split_suffix(path.name)
    sibling = path.with_name(stem + ".nii")
    if suffix.lower() != ".nii.gz" or not sibling.exists():
        yield path
        return
    with tempfile.TemporaryDirectory(prefix="workbench-nifti-") as d:
        alias = Path(d) / ("image" + suffix)
        try:
            os.symlink(path.resolve(), alias)
        except OSError:
            shutil.copyfile(path, alias)
        yield alias


# ---------------------------------------------------------------------------
# DICOM series
# ---------------------------------------------------------------------------


def _dicom_tag(reader: sitk.ImageFileReader, tag: str) -> str | None:
    return reader.GetMetaData(tag).strip() if reader.HasMetaDataKey(tag) else None


def _dicom_file_info(file: str) -> sitk.ImageFileReader:
    r = sitk.ImageFileReader()
    r.SetImageIO("GDCMImageIO")
    r.SetFileName(file)
    r.ReadImageInformation()
    return r


def _dicom_series_files(folder: Path, series_uid: str | None) -> list[str]:
    """File names of the chosen series, ordered by GDCM along the slice normal."""
    try:
        ids = list(sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder)))
    except RuntimeError as e:
        raise UnreadableFileError(
            f"{folder}: could not scan the folder for DICOM files ({_first_line(e)}).", folder
        ) from e
    if not ids:
        raise UnreadableFileError(
            f"{folder}: no DICOM series found in this folder (sub-folders are not searched). "
            "Point to the folder that holds the .dcm slices of one series, or give an image file "
            f"({', '.join(SUPPORTED_SUFFIXES)}).",
            folder,
        )
    if series_uid is None and len(ids) == 1:
        uid = ids[0]
    elif series_uid is not None and series_uid in ids:
        uid = series_uid
    else:
        lines = []
        for sid in ids:
            files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), sid)
            try:
                desc = _dicom_tag(_dicom_file_info(files[0]), "0008|103e") or "(no description)"
            except RuntimeError:
                desc = "(unreadable)"
            lines.append(f"  {sid}  {desc!r}  {len(files)} slices")
        listing = "\n".join(lines)
        if series_uid is None:
            raise AmbiguousSeriesError(
                f"{folder}: the folder holds {len(ids)} DICOM series:\n{listing}\n"
                "Choose one by passing series_uid=<one of the UIDs above>, or move each "
                "series into its own folder.",
                folder,
            )
        raise SeriesNotFoundError(
            f"{folder}: no DICOM series with SeriesInstanceUID {series_uid!r}. The folder holds:\n"
            f"{listing}\nPass one of these UIDs as series_uid=.",
            folder,
        )
    return list(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), uid))


def _dicom_slice_positions(files: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
    """Slice positions (mm) projected on the slice normal, and the normal; None if tags are absent."""
    positions, normal = [], None
    for f in files:
        r = _dicom_file_info(f)
        ipp, iop = _dicom_tag(r, "0020|0032"), _dicom_tag(r, "0020|0037")
        if ipp is None or iop is None:
            return None
        cosines = np.array([float(v) for v in iop.split("\\")])
        n = np.cross(cosines[:3], cosines[3:6])
        normal = n if normal is None else normal
        positions.append(np.array([float(v) for v in ipp.split("\\")]) @ normal)
    return np.asarray(positions), normal


def _check_dicom_spacing(folder: Path, files: list[str], *, rtol: float = 1e-3) -> np.ndarray | None:
    """Check that slices are at distinct, equally spaced positions along the normal."""
    found = _dicom_slice_positions(files)
    if found is None or len(files) < 2:
        return None
    pos, _ = found
    gaps = np.diff(pos)
    if np.any(np.abs(gaps) < 1e-6) or not (np.all(gaps > 0) or np.all(gaps < 0)):
        raise UnreadableFileError(
            f"{folder}: several DICOM slices of the series share a position along the slice "
            f"normal (positions {np.round(pos, 4).tolist()} mm); the series mixes acquisitions "
            "(e.g. echoes or time points). Split them into separate folders.",
            folder,
        )
    mean = (pos[-1] - pos[0]) / (len(pos) - 1)
    if np.max(np.abs(gaps - mean)) > rtol * abs(mean):
        raise UnreadableFileError(
            f"{folder}: DICOM slices are not equally spaced along the slice normal "
            f"(gaps {np.round(gaps, 4).tolist()} mm): slices are missing or the series is "
            "irregular, and a voxel grid would misplace them. Complete the series or "
            "resample it with a DICOM tool first.",
            folder,
        )
    return pos


def _read_dicom(folder: Path, series_uid: str | None) -> sitk.Image:
    files = _dicom_series_files(folder, series_uid)
    try:
        _check_dicom_spacing(folder, files)
        reader = sitk.ImageSeriesReader()
        reader.SetFileNames(files)
        return reader.Execute()
    except RuntimeError as e:
        raise UnreadableFileError(
            f"{folder}: SimpleITK could not read the DICOM series ({_first_line(e)}). "
            "A slice is probably truncated or corrupt; remove or replace it.",
            folder,
        ) from e


def _dicom_geometry(folder: Path, series_uid: str | None) -> GridGeometry:
    files = _dicom_series_files(folder, series_uid)
    try:
        first = _dicom_file_info(files[0])
        pos = _check_dicom_spacing(folder, files)
    except RuntimeError as e:
        raise UnreadableFileError(f"{folder}: unreadable DICOM header ({_first_line(e)}).", folder) from e
    nx, ny = first.GetSize()[:2]
    spacing = list(first.GetSpacing())
    if pos is not None:
        spacing[2] = abs(pos[-1] - pos[0]) / (len(pos) - 1)
    _require_plausible_geometry((nx, ny, len(files)), spacing, folder)
    return GridGeometry(
        size=(nx, ny, len(files)), spacing=spacing, origin=first.GetOrigin(), direction=first.GetDirection()
    )


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Loaded:
    image: sitk.Image
    path: Path
    # NIfTI only: NaN/inf values that niftilib zeroed while reading.
    nifti: tuple[_NiftiLayout, _NonFinite] | None = None

    def voxels(self) -> np.ndarray:
        """The voxels as in the file: ``[z, y, x]`` or ``[z, y, x, c]``.

        For NIfTI, the NaN and infinite values that niftilib replaced by 0
        are put back, so that every format reports them the same way.
        """
        data = sitk.GetArrayFromImage(self.image)
        if self.nifti is None or self.nifti[1].index.size == 0 or np.iscomplexobj(data):
            return data
        layout, found = self.nifti
        if data.size != layout.n_values or data.dtype.kind != "f":
            return data
        n_comp = layout.dims[4] if len(layout.dims) >= 5 else 1
        n_spatial = layout.n_values // n_comp
        values = found.value
        if layout.scl_slope != 0 and (layout.scl_slope, layout.scl_inter) != (1.0, 0.0):
            values = values * layout.scl_slope + layout.scl_inter  # as ITK scales the others
        # NIfTI stores x fastest, then y, z, t, and the vector component slowest.
        data.reshape(n_spatial, n_comp)[found.index % n_spatial, found.index // n_spatial] = values
        return data


def _read_sitk(path: str | os.PathLike, *, series_uid: str | None = None) -> _Loaded:
    p = Path(path)
    _require_exists(p)
    fmt = image_format(p)
    if fmt == DICOM:
        return _Loaded(_read_dicom(p, series_uid), p)
    if series_uid is not None:
        raise TypeError(f"{p}: series_uid= applies to DICOM folders only, not to {fmt} files.")
    if not p.is_file():
        raise UnreadableFileError(f"{p}: not a regular file. Give the path of an image file.", p)
    if fmt in _DETACHED:
        data = _detached_data_file(p, fmt)
        if data is not None and not data.exists():
            raise MissingFileError(
                f"{p}: the header refers to the data file {data.name}, which does not exist in "
                f"{data.parent}. Copy the data file next to the header (keep its name).",
                data,
            )
    nifti = _scan_nifti(p) if fmt in (".nii", ".nii.gz") else None
    reader = sitk.ImageFileReader()
    reader.SetImageIO(_IMAGE_IO[fmt])
    try:
        with _nifti_read_name(p) if nifti is not None else contextlib.nullcontext(p) as name:
            reader.SetFileName(str(name))
            image = reader.Execute()
    except RuntimeError as e:
        raise UnreadableFileError(
            f"{p}: SimpleITK could not read this {fmt} file: it is truncated, corrupt or not "
            f"really {fmt} ({_first_line(e)}). Copy or export it again"
            + (" and check that its data file is complete." if fmt in _DETACHED else "."),
            p,
        ) from e
    if image.GetDimension() == 3:
        _require_plausible_geometry(image.GetSize(), image.GetSpacing(), p)
    return _Loaded(image, p, nifti)


def _require_plausible_geometry(size, spacing, path: Path) -> None:
    """One clear error for a header whose voxel spacing or field of view no scan of a body has."""
    lo, hi = SPACING_RANGE_MM
    bad = [(a, float(v)) for a, v in zip("xyz", spacing) if not lo <= float(v) <= hi]
    if bad:
        said = ", ".join(f"{a} {v:g} mm" for a, v in bad)
        raise ImplausibleGeometryError(
            f"{path}: voxel spacing {said} is outside {lo:g}–{hi:g} mm, which no scan of a body has; the header's "
            "spacing is wrong (metres or micrometres for millimetres?). Fix the spacing in the header, e.g. with "
            "SimpleITK's image.SetSpacing(...) and WriteImage, or 3D Slicer's Volumes module.",
            path,
        )
    extent = [float(n) * float(v) for n, v in zip(size, spacing)]
    if max(extent) > MAX_EXTENT_MM:
        raise ImplausibleGeometryError(
            f"{path}: a field of view of {' x '.join(f'{e:g}' for e in extent)} mm is longer than {MAX_EXTENT_MM:g} "
            "mm along an axis, which no scan of a body has; check the header's spacing and size.",
            path,
        )


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


def _check_finite(data: np.ndarray, path: Path, what: str, fix: str) -> None:
    finite = np.isfinite(data)
    if finite.all():
        return
    bad = ~finite if data.ndim == 3 else ~finite.all(axis=-1)
    n_bad = int(bad.sum())
    n_nan = int(np.isnan(data).any(axis=-1).sum() if data.ndim == 4 else np.isnan(data).sum())
    zyx = np.unravel_index(int(np.argmax(bad)), bad.shape)
    ijk = tuple(int(v) for v in zyx[::-1])
    value = data[zyx]
    raise NonFiniteError(
        f"{path}: {n_bad} of {bad.size} voxels of this {what} are not finite "
        f"({n_nan} NaN, {n_bad - n_nan} infinite); the first is at voxel index (i, j, k) = {ijk} "
        f"(array [z, y, x] = {tuple(int(v) for v in zyx)}), value {value}. {fix}",
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
_FIX_WRITE = "Nothing was written. Replace or mask these voxels first (e.g. numpy.nan_to_num)"


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
        _check_finite(data, p, "volume", _FIX_READ + ".")
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
        _check_finite(data, p, "displacement field", _FIX_READ_FIELD + ".")
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
    _require_exists(p)
    fmt = image_format(p)
    if fmt == DICOM:
        return _dicom_geometry(p, series_uid)
    reader = sitk.ImageFileReader()
    reader.SetImageIO(_IMAGE_IO[fmt])
    reader.SetFileName(str(p))
    try:
        reader.ReadImageInformation()
    except RuntimeError as e:
        raise UnreadableFileError(
            f"{p}: SimpleITK could not read the header of this {fmt} file ({_first_line(e)}). "
            "It is corrupt or not really of this format: export it again.",
            p,
        ) from e
    if reader.GetDimension() != 3:
        raise DimensionError(
            f"{p}: the image is {reader.GetDimension()}-D (size {reader.GetSize()}); a 3-D grid is needed.",
            p,
        )
    _require_plausible_geometry(reader.GetSize(), reader.GetSpacing(), p)
    return GridGeometry(
        size=reader.GetSize(), spacing=reader.GetSpacing(), origin=reader.GetOrigin(), direction=reader.GetDirection()
    )


# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------


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
    group = atomic_file_group if fmt in _DETACHED else atomic_path
    with group(path, overwrite=overwrite) as tmp:
        writer = sitk.ImageFileWriter()
        writer.SetImageIO(_IMAGE_IO[fmt])
        writer.SetFileName(str(tmp))
        # NIfTI compression follows the suffix (.nii.gz); the flag would be ignored.
        writer.SetUseCompression(bool(compress) or fmt == ".nii.gz")
        try:
            writer.Execute(image)
        except RuntimeError as e:
            raise OSError(f"{path}: SimpleITK could not write the file ({_first_line(e)}).") from e
        if fmt in (".nii", ".nii.gz"):
            _check_nifti_written(tmp)
    return path


def _check_nifti_written(path: Path) -> None:
    """Raise :class:`OSError` unless the NIfTI file ``path`` holds its whole header and data.

    niftilib (ITK's NIfTI writer) reports a short write only on its own
    standard error ("NWAD: wrote only 0 of N bytes") and returns normally; the
    MetaImage and NRRD writers raise.  A plain file must be at least
    ``vox_offset`` + the data's size; a gzip file must end with the trailer of
    a stream of exactly that size (RFC 1952's ISIZE, the length modulo 2³²):
    a stream cut short ends in compressed data instead.
    """
    with open(path, "rb") as f:
        is_gzip = f.read(2) == b"\x1f\x8b"
    try:
        with (gzip.open if is_gzip else open)(path, "rb") as f:
            layout = _nifti_layout(f.read(540), path)
    except (EOFError, gzip.BadGzipFile, zlib.error, UnreadableFileError) as e:
        raise OSError(f"the written header is incomplete ({_first_line(e)})") from e
    expected = layout.vox_offset + layout.n_bytes
    size = path.stat().st_size
    if not is_gzip:
        if size < expected:
            raise OSError(f"wrote only {size} of {expected} bytes")
        return
    with open(path, "rb") as f:
        f.seek(max(size - 4, 0))
        isize = int.from_bytes(f.read(4), "little") if size >= 18 else -1
    if isize != expected % (1 << 32):
        raise OSError(f"the gzip stream is cut short after {size} bytes")


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
        Replace an existing file; otherwise :class:`OutputExistsError`.
    compress : bool, optional
        zlib/gzip compression for MetaImage and NRRD.  NIfTI follows its
        suffix (``.nii.gz`` compressed, ``.nii`` not).
    allow_nonfinite : bool, optional
        Write NaN/inf voxels (the default refuses, because :func:`read_volume`
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
        _check_finite(data, p, "volume", _FIX_WRITE + ", or pass allow_nonfinite=True.")
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
        _check_finite(data, p, "displacement field", _FIX_WRITE + ".")
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
        _check_finite(data, p, "vector image", _FIX_WRITE + ".")
    return _write_sitk(_image_from(volume, data, is_vector=True), p, overwrite=overwrite, compress=compress)


def read_vector_image(path: str | os.PathLike, *, components: int | None = None) -> Volume:
    """Read a 3-D vector image as ``(nz, ny, nx, c)`` in its stored dtype (scalars get ``c = 1``).

    ``components`` checks the number of components per voxel
    (:class:`DimensionError` naming the file when it differs).
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
        _check_finite(data, p, "vector image", _FIX_READ_FIELD + ".")
    return Volume(data, GridGeometry.from_sitk(image))
