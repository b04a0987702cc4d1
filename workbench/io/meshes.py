"""Reading and writing triangle surface meshes (PLY, OBJ, STL, VTP).

Formats, chosen by suffix (case-insensitive):

``.ply``
    Through Open3D.  Written binary with float64 (``double``) vertices, so a round trip is exact; float32 PLY
    files (common from VTK and scanners) are read exactly and widened to float64.  Vertex order and unused
    vertices are kept.
``.obj``
    Read and written by this module, not Open3D: Open3D writes OBJ vertices with 6 significant digits, parses
    them into float32, and renumbers the vertices in the order the faces first use them, dropping unused ones.
    Here vertices are written with 17 significant digits (exact round trip), order is kept, polygons are
    fan-triangulated and ``v/vt/vn`` face references and negative indices are understood.
``.stl``
    Through Open3D.  STL has no shared vertices: each triangle stores its own three corners in **float32**.
    :func:`read_mesh` merges corners with identical coordinates into one vertex (numbered in order of first
    appearance), so connectivity survives, but coordinates are rounded to float32, the original vertex order is
    lost, and distinct vertices that round to the same float32 point merge.
``.vtp``
    VTK XML PolyData through VTK, float64 points, exact.  Polygons and triangle strips are triangulated on
    reading; vertices and lines are ignored.

Errors: :class:`~workbench.errors.MissingFileError`, :class:`~workbench.errors.UnknownFormatError`, and
:class:`~workbench.errors.UnreadableFileError` for truncated, corrupt or empty meshes (no triangles).  Writers are
atomic and refuse to overwrite unless ``overwrite=True``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from deformation.meshes.mesh import SurfaceMesh
from workbench.errors import MissingFileError, UnknownFormatError, UnreadableFileError
from workbench.io.atomic import atomic_path, split_suffix

__all__ = ["MESH_SUFFIXES", "read_mesh", "write_mesh", "read_mesh_point_data", "capture_vtk_output", "write_vtk_xml"]

#: File suffixes understood by :func:`read_mesh` and :func:`write_mesh`.
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".vtp")


def _mesh_format(path: Path) -> str:
    _, suffix = split_suffix(path.name)
    suffix = suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise UnknownFormatError(
            f"{path}: cannot tell the mesh format from the suffix {suffix or '(none)'!r}. "
            f"Supported suffixes: {', '.join(MESH_SUFFIXES)}. Convert the mesh or rename the file.",
            path,
        )
    return suffix


def _require_file(path: Path) -> None:
    if not path.exists():
        where = "" if path.is_absolute() else f" (relative to the working folder {Path.cwd()})"
        raise MissingFileError(f"{path}: no such file{where}. Check the path and the file name.", path)
    if not path.is_file():
        raise UnreadableFileError(f"{path}: not a regular file. Give the path of a mesh file.", path)


def _unreadable(path: Path, fmt: str, detail: str) -> UnreadableFileError:
    return UnreadableFileError(
        f"{path}: could not read a triangle mesh from this {fmt} file ({detail}). The file is "
        "truncated, corrupt, empty or not really of this format: export it again.",
        path,
    )


# ---------------------------------------------------------------------------
# Open3D (PLY, STL)
# ---------------------------------------------------------------------------


@contextlib.contextmanager
def _quiet_open3d() -> Iterator[None]:
    """Silence Open3D's console warnings; failures are detected from the result instead."""
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        yield


def _ply_element_counts(path: Path) -> dict[str, int]:
    """Element counts declared in a PLY header (``{"vertex": n, "face": m, ...}``)."""
    counts: dict[str, int] = {}
    with open(path, "rb") as f:
        if f.read(4) not in (b"ply\n", b"ply\r"):
            raise _unreadable(path, ".ply", "it does not start with the PLY magic word 'ply'")
        f.seek(0)
        for _ in range(10000):
            line = f.readline()
            if not line:
                raise _unreadable(path, ".ply", "the header has no 'end_header' line")
            words = line.decode("latin-1").split()
            if words[:1] == ["end_header"]:
                return counts
            if words[:1] == ["element"] and len(words) == 3:
                try:
                    counts[words[1]] = int(words[2])
                except ValueError:
                    raise _unreadable(path, ".ply", f"bad header line {line.strip()!r}") from None
    raise _unreadable(path, ".ply", "the header has no 'end_header' line")


