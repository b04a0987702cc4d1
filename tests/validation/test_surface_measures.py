"""The surface model's measures against a phantom's truth (validation.surface_measures)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.isosurface import isosurface, signed_volume
from validation.phantoms import Phantom, PhantomSpec
from validation.surface_measures import away_from_the_edge, posed_truth, skin_distance, true_skin, vertex_errors


@pytest.fixture(scope="module")
def phantom():
    # anisotropic voxels on a turned grid, as real scans have
    d = Rotation.from_euler("xyz", [10, -6, 15], degrees=True).as_matrix()
    return Phantom(PhantomSpec(region="knee", direction=tuple(d.ravel()), spacing=(3.0, 3.5, 4.0), n_poses=2))


def test_true_skin_is_the_bodys_zero_set_facing_out(phantom):
    skin = true_skin(phantom)
    keep = away_from_the_edge(skin.vertices, phantom.geometry)
    assert 0.5 < keep.mean() < 1.0  # the caps where the field of view cuts the leg are dropped, nothing else
    sdf = phantom.anatomy.distances_fast(skin.vertices)[:, -1]
    # flying edges on the signed distance sampled at half the voxel (1.5-2 mm): linear interpolation of a
    # smooth distance puts the zero within ~h²/(8R) ≤ 0.1 mm for radii of curvature ≥ 5 mm (0.02 measured)
    assert np.abs(sdf[keep]).max() < 0.1
    assert signed_volume(skin.vertices, skin.triangles) > 0  # outward winding on a left-handed-looking grid


def test_posed_truth_at_rest_is_the_identity_and_moves_points_otherwise(phantom):
    pts = true_skin(phantom).vertices[::50]
    angles = phantom.poses[1][1]
    rest = {k: np.zeros_like(v) for k, v in angles.items()}
    np.testing.assert_array_equal(posed_truth(phantom, rest, pts), pts)
    moved = posed_truth(phantom, angles, pts)
    assert np.linalg.norm(moved - pts, axis=1).max() > 5.0  # the knee bends: the shank's skin moves cm


def test_skin_distance_and_vertex_errors_of_known_offsets():
    g = GridGeometry((40, 40, 40), (1.0, 1.0, 1.0), (-20.0, -20.0, -20.0))
    r = np.linalg.norm(g.world_coordinates(), axis=-1)
    sphere = isosurface(Volume((10.0 - r).astype(np.float32), g), 0.0)
    u = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    out = u * 10.5
    d = skin_distance(out, sphere)
    # 0.5 mm outside a R 10 sphere; the facets sag inward by ≤ h²/(8R) ≈ 0.0125 mm with 1 mm voxels
    assert abs(d["mean_mm"] - 0.5) < 0.02 and d["max_mm"] < 0.52 and d["n_vertices"] == sphere.n_vertices
    keep = u[:, 2] > 0
    assert skin_distance(out, sphere, keep)["n_vertices"] == keep.sum()
    e = vertex_errors(sphere.vertices + [0.0, 0.0, 2.0], sphere.vertices, keep)
    assert e["mean_mm"] == pytest.approx(2.0) and e["max_mm"] == pytest.approx(2.0) and e["n_vertices"] == keep.sum()


def test_the_edge_test_uses_the_grid_in_index_space():
    d = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    g = GridGeometry((10, 12, 14), (2.0, 1.0, 3.0), (5.0, -3.0, 1.0), tuple(d.ravel()))
    inner = g.index_to_world(np.array([[1.5, 1.5, 1.5], [8.0, 10.0, 12.0]]))
    edge = g.index_to_world(np.array([[0.0, 5.0, 5.0], [4.0, 11.0, 5.0], [4.0, 5.0, 13.4]]))
    assert away_from_the_edge(inner, g).all() and not away_from_the_edge(edge, g).any()
