"""Image file formats: which suffix is which format, and the checks every reader makes first.

Formats, chosen by suffix (case-insensitive):

* ``.nii``, ``.nii.gz`` — NIfTI-1.  Geometry is float32-exact only: the
  header stores spacing, origin and direction in single precision, so after a
  round trip spacing and origin are the float32-rounded values (relative
  error ≤ 2**-24) and direction entries differ by about one float32 ulp
  (docs/measurements/workbench.md).  Integer-valued geometry is exact;
  voxels are exact.
* ``.mha``, ``.mhd`` (+ ``.raw``/``.zraw``) — MetaImage: geometry as decimal
  text with 17 significant digits, an exact round trip of every float64.
* ``.nrrd``, ``.nhdr`` (+ ``.raw``/``.raw.gz``) — NRRD: the origin is exact;
  spacing and direction are stored as their product (``space directions``)
  and recovered as the column norm and the normalised column, which costs up
  to about two float64 ulps (relative error ≤ 4.5e-16).
* a folder — a DICOM series (:mod:`workbench.io.dicom`), reading only.

Geometry no scan of a body has (a voxel spacing outside
:data:`SPACING_RANGE_MM`, a field of view longer than :data:`MAX_EXTENT_MM`)
is refused with :class:`~workbench.errors.ImplausibleGeometryError`; NaN and infinite voxels,
unless asked for, with :class:`~workbench.errors.NonFiniteError` (:func:`check_finite`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from workbench.errors import ImplausibleGeometryError, MissingFileError, NonFiniteError, UnknownFormatError
from workbench.io.atomic import split_suffix

__all__ = [
    "SUPPORTED_SUFFIXES",
    "IMAGE_IO",
    "DETACHED",
    "DICOM",
    "SPACING_RANGE_MM",
    "MAX_EXTENT_MM",
    "image_format",
    "require_exists",
    "sitk_error_line",
    "detached_data_file",
    "require_plausible_geometry",
    "check_finite",
]

#: File suffixes understood by the readers and writers (a folder is read as DICOM).
SUPPORTED_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")

IMAGE_IO = {
    ".nii": "NiftiImageIO",
    ".nii.gz": "NiftiImageIO",
    ".nrrd": "NrrdImageIO",
    ".nhdr": "NrrdImageIO",
    ".mha": "MetaImageIO",
    ".mhd": "MetaImageIO",
}
# Header formats whose voxels live in a companion file named in the header.
DETACHED = {".mhd", ".nhdr"}

DICOM = "dicom"

#: Voxel spacings (mm) of scans of a body: from synchrotron micro-CT (about a micrometre) to thick-slice CT or MRI
#: (10 mm); beyond this range the header is wrong (a unit slip: metres or micrometres for millimetres).
SPACING_RANGE_MM = (1e-3, 20.0)
#: A field of view longer than this along an axis (mm) holds no scan of a body (a whole body is about 2 m).
MAX_EXTENT_MM = 4000.0


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
        The suffix is not one of :data:`~workbench.io.formats.SUPPORTED_SUFFIXES`.
    """
    p = Path(path)
    if not for_writing and p.is_dir():
        return DICOM
    _, suffix = split_suffix(p.name)
    suffix = suffix.lower()
    if suffix in IMAGE_IO:
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


def require_exists(path: Path) -> None:
    if not path.exists():
        where = "" if path.is_absolute() else f" (relative to the working folder {Path.cwd()})"
        raise MissingFileError(f"{path}: no such file or folder{where}. Check the path and the file name.", path)


def sitk_error_line(e: BaseException) -> str:
    """The informative line of a SimpleITK error (the last non-empty one)."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return lines[-1] if lines else type(e).__name__


def detached_data_file(path: Path, fmt: str) -> Path | None:
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


def require_plausible_geometry(size, spacing, path: Path) -> None:
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


def check_finite(data: np.ndarray, path: Path, what: str, fix: str) -> None:
    """Raise :class:`~workbench.errors.NonFiniteError` naming the first NaN or infinite voxel of ``data`` (and how
    many), then ``fix``."""
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