def _check_stl_complete(path: Path) -> None:
    """Binary STL declares its triangle count: check the file is long enough."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
    if head[:5].lower() == b"solid" and (size < 84 or size != 84 + 50 * int.from_bytes(head[80:84], "little")):
        return  # ASCII STL: Open3D's parser is the check
    if size < 84:
        raise _unreadable(path, ".stl", f"only {size} bytes, shorter than a binary STL header")
    n = int.from_bytes(head[80:84], "little")
    if size < 84 + 50 * n:
        raise _unreadable(
            path,
            ".stl",
            f"truncated: the header declares {n} triangles ({84 + 50 * n} bytes), the file has {size} bytes",
        )


def _read_open3d(path: Path, fmt: str) -> SurfaceMesh:
    import open3d as o3d

    if path.stat().st_size == 0:
        raise _unreadable(path, fmt, "the file is empty")
    declared = _ply_element_counts(path) if fmt == ".ply" else None
    if fmt == ".stl":
        _check_stl_complete(path)
    with _quiet_open3d():
        m = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(m.vertices, dtype=np.float64)
    triangles = np.asarray(m.triangles, dtype=np.int64)
    if len(triangles) == 0:
        raise _unreadable(path, fmt, f"Open3D found {len(vertices)} vertices and no triangles")
    if declared is not None:
        # Open3D returns what it read before a truncation without an error.
        n_v, n_f = declared.get("vertex", 0), declared.get("face", 0)
        if len(vertices) != n_v or len(triangles) < n_f:
            raise _unreadable(
                path,
                fmt,
                f"truncated: the header declares {n_v} vertices and {n_f} faces, "
                f"Open3D read {len(vertices)} vertices and {len(triangles)} triangles",
            )
    if fmt == ".stl":
        vertices, triangles = _merge_identical_vertices(vertices, triangles)
    try:
        return SurfaceMesh(vertices, triangles)
    except ValueError as e:
        raise _unreadable(path, fmt, str(e)) from e


def _merge_identical_vertices(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge exactly coincident vertices, numbering them by first appearance."""
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # unique rows in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return vertices[first[order]], rank[inverse.reshape(-1)][triangles]


def _write_open3d(mesh: SurfaceMesh, tmp: Path, fmt: str) -> None:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.array(mesh.vertices, dtype=np.float64)),  # writeable copy
        o3d.utility.Vector3iVector(np.array(mesh.triangles, dtype=np.int32)),
    )
    if fmt == ".stl":
        m.compute_triangle_normals()  # STL stores a normal per facet; Open3D requires them
    with _quiet_open3d():
        ok = o3d.io.write_triangle_mesh(
            str(tmp),
            m,
            write_ascii=False,
            compressed=False,
            write_vertex_normals=False,
            write_vertex_colors=False,
            write_triangle_uvs=False,
        )
    if not ok or not tmp.is_file():
        raise OSError(f"{tmp}: Open3D could not write the {fmt} file.")
    _check_binary_written(tmp, fmt, mesh.n_vertices, mesh.n_triangles)


#: bytes of the PLY scalar types Open3D writes
_PLY_SIZES = {
    "char": 1,
    "uchar": 1,
    "int8": 1,
    "uint8": 1,
    "short": 2,
    "ushort": 2,
    "int16": 2,
    "uint16": 2,
    "int": 4,
    "uint": 4,
    "int32": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}


def _check_binary_written(path: Path, fmt: str, n_vertices: int, n_triangles: int) -> None:
    """Raise :class:`OSError` unless Open3D's binary PLY or STL file is whole: its writer (RPly) reports a
    short write on standard error and returns success.  The size a whole file has follows from its header
    (PLY: each element's count times its record's size; a face's list holds 3 indices) or from the triangle
    count (STL: 84 + 50 bytes a triangle)."""
    size = path.stat().st_size
    if fmt == ".stl":
        expected = 84 + 50 * n_triangles
    else:
        with open(path, "rb") as f:
            head = f.read(4096)
        end = head.find(b"end_header\n")
        if end < 0:
            raise OSError(f"wrote only {size} bytes: the PLY header is cut short")
        expected, record, count = end + len(b"end_header\n"), 0, 0
        for line in head[:end].decode("ascii", "replace").splitlines():
            words = line.split()
            if words[:1] == ["element"]:
                expected += record * count
                record, count = 0, int(words[2])
            elif words[:2] == ["property", "list"]:
                record += _PLY_SIZES[words[2]] + 3 * _PLY_SIZES[words[3]]
            elif words[:1] == ["property"]:
                record += _PLY_SIZES[words[1]]
        expected += record * count
    if size < expected:
        raise OSError(f"wrote only {size} of {expected} bytes")


# ---------------------------------------------------------------------------
# OBJ (own reader and writer, exact)
# ---------------------------------------------------------------------------


def _obj_index(token: str, n_vertices: int, path: Path, line_no: int) -> int:
    ref = token.split("/", 1)[0]
    try:
        i = int(ref)
    except ValueError:
        raise UnreadableFileError(
            f"{path}: line {line_no}: bad face vertex reference {token!r}. Fix or re-export the OBJ file.",
            path,
        ) from None
    return i - 1 if i > 0 else n_vertices + i  # OBJ is 1-based; negative counts back


