"""DICOM series: one folder, one series, read with ``SimpleITK.ImageSeriesReader`` (GDCM).

GDCM orders the slices by their position along the slice normal (Image
Position Patient projected on the normal from Image Orientation Patient), not
by file name or instance number; the slice spacing is the distance between
slice positions.  Series whose slices share a position or are not equally
spaced are refused (:class:`~workbench.errors.UnreadableFileError`); a folder with several
series needs the ``series_uid`` of one (:class:`~workbench.errors.AmbiguousSeriesError`,
:class:`~workbench.errors.SeriesNotFoundError`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from deformation.geometry import GridGeometry
from workbench.errors import AmbiguousSeriesError, SeriesNotFoundError, UnreadableFileError
from workbench.io.formats import SUPPORTED_SUFFIXES, require_plausible_geometry, sitk_error_line

__all__ = ["read_dicom_series", "dicom_geometry"]


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
            f"{folder}: could not scan the folder for DICOM files ({sitk_error_line(e)}).", folder
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


def read_dicom_series(folder: Path, series_uid: str | None) -> sitk.Image:
    files = _dicom_series_files(folder, series_uid)
    try:
        _check_dicom_spacing(folder, files)
        reader = sitk.ImageSeriesReader()
        reader.SetFileNames(files)
        return reader.Execute()
    except RuntimeError as e:
        raise UnreadableFileError(
            f"{folder}: SimpleITK could not read the DICOM series ({sitk_error_line(e)}). "
            "A slice is probably truncated or corrupt; remove or replace it.",
            folder,
        ) from e


def dicom_geometry(folder: Path, series_uid: str | None) -> GridGeometry:
    files = _dicom_series_files(folder, series_uid)
    try:
        first = _dicom_file_info(files[0])
        pos = _check_dicom_spacing(folder, files)
    except RuntimeError as e:
        raise UnreadableFileError(f"{folder}: unreadable DICOM header ({sitk_error_line(e)}).", folder) from e
    nx, ny = first.GetSize()[:2]
    spacing = list(first.GetSpacing())
    if pos is not None:
        spacing[2] = abs(pos[-1] - pos[0]) / (len(pos) - 1)
    require_plausible_geometry((nx, ny, len(files)), spacing, folder)
    return GridGeometry(
        size=(nx, ny, len(files)), spacing=spacing, origin=first.GetOrigin(), direction=first.GetDirection()
    )
