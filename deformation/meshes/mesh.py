"""Triangle surface meshes: vertices in world millimetres and their triangles.

Pure NumPy/SciPy; reading and writing mesh files lives in
:mod:`workbench.io.meshes`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _graph_components

__all__ = ["SurfaceMesh", "connected_components", "submesh", "checked_cells"]


def checked_cells(vertices, cells, corners: int, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Read-only float64 ``(n, 3)`` vertices and int64 ``(m, corners)`` cells, validated (meshes' shared check)."""
    v = np.array(vertices, dtype=np.float64, copy=True)
    t = np.asarray(cells)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (n, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        bad = int(np.argmin(np.isfinite(v).all(axis=1)))
        raise ValueError(f"vertices must be finite; vertex {bad} is {v[bad].tolist()}")
    if t.size == 0:
        t = np.zeros((0, corners), dtype=np.int64)
    if t.ndim != 2 or t.shape[1] != corners:
        raise ValueError(f"{name} must have shape (m, {corners}), got {t.shape}")
    if t.dtype.kind not in "iu" and not np.all(t == np.round(t)):
        raise ValueError(f"{name} must hold integer vertex indices")
    t = np.array(t, dtype=np.int64, copy=True)
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError(f"{name[:-1]} indices must lie in [0, {len(v)}), got range [{t.min()}, {t.max()}]")
    v.flags.writeable = False
    t.flags.writeable = False
    return v, t


@dataclass(frozen=True, eq=False)
class SurfaceMesh:
    """A triangle mesh.

    Parameters
    ----------
    vertices : (n, 3) array_like
        Vertex positions ``(x, y, z)`` in world mm; stored as float64.
    triangles : (m, 3) array_like
        Vertex indices of each triangle (counter-clockwise seen from outside
        for a closed, outward-oriented surface); stored as int64.

    Raises
    ------
    ValueError
        Wrong shapes, non-finite vertices, or indices outside ``[0, n)``.

    Notes
    -----
    The arrays are made read-only so that a mesh can be shared without
    copies; build a new mesh to change it.
    """

    vertices: np.ndarray
    triangles: np.ndarray

    def __post_init__(self):
        v, t = checked_cells(self.vertices, self.triangles, 3, "triangles")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "triangles", t)

    @property
    def n_vertices(self) -> int:
        """Number of vertices."""
        return int(self.vertices.shape[0])

    @property
    def n_triangles(self) -> int:
        """Number of triangles."""
        return int(self.triangles.shape[0])

    def __repr__(self) -> str:
        return f"SurfaceMesh(n_vertices={self.n_vertices}, n_triangles={self.n_triangles})"


def connected_components(mesh: SurfaceMesh) -> tuple[int, np.ndarray]:
    """Label the connected components of a mesh (triangles sharing a vertex are connected).

    Parameters
    ----------
    mesh : SurfaceMesh
        The mesh.

    Returns
    -------
    n_components : int
        Number of components that contain at least one triangle.
    triangle_labels : (m,) ndarray of int64
        Component of each triangle, ``0 .. n_components-1``, numbered in the
        order of each component's lowest vertex index (so the numbering does
        not depend on triangle order).  Vertices used by no triangle belong to
        no component.
    """
    n, t = mesh.n_vertices, mesh.triangles
    if mesh.n_triangles == 0:
        return 0, np.zeros(0, dtype=np.int64)
    # Vertex adjacency from the triangle edges; components of that graph.
    rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
    cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    graph = sp.coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n, n)).tocsr()
    _, vertex_labels = _graph_components(graph, directed=False)
    tri_vertex_label = vertex_labels[t[:, 0]]
    # Renumber by the lowest vertex index of each component that has triangles.
    used = np.zeros(n, dtype=bool)
    used[t.ravel()] = True
    used_ids = np.flatnonzero(used)
    labels_of_used = vertex_labels[used_ids]
    _, first = np.unique(labels_of_used, return_index=True)
    order = labels_of_used[np.sort(first)]  # graph labels sorted by lowest vertex
    remap = np.full(vertex_labels.max() + 1, -1, dtype=np.int64)
    remap[order] = np.arange(order.size)
    return int(order.size), remap[tri_vertex_label]


def submesh(mesh: SurfaceMesh, triangle_mask) -> tuple[SurfaceMesh, np.ndarray]:
    """The triangles selected by a mask, keeping only the vertices they use.

    Parameters
    ----------
    mesh : SurfaceMesh
        The mesh.
    triangle_mask : (m,) array_like of bool
        Which triangles to keep.

    Returns
    -------
    SurfaceMesh
        The kept triangles, re-indexed into the kept vertices.  Vertices keep
        their relative order.
    vertex_index_map : (k,) ndarray of int64
        Original index of each vertex of the sub-mesh:
        ``sub.vertices == mesh.vertices[vertex_index_map]``.
    """
    mask = np.asarray(triangle_mask)
    if mask.dtype != np.bool_ or mask.shape != (mesh.n_triangles,):
        raise ValueError(
            f"triangle_mask must be a boolean array of shape ({mesh.n_triangles},), got {mask.dtype} {mask.shape}"
        )
    kept = mesh.triangles[mask]
    vertex_ids = np.unique(kept)
    local = np.full(mesh.n_vertices, -1, dtype=np.int64)
    local[vertex_ids] = np.arange(vertex_ids.size)
    return SurfaceMesh(mesh.vertices[vertex_ids], local[kept]), vertex_ids.astype(np.int64)
