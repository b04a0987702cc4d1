"""Exceptions raised by the workbench's file input and output.

Every input error carries the offending path in ``.path`` and a message that
names the file and says how to fix the problem.  The classes also derive from
the matching built-in exception (``ValueError``, ``FileNotFoundError``,
``FileExistsError``) so that callers who do not know this module can still
catch them.

Hierarchy::

    WorkbenchError(Exception)
    ├── InputFileError(WorkbenchError, ValueError)          .path
    │   ├── MissingFileError(InputFileError, FileNotFoundError)
    │   ├── UnknownFormatError
    │   ├── UnreadableFileError      truncated, corrupt or empty data
    │   ├── DimensionError           wrong number of dimensions or components
    │   ├── PixelTypeError           e.g. non-integer values in a label map
    │   ├── NonFiniteError           NaN / inf voxels
    │   ├── AmbiguousSeriesError     DICOM folder with several series
    │   └── SeriesNotFoundError      ``series_uid=`` not in the folder
    └── OutputExistsError(WorkbenchError, FileExistsError)  .path

``GeometryMismatchError`` (two grids that must agree do not) is defined in
:mod:`deformation.geometry` and re-exported here.
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
    "AmbiguousSeriesError",
    "SeriesNotFoundError",
    "OutputExistsError",
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


class OutputFolderError(WorkbenchError, OSError):
    """An output's folder is missing or not writable: said before any work (no output is half-written)."""
