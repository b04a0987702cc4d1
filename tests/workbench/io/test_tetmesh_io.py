"""Tetrahedral mesh files (workbench.io.tetmeshes): VTK XML unstructured grids (.vtu)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from deformation.meshes.tetmesh import TetMesh
from workbench.errors import MissingFileError, OutputExistsError, UnknownFormatError, UnreadableFileError
from workbench.io.tetmeshes import read_tetmesh, weight_arrays, weights_from_point_data, write_tetmesh


def _mesh() -> TetMesh:
    """A sheared cube in 6 tets with awkward float64 coordinates."""
    rng = np.random.default_rng(3)
    bits = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=float)
    v = bits * 37.123456789 + rng.normal(0, 0.1, (8, 3)) + [0.1 + 0.2, -123456.789012345, 1e-17]
    paths = [(1, 2), (1, 4), (2, 1), (2, 4), (4, 1), (4, 2)]
    return TetMesh(v, [[0, a, a + b, 7] for a, b in paths]).oriented()


def test_exact_round_trip_with_point_data(tmp_path):
    mesh = _mesh()
    rng = np.random.default_rng(0)
    dense = rng.dirichlet(np.ones(3), size=mesh.n_vertices)
    pd = weight_arrays(["femur", "tibia", "patella"], dense)
    pd["bone_of_vertex"] = np.array([0, -1, 1, -1, 2, -1, -1, 0], dtype=np.int64)
    pd["displacement"] = rng.normal(size=(mesh.n_vertices, 3))
    path = write_tetmesh(mesh, tmp_path / "body.vtu", point_data=pd)
    assert os.listdir(tmp_path) == ["body.vtu"]  # atomic: no temporary file left
    back, pd_back = read_tetmesh(path)
    assert back.vertices.dtype == np.float64 and back.tets.dtype == np.int64
    np.testing.assert_array_equal(back.vertices, mesh.vertices)  # bit-exact
    np.testing.assert_array_equal(back.tets, mesh.tets)
    assert list(pd_back) == list(pd)  # file order kept
    for k in pd:
        assert pd_back[k].dtype == pd[k].dtype, k
        np.testing.assert_array_equal(pd_back[k], pd[k])
    bones, d = weights_from_point_data(pd_back)
    assert bones == ("femur", "tibia", "patella")
    np.testing.assert_array_equal(d, dense)
    # Without point data
    back2, pd2 = read_tetmesh(write_tetmesh(mesh, tmp_path / "plain.vtu"))
    assert pd2 == {} and np.array_equal(back2.tets, mesh.tets)


def test_file_is_a_vtk_unstructured_grid_of_tetrahedra(tmp_path):
    """What ParaView sees (VTK's own XML reader): an UnstructuredGrid of VTK_TETRA cells with one weight array
    per bone."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import VTK_TETRA
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

    mesh = _mesh()
    path = write_tetmesh(mesh, tmp_path / "body.vtu", point_data=weight_arrays(["a", "b"], np.full((8, 2), 0.5)))
    with open(path, "rb") as f:
        head = f.read(300)
    assert b'type="UnstructuredGrid"' in head and b"vtkZLibDataCompressor" in head
    reader = vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    assert grid.GetNumberOfCells() == mesh.n_tets
    assert {grid.GetCellType(c) for c in range(grid.GetNumberOfCells())} == {VTK_TETRA}
    pd = grid.GetPointData()
    assert {pd.GetArrayName(a) for a in range(pd.GetNumberOfArrays())} == {"weight_a", "weight_b"}
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetPoints().GetData()), mesh.vertices)


def test_refuses_to_overwrite(tmp_path):
    mesh = _mesh()
    path = write_tetmesh(mesh, tmp_path / "body.vtu")
    before = path.read_bytes()
    with pytest.raises(OutputExistsError):
        write_tetmesh(mesh.with_vertices(mesh.vertices + 1.0), path)
    assert path.read_bytes() == before
    write_tetmesh(mesh.with_vertices(mesh.vertices + 1.0), path, overwrite=True)
    np.testing.assert_array_equal(read_tetmesh(path)[0].vertices, mesh.vertices + 1.0)
    assert os.listdir(tmp_path) == ["body.vtu"]


def test_write_checks(tmp_path):
    mesh = _mesh()
    with pytest.raises(UnknownFormatError, match=r"\.vtu"):
        write_tetmesh(mesh, tmp_path / "body.vtk")
    with pytest.raises(ValueError, match="one per vertex"):
        write_tetmesh(mesh, tmp_path / "body.vtu", point_data={"w": np.zeros(3)})
    with pytest.raises(TypeError, match="TetMesh"):
        write_tetmesh("not a mesh", tmp_path / "body.vtu")
    assert os.listdir(tmp_path) == []


def _corrupt_zlib(data: bytes) -> bytes:
    """Overwrite the second half of the first binary array's compressed data (its header stays intact)."""
    b = bytearray(data)
    start = b.index(b">", b.index(b'format="binary"')) + 1
    end = b.index(b"<", start)
    text = bytes(b[start:end]).strip()
    mid = start + (end - start) // 2
    b[mid : mid + 12] = b"QUJDREVGR0hJ"  # valid base64, wrong bytes
    assert len(text) > 40
    return bytes(b)


@pytest.mark.parametrize(
    "damage, detail",
    [
        (lambda d: d[: len(d) // 2], "parsing XML"),
        (lambda d: b"", "empty"),
        (lambda d: b"hello, not XML at all\n" * 5, "parsing XML"),
        (_corrupt_zlib, "Zlib"),
    ],
)
def test_bad_files_raise_clear_errors(tmp_path, damage, detail):
    good = write_tetmesh(_mesh(), tmp_path / "good.vtu", point_data={"w": np.arange(8.0)})
    bad = tmp_path / "bad.vtu"
    bad.write_bytes(damage(good.read_bytes()))
    with pytest.raises(UnreadableFileError, match=detail) as e:
        read_tetmesh(bad)
    assert str(bad) in str(e.value) and e.value.path == bad


def test_missing_wrong_suffix_and_non_tet_files(tmp_path):
    with pytest.raises(MissingFileError, match="no such file") as e:
        read_tetmesh(tmp_path / "nothing.vtu")
    assert "nothing.vtu" in str(e.value)
    with pytest.raises(UnknownFormatError, match="must be .vtu"):
        read_tetmesh(tmp_path / "mesh.vtp")
    # A valid unstructured grid of triangles is not a tet mesh.
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import VTK_TRIANGLE, vtkCellArray, vtkUnstructuredGrid
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter

    pts = vtkPoints()
    pts.SetData(numpy_to_vtk(np.eye(3), deep=True))
    cells = vtkCellArray()
    cells.SetData(
        numpy_to_vtk(np.array([0, 3], dtype=np.int64), deep=True),
        numpy_to_vtk(np.array([0, 1, 2], dtype=np.int64), deep=True),
    )
    grid = vtkUnstructuredGrid()
    grid.SetPoints(pts)
    grid.SetCells(VTK_TRIANGLE, cells)
    w = vtkXMLUnstructuredGridWriter()
    path = tmp_path / "triangles.vtu"
    w.SetFileName(str(path))
    w.SetInputData(grid)
    w.Write()
    with pytest.raises(UnreadableFileError, match="not only tetrahedra") as e:
        read_tetmesh(path)
    assert "triangles.vtu" in str(e.value)
    with pytest.raises(ValueError, match="weight_"):
        weights_from_point_data({"displacement": np.zeros((3, 3))})
