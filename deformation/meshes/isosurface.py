"""Isosurfaces of volumes in world millimetres: the project's one numpy → VTK → triangle mesh path.

Kurihara §3–4 works on isosurfaces of CT scans: the bones' (aligned by ICP
for the joint centres of Kurihara Eq. 1) and the skin's.  Every isosurface of the project is extracted here:

* :func:`flying_edges` — VTK's flying edges (``vtkFlyingEdges3D``, or its
  discrete variant for one label) on a ``[z, y, x]`` array in index space.
* :func:`isosurface` — the ``level`` surface of a :class:`~deformation.geometry.Volume` in world mm
  through its full geometry (anisotropic spacing, origin, any orthonormal
  direction), triangles wound so that their normals point from the inside
  (values above ``level``) to the outside — outward for a bright object such
  as bone or a CT body, whatever the handedness of the grid's direction.
  ``pad_value`` closes a surface cut by the field of view.
* :func:`largest_components` — debris removal: the connected pieces of a
  mesh holding at least a fraction of its triangles.
* :func:`decimate` — Open3D's quadric error simplification (Garland &
  Heckbert 1997) to a target triangle count (Kurihara §4 reduced ~800 k to
  ~100 k triangles), in world mm so that the error metric is isotropic.

References: Schroeder W, Maynard R, Geveci B. Flying edges: a high-performance
scalable isocontouring algorithm. IEEE LDAV 2015. https://doi.org/10.1109/LDAV.2015.7348069
Garland M, Heckbert PS. Surface simplification using quadric error metrics.
SIGGRAPH 1997. https://doi.org/10.1145/258734.258849
"""

from __future__ import annotations

import numpy as np

from deformation.geometry import Volume
from deformation.meshes.mesh import SurfaceMesh, connected_components, submesh

__all__ = [
    "vtk_image",
    "poly_arrays",
    "vtk_polydata",
    "flying_edges",
    "isosurface",
    "label_surfaces",
    "largest_components",
    "decimate",
    "signed_volume",
]


def vtk_image(array_zyx: np.ndarray):
    """A ``vtkImageData`` of a ``[z, y, x]`` array in index space (spacing 1, origin 0; a deep copy)."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData

    a = np.asarray(array_zyx)
    if a.ndim != 3:
        raise ValueError(f"an isosurface needs a 3-D [z, y, x] array, got shape {a.shape}")
    nz, ny, nx = a.shape
    img = vtkImageData()
    img.SetDimensions(nx, ny, nz)  # VTK's point order is x fastest: the C order of a [z, y, x] array
    img.GetPointData().SetScalars(numpy_to_vtk(np.ascontiguousarray(a).ravel(), deep=True))
    return img


def poly_arrays(poly) -> tuple[np.ndarray, np.ndarray]:
    """``(points (n, 3) float64, triangles (m, 3) int64)`` of a triangle ``vtkPolyData``."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    if poly.GetNumberOfPolys() == 0 or poly.GetPoints() is None:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    pts = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    polys = poly.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    if not np.all(np.diff(offsets) == 3):
        raise RuntimeError("VTK returned non-triangular polygons")
    tri = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64).reshape(-1, 3)
    return pts, tri


