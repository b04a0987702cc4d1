"""Mesh files (workbench.io.meshes): PLY, OBJ, STL, VTP."""

from __future__ import annotations

import os

import numpy as np
import pytest

from deformation.meshes.mesh import SurfaceMesh, connected_components
from workbench.errors import MissingFileError, OutputExistsError, UnknownFormatError, UnreadableFileError
from workbench.io.meshes import read_mesh, read_mesh_point_data, write_mesh


def _mesh() -> SurfaceMesh:
    """Two tetrahedra with awkward float64 coordinates and one unused vertex."""
    rng = np.random.default_rng(7)
    vertices = rng.normal(0.0, 37.123456789, size=(9, 3))
    vertices[0] = [0.1 + 0.2, 1e-17, -123456.789012345]
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    # Vertex 8 is unused; the second tetrahedron's triangles come first.
    return SurfaceMesh(vertices, np.vstack([faces + 4, faces]))


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".vtp"])
def test_exact_round_trip(tmp_path, suffix):
    mesh = _mesh()
    before = mesh.vertices.copy()
    path = write_mesh(mesh, tmp_path / f"bones{suffix}")
    back = read_mesh(path)
    assert back.vertices.dtype == np.float64 and back.triangles.dtype == np.int64
    np.testing.assert_array_equal(back.vertices, mesh.vertices)  # bit-exact, order and unused vertex kept
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    np.testing.assert_array_equal(mesh.vertices, before)
    assert os.listdir(tmp_path) == [f"bones{suffix}"]


def test_stl_merges_corners_and_rounds_to_float32(tmp_path):
    mesh = _mesh()
    path = write_mesh(mesh, tmp_path / "bones.stl")
    assert path.stat().st_size == 84 + 50 * 8  # binary STL: 8 facets, no shared vertices
    back = read_mesh(path)
    used = np.unique(mesh.triangles)
    assert back.n_vertices == used.size == 8  # corners merged, unused vertex gone
    expected = mesh.vertices[used].astype(np.float32).astype(np.float64)
    # Equal as sets (STL keeps no vertex order) after float32 rounding.
    assert sorted(map(tuple, back.vertices)) == sorted(map(tuple, expected))
    # Same triangles, in terms of coordinates.
    np.testing.assert_array_equal(
        back.vertices[back.triangles], mesh.vertices[mesh.triangles].astype(np.float32).astype(np.float64)
    )
    assert connected_components(back)[0] == 2


def test_obj_with_polygons_texture_references_and_negative_indices(tmp_path):
    (tmp_path / "quad.obj").write_text(
        "# a unit square as one quad, then a triangle by negative indices\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
        "f 1/1/1 2/1/1 3/1/1 4/1/1\n"
        "v 0 0 2\n"
        "f -1 -5 -4\n"
    )
    m = read_mesh(tmp_path / "quad.obj")
    assert m.n_vertices == 5
    np.testing.assert_array_equal(m.triangles, [[0, 1, 2], [0, 2, 3], [4, 0, 1]])


def test_connected_components_after_reading(tmp_path):
    write_mesh(_mesh(), tmp_path / "m.vtp")
    n, labels = connected_components(read_mesh(tmp_path / "m.vtp"))
    assert n == 2
    np.testing.assert_array_equal(labels, [1, 1, 1, 1, 0, 0, 0, 0])


def test_missing_and_unknown(tmp_path):
    with pytest.raises(MissingFileError) as err:
        read_mesh(tmp_path / "nope.ply")
    assert "nope.ply" in str(err.value)
    (tmp_path / "mesh.off").write_text("OFF\n0 0 0\n")
    with pytest.raises(UnknownFormatError) as err:
        read_mesh(tmp_path / "mesh.off")
    assert all(s in str(err.value) for s in (".ply", ".obj", ".stl", ".vtp"))
    with pytest.raises(UnknownFormatError):
        write_mesh(_mesh(), tmp_path / "mesh.gltf")
    assert os.listdir(tmp_path) == ["mesh.off"]


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".vtp"])
def test_truncated_files(tmp_path, suffix):
    write_mesh(_mesh(), tmp_path / f"full{suffix}")
    data = (tmp_path / f"full{suffix}").read_bytes()
    (tmp_path / f"cut{suffix}").write_bytes(data[: len(data) - 30])
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(UnreadableFileError) as err:
        read_mesh(tmp_path / f"cut{suffix}")
    assert f"cut{suffix}" in str(err.value)
    assert sorted(os.listdir(tmp_path)) == before


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".vtp"])
def test_garbage_and_empty_files(tmp_path, suffix):
    rng = np.random.default_rng(3)
    (tmp_path / f"junk{suffix}").write_bytes(rng.integers(0, 256, 3000, dtype=np.uint8).tobytes())
    (tmp_path / f"empty{suffix}").write_bytes(b"")
    for name in (f"junk{suffix}", f"empty{suffix}"):
        with pytest.raises(UnreadableFileError) as err:
            read_mesh(tmp_path / name)
        assert name in str(err.value)


def test_mesh_without_triangles(tmp_path):
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(UnreadableFileError, match="no faces"):
        read_mesh(tmp_path / "points.obj")
    with pytest.raises(ValueError):
        write_mesh(SurfaceMesh(np.zeros((3, 3)), np.zeros((0, 3), int)), tmp_path / "empty.ply")
    assert os.listdir(tmp_path) == ["points.obj"]


def test_overwrite_refused(tmp_path):
    path = write_mesh(_mesh(), tmp_path / "m.ply")
    before = path.read_bytes()
    with pytest.raises(OutputExistsError):
        write_mesh(_mesh(), path)
    assert path.read_bytes() == before
    write_mesh(SurfaceMesh(_mesh().vertices * 2, _mesh().triangles), path, overwrite=True)
    np.testing.assert_array_equal(read_mesh(path).vertices, _mesh().vertices * 2)
    assert os.listdir(tmp_path) == ["m.ply"]


def test_failing_write_leaves_no_temporary_file(tmp_path, monkeypatch):
    import workbench.io.meshes as meshio

    def half_write_then_fail(mesh, tmp, point_data=None):
        tmp.write_bytes(b"<?xml partial")
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(meshio, "_write_vtp", half_write_then_fail)
    with pytest.raises(OSError, match="disk full"):
        write_mesh(_mesh(), tmp_path / "m.vtp")
    assert os.listdir(tmp_path) == []


def test_vtp_point_data_round_trip(tmp_path):
    """Per-vertex arrays (a surface's skinning weights) travel with a .vtp mesh, exactly (float64)."""
    m = _mesh()
    rng = np.random.default_rng(2)
    data = {"weight_radius": rng.random(m.n_vertices), "normal": rng.normal(size=(m.n_vertices, 3))}
    p = write_mesh(m, tmp_path / "s.vtp", point_data=data)
    back = read_mesh_point_data(p)
    assert set(back) == set(data)
    for k, v in data.items():
        np.testing.assert_array_equal(back[k], v)
    np.testing.assert_array_equal(read_mesh(p).vertices, m.vertices)
    with pytest.raises(ValueError, match="one value"):
        write_mesh(m, tmp_path / "bad.vtp", point_data={"w": np.zeros(m.n_vertices + 1)})
    assert not (tmp_path / "bad.vtp").exists()
    with pytest.raises(ValueError, match=".vtp meshes only"):
        write_mesh(m, tmp_path / "s.ply", point_data=data)
    with pytest.raises(UnknownFormatError):
        read_mesh_point_data(tmp_path / "s.ply")
