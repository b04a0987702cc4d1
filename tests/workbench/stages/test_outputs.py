"""What a stage's ``run`` returns, written by write_output (workbench.stages.outputs): each kind of output reads
back as it was, with its grid geometry, and only the files write_output names are left in the folder."""

from __future__ import annotations

import math

import numpy as np
import pytest

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.mesh import SurfaceMesh
from deformation.meshes.tetmesh import TetMesh
from deformation.models.skinning import SkinningWeights
from workbench.errors import OutputExistsError
from workbench.io.jsonio import read_json
from workbench.io.meshes import read_mesh, read_mesh_point_data
from workbench.io.tetmeshes import read_tetmesh
from workbench.io.volumes import read_displacement, read_labels, read_vector_image, read_volume
from workbench.io.weights import read_voxel_weights
from workbench.stages.outputs import (
    CopyFile,
    Field,
    Image,
    Json,
    Labels,
    MeshFile,
    TetMeshFile,
    Text,
    VectorImage,
    WeightMap,
    write_output,
)

_C, _S = math.cos(math.radians(30)), math.sin(math.radians(30))
# anisotropic spacing, an origin off the grid and a direction that is a rotation of 30° about z
GRID = GridGeometry(
    size=(4, 3, 2),
    spacing=(0.5, 1.25, 2.5),
    origin=(-10.1, 3.3, 7.7),
    direction=(_C, -_S, 0.0, _S, _C, 0.0, 0.0, 0.0, 1.0),
)
RNG = np.random.default_rng(0)


def _same_grid_exactly(a: GridGeometry, b: GridGeometry):
    assert a.size == b.size
    assert a.spacing == b.spacing and a.origin == b.origin
    np.testing.assert_array_equal(a.direction, b.direction)


def _written(tmp_path, obj, name):
    path = tmp_path / name
    files = write_output(obj, path)
    # every file written is returned and nothing else (no temporary file) is left in the folder
    assert sorted(files) == sorted(tmp_path.iterdir())
    return path, files


@pytest.mark.parametrize("suffix", [".mha", ".nrrd"])
def test_an_image_reads_back_with_its_voxels_and_geometry(tmp_path, suffix):
    v = Volume(RNG.normal(size=GRID.array_shape).astype(np.float32), GRID)
    path, files = _written(tmp_path, Image(v), "scan" + suffix)
    assert files == [path]
    back = read_volume(path)
    np.testing.assert_array_equal(back.data, v.data)
    assert back.data.dtype == np.float32
    if suffix == ".mha":  # decimal geometry with 17 digits: exact
        _same_grid_exactly(back.geometry, GRID)
    else:  # NRRD: about two float64 ulps (workbench.io.formats)
        assert back.geometry.is_close(GRID, rtol=1e-15, atol_mm=1e-14)


def test_an_image_in_nifti_keeps_its_geometry_to_float32(tmp_path):
    v = Volume(RNG.normal(size=GRID.array_shape).astype(np.float32), GRID)
    path, _ = _written(tmp_path, Image(v), "scan.nii.gz")
    back = read_volume(path)
    np.testing.assert_array_equal(back.data, v.data)
    np.testing.assert_allclose(back.geometry.spacing, GRID.spacing, rtol=2.0**-24, atol=0)
    np.testing.assert_allclose(back.geometry.origin, np.float32(GRID.origin), rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.geometry.direction, GRID.direction, rtol=0, atol=1e-6)


def test_labels_read_back_as_integers_on_the_grid(tmp_path):
    labels = Volume(RNG.integers(0, 4, size=GRID.array_shape).astype(np.uint8), GRID)
    path, _ = _written(tmp_path, Labels(labels), "labels.nii.gz")
    back = read_labels(path, reference=GRID)  # refused unless on the grid (to NIfTI's float32)
    np.testing.assert_array_equal(back.data, labels.data)
    assert back.data.dtype.kind in "iu"
    assert back.geometry.is_close(GRID)


def test_a_field_reads_back_as_a_displacement_field(tmp_path):
    f = Volume(RNG.normal(size=GRID.array_shape + (3,)), GRID)
    path, _ = _written(tmp_path, Field(f), "correspondence.mha")
    back = read_displacement(path)
    assert back.data.shape == GRID.array_shape + (3,)
    np.testing.assert_array_equal(back.data, f.data)
    _same_grid_exactly(back.geometry, GRID)