def _read_obj(path: Path) -> SurfaceMesh:
    vertices: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    try:
        with open(path, encoding="utf-8", errors="strict") as f:
            for line_no, line in enumerate(f, start=1):
                parts = line.split()
                if not parts:
                    continue
                if parts[0] == "v":
                    try:
                        vertices.append([float(x) for x in parts[1:4]])
                    except ValueError:
                        raise UnreadableFileError(
                            f"{path}: line {line_no}: bad vertex {line.strip()!r}. Fix or re-export the OBJ file.",
                            path,
                        ) from None
                    if len(vertices[-1]) != 3:
                        raise UnreadableFileError(
                            f"{path}: line {line_no}: a vertex needs 3 coordinates, got {line.strip()!r}.",
                            path,
                        )
                elif parts[0] == "f":
                    ids = [_obj_index(tok, len(vertices), path, line_no) for tok in parts[1:]]
                    if len(ids) < 3:
                        raise UnreadableFileError(
                            f"{path}: line {line_no}: a face needs at least 3 vertices, got {line.strip()!r}.",
                            path,
                        )
                    # Fan triangulation of polygons (exact for convex faces).
                    triangles.extend((ids[0], ids[k], ids[k + 1]) for k in range(1, len(ids) - 1))
    except UnicodeDecodeError as e:
        raise _unreadable(path, ".obj", "not a text file") from e
    if not triangles:
        raise _unreadable(path, ".obj", f"{len(vertices)} vertices and no faces")
    try:
        return SurfaceMesh(np.array(vertices, dtype=np.float64), np.array(triangles, dtype=np.int64))
    except ValueError as e:
        raise _unreadable(path, ".obj", str(e)) from e


def _write_obj(mesh: SurfaceMesh, tmp: Path) -> None:
    with open(tmp, "w", encoding="utf-8", newline="\n") as f:
        f.write(f"# {mesh.n_vertices} vertices, {mesh.n_triangles} triangles; millimetres\n")
        # '%.17g' round-trips every float64 exactly.
        np.savetxt(f, mesh.vertices, fmt="v %.17g %.17g %.17g")
        np.savetxt(f, mesh.triangles + 1, fmt="f %d %d %d")


# ---------------------------------------------------------------------------
# VTP (VTK)
# ---------------------------------------------------------------------------


class _VtkMessages:
    """VTK error and warning text captured during a call."""

    def __init__(self):
        self.text = ""

    @property
    def errors(self) -> list[str]:
        """The first line of each ``ERROR`` block, with VTK's object address removed."""
        out = []
        for block in self.text.split("ERROR:")[1:]:
            lines = [ln.strip() for ln in block.strip().splitlines() if ln.strip()]
            if len(lines) >= 2:
                out.append(lines[1].split("): ", 1)[-1])
        return out


@contextlib.contextmanager
def capture_vtk_output() -> Iterator[_VtkMessages]:
    """Capture VTK's console messages (as PyVista's ``VtkErrorCatcher`` does).

    VTK reports errors of the reader's helpers (the XML parser, the pipeline
    executive) by printing them, not by raising.  The output window and the
    logger's console output are global: they are swapped for the duration of
    the call and restored afterwards (not thread-safe).
    """
    from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow

    messages = _VtkMessages()
    previous_window = vtkOutputWindow.GetInstance()
    previous_cutoff = vtkLogger.GetCurrentVerbosityCutoff()
    window = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(window)
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    try:
        yield messages
    finally:
        vtkOutputWindow.SetInstance(previous_window)
        vtkLogger.SetStderrVerbosity(vtkLogger.ConvertToVerbosity(previous_cutoff))
        messages.text = window.GetOutput()


def _read_vtp(path: Path) -> SurfaceMesh:
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkFiltersCore import vtkTriangleFilter
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    with capture_vtk_output() as caught:
        reader.Update()
    poly = reader.GetOutput()
    if caught.errors or poly is None or poly.GetPoints() is None:
        detail = caught.errors[0] if caught.errors else "no points"
        raise _unreadable(path, ".vtp", detail)
    polys = poly.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray()) if polys.GetNumberOfCells() else np.zeros(1)
    all_triangles = poly.GetNumberOfStrips() == 0 and np.all(np.diff(offsets) == 3)
    if not all_triangles:
        tri = vtkTriangleFilter()
        tri.SetInputData(poly)
        tri.PassVertsOff()
        tri.PassLinesOff()
        with capture_vtk_output() as caught:
            tri.Update()
        if caught.errors:
            raise _unreadable(path, ".vtp", caught.errors[0])
        poly = tri.GetOutput()
        polys = poly.GetPolys()
    vertices = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    if polys.GetNumberOfCells() == 0:
        raise _unreadable(path, ".vtp", f"{len(vertices)} points and no polygons")
    triangles = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64).reshape(-1, 3)
    try:
        return SurfaceMesh(vertices, triangles)
    except ValueError as e:
        raise _unreadable(path, ".vtp", str(e)) from e


