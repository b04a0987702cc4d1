"""NIfTI files: their data layout, and the guards against three behaviours of ITK's NIfTI library (niftilib).

* It pads a **truncated** ``.nii``/``.nii.gz`` with zeros and reports
  success.  Before reading, :func:`scan_nifti` checks the data length in the
  file against the header (``vox_offset + voxels × bitpix/8``); a gzip stream
  is decompressed once to check that it is complete and its CRC is right.
* It **replaces every NaN and infinity by 0** (``nifti_read_buffer``),
  silently.  The same pass over the data records the non-finite values and
  their positions; :func:`restore_nonfinite` puts them back into the array,
  so NIfTI reports them like the other formats do.
* When asked for ``scan.nii.gz``, it takes the header from ``scan.nii.gz``
  but the **voxels from** ``scan.nii`` if that file exists beside it
  (``nifti_findimgname``).  :func:`nifti_read_name` reads such files through
  a private symbolic link, so the voxels come from the file asked for.

Its writer reports a short write only on its standard error;
:func:`check_nifti_written` checks the written file instead.
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

from workbench.errors import UnreadableFileError
from workbench.io.atomic import split_suffix
from workbench.io.formats import sitk_error_line

__all__ = ["NiftiLayout", "NonFinite", "scan_nifti", "restore_nonfinite", "nifti_read_name", "check_nifti_written"]


@dataclass(frozen=True)
class NiftiLayout:
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
class NonFinite:
    """Non-finite numbers found in a file's data, by flat index in file order."""

    index: np.ndarray
    value: np.ndarray


def _nifti_layout(header: bytes, path: Path) -> NiftiLayout:
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
    return NiftiLayout(
        dims=tuple(int(d) for d in dims[1 : ndim + 1]),
        datatype=int(datatype),
        bitpix=int(bitpix),
        vox_offset=int(vox_offset),
        endian=endian,
        scl_slope=float(slope),
        scl_inter=float(inter),
    )


def scan_nifti(path: Path) -> tuple[NiftiLayout, NonFinite]:
    """Check a NIfTI file is complete, and find its NaN/inf values.

    Both checks are needed because niftilib (inside ITK) pads a truncated
    file with zeros and replaces every NaN and infinity by 0 while reading,
    without reporting either.  A gzip stream is decompressed in full, which
    also checks its CRC.
    """
    none = NonFinite(np.zeros(0, np.int64), np.zeros(0))
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
) -> tuple[int, NonFinite]:
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
    found = NonFinite(
        np.concatenate(indices) if indices else np.zeros(0, np.int64),
        np.concatenate(values) if values else np.zeros(0),
    )
    return n_read, found


@contextlib.contextmanager
def nifti_read_name(path: Path) -> Iterator[Path]:
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


def restore_nonfinite(data: np.ndarray, layout: NiftiLayout, found: NonFinite) -> np.ndarray:
    """``data`` as read by ITK (``[z, y, x]`` or ``[z, y, x, c]``) with the NaN and infinite values that niftilib
    replaced by 0 put back (in place), scaled as ITK scales the others."""
    if found.index.size == 0 or np.iscomplexobj(data):
        return data
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


def check_nifti_written(path: Path) -> None:
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
        raise OSError(f"the written header is incomplete ({sitk_error_line(e)})") from e
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
