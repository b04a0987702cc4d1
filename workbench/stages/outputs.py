"""What a stage's ``run`` returns: one object per output file, written by
:func:`~workbench.stages.outputs.write_output` into the staging folder of :func:`workbench.stages.mechanism.execute`
(re-exported there).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

from workbench.io.jsonio import write_json

__all__ = [
    "Image",
    "Labels",
    "Field",
    "VectorImage",
    "Json",
    "Text",
    "WeightMap",
    "TetMeshFile",
    "MeshFile",
    "CopyFile",
    "write_output",
]


@dataclass(frozen=True)
class Image:
    """An intensity volume (float32 NIfTI/MHA/NRRD with its geometry)."""

    volume: object


@dataclass(frozen=True)
class Labels:
    """A label map (unsigned integers)."""

    volume: object


@dataclass(frozen=True)
class Field:
    """A displacement field (ITK vector image, mm), usable by ``sitk.DisplacementFieldTransform``."""

    volume: object


@dataclass(frozen=True)
class VectorImage:
    """A multi-component image (any number of components)."""

    volume: object


@dataclass(frozen=True)
class Json:
    """A JSON document (keys sorted, floats round-trip exactly)."""

    doc: object


@dataclass(frozen=True)
class Text:
    """A UTF-8 text file."""

    text: str


@dataclass(frozen=True)
class WeightMap:
    """A voxel weight map (``.json`` + two vector images, :mod:`workbench.io.weights`)."""

    weights: object
    geometry: object
    meta: dict = field(default_factory=dict)


@dataclass(frozen=True)
class TetMeshFile:
    """A tetrahedral mesh (VTU) with point arrays."""

    mesh: object
    point_data: dict = field(default_factory=dict)


@dataclass(frozen=True)
class MeshFile:
    """A triangle mesh in world mm (PLY, VTP — with named per-vertex arrays —, OBJ or STL by the suffix)."""

    mesh: object
    point_data: dict = field(default_factory=dict)


@dataclass(frozen=True)
class CopyFile:
    """A file copied as it is (e.g. a kept mesh, byte for byte)."""

    source: Path


def write_output(obj, path: Path) -> list[Path]:
    """Write one output into the staging folder; returns every file written (companions included)."""
    from workbench.io import volumes

    if isinstance(obj, Image):
        volumes.write_volume(obj.volume, path)
    elif isinstance(obj, Labels):
        volumes.write_labels(obj.volume, path)
    elif isinstance(obj, Field):
        volumes.write_displacement(obj.volume, path)
    elif isinstance(obj, VectorImage):
        volumes.write_vector_image(obj.volume, path)
    elif isinstance(obj, Json):
        write_json(obj.doc, path)
    elif isinstance(obj, Text):
        path.write_text(obj.text if obj.text.endswith("\n") else obj.text + "\n", encoding="utf-8")
    elif isinstance(obj, WeightMap):
        from workbench.io.weights import write_voxel_weights

        write_voxel_weights(obj.weights, obj.geometry, path, **obj.meta)
        return [path, path.with_name(f"{path.stem}_index.mha"), path.with_name(f"{path.stem}_value.mha")]
    elif isinstance(obj, CopyFile):
        shutil.copy2(obj.source, path)
    elif isinstance(obj, TetMeshFile):
        from workbench.io.tetmeshes import write_tetmesh

        write_tetmesh(obj.mesh, path, point_data=obj.point_data)
    elif isinstance(obj, MeshFile):
        from workbench.io.meshes import write_mesh

        write_mesh(obj.mesh, path, point_data=obj.point_data or None)
    else:
        raise TypeError(
            f"{path.name}: a stage output must be Image, Labels, Field, VectorImage, Json, Text, "
            f"WeightMap, TetMeshFile, MeshFile or CopyFile, got {type(obj).__name__}"
        )
    return [path]