def vtk_polydata(vertices: np.ndarray, triangles: np.ndarray, point_data: dict | None = None):
    """A triangle ``vtkPolyData`` of ``vertices (n, 3)`` and ``triangles (m, 3)`` (deep copies), with optional
    per-vertex ``point_data`` arrays ``{name: (n,) or (n, k)}`` (float64)."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    v = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    t = np.ascontiguousarray(triangles, dtype=np.int64).reshape(-1, 3)
    points = vtkPoints()
    points.SetData(numpy_to_vtk(v, deep=True))
    cells = vtkCellArray()
    cells.SetData(
        numpy_to_vtk(np.arange(0, 3 * len(t) + 1, 3, dtype=np.int64), deep=True), numpy_to_vtk(t.ravel(), deep=True)
    )
    poly = vtkPolyData()
    poly.SetPoints(points)
    poly.SetPolys(cells)
    for name, values in (point_data or {}).items():
        a = np.ascontiguousarray(values, dtype=np.float64)
        if a.shape[0] != len(v) or a.ndim > 2:
            raise ValueError(
                f"point-data array {name!r} has shape {a.shape}; one value (or vector) per vertex ({len(v)}) needed"
            )
        arr = numpy_to_vtk(a, deep=True)
        arr.SetName(str(name))
        poly.GetPointData().AddArray(arr)
    return poly


def flying_edges(array_zyx: np.ndarray, level: float, *, discrete: bool = False):
    """The ``level`` isosurface of an index-space array as ``vtkPolyData`` (points in voxel indices x, y, z).

    ``discrete``: the boundary of the voxels equal to ``level`` (a label of a label map;
    ``vtkDiscreteFlyingEdges3D``).  In index space, flying edges winds its triangles with normals
    pointing to lower values (outward for a bright object).
    """
    if discrete:
        from vtkmodules.vtkFiltersGeneral import vtkDiscreteFlyingEdges3D as Filter

        data = np.asarray(array_zyx).astype(np.int32)
    else:
        from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D as Filter

        data = np.asarray(array_zyx, dtype=np.float32)
    fe = Filter()
    fe.SetInputData(vtk_image(data))
    fe.SetValue(0, float(level))
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.Update()
    return fe.GetOutput()


def signed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """The signed volume (mm³) a closed triangle mesh encloses: positive when its normals point outward."""
    p = np.asarray(vertices, float)[np.asarray(triangles)]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def isosurface(image: Volume, level: float, *, pad_value: float | None = None) -> SurfaceMesh:
    """The ``level`` isosurface of ``image`` in world mm (module docstring); an empty mesh when there is none.

    ``pad_value`` (e.g. the air's intensity) closes a surface cut by the grid's edge; ``None`` leaves it
    open there.
    """
    if image.is_vector:
        raise ValueError("an isosurface needs a scalar volume")
    data = np.asarray(image.data, dtype=np.float32)
    pad = 0
    if pad_value is not None:
        pad = 1
        data = np.pad(data, 1, constant_values=np.float32(pad_value))
    ijk, tri = poly_arrays(flying_edges(data, level))
    if not len(tri):
        return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    g = image.geometry
    if np.linalg.det(np.asarray(g.index_to_world_matrix)[:3, :3]) < 0:  # a reflection reverses the winding
        tri = tri[:, [0, 2, 1]]
    return SurfaceMesh(g.index_to_world(ijk - pad), tri)


def label_surfaces(labels: Volume, ids=None) -> tuple[SurfaceMesh, np.ndarray]:
    """The boundary of each label (``ids``, default every non-zero one) of a label map as one mesh in world
    mm (discrete flying edges, padded with the background so each is closed), and every vertex's label."""
    lab = np.pad(np.asarray(labels.data).astype(np.int32), 1)
    ids = [int(v) for v in np.unique(lab) if v != 0] if ids is None else [int(v) for v in ids]
    g = labels.geometry
    flip = np.linalg.det(np.asarray(g.index_to_world_matrix)[:3, :3]) < 0
    verts, tris, vlab, n = [], [], [], 0
    for lid in ids:
        ijk, tri = poly_arrays(flying_edges(lab, lid, discrete=True))
        if not len(tri):
            continue
        verts.append(g.index_to_world(ijk - 1))
        tris.append((tri[:, [0, 2, 1]] if flip else tri) + n)
        vlab.append(np.full(len(ijk), lid, np.int64))
        n += len(ijk)
    if not verts:
        return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)), np.zeros(0, np.int64)
    return SurfaceMesh(np.concatenate(verts), np.concatenate(tris)), np.concatenate(vlab)


def largest_components(mesh: SurfaceMesh, *, min_fraction: float = 0.05) -> SurfaceMesh:
    """The connected pieces of ``mesh`` with at least ``min_fraction`` of the largest piece's triangles
    (debris — noise voxels, a scanner table's fragments — dropped); vertices no kept triangle uses dropped."""
    if mesh.n_triangles == 0:
        return mesh
    n, lab = connected_components(mesh)
    if n <= 1:
        return mesh
    sizes = np.bincount(lab, minlength=n)
    keep = sizes >= min_fraction * sizes.max()
    return submesh(mesh, keep[lab])[0]


def decimate(mesh: SurfaceMesh, target_triangles: int) -> SurfaceMesh:
    """Open3D's quadric error simplification to about ``target_triangles`` (unchanged when it has fewer)."""
    import open3d as o3d

    if int(target_triangles) < 4:
        raise ValueError(f"target_triangles must be at least 4, got {target_triangles}")
    if mesh.n_triangles <= target_triangles:
        return mesh
    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.array(mesh.vertices, np.float64)),
        o3d.utility.Vector3iVector(np.array(mesh.triangles, np.int32)),
    )
    d = m.simplify_quadric_decimation(int(target_triangles))
    d.remove_unreferenced_vertices()
    return SurfaceMesh(np.asarray(d.vertices, np.float64), np.asarray(d.triangles, np.int64))
