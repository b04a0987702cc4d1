"""Replacing an image's NaN and infinite voxels (``workbench clean-image``).

The workbench refuses images with such voxels; :func:`clean_image` writes a copy with the same geometry whose
non-finite voxels hold one value (by default the image's lowest finite value, i.e. background).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from workbench.errors import OutputExistsError
from workbench.io.atomic import check_output_folder
from workbench.io.volumes import image_format, read_volume, write_volume

__all__ = ["fill_nonfinite", "clean_image"]


def fill_nonfinite(volume, value: float | None = None):
    """``(cleaned volume, number of voxels replaced, the value they took)``: ``volume``'s NaN and infinite voxels
    replaced by ``value`` (default: the lowest finite value), same dtype and geometry."""
    data = np.asarray(volume.data)
    bad = ~np.isfinite(data)
    if bad.all() and value is None:
        raise ValueError("no finite voxel at all; give --value")
    fill = float(value) if value is not None else float(data[~bad].min())
    return type(volume)(np.where(bad, fill, data).astype(data.dtype), volume.geometry), int(bad.sum()), fill


def clean_image(image: str | os.PathLike, out: str | os.PathLike, *, value=None, overwrite: bool = False) -> dict:
    """Write a copy of ``image`` to ``out`` with its non-finite voxels replaced (:func:`fill_nonfinite`); the
    output is checked (not the input, a writable folder, a format that can be written, not there unless
    ``overwrite``) before the image is read.  Returns ``{"replaced", "voxels", "fill", "out"}``."""
    image, out = Path(image), Path(out)
    if out.resolve() == image.resolve():
        raise ValueError(f"--out {out} is the input: write the cleaned copy elsewhere (the input is kept)")
    if value is not None and not np.isfinite(value):
        raise ValueError(f"--value must be a finite number, got {value}")
    check_output_folder(out, "--out")
    image_format(out, for_writing=True)
    if out.exists() and not overwrite:
        raise OutputExistsError(out, f"{out} exists; pass --force to replace it.")
    v = read_volume(image, allow_nonfinite=True)
    try:
        clean, n, fill = fill_nonfinite(v, value)
    except ValueError as e:
        raise ValueError(f"{image}: {e}") from None
    write_volume(clean, out, overwrite=overwrite)
    return {"replaced": n, "voxels": int(np.asarray(v.data).size), "fill": fill, "out": out}
