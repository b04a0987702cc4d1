"""Reading and writing tetrahedral meshes as VTK XML unstructured grids (``.vtu``).

The weights stage writes its body mesh, with each bone's harmonic weight, as
a ``.vtu`` file, which ParaView, 3D Slicer and PyVista open directly.

The format:

* Points: float64 world millimetres (``x, y, z``), written in VTK's binary
  (base64, zlib-compressed) encoding, so the round trip is bit-exact.
* Cells: one ``VTK_TETRA`` per tetrahedron, vertex order kept (positively
  oriented for meshes from :func:`deformation.meshes.tetmesh.lattice_tetmesh`).
* Point data: any named per-vertex arrays, float64 (or their own dtype).
  Skinning weights are stored as one scalar array per bone named
  ``weight_<bone>`` (:func:`weight_arrays`), so each bone's weight field can
  be looked at on its own in ParaView; :func:`weights_from_point_data`
  collects them back in file order.

Errors: :class:`~workbench.errors.MissingFileError`, :class:`~workbench.errors.UnknownFormatError` (not
``.vtu``), and :class:`~workbench.errors.UnreadableFileError` for truncated, corrupt or empty
files and for grids holding cells other than tetrahedra.  The writer is
atomic and refuses to overwrite unless ``overwrite=True``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deformation.meshes.tetmesh import TetMesh
from workbench.errors import MissingFileError, UnknownFormatError, UnreadableFileError
from workbench.io.atomic import atomic_path, split_suffix
from workbench.io.meshes import capture_vtk_output, write_vtk_xml  # VTK prints errors instead of raising

__all__ = ["WEIGHT_PREFIX", "read_tetmesh", "write_tetmesh", "weight_arrays", "weights_from_point_data"]

#: Point-data name prefix of per-bone skinning weights: ``weight_<bone>``.
WEIGHT_PREFIX = "weight_"
_VTK_TETRA = 10


def _check_suffix(path: Path) -> None:
    _, suffix = split_suffix(path.name)
    if suffix.lower() != ".vtu":
        raise UnknownFormatError(
            f"{path}: tetrahedral meshes are read and written as VTK XML unstructured grids; the suffix "
            f"must be .vtu, not {suffix or '(none)'!r}. Rename the file or convert it (e.g. with ParaView).",
            path,
        )


def _unreadable(path: Path, detail: str) -> UnreadableFileError:
    return UnreadableFileError(
        f"{path}: could not read a tetrahedral mesh from this .vtu file ({detail}). The file is truncated, "
        "corrupt, empty or not a VTK XML unstructured grid of tetrahedra: write it again (or mesh the study "
        "again).",
        path,
    )


def weight_arrays(bones, dense) -> dict[str, np.ndarray]:
    """``{"weight_<bone>": column}`` point-data arrays of dense weights ``(n, n_bones)``, in bone order."""
    dense = np.asarray(dense, dtype=np.float64)
    bones = [str(b) for b in bones]
    if dense.ndim != 2 or dense.shape[1] != len(bones):
        raise ValueError(f"dense weights must be (n, {len(bones)}) for bones {bones}, got {dense.shape}")
    return {f"{WEIGHT_PREFIX}{b}": np.ascontiguousarray(dense[:, k]) for k, b in enumerate(bones)}


def weights_from_point_data(point_data: dict) -> tuple[tuple[str, ...], np.ndarray]:
    """The bones and dense weights ``(n, n_bones)`` stored as ``weight_<bone>`` arrays, in file order.

    Raises
    ------
    ValueError
        No ``weight_*`` array, or one that is not a scalar per vertex.
    """
    names = [k for k in point_data if k.startswith(WEIGHT_PREFIX)]
    if not names:
        raise ValueError(f"no '{WEIGHT_PREFIX}<bone>' point-data arrays; found {sorted(point_data)}")
    cols = []
    for k in names:
        a = np.asarray(point_data[k], dtype=np.float64)
        if a.ndim != 1:
            raise ValueError(f"point-data array {k!r} must hold one value per vertex, got shape {a.shape}")
        cols.append(a)
    return tuple(k[len(WEIGHT_PREFIX) :] for k in names), np.stack(cols, axis=1)


def write_tetmesh(
    mesh: TetMesh, path: str | os.PathLike, *, point_data: dict | None = None, overwrite: bool = False
) -> Path:
    """Write a tet mesh (and per-vertex arrays) as a binary VTK XML unstructured grid, atomically.

    Parameters
    ----------
    mesh : TetMesh
        The mesh; not modified.
    path : str or os.PathLike
        Output ``.vtu`` file; its folder must exist.
    point_data : dict, optional
        ``{name: array}`` with one row per vertex: ``(n,)`` scalars or
        ``(n, c)`` vectors.  Use :func:`weight_arrays` for skinning weights.
    overwrite : bool
        Replace an existing file; otherwise :class:`~workbench.errors.OutputExistsError`.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkUnstructuredGrid
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter

    p = Path(path)
    _check_suffix(p)
    if not isinstance(mesh, TetMesh):
        raise TypeError(f"{p}: write_tetmesh takes a TetMesh, got {type(mesh).__name__}")
    if mesh.n_tets == 0:
        raise ValueError(f"{p}: refusing to write a mesh without tetrahedra.")
    arrays = []
    for name, arr in (point_data or {}).items():
        a = np.asarray(arr)
        if a.shape[:1] != (mesh.n_vertices,) or a.ndim not in (1, 2):
            raise ValueError(
                f"{p}: point-data array {name!r} must have {mesh.n_vertices} rows (one per vertex) "
                f"and 1 or 2 dimensions, got shape {a.shape}"
            )
        if a.dtype.kind not in "fiub":
            raise ValueError(f"{p}: point-data array {name!r} must be numeric, got {a.dtype}")
        if a.dtype.kind == "b":
            a = a.astype(np.uint8)
        arrays.append((str(name), np.ascontiguousarray(a)))
    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(mesh.vertices, dtype=np.float64), deep=True))
    cells = vtkCellArray()
    offsets = np.arange(0, 4 * mesh.n_tets + 1, 4, dtype=np.int64)
    cells.SetData(numpy_to_vtk(offsets, deep=True), numpy_to_vtk(np.ascontiguousarray(mesh.tets.ravel()), deep=True))
    grid = vtkUnstructuredGrid()
    grid.SetPoints(points)
    grid.SetCells(_VTK_TETRA, cells)
    for name, a in arrays:
        va = numpy_to_vtk(a, deep=True)
        va.SetName(name)
        grid.GetPointData().AddArray(va)
    with atomic_path(p, overwrite=overwrite) as tmp:
        writer = vtkXMLUnstructuredGridWriter()
        writer.SetInputData(grid)
        writer.SetDataModeToBinary()
        writer.SetCompressorTypeToZLib()
        write_vtk_xml(writer, tmp)
    return p


