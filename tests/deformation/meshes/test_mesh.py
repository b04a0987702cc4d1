"""SurfaceMesh, connected_components and submesh (deformation.meshes.mesh)."""

from __future__ import annotations

import numpy as np
import pytest

from deformation.meshes.mesh import SurfaceMesh, connected_components, submesh

TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def two_tetrahedra(offset=(10.0, 0.0, 0.0)) -> SurfaceMesh:
    """Two disjoint tetrahedron surfaces; the second's vertices come first in the list."""
    unit = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    vertices = np.vstack([unit + offset, unit])  # vertices 0-3: far tetra, 4-7: near tetra
    triangles = np.vstack([TETRA_FACES + 4, TETRA_FACES])  # near tetra's triangles listed first
    return SurfaceMesh(vertices, triangles)


def test_validation_and_counts():
    m = two_tetrahedra()
    assert (m.n_vertices, m.n_triangles) == (8, 8)
    assert m.vertices.dtype == np.float64 and m.triangles.dtype == np.int64
    with pytest.raises(ValueError, match=r"\[0, 8\)"):
        SurfaceMesh(m.vertices, m.triangles + 1)
    with pytest.raises(ValueError, match="shape"):
        SurfaceMesh(m.vertices[:, :2], m.triangles)
    with pytest.raises(ValueError, match="finite"):
        SurfaceMesh(np.full((3, 3), np.nan), [[0, 1, 2]])
    with pytest.raises(ValueError):
        m.vertices[0, 0] = 5.0  # read-only: a mesh is shared without copies


def test_input_arrays_are_copied():
    v = np.zeros((3, 3))
    t = np.array([[0, 1, 2]])
    m = SurfaceMesh(v, t)
    v[0, 0] = 7.0
    assert m.vertices[0, 0] == 0.0


def test_connected_components_of_two_disjoint_tetrahedra():
    m = two_tetrahedra()
    n, labels = connected_components(m)
    assert n == 2
    # Numbered by lowest vertex index: the far tetrahedron (vertices 0-3) is component 0,
    # although its triangles come second.
    np.testing.assert_array_equal(labels, [1, 1, 1, 1, 0, 0, 0, 0])
    assert np.bincount(labels).tolist() == [4, 4]


def test_components_ignore_unused_vertices_and_join_through_shared_vertex():
    m = two_tetrahedra()
    # An unused vertex belongs to no component.
    with_unused = SurfaceMesh(np.vstack([m.vertices, [[5.0, 5.0, 5.0]]]), m.triangles)
    assert connected_components(with_unused)[0] == 2
    # One triangle touching both tetrahedra merges them.
    bridged = SurfaceMesh(m.vertices, np.vstack([m.triangles, [[0, 4, 5]]]))
    n, labels = connected_components(bridged)
    assert n == 1 and set(labels.tolist()) == {0}


def test_submesh_keeps_used_vertices_and_maps_back():
    m = two_tetrahedra()
    _, labels = connected_components(m)
    sub, vertex_map = submesh(m, labels == 1)  # the near tetrahedron: vertices 4-7
    np.testing.assert_array_equal(vertex_map, [4, 5, 6, 7])
    assert (sub.n_vertices, sub.n_triangles) == (4, 4)
    np.testing.assert_array_equal(sub.triangles, TETRA_FACES)
    np.testing.assert_array_equal(sub.vertices, m.vertices[vertex_map])
    np.testing.assert_array_equal(vertex_map[sub.triangles], m.triangles[labels == 1])
    with pytest.raises(ValueError, match="boolean"):
        submesh(m, np.arange(8))
