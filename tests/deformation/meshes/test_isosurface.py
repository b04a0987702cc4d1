"""Isosurfaces in world mm (deformation.meshes.isosurface): geometry, winding, closing at the field of view, debris,
decimation — on a sphere whose surface is known exactly."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.isosurface import decimate, isosurface, label_surfaces, largest_components, signed_volume
from deformation.meshes.mesh import SurfaceMesh

ROT = Rotation.from_euler("xyz", [8, -5, 12], degrees=True).as_matrix()
CENTRE = np.array([2.0, -3.0, 1.0])


def _grid(reflect: bool = False) -> GridGeometry:
    d = ROT @ np.diag([1.0, 1.0, -1.0]) if reflect else ROT
    size, spacing = np.array([40, 36, 30]), np.array([1.5, 1.7, 2.0])
    origin = CENTRE + [1.0, 2.0, 3.0] - d @ ((size - 1) * spacing / 2)  # the sphere a little off the centre
    return GridGeometry(tuple(size), tuple(spacing), tuple(origin), tuple(d.ravel()))


def _sphere(g: GridGeometry, radius: float = 10.0) -> Volume:
    """Bright inside: value radius + 5 − |x − c|, so the level-5 surface is the sphere of ``radius``."""
    x = g.world_coordinates().reshape(-1, 3)
    return Volume((radius + 5.0 - np.linalg.norm(x - CENTRE, axis=1)).reshape(g.array_shape).astype(np.float32), g)


def _edges_shared_twice(m: SurfaceMesh) -> bool:
    t = m.triangles
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


@pytest.mark.parametrize("reflect", [False, True])
def test_sphere_in_world_mm_wound_outward_on_any_direction(reflect):
    m = isosurface(_sphere(_grid(reflect)), 5.0)
    r = np.linalg.norm(m.vertices - CENTRE, axis=1)
    # Linear interpolation along a grid edge of length h across a sphere of radius R errs by at most about
    # h² / (8 R) = 2² / 80 = 0.05 mm (largest spacing 2 mm): vertices lie within 0.05 mm of the sphere.
    assert m.n_vertices > 500 and np.abs(r - 10.0).max() < 0.05
    assert _edges_shared_twice(m)  # the sphere lies inside the grid: closed
    # outward normals whatever the direction's handedness: positive enclosed volume, 4/3 π R³ within the
    # polyhedron's inscribed shortfall (≈ 3 × 0.05 mm / 10 mm relative, measured 0.4 %)
    assert signed_volume(m.vertices, m.triangles) == pytest.approx(4.0 / 3.0 * np.pi * 1000.0, rel=0.02)


def test_pad_value_closes_a_surface_cut_by_the_field_of_view():
    g = _grid()
    vol = _sphere(g, radius=28.0)  # beyond the grid's half-extent along x (40 × 1.5 mm / 2 = 30, off-centre)
    open_ = isosurface(vol, 5.0)
    closed = isosurface(vol, 5.0, pad_value=-100.0)
    assert not _edges_shared_twice(open_)
    assert _edges_shared_twice(closed) and signed_volume(closed.vertices, closed.triangles) > 0


def test_largest_components_drops_debris():
    g = _grid()
    vol = _sphere(g)
    data = vol.data.copy()
    data[2, 2, 2] = 100.0  # one noise voxel far above the level: a tiny closed surface of its own
    m = isosurface(Volume(data, g), 5.0)
    clean = largest_components(m)
    assert clean.n_triangles < m.n_triangles
    assert np.abs(np.linalg.norm(clean.vertices - CENTRE, axis=1) - 10.0).max() < 0.05


def test_decimate_reaches_the_target_and_keeps_the_shape():
    m = isosurface(_sphere(_grid()), 5.0)
    d = decimate(m, 500)
    assert 450 <= d.n_triangles <= 500
    # quadric error simplification of a 10 mm sphere to 500 triangles (edges ~3 mm): the chord sag of a
    # 3 mm edge on a 10 mm radius is 3² / (8 · 10) ≈ 0.11 mm; vertices themselves stay within ~0.2 mm
    r = np.linalg.norm(d.vertices - CENTRE, axis=1)
    assert np.abs(r - 10.0).max() < 0.25
    assert _edges_shared_twice(d)
    assert decimate(d, 10_000) is d  # fewer triangles than asked: unchanged
    with pytest.raises(ValueError, match="target_triangles"):
        decimate(m, 2)


def test_label_surfaces_bound_each_label_in_world_mm():
    g = _grid(reflect=True)
    lab = np.zeros(g.array_shape, np.uint8)
    lab[5:12, 6:14, 8:20] = 3  # two boxes, apart
    lab[15:25, 20:30, 22:34] = 7
    mesh, vlab = label_surfaces(Volume(lab, g))
    assert set(np.unique(vlab)) == {3, 7} and len(vlab) == mesh.n_vertices
    for lid in (3, 7):
        k, j, i = np.nonzero(lab == lid)
        v = mesh.vertices[vlab == lid]
        # the discrete surface runs half-way between a label voxel and its neighbour: mapped back through the
        # reflected, anisotropic grid, its extent is the box's voxel centres ± half a voxel (round-off only)
        ijk = g.world_to_index(v)
        np.testing.assert_allclose(ijk.min(axis=0), [i.min() - 0.5, j.min() - 0.5, k.min() - 0.5], atol=1e-6)
        np.testing.assert_allclose(ijk.max(axis=0), [i.max() + 0.5, j.max() + 0.5, k.max() + 0.5], atol=1e-6)
    # each label's piece is closed and wound outward on the reflected grid
    assert _edges_shared_twice(mesh) and signed_volume(mesh.vertices, mesh.triangles) > 0
