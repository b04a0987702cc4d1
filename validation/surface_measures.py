"""Kurihara's surface model (Kurihara §4–5) against a phantom's truth: fitted meshes and posed skins.

The paper could only look at its meshes; a phantom knows where every skin
point goes.  For a template point ``v`` the phantom's posing model gives its
place ``F_i(v)`` in scan ``i`` exactly, and the template's true skin (the zero
set of the body's signed distance) posed by ``F_i`` is scan ``i``'s true skin:

* :func:`true_skin` — the template's true skin as a mesh (flying edges on the
  signed distance sampled at half the template's voxel);
* :func:`away_from_the_edge` — the vertices of a mesh not on the cap the
  field of view puts on a limb it cuts (that cap is no skin: no measure
  counts it);
* :func:`skin_distance` — how far a mesh's vertices are from a true skin
  (closest point on its triangles; mean, P95, max in mm);
* :func:`vertex_errors` — how far each vertex is from where the truth puts
  the base mesh's vertex (``|S_i(v) − F_i(S_0(v))|``: the correspondence
  error, which a distance to the skin cannot see — a vertex sliding along
  the skin has none of the latter).
"""

from __future__ import annotations

import numpy as np

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.isosurface import isosurface, largest_components
from deformation.meshes.mesh import SurfaceMesh

__all__ = ["true_skin", "away_from_the_edge", "skin_distance", "vertex_errors", "posed_truth"]


def true_skin(phantom, *, refine: float = 2.0) -> SurfaceMesh:
    """The template's true skin in world mm: the body's signed distance sampled on the template's field of
    view at ``1 / refine`` of its spacing, its zero isosurface (flying edges: within ~h²/8R of the surface),
    closed at the field of view."""
    g = phantom.geometry
    size = tuple(int(np.ceil(n * refine)) for n in g.size)
    spacing = tuple(float(s) / refine for s in g.spacing)
    # the fine grid's first voxel centre at the template's first corner + half a fine voxel
    d = np.asarray(g.direction_matrix)
    origin = np.asarray(g.origin, float) + d @ (-0.5 * np.asarray(g.spacing) + 0.5 * np.asarray(spacing))
    fine = GridGeometry(size, spacing, tuple(origin), tuple(d.ravel()))
    sdf = phantom.anatomy.distances_fast(fine.world_coordinates().reshape(-1, 3))[:, -1]
    inside = Volume((-sdf).reshape(fine.array_shape).astype(np.float32), fine)
    return largest_components(isosurface(inside, 0.0, pad_value=-1e3))


def away_from_the_edge(vertices, geometry: GridGeometry, margin_voxels: float = 1.0) -> np.ndarray:
    """Vertices farther than ``margin_voxels`` inside the grid's box from its faces (bool): the others lie on the
    cap where the field of view cuts a limb."""
    ijk = geometry.world_to_index(np.asarray(vertices, float))
    hi = np.asarray(geometry.size, float) - 1.0
    return np.all((ijk > margin_voxels - 0.5) & (ijk < hi - margin_voxels + 0.5), axis=1)


def posed_truth(phantom, angles: dict, points) -> np.ndarray:
    """Where the phantom's posing model puts template points at ``angles`` (world mm)."""
    return phantom.posing_model(angles).forward(np.asarray(points, float))


def skin_distance(mesh_vertices, skin: SurfaceMesh, keep=None) -> dict:
    """Distance (mm) of ``mesh_vertices`` (those where ``keep``) from the triangles of ``skin``."""
    from registration.surface_fit import closest_points

    v = np.asarray(mesh_vertices, float)
    if keep is not None:
        v = v[np.asarray(keep, bool)]
    _, d, _ = closest_points(skin, v)
    return {
        "mean_mm": float(d.mean()),
        "p95_mm": float(np.percentile(d, 95)),
        "max_mm": float(d.max()),
        "n_vertices": int(len(d)),
    }


def vertex_errors(mesh_vertices, true_vertices, keep=None) -> dict:
    """``|mesh − truth|`` per vertex (those where ``keep``): mean, P95 and max in mm."""
    e = np.linalg.norm(np.asarray(mesh_vertices, float) - np.asarray(true_vertices, float), axis=1)
    if keep is not None:
        e = e[np.asarray(keep, bool)]
    return {
        "mean_mm": float(e.mean()),
        "p95_mm": float(np.percentile(e, 95)),
        "max_mm": float(e.max()),
        "n_vertices": int(len(e)),
    }