def read_tetmesh(path: str | os.PathLike) -> tuple[TetMesh, dict[str, np.ndarray]]:
    """Read a tet mesh and its point-data arrays from a ``.vtu`` file.

    Returns
    -------
    mesh : TetMesh
        Vertices as float64 (exact for files this module wrote) and tets int64,
        vertex order kept.
    point_data : dict
        ``{name: array}`` in file order, ``(n,)`` for scalars, ``(n, c)`` for
        vectors.

    Raises
    ------
    MissingFileError, UnknownFormatError, UnreadableFileError
        See the module docstring.
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

    p = Path(path)
    _check_suffix(p)
    if not p.exists():
        where = "" if p.is_absolute() else f" (relative to the working folder {Path.cwd()})"
        raise MissingFileError(f"{p}: no such file{where}. Check the path and the file name.", p)
    if not p.is_file():
        raise UnreadableFileError(f"{p}: not a regular file. Give the path of a .vtu file.", p)
    if p.stat().st_size == 0:
        raise _unreadable(p, "the file is empty")
    reader = vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(p))
    with capture_vtk_output() as caught:
        reader.Update()
    grid = reader.GetOutput()
    if caught.errors or grid is None or grid.GetPoints() is None:
        raise _unreadable(p, caught.errors[0] if caught.errors else "no points")
    n_cells = grid.GetNumberOfCells()
    if n_cells == 0:
        raise _unreadable(p, f"{grid.GetNumberOfPoints()} points and no cells")
    try:
        types_array = grid.GetCellTypes()  # VTK >= 9.6 (GetCellTypesArray is deprecated there)
    except TypeError:  # older VTK: GetCellTypes needs a vtkCellTypes argument
        types_array = grid.GetCellTypesArray()
    types = vtk_to_numpy(types_array)
    if not np.all(types == _VTK_TETRA):
        other = sorted(set(int(t) for t in np.unique(types)) - {_VTK_TETRA})
        raise _unreadable(p, f"it holds cells of VTK type(s) {other}, not only tetrahedra (type {_VTK_TETRA})")
    cells = grid.GetCells()
    offsets = vtk_to_numpy(cells.GetOffsetsArray())
    if not np.all(np.diff(offsets) == 4):
        raise _unreadable(p, "a tetrahedron without exactly 4 vertices")
    tets = vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64).reshape(-1, 4)
    vertices = vtk_to_numpy(grid.GetPoints().GetData()).astype(np.float64)
    point_data: dict[str, np.ndarray] = {}
    pd = grid.GetPointData()
    for i in range(pd.GetNumberOfArrays()):
        arr = pd.GetAbstractArray(i)
        name = arr.GetName()
        try:
            a = vtk_to_numpy(arr)
        except Exception as e:  # string arrays and other non-numeric data
            raise _unreadable(p, f"point-data array {name!r} is not numeric ({e})") from e
        if a.shape[0] != len(vertices):
            raise _unreadable(p, f"point-data array {name!r} has {a.shape[0]} rows for {len(vertices)} points")
        point_data[str(name)] = np.array(a, copy=True)
    try:
        mesh = TetMesh(vertices, tets)
    except ValueError as e:
        raise _unreadable(p, str(e)) from e
    return mesh, point_data
