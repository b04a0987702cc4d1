"""Reading and writing voxel skinning weights (open formats, no pickle).

A weight map is three files side by side::

    weights.json          {"format": "avw-weights", "version": 1, "bones": [...],
                           "max_influences": 4, "index": "weights_index.mha",
                           "value": "weights_value.mha", "method": "harmonic", ...}
    weights_index.mha     uint8 (uint16 beyond 256 bones) vector image, K components: the bone (position in
                          "bones") of each influence, strongest first
    weights_value.mha     float32 vector image, K components: the weights, summing to one

Both images carry the template's grid geometry and open in 3D Slicer,
ITK-SNAP and ParaView as vector images (component 0 of the value image is
the strongest bone's weight).  The JSON is written last, so a folder without
it holds no weight map; readers check that the two images share one grid
and that the weights are a partition of unity.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deformation.geometry import GridGeometry, Volume
from deformation.models.skinning import SkinningWeights
from workbench.errors import InputFileError
from workbench.io.jsonio import read_json, write_json
from workbench.io.volumes import read_image_geometry, read_vector_image, write_vector_image

__all__ = ["WEIGHTS_FORMAT", "write_voxel_weights", "read_voxel_weights", "read_voxel_weights_geometry"]

WEIGHTS_FORMAT = "avw-weights"


def write_voxel_weights(
    weights: SkinningWeights, geometry: GridGeometry, path: str | os.PathLike, *, overwrite: bool = False, **meta
) -> Path:
    """Write per-voxel weights on ``geometry`` to ``path`` (the ``.json``) and its two images beside it.

    Extra keyword arguments (method, parameters, timings) are recorded in the JSON.
    """
    path = Path(path)
    if path.suffix != ".json":
        raise ValueError(f"{path}: the weight map's manifest must be a .json file")
    if weights.n_points != geometry.n_voxels:
        raise ValueError(f"{weights.n_points} weighted points but the grid has {geometry.n_voxels} voxels")
    stem = path.stem
    shape = geometry.array_shape + (weights.max_influences,)
    idx_name, val_name = f"{stem}_index.mha", f"{stem}_value.mha"
    write_vector_image(
        Volume(weights.index.astype(np.uint8 if weights.n_bones <= 256 else np.uint16).reshape(shape), geometry),
        path.parent / idx_name,
        overwrite=overwrite,
    )
    write_vector_image(Volume(weights.value.reshape(shape), geometry), path.parent / val_name, overwrite=overwrite)
    doc = {
        "format": WEIGHTS_FORMAT,
        "version": 1,
        "bones": list(weights.bones),
        "max_influences": weights.max_influences,
        "index": idx_name,
        "value": val_name,
        "layout": "per voxel, strongest influence first; unused slots have weight 0",
        "geometry": geometry.to_dict(),
    }
    doc.update(meta)
    return write_json(doc, path, overwrite=overwrite)


def _manifest(path: Path) -> dict:
    doc = read_json(path)
    if doc.get("format") != WEIGHTS_FORMAT:
        raise InputFileError(
            f"{path}: not a weight map ('format' is {doc.get('format')!r}, expected {WEIGHTS_FORMAT!r}).", path
        )
    for key in ("bones", "index", "value"):
        if key not in doc:
            raise InputFileError(f"{path}: the weight map lacks the key {key!r}.", path)
    return doc


def read_voxel_weights_geometry(path: str | os.PathLike) -> GridGeometry:
    """The grid of a weight map written by :func:`write_voxel_weights`, from its index image's header only (no
    voxel is read): to refuse a map on the wrong grid before reading it."""
    path = Path(path)
    return read_image_geometry(path.parent / _manifest(path)["index"])


def read_voxel_weights(path: str | os.PathLike) -> tuple[SkinningWeights, GridGeometry, dict]:
    """Read a weight map written by :func:`write_voxel_weights`: ``(weights, geometry, manifest)``."""
    path = Path(path)
    doc = _manifest(path)
    idx = read_vector_image(path.parent / doc["index"])
    val = read_vector_image(path.parent / doc["value"], components=idx.n_components)
    idx.geometry.check_same(
        val.geometry,
        names=(doc["index"], doc["value"]),
        remedy="write the weight map again (workbench weights --force)",
    )
    if idx.data.dtype.kind not in "iu":
        raise InputFileError(
            f"{path.parent / doc['index']}: bone indices must be integers, got {idx.data.dtype}.",
            path.parent / doc["index"],
        )
    k = idx.n_components
    try:
        w = SkinningWeights(doc["bones"], idx.data.reshape(-1, k), val.data.reshape(-1, k).astype(np.float64))
    except ValueError as e:
        raise InputFileError(f"{path}: {e}", path) from e
    return w, idx.geometry, doc
