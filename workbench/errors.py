"""Exceptions raised by the workbench's file input and output.

Every input error carries the offending path in ``.path`` and a message that names the file and says how to fix
the problem.  The classes also derive from the matching built-in exception (``ValueError``, ``FileNotFoundError``,
``FileExistsError``) so that callers who do not know this module can still catch them.

Hierarchy::

    WorkbenchError(Exception)
    ├── InputFileError(WorkbenchError, ValueError)          .path
    │   ├── MissingFileError(InputFileError, FileNotFoundError)
    │   ├── UnknownFormatError
    │   ├── UnreadableFileError      truncated, corrupt or empty data
    │   ├── DimensionError           wrong number of dimensions or components
    │   ├── PixelTypeError           e.g. non-integer values in a label map
    │   ├── NonFiniteError           NaN / inf voxels
    │   ├── ImplausibleGeometryError a voxel spacing or field of view no scan of a body has
    │   ├── AmbiguousSeriesError     DICOM folder with several series
    │   └── SeriesNotFoundError      ``series_uid=`` not in the folder
    ├── OutputExistsError(WorkbenchError, FileExistsError)  .path
    ├── OutputFolderError(WorkbenchError, OSError)           an output's folder is missing or read-only
    └── OutputWriteError(WorkbenchError, OSError)            .path: a write that did not complete

``GeometryMismatchError`` (two grids that must agree do not) is :mod:`deformation.geometry`'s, re-exported here.
"""

from __future__ import annotations

import os
from pathlib import Path

from deformation.geometry import GeometryMismatchError

__all__ = [
    "WorkbenchError",
    "InputFileError",
    "MissingFileError",
    "UnknownFormatError",
    "UnreadableFileError",
    "DimensionError",
    "PixelTypeError",
    "NonFiniteError",
    "ImplausibleGeometryError",
    "AmbiguousSeriesError",
    "SeriesNotFoundError",
    "OutputExistsError",
    "OutputFolderError",
    "OutputWriteError",
    "GeometryMismatchError",
]


class WorkbenchError(Exception):
    """Base class of the workbench's own errors."""


class InputFileError(WorkbenchError, ValueError):
    """An input file is missing, malformed or holds data of the wrong kind.

    Parameters
    ----------
    message : str
        Full message; it names the file and the fix.
    path : str or os.PathLike
        The offending file (or DICOM folder).
    """

    def __init__(self, message: str, path: str | os.PathLike):
        super().__init__(message)
        self.path = Path(path)

    def __reduce__(self):  # pickled whole (a task's error reaches the coordinator: workbench.scale)
        return type(self), (self.args[0], self.path)


class MissingFileError(InputFileError, FileNotFoundError):
    """The input file (or a data file its header refers to) does not exist."""

    def __init__(self, message: str, path: str | os.PathLike):
        # FileNotFoundError's OSError.__init__ would reinterpret the arguments.
        InputFileError.__init__(self, message, path)
        self.filename = str(path)

    def __str__(self) -> str:
        return self.args[0]


class UnknownFormatError(InputFileError):
    """The file's suffix is not one of the supported formats."""


class UnreadableFileError(InputFileError):
    """The file exists but cannot be decoded: truncated, corrupt or empty."""


class DimensionError(InputFileError):
    """Wrong number of dimensions (2-D where 3-D is needed) or of vector components."""


class PixelTypeError(InputFileError):
    """The voxel type does not suit the request (e.g. fractional values in a label map)."""


class NonFiniteError(InputFileError):
    """The data hold NaN or infinite values."""


class ImplausibleGeometryError(InputFileError):
    """The header's voxel spacing or field of view is one no scan of a body has (a unit slip)."""


class AmbiguousSeriesError(InputFileError):
    """A DICOM folder holds several series and none was chosen with ``series_uid=``."""


class SeriesNotFoundError(InputFileError):
    """The ``series_uid=`` given is not among the series of the DICOM folder."""


class OutputExistsError(WorkbenchError, FileExistsError):
    """The output file exists and overwriting was not asked for.

    Parameters
    ----------
    path : str or os.PathLike
        The existing file.
    """

    def __init__(self, path: str | os.PathLike, message: str | None = None):
        self.path = Path(path)
        msg = message or (
            f"{self.path}: output file already exists; refusing to overwrite it. "
            "Pass overwrite=True (on the command line: --force) to replace it, "
            "or choose another output path."
        )
        WorkbenchError.__init__(self, msg)
        self.filename = str(self.path)

    def __str__(self) -> str:
        return self.args[0]

    def __reduce__(self):
        return type(self), (self.path, self.args[0])


class OutputFolderError(WorkbenchError, OSError):
    """An output's folder is missing or not writable: said before any work (no output is half-written)."""


class OutputWriteError(WorkbenchError, OSError):
    """An output file could not be written completely (a full disk, a file-size limit, an I/O error).

    The message names the file (its final name, not a temporary one) and the
    reason; nothing is left under that name (:mod:`workbench.io.atomic`).

    Parameters
    ----------
    path : str or os.PathLike
        The output file as the user knows it.
    reason : str
        What failed, e.g. ``"[Errno 28] No space left on device"``.
    """

    def __init__(self, path: str | os.PathLike, reason: str):
        self.path = Path(path)
        self.reason = reason
        WorkbenchError.__init__(
            self,
            f"{self.path}: the file could not be written completely ({reason}); nothing "
            "was left under that name. Free disk space (or raise the file-size limit) and "
            "run the command again.",
        )
        self.filename = str(self.path)

    def __str__(self) -> str:
        return self.args[0]

    def __reduce__(self):
        return type(self), (self.path, self.reason)

    @classmethod
    def of(cls, path: str | os.PathLike, error: BaseException) -> OutputWriteError:
        """The error ``error`` (raised while writing) as a write error naming ``path``."""
        if isinstance(error, OutputWriteError):
            return cls(path, error.reason)
        if isinstance(error, OSError) and error.strerror:
            reason = f"[Errno {error.errno}] {error.strerror}"
        else:
            reason = str(error).split("\n", 1)[0]
            # drop a leading "<temporary path>: " the writer put before its reason
            head, sep, tail = reason.partition(": ")
            if sep and ("/" in head or head.startswith(".")):
                reason = tail
        return cls(path, reason)