def _write_vtp(mesh: SurfaceMesh, tmp: Path, point_data: dict | None = None) -> None:
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    from deformation.meshes.isosurface import vtk_polydata

    poly = vtk_polydata(mesh.vertices, mesh.triangles, point_data)
    writer = vtkXMLPolyDataWriter()
    writer.SetInputData(poly)
    writer.SetDataModeToBinary()
    write_vtk_xml(writer, tmp)


def write_vtk_xml(writer, path: Path) -> None:
    """Run a VTK XML writer (binary data mode: base64 text) into memory, then write its text to ``path`` from
    Python.  VTK's own file output crashes the process (SIGSEGV) when a write fails for a full disk or a
    file-size limit; Python's raises :class:`OSError`, which :mod:`workbench.io.atomic` names."""
    writer.WriteToOutputStringOn()
    with capture_vtk_output() as caught:
        ok = writer.Write()
    if ok != 1 or caught.errors:
        raise OSError(
            f"{path}: VTK could not write the {path.suffix} file ({'; '.join(caught.errors) or 'unknown error'})."
        )
    with open(path, "w", encoding="ascii", newline="") as f:
        f.write(writer.GetOutputString())


# ---------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------


def read_mesh(path: str | os.PathLike) -> SurfaceMesh:
    """Read a triangle mesh (PLY, OBJ, STL or VTP).

    Parameters
    ----------
    path : str or os.PathLike
        Mesh file; the suffix chooses the reader.  Coordinates are taken to be
        world millimetres.

    Returns
    -------
    SurfaceMesh
        Vertices (float64) and triangles (int64).  See the module docstring
        for what each format preserves (STL merges corners and is float32).

    Raises
    ------
    MissingFileError
        No such file.
    UnknownFormatError
        Unsupported suffix.
    UnreadableFileError
        Truncated, corrupt or empty file, or a file without triangles.
    """
    p = Path(path)
    fmt = _mesh_format(p)
    _require_file(p)
    if fmt == ".obj":
        return _read_obj(p)
    if fmt == ".vtp":
        return _read_vtp(p)
    return _read_open3d(p, fmt)


def read_mesh_point_data(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The named point-data arrays of a ``.vtp`` mesh (e.g. ``weight_<bone>`` skinning weights)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    p = Path(path)
    if _mesh_format(p) != ".vtp":
        raise UnknownFormatError(f"{p}: point data is read from .vtp meshes only.", p)
    _require_file(p)
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(p))
    with capture_vtk_output() as caught:
        reader.Update()
    if caught.errors:
        raise _unreadable(p, ".vtp", caught.errors[0])
    pd = reader.GetOutput().GetPointData()
    return {pd.GetArrayName(i): vtk_to_numpy(pd.GetArray(i)).astype(np.float64) for i in range(pd.GetNumberOfArrays())}


def write_mesh(
    mesh: SurfaceMesh, path: str | os.PathLike, *, overwrite: bool = False, point_data: dict | None = None
) -> Path:
    """Write a triangle mesh atomically (PLY, OBJ, STL or VTP).

    Parameters
    ----------
    mesh : SurfaceMesh
        The mesh; not modified.
    path : str or os.PathLike
        Output file; the suffix chooses the format.  PLY, OBJ and VTP are
        exact; STL stores float32 corners per triangle.
    overwrite : bool, optional
        Replace an existing file; otherwise :class:`~workbench.errors.OutputExistsError`.
    point_data : dict, optional
        Named per-vertex arrays (``.vtp`` only), e.g. skinning weights.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    p = Path(path)
    fmt = _mesh_format(p)
    if point_data and fmt != ".vtp":
        raise ValueError(f"{p}: per-vertex arrays are written to .vtp meshes only")
    if not isinstance(mesh, SurfaceMesh):
        raise TypeError(f"{p}: write_mesh takes a SurfaceMesh, got {type(mesh).__name__}")
    if mesh.n_triangles == 0:
        raise ValueError(f"{p}: refusing to write a mesh without triangles.")
    with atomic_path(p, overwrite=overwrite) as tmp:
        if fmt == ".obj":
            _write_obj(mesh, tmp)
        elif fmt == ".vtp":
            _write_vtp(mesh, tmp, point_data)
        else:
            _write_open3d(mesh, tmp, fmt)
    return p