def test_a_vector_image_keeps_its_components(tmp_path):
    v = Volume(RNG.normal(size=GRID.array_shape + (5,)).astype(np.float32), GRID)
    path, _ = _written(tmp_path, VectorImage(v), "features.mha")
    back = read_vector_image(path, components=5)
    np.testing.assert_array_equal(back.data, v.data)
    _same_grid_exactly(back.geometry, GRID)


def test_json_reads_back_exactly(tmp_path):
    doc = {"b": [0.1 + 0.2, None, True], "a": {"n": 3, "x": 1e-17}}
    path, _ = _written(tmp_path, Json(doc), "log.json")
    assert read_json(path) == doc
    text = path.read_text(encoding="utf-8")
    assert text.index('"a"') < text.index('"b"') and text.endswith("\n")  # keys sorted, final newline


@pytest.mark.parametrize("text", ["one line", "two\nlines\n", ""])
def test_text_is_utf8_with_one_final_newline(tmp_path, text):
    path, _ = _written(tmp_path, Text(text + " é"), "report.txt")
    assert path.read_bytes() == (text + " é\n").encode("utf-8")


def test_a_weight_map_writes_its_json_and_two_images(tmp_path):
    n = GRID.n_voxels
    strongest = RNG.uniform(0.5, 1.0, size=n)
    value = np.stack([strongest, 1.0 - strongest], axis=1)
    index = np.stack([RNG.integers(0, 3, size=n), np.full(n, 2)], axis=1)
    w = SkinningWeights(("femur", "tibia", "patella"), index, value)
    path, files = _written(tmp_path, WeightMap(w, GRID, {"method": "harmonic"}), "weights.json")
    assert files == [path, tmp_path / "weights_index.mha", tmp_path / "weights_value.mha"]
    back, grid, manifest = read_voxel_weights(path)
    assert back.bones == w.bones and manifest["method"] == "harmonic"
    np.testing.assert_array_equal(back.index, index)
    np.testing.assert_array_equal(back.value, value.astype(np.float32))
    _same_grid_exactly(grid, GRID)


def test_a_tet_mesh_reads_back_with_its_point_data(tmp_path):
    mesh = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.5]]), [[0, 1, 2, 3], [1, 2, 3, 4]])
    weight = np.array([1.0, 0.75, 0.5, 0.25, 0.0])
    path, _ = _written(tmp_path, TetMeshFile(mesh, {"weight_femur": weight}), "mesh.vtu")
    back, data = read_tetmesh(path)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_array_equal(data["weight_femur"], weight)


@pytest.mark.parametrize("suffix", [".ply", ".vtp"])
def test_a_surface_mesh_reads_back_exactly(tmp_path, suffix):
    mesh = SurfaceMesh(np.array([[0.1, 0.2, 0.3], [1.0, 0.0, 0.0], [0.0, 1.0 / 3.0, 0.0]]), [[0, 1, 2]])
    point_data = {"error_mm": np.array([0.5, 1.5, 2.5])} if suffix == ".vtp" else {}
    path, _ = _written(tmp_path, MeshFile(mesh, point_data), "bone" + suffix)
    back = read_mesh(path)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    if point_data:
        np.testing.assert_array_equal(read_mesh_point_data(path)["error_mm"], point_data["error_mm"])


def test_a_copied_file_is_byte_for_byte(tmp_path):
    src = tmp_path / "src" / "kept.ply"
    src.parent.mkdir()
    src.write_bytes(bytes(range(256)))
    out = tmp_path / "out"
    out.mkdir()
    path, _ = _written(out, CopyFile(src), "kept.ply")
    assert path.read_bytes() == src.read_bytes()


def test_the_volume_writers_refuse_to_replace_a_file_and_keep_it(tmp_path):
    path = tmp_path / "scan.mha"
    path.write_bytes(b"old")
    with pytest.raises(OutputExistsError):
        write_output(Image(Volume(np.zeros(GRID.array_shape, np.float32), GRID)), path)
    assert path.read_bytes() == b"old" and list(tmp_path.iterdir()) == [path]


def test_anything_else_is_refused_naming_the_kinds(tmp_path):
    with pytest.raises(TypeError, match=r"^x\.npy: a stage output must be Image, Labels, .* or CopyFile, got ndarray$"):
        write_output(np.zeros(3), tmp_path / "x.npy")
    assert list(tmp_path.iterdir()) == []
