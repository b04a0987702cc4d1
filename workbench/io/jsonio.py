"""JSON files for skeletons, poses, markers and manifests.

* :func:`write_json` writes keys sorted, two-space indented, UTF-8 with a
  final newline, atomically.  Floats are written with Python's shortest
  round-trip representation (``repr``), so ``read_json(write_json(x)) == x``
  exactly — ``0.1 + 0.2`` comes back as ``0.30000000000000004`` and
  ``1e-17`` as ``1e-17``.  NumPy arrays become (nested) lists and NumPy
  scalars Python numbers (a float32 is widened to the float64 of the same
  value).  Tuples become lists; ``pathlib`` paths become strings.  NaN and
  infinity are refused (JSON has no such numbers), as are keys that are not
  strings (JSON would turn them into strings silently).
* :func:`read_json` refuses syntax errors (naming the line and column),
  ``NaN``/``Infinity`` literals, duplicate keys and a top level that is not
  an object.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from workbench.errors import MissingFileError, UnreadableFileError
from workbench.io.atomic import write_text_atomic

__all__ = ["read_json", "write_json", "to_jsonable"]


def to_jsonable(obj: Any, *, where: str = "$") -> Any:
    """Convert ``obj`` into plain JSON types, refusing what JSON cannot hold exactly.

    Parameters
    ----------
    obj : Any
        Nested dicts (string keys), lists, tuples, strings, booleans, None,
        ints, finite floats, NumPy arrays and scalars, paths.
    where : str, optional
        Location of ``obj`` used in error messages (JSONPath-like).

    Returns
    -------
    Any
        A structure of dict, list, str, int, float, bool and None.

    Raises
    ------
    ValueError
        A NaN or infinite number, naming where it is.
    TypeError
        A key that is not a string, or an object of another type.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist(), where=where)
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item(), where=where)
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise ValueError(
                f"{where} is {obj!r}; JSON cannot store NaN or infinity. Replace it (e.g. by "
                "None for a missing value) before writing."
            )
        return float(obj)
    if isinstance(obj, dict):
        out = {}
        for key, value in obj.items():
            if not isinstance(key, str):
                raise TypeError(
                    f"{where} has the key {key!r} of type {type(key).__name__}; JSON keys are "
                    "strings. Convert the keys with str() first."
                )
            out[key] = to_jsonable(value, where=f"{where}.{key}")
        return out
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v, where=f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, PurePath):
        return obj.as_posix()
    raise TypeError(
        f"{where} is a {type(obj).__name__}, which JSON cannot store. Convert it to a dict, "
        "list, number or string first."
    )


def write_json(obj: Any, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write ``obj`` as JSON, atomically, with sorted keys and exact floats.

    Parameters
    ----------
    obj : Any
        Data (see :func:`to_jsonable` for what is accepted); not modified.
    path : str or os.PathLike
        Output file.
    overwrite : bool, optional
        Replace an existing file; otherwise :class:`~workbench.errors.OutputExistsError`.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    ValueError
        NaN or infinity somewhere in ``obj`` (the message says where);
        nothing is written.
    TypeError
        A non-string key or an unsupported object; nothing is written.
    """
    p = Path(path)
    try:
        plain = to_jsonable(obj)
    except (ValueError, TypeError) as e:
        raise type(e)(f"{p}: not written: {e}") from e
    text = json.dumps(plain, indent=2, sort_keys=True, ensure_ascii=False, allow_nan=False) + "\n"
    return write_text_atomic(p, text, overwrite=overwrite)


def _refuse_constant(name: str):
    raise ValueError(f"the non-standard literal {name} (NaN/infinity are not JSON numbers)")


def read_json(path: str | os.PathLike, *, expected: str = "an object ({...})") -> dict:
    """Read a JSON file whose top level is an object.

    Parameters
    ----------
    path : str or os.PathLike
        The file (UTF-8).
    expected : str
        What the file should hold, for the message when its top level is not an object (e.g. a manifest's
        outline and where it is documented).

    Returns
    -------
    dict
        The parsed object; floats are exactly those written by :func:`write_json`.

    Raises
    ------
    MissingFileError
        No such file.
    UnreadableFileError
        Not UTF-8, a syntax error (the message gives line and column),
        ``NaN``/``Infinity``, a duplicate key, or a top level that is not an
        object.
    """
    p = Path(path)
    if not p.is_file():
        if p.exists():
            raise UnreadableFileError(f"{p}: not a regular file. Give the path of a .json file.", p)
        where = "" if p.is_absolute() else f" (relative to the working folder {Path.cwd()})"
        raise MissingFileError(f"{p}: no such file{where}. Check the path and the file name.", p)
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise UnreadableFileError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start}). Save it as UTF-8.", p) from e

    def no_duplicates(pairs):
        out = {}
        for key, value in pairs:
            if key in out:
                raise ValueError(f"the key {key!r} appears twice in one object")
            out[key] = value
        return out

    try:
        data = json.loads(text, object_pairs_hook=no_duplicates, parse_constant=_refuse_constant)
    except json.JSONDecodeError as e:
        raise UnreadableFileError(
            f"{p}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}. Fix the file there "
            "(a missing comma or quote, or a trailing comma, are the usual causes).",
            p,
        ) from e
    except ValueError as e:
        raise UnreadableFileError(f"{p}: {e}. Fix the file.", p) from e
    if not isinstance(data, dict):
        raise UnreadableFileError(
            f"{p}: the top level is a JSON {type(data).__name__}, but {expected} is expected. "
            "Check that this is the right file.",
            p,
        )
    return data
