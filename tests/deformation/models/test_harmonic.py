"""Tet meshes (deformation.meshes.tetmesh) and harmonic skinning weights (deformation.models.harmonic).

The test knee's body is meshed once per module (the Kuhn lattice,
deformation.meshes.tetmesh.lattice_tetmesh, every 2nd voxel) and written as a VTU
file; the tests downstream read that file.  The lattice mesher itself, the
stiffness matrix on it and determinism across processes are tested in
test_lattice_tetmesh.py.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.isosurface import isosurface
from deformation.meshes.tetmesh import TIE_DIRECTION, TetMesh, lattice_cubes, lattice_tetmesh, locate, rasterize
from deformation.models.harmonic import (
    constrained_vertices,
    harmonic_voxel_weights,
    harmonic_weights,
    stiffness_matrix,
    weights_at_points,
    weights_on_grid,
)
from deformation.models.skinning import SkinningWeights, distance_weights
from registration.segmentation import segment_body
from workbench.io.tetmeshes import read_tetmesh, weight_arrays, write_tetmesh

KNEE_STEP = 2  # lattice step (voxels): the test knee's grid is 4.98×4.98×3.69 mm, so 10×10×7.4 mm cubes


# ---------------------------------------------------------------------------------------------
# Fixtures: the test-size knee, meshed once
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def knee(phantom, tmp_path_factory):
    ph = phantom("knee", size="test", modality="ct", n_poses=2, seed=3)
    template, labels = ph.template()
    mask = segment_body(template, threshold=-500.0, smooth_voxels=0)  # CT: air ≈ −1000 HU
    t0 = time.perf_counter()
    mesh = lattice_tetmesh(mask, step=KNEE_STEP)
    t1 = time.perf_counter()
    path = write_tetmesh(mesh, tmp_path_factory.mktemp("knee-tet") / "body.vtu")
    bone_labels = {b: ph.skeleton.label_of(b) for b in ph.skeleton.bone_names}
    # the skin: the 0.5 isosurface of the mask (voxel staircase and all), closed at the field of view
    surface = isosurface(Volume(mask.data.astype(np.float32), mask.geometry), 0.5, pad_value=0.0)
    return {
        "phantom": ph,
        "template": template,
        "labels": labels,
        "mask": mask,
        "surface": surface,
        "path": path,
        "bone_labels": bone_labels,
        "seconds": {"mesh": t1 - t0},
    }


@pytest.fixture(scope="module")
def knee_mesh(knee) -> TetMesh:
    mesh, _ = read_tetmesh(knee["path"])
    return mesh


@pytest.fixture(scope="module")
def knee_weights(knee, knee_mesh):
    t0 = time.perf_counter()
    w, info = harmonic_weights(knee_mesh, knee["labels"], knee["bone_labels"])
    info["seconds_total"] = time.perf_counter() - t0
    return w, info


@pytest.fixture(scope="module")
def knee_grid_weights(knee, knee_mesh, knee_weights):
    w, info = knee_weights
    t0 = time.perf_counter()
    sw = weights_on_grid(knee_mesh, w, info["bones"], knee["template"].geometry, knee["labels"], knee["bone_labels"])
    return sw, time.perf_counter() - t0


def _rotated_grid(size=(13, 11, 9), spacing=(0.7, 1.3, 0.9), origin=(3.0, -2.0, 5.0)) -> GridGeometry:
    r = Rotation.from_euler("zyx", [31.0, -17.0, 52.0], degrees=True).as_matrix()
    return GridGeometry(size, spacing, origin, r.reshape(-1))


# ---------------------------------------------------------------------------------------------
# TetMesh and the knee's lattice mesh
# ---------------------------------------------------------------------------------------------


def test_tetmesh_validation_and_orientation():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    neg = TetMesh(v, [[0, 2, 1, 3], [1, 2, 3, 4]])
    assert neg.signed_volumes()[0] < 0
    fixed = neg.oriented()
    np.testing.assert_allclose(fixed.signed_volumes(), np.abs(neg.signed_volumes()))
    assert fixed.vertices.flags.writeable is False and fixed.tets.dtype == np.int64
    with pytest.raises(ValueError, match=r"\[0, 5\)"):
        TetMesh(v, [[0, 1, 2, 5]])
    with pytest.raises(ValueError, match="shape"):
        TetMesh(v, [[0, 1, 2]])
    with pytest.raises(ValueError, match="finite"):
        TetMesh(np.full((4, 3), np.nan), [[0, 1, 2, 3]])
    faces, owner = fixed.boundary_faces()
    assert len(faces) == 6 and set(owner.tolist()) == {0, 1}  # the two tets share one face
    assert len(fixed.edges()) == 9


def test_knee_mesh_is_positive_conforming_and_fills_its_cubes(knee, knee_mesh, record_property):
    mesh, mask = knee_mesh, knee["mask"]
    g = mask.geometry
    vol = mesh.signed_volumes()
    assert vol.min() > 0
    assert np.array_equal(np.unique(mesh.tets), np.arange(mesh.n_vertices))  # no unused vertex
    assert connected_components(mesh.edge_graph(), directed=False)[0] == 1
    cubes, (nx_, ny_, nz_) = lattice_cubes(mask, KNEE_STEP)
    assert mesh.n_tets == 6 * cubes.sum()  # the knee is one piece at this step: every body cube is meshed
    hz, hy, hx = np.diff(nz_) * g.spacing[2], np.diff(ny_) * g.spacing[1], np.diff(nx_) * g.spacing[0]
    cube_mm3 = np.multiply.outer(np.multiply.outer(hz, hy), hx)
    assert vol.sum() == pytest.approx(cube_mm3[cubes].sum(), rel=1e-12)  # exact up to summation round-off
    faces, _ = mesh.boundary_faces()
    q = mesh.vertices[faces]
    enclosed = np.einsum("ij,ij->i", q[:, 0], np.cross(q[:, 1], q[:, 2])).sum() / 6
    assert enclosed == pytest.approx(vol.sum(), rel=1e-9)  # boundary faces oriented outward
    # A voxel centre strictly inside a body cube is covered exactly once; none outside every body cube's
    # closed block is covered at all.
    tet, _, count = rasterize(mesh, g)
    assert count.max() == 1
    cz, cy, cx = np.nonzero(cubes)
    keep = (np.diff(nz_)[cz] == 2) & (np.diff(ny_)[cy] == 2) & (np.diff(nx_)[cx] == 2)  # cubes with a centre voxel
    assert np.all(tet[nz_[cz[keep]] + 1, ny_[cy[keep]] + 1, nx_[cx[keep]] + 1] >= 0)
    near = np.zeros(g.array_shape, bool)
    for dz in range(3):
        for dy in range(3):
            for dx in range(3):
                near[
                    np.minimum(nz_[cz] + dz, nz_[cz + 1]),
                    np.minimum(ny_[cy] + dy, ny_[cy + 1]),
                    np.minimum(nx_[cx] + dx, nx_[cx + 1]),
                ] = True  # the cubes' closed blocks
    assert not np.any(tet[~near] >= 0)
    body = mask.data.astype(bool)
    print(
        f"\nknee lattice mesh (step {KNEE_STEP}): {mesh.n_vertices} vertices, {mesh.n_tets} tets in "
        f"{knee['seconds']['mesh']:.2f} s; body voxel centres in the mesh {100 * np.mean(tet[body] >= 0):.1f} %, "
        f"air voxel centres {100 * np.mean(tet[~body] >= 0):.1f} %"
    )
    record_property("knee_tet_vertices", mesh.n_vertices)
    record_property("knee_tets", mesh.n_tets)


# ---------------------------------------------------------------------------------------------
# Rasterisation and point location
# ---------------------------------------------------------------------------------------------


def _kuhn_tets(corners: np.ndarray) -> np.ndarray:
    """The 6 tets of a (deformed) cube whose 8 corners are indexed by bits (x + 2y + 4z)."""
    paths = [(1, 2, 4), (1, 4, 2), (2, 1, 4), (2, 4, 1), (4, 1, 2), (4, 2, 1)]
    return np.array([[0, a, a + b, 7] for a, b, _ in paths], dtype=np.int64)


def _brute_force(mesh: TetMesh, points: np.ndarray):
    """Barycentric coordinates of every point in every tet, (n_points, n_tets, 4)."""
    p = mesh.vertices[mesh.tets]
    d = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    inv = np.linalg.inv(d)
    lam123 = np.einsum("tij,ntj->nti", inv, points[:, None, :] - p[None, :, 0])
    return np.concatenate([1 - lam123.sum(axis=2, keepdims=True), lam123], axis=2)


def _analytic_mesh(g: GridGeometry) -> TetMesh:
    """A sheared cube (6 Kuhn tets) inside the grid, plus one extra tet overlapping it (a 'fold')."""
    rng = np.random.default_rng(11)
    bits = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=float)
    ijk = 1.37 + bits * (np.array(g.size) - 3.1) + rng.uniform(-0.3, 0.3, (8, 3))
    corners = g.index_to_world(ijk)
    extra = g.index_to_world(np.array([[2.2, 2.9, 1.6], [8.3, 3.1, 2.4], [3.3, 8.2, 2.1], [4.1, 4.4, 6.7]]))
    tets = np.vstack([_kuhn_tets(corners), [[8, 9, 10, 11]]])
    return TetMesh(np.vstack([corners, extra]), tets).oriented()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_rasterize_matches_brute_force_on_rotated_anisotropic_grid(dtype):
    g = _rotated_grid()
    mesh = _analytic_mesh(g)
    assert mesh.signed_volumes().min() > 0
    centres = g.world_coordinates().reshape(-1, 3)
    lam = _brute_force(mesh, centres)
    ambiguous = np.any(np.abs(lam) < 1e-9, axis=2).any(axis=1)
    assert ambiguous.sum() == 0  # no voxel centre on a face: containment is clear-cut here
    inside = np.all(lam > 0, axis=2)  # (n, m)
    want_count = inside.sum(axis=1)
    want_tet = np.where(want_count > 0, np.argmax(inside, axis=1), -1)  # lowest containing tet

    tet, bary, count = rasterize(mesh, g, dtype=dtype)
    assert tet.shape == g.array_shape and bary.shape == g.array_shape + (4,) and bary.dtype == dtype
    np.testing.assert_array_equal(count.reshape(-1), want_count)
    np.testing.assert_array_equal(tet.reshape(-1), want_tet)
    assert want_count.max() == 2 and (want_count == 1).sum() > 100  # the extra tet really overlaps
    hit = tet.reshape(-1) >= 0
    b = bary.reshape(-1, 4)[hit].astype(np.float64)
    rec = np.einsum("nc,ncx->nx", b, mesh.vertices[mesh.tets[tet.reshape(-1)[hit]]])
    tol = 1e-9 if dtype == np.float64 else 1e-4
    np.testing.assert_allclose(rec, centres[hit], atol=tol, rtol=0)
    np.testing.assert_allclose(b.sum(axis=1), 1.0, atol=tol / 10)
    assert b.min() >= 0
    assert np.all(bary.reshape(-1, 4)[~hit] == 0)
    # locate agrees with the rasteriser at the voxel centres, and is exact in float64.
    lt, lb, lin = locate(mesh, centres)
    np.testing.assert_array_equal(lt[lin], tet.reshape(-1)[lin])
    np.testing.assert_array_equal(lin, hit)
    rec = np.einsum("nc,ncx->nx", lb[lin], mesh.vertices[mesh.tets[lt[lin]]])
    np.testing.assert_allclose(rec, centres[lin], atol=1e-9, rtol=0)


def test_points_on_shared_faces_are_covered_exactly_once():
    """An axis-aligned cube cut into 6 tets: many voxel centres lie on the shared diagonal faces."""
    g = GridGeometry((9, 9, 9), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    bits = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=float)
    mesh = TetMesh(1.0 + 6.0 * bits, _kuhn_tets(bits)).oriented()
    _, _, count = rasterize(mesh, g)
    assert count.max() == 1
    assert np.all(count[2:7, 2:7, 2:7] == 1)  # every interior centre once, on the diagonal planes too
    # locate: the same points, the same tet choice
    pts = g.world_coordinates()[2:7, 2:7, 2:7].reshape(-1, 3)
    t_r, _, _ = rasterize(mesh, g)
    t_l, _, inside = locate(mesh, pts)
    assert inside.all()
    np.testing.assert_array_equal(t_l, t_r[2:7, 2:7, 2:7].reshape(-1))


def test_points_a_hair_off_a_shared_face_are_claimed_by_exactly_one_tet():
    """A flat and a tall tet share a face: within round-off of it, exactly one of them claims a point."""
    v = np.array([[0.0, 0, 0], [10, 0.3, 0.1], [0.2, 10, -0.1], [3, 3, 1e-3], [3, 3, -25.0]])
    mesh = TetMesh(v, [[0, 1, 2, 3], [0, 2, 1, 4]]).oriented()
    assert mesh.signed_volumes().min() > 0
    rng = np.random.default_rng(2)
    bc = rng.dirichlet(np.ones(3), 150)
    on_face = bc @ v[:3]
    normal = np.cross(v[1] - v[0], v[2] - v[0])
    normal /= np.linalg.norm(normal)
    offsets = rng.choice([-1e-9, -1e-12, -1e-15, 0.0, 1e-15, 1e-12, 1e-9], size=150)
    for p in on_face + offsets[:, None] * normal:
        _, _, count = rasterize(mesh, GridGeometry((1, 1, 1), (1.0, 1.0, 1.0), p))
        assert count[0, 0, 0] == 1


def test_mesh_vertices_are_located_in_one_of_their_own_tets(knee_mesh):
    """A vertex lies on many faces at once: the tie rule still puts it in exactly one incident tet."""
    mesh = knee_mesh
    tet, bary, inside = locate(mesh, mesh.vertices)
    interior = np.ones(mesh.n_vertices, bool)
    interior[mesh.boundary_vertices()] = False
    assert inside[interior].all()
    own = mesh.tets[tet] == np.arange(mesh.n_vertices)[:, None]
    assert own[inside].any(axis=1).all()
    np.testing.assert_allclose(bary[own & inside[:, None]], 1.0, atol=1e-9)


def test_locate_outside_points_take_the_nearest_boundary_point(knee_mesh):
    mesh = knee_mesh
    faces, _ = mesh.boundary_faces()
    rng = np.random.default_rng(5)
    pick = rng.choice(len(faces), 300, replace=False)
    p = mesh.vertices[faces[pick]]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    foot = p.mean(axis=1)
    out_pts = foot + 0.7 * n  # 0.7 mm outside, above a face centroid
    tet, bary, inside = locate(mesh, out_pts)
    # Where the skin has a tight crease, 0.7 mm along the normal can re-enter the mesh.
    assert inside.mean() < 0.05
    tet, bary, out_pts, foot = tet[~inside], bary[~inside], out_pts[~inside], foot[~inside]
    assert bary.min() >= 0 and np.allclose(bary.sum(axis=1), 1.0)
    proj = np.einsum("nc,ncx->nx", bary, mesh.vertices[mesh.tets[tet]])
    d = np.linalg.norm(proj - out_pts, axis=1)
    assert d.max() <= 0.7 + 1e-6  # the projection is at least as near as the face we started from
    assert np.median(np.linalg.norm(proj - foot, axis=1)) < 1e-6
    with pytest.raises(ValueError, match="finite"):
        locate(mesh, [[np.nan, 0, 0]])


# ---------------------------------------------------------------------------------------------
# Harmonic weights on the knee
# ---------------------------------------------------------------------------------------------


def test_harmonic_weights_are_a_partition_of_unity_fixed_on_bones(knee_mesh, knee_weights, record_property):
    w, info = knee_weights
    assert w.shape == (knee_mesh.n_vertices, 4) and info["bones"] == ("femur", "tibia", "fibula", "patella")
    assert w.min() >= 0 and w.max() <= 1
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    bov = info["bone_of_vertex"]
    for k, b in enumerate(info["bones"]):
        assert info["n_constrained"][b] >= 3, b
        np.testing.assert_array_equal(w[bov == k, k], 1.0)
        np.testing.assert_array_equal(np.delete(w[bov == k], k, axis=1), 0.0)
    assert info["sum_error_raw"] < 1e-9
    print(
        f"\nharmonic solve: {info['n_free']} free vertices, constrained {info['n_constrained']}, "
        f"raw range [{info['raw_min']:.3g}, {info['raw_max']:.6f}], clipped ≤ {info['clipped_max']:.2g} "
        f"({100 * info['clipped_fraction']:.2f} % of free entries), {info['seconds_total']:.2f} s "
        f"({', '.join(f'{k} {v:.2f}' for k, v in info['seconds'].items())})"
    )
    record_property("harmonic_seconds", info["seconds_total"])
    record_property("harmonic_clipped_max", info["clipped_max"])


def test_harmonic_weights_solve_laplace_and_obey_the_maximum_principle(knee_mesh, knee_weights):
    w, info = knee_weights
    raw, bov = info["raw"], info["bone_of_vertex"]
    free = bov < 0
    L = stiffness_matrix(knee_mesh)
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0.0, atol=1e-9 * abs(L).max())
    r = L @ raw
    assert np.abs(r[free]).max() < 1e-9 * np.abs(r[~free]).max()  # harmonic at the free vertices
    assert info["residual"] < 1e-9
    # Maximum principle: the lattice's stiffness matrix is an M-matrix, so no weight leaves [0, 1] beyond the
    # LU solve's round-off (a few ulp) and clipping removes nothing more (on fTetWild's meshes, with positive
    # off-diagonals at obtuse dihedral angles, it could)
    assert -1e-12 <= raw[free].min() and raw[free].max() <= 1.0 + 1e-12
    assert info["clipped_max"] <= 1e-12


@pytest.mark.parametrize("level", [1e-3, 0.05, 0.5])
def test_no_island_of_influence(knee_mesh, knee_weights, level):
    """Every region where a bone's weight exceeds ``level`` holds vertices of that bone (maximum
    principle); at low levels it is a single region containing the whole bone."""
    w, info = knee_weights
    graph = knee_mesh.edge_graph()
    for k, b in enumerate(info["bones"]):
        s = np.flatnonzero(w[:, k] > level)
        n, lab = connected_components(graph[s][:, s], directed=False)
        on_bone = info["bone_of_vertex"][s] == k
        assert np.all(np.isin(np.arange(n), lab[on_bone])), f"{b}: a region of weight > {level} without the bone"
        if level <= 0.05:
            assert n == 1, f"{b}: {n} regions of weight > {level}: sizes {np.bincount(lab).tolist()}"
            assert on_bone.sum() == np.sum(info["bone_of_vertex"] == k)


def test_bone_without_vertices_is_an_error_or_snapped(knee, knee_mesh):
    labels = knee["labels"]
    g = labels.geometry
    hit = np.floor(g.world_to_index(knee_mesh.vertices) + 0.5).astype(int)
    taken = np.zeros(g.array_shape, bool)
    ok = np.all((hit >= 0) & (hit < g.size), axis=1)
    taken[hit[ok, 2], hit[ok, 1], hit[ok, 0]] = True
    candidates = np.argwhere(knee["mask"].data.astype(bool) & (labels.data == 0) & ~taken)
    k, j, i = candidates[len(candidates) // 2]
    data = labels.data.copy()
    data[k, j, i] = 9  # a one-voxel "sesamoid" no vertex falls into
    tiny = Volume(data, g)
    bl = dict(knee["bone_labels"], sesamoid=9)
    with pytest.raises(ValueError, match=r"sesamoid.*smaller lattice step"):
        harmonic_weights(knee_mesh, tiny, bl)
    w, info = harmonic_weights(knee_mesh, tiny, bl, snap_missing=True)
    assert info["snapped"] == ["sesamoid"] and info["n_constrained"]["sesamoid"] == 1
    v = int(np.flatnonzero(info["bone_of_vertex"] == 4)[0])
    # the nearest free vertex: within a lattice cube's diagonal of the voxel (the cube around it has 8 nodes)
    assert np.linalg.norm(knee_mesh.vertices[v] - g.index_to_world([i, j, k])) < np.linalg.norm(
        KNEE_STEP * np.asarray(g.spacing)
    )
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="no voxels"):
        harmonic_weights(knee_mesh, labels, dict(knee["bone_labels"], ghost=42))
    bov, snapped = constrained_vertices(knee_mesh, labels, knee["bone_labels"])
    np.testing.assert_array_equal(bov, harmonic_weights(knee_mesh, labels, knee["bone_labels"])[1]["bone_of_vertex"])
    # the voxel weights the weights stage asks for (snap_missing=True: a lattice coarser than a tiny bone holds
    # no vertex in it, which must not fail the stage): the bone's voxel is one-hot for it, the weights sum to one
    told = []
    r = harmonic_voxel_weights(tiny, bl, knee["mask"], mesh=knee_mesh, snap_missing=True, progress=told.append)
    assert r.info["snapped"] == "sesamoid" and any("sesamoid" in m for m in told)
    col = list(bl).index("sesamoid")
    assert np.count_nonzero(r.vertex_weights[:, col] == 1.0) == 1  # the one snapped vertex is fixed to it
    np.testing.assert_allclose(r.vertex_weights.sum(axis=1), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="sesamoid"):
        harmonic_voxel_weights(tiny, bl, knee["mask"], mesh=knee_mesh)


# ---------------------------------------------------------------------------------------------
# Weights of voxels and points
# ---------------------------------------------------------------------------------------------


def _reference_grid_dense(mesh, w, geometry, labels, lut):
    """NumPy reference of weights_on_grid before truncation: dense (n_voxels, n_bones)."""
    tet, bary, _ = rasterize(mesh, geometry, dtype=np.float64)
    tet, bary = tet.reshape(-1), bary.reshape(-1, 4)
    dense = np.zeros((geometry.n_voxels, w.shape[1]))
    inside = tet >= 0
    dense[inside] = np.einsum("nc,ncb->nb", bary[inside], w[mesh.tets[tet[inside]]])
    bverts = mesh.boundary_vertices()
    tie = 1e-6 * min(geometry.spacing) * TIE_DIRECTION  # ties (common on a lattice) by a hair along TIE_DIRECTION
    _, q = cKDTree(mesh.vertices[bverts]).query(geometry.world_coordinates().reshape(-1, 3)[~inside] + tie)
    dense[~inside] = w[bverts[q]]
    bone = lut[labels.data.reshape(-1)]
    dense[bone >= 0] = np.eye(w.shape[1])[bone[bone >= 0]]
    return dense, bone


def test_voxel_weights_on_the_knee(knee, knee_mesh, knee_weights, knee_grid_weights, record_property):
    w, info = knee_weights
    sw, seconds = knee_grid_weights
    g, labels = knee["template"].geometry, knee["labels"]
    assert isinstance(sw, SkinningWeights) and sw.n_points == g.n_voxels and sw.max_influences == 4
    assert sw.value.min() >= 0
    np.testing.assert_allclose(sw.value.astype(np.float64).sum(axis=1), 1.0, atol=1e-6)
    lut = np.full(256, -1)
    for k, b in enumerate(info["bones"]):
        lut[knee["bone_labels"][b]] = k
    dense_ref, bone = _reference_grid_dense(knee_mesh, w, g, labels, lut)
    on_bone = bone >= 0
    assert on_bone.sum() == np.count_nonzero(labels.data)
    assert np.all(sw.value[on_bone, 0] == 1) and np.all(sw.value[on_bone, 1:] == 0)
    np.testing.assert_array_equal(sw.index[on_bone, 0], bone[on_bone])
    np.testing.assert_allclose(sw.dense(), dense_ref / dense_ref.sum(axis=1, keepdims=True), atol=2e-6)
    # At most two influences: the two largest of the same blend, renormalised.
    sw2 = weights_on_grid(knee_mesh, w, info["bones"], g, labels, knee["bone_labels"], max_influences=2)
    assert sw2.max_influences == 2
    ref2 = SkinningWeights.from_dense(dense_ref, info["bones"], max_influences=2)
    np.testing.assert_allclose(sw2.dense(), ref2.dense(), atol=2e-6)
    with pytest.raises(ValueError, match="outside the tet mesh"):
        weights_on_grid(knee_mesh, w, info["bones"], g, labels, knee["bone_labels"], outside="raise")
    print(f"\nweights_on_grid: {g.size} grid in {seconds:.2f} s")
    record_property("weights_on_grid_seconds", seconds)


def test_compare_with_distance_weights(knee, knee_grid_weights, record_property):
    """Harmonic vs distance-based weights on the knee's soft tissue: recorded, only sanity asserted."""
    sw, _ = knee_grid_weights
    g, labels, body = knee["template"].geometry, knee["labels"], knee["mask"].data.astype(bool)
    spacing_zyx = np.asarray(g.spacing)[::-1]
    dist = np.empty((g.n_voxels, sw.n_bones))
    for k, b in enumerate(sw.bones):
        in_bone = labels.data == knee["bone_labels"][b]
        d = ndimage.distance_transform_edt(~in_bone, sampling=spacing_zyx) - ndimage.distance_transform_edt(
            in_bone, sampling=spacing_zyx
        )
        dist[:, k] = d.reshape(-1)
    dw = distance_weights(dist, sw.bones)
    soft = (body & (labels.data == 0)).reshape(-1)
    h, d = sw.dense()[soft], dw.dense()[soft]
    tv = 0.5 * np.abs(h - d).sum(axis=1)  # total-variation distance per voxel, in [0, 1]
    same = np.mean(h.argmax(axis=1) == d.argmax(axis=1))
    print(
        f"\nharmonic vs distance weights over {soft.sum()} soft-tissue voxels: mean TV distance "
        f"{tv.mean():.3f} (median {np.median(tv):.3f}, 95th pct {np.percentile(tv, 95):.3f}); "
        f"same dominant bone {100 * same:.1f} %; mean influences > 1 %: harmonic "
        f"{(h > 0.01).sum(axis=1).mean():.2f}, distance {(d > 0.01).sum(axis=1).mean():.2f}"
    )
    record_property("harmonic_vs_distance_mean_tv", float(tv.mean()))
    record_property("harmonic_vs_distance_same_dominant", float(same))
    assert 0 <= tv.mean() < 1 and same > 0.5


def test_weights_at_points(knee, knee_mesh, knee_weights):
    w, info = knee_weights
    at_vertices = weights_at_points(knee_mesh, w, info["bones"], knee_mesh.vertices)
    np.testing.assert_allclose(at_vertices.dense(), w, atol=1e-6)
    skin = knee["surface"].vertices  # the skin mesh: some vertices lie slightly outside the tet mesh
    _, _, inside = locate(knee_mesh, skin)
    sw = weights_at_points(knee_mesh, w, info["bones"], skin, max_influences=3)
    assert sw.n_points == len(skin) and sw.max_influences == 3
    np.testing.assert_allclose(sw.value.astype(np.float64).sum(axis=1), 1.0, atol=1e-6)
    print(f"\nskin vertices outside the tet mesh: {(~inside).sum()} of {len(skin)}")


def test_same_vtu_file_gives_identical_weights(knee, tmp_path):
    """Everything downstream of the mesh file is deterministic."""
    g = knee["template"].geometry
    results = []
    for _ in range(2):
        mesh, _ = read_tetmesh(knee["path"])
        w, info = harmonic_weights(mesh, knee["labels"], knee["bone_labels"])
        sw = weights_on_grid(mesh, w, info["bones"], g, knee["labels"], knee["bone_labels"])
        results.append((w, sw))
    (w1, s1), (w2, s2) = results
    assert np.array_equal(w1, w2)
    assert np.array_equal(s1.index, s2.index) and np.array_equal(s1.value, s2.value)
    # The weights stored with the mesh (one array per bone) come back exactly.
    out = write_tetmesh(mesh, tmp_path / "weights.vtu", point_data=weight_arrays(info["bones"], w1))
    _, pd = read_tetmesh(out)
    assert list(pd) == [f"weight_{b}" for b in info["bones"]]
    np.testing.assert_array_equal(np.stack(list(pd.values()), axis=1), w1)


def test_input_checks(knee, knee_mesh, knee_weights):
    w, info = knee_weights
    g = knee["template"].geometry
    other = GridGeometry(g.size, g.spacing, np.asarray(g.origin) + 1.0, g.direction)
    with pytest.raises(ValueError, match="grid geometries differ"):
        weights_on_grid(knee_mesh, w, info["bones"], other, knee["labels"], knee["bone_labels"])
    with pytest.raises(ValueError, match="vertex_dense"):
        weights_on_grid(knee_mesh, w[:, :3], info["bones"], g, knee["labels"], knee["bone_labels"])
    with pytest.raises(ValueError, match="no weight column"):
        weights_on_grid(knee_mesh, w, info["bones"], g, knee["labels"], dict(knee["bone_labels"], ulna=7))


def test_bounded_biharmonic_weights_solve_their_quadratic_program(knee, knee_mesh, knee_weights):
    # BBW (libigl) on the same mesh and constraints as the harmonic weights: a partition of unity in [0, 1],
    # one-hot on the bones, and — each column minimising the Laplacian energy wᵀ L M⁻¹ L w over the bones'
    # values and 0 ≤ w ≤ 1 — no column's energy above that of the harmonic column, which is feasible after
    # clipping (checked to 1e-6 relative: the active-set solver's tolerance)
    igl = pytest.importorskip("igl", reason="libigl is in the bench extra: pip install -e '.[bench]'")
    import scipy.sparse as sp_

    from deformation.models.harmonic import bbw_weights

    w, info = bbw_weights(knee_mesh, knee["labels"], knee["bone_labels"])
    hw, hinfo = knee_weights
    assert w.shape == hw.shape and info["bones"] == hinfo["bones"]
    assert w.min() >= 0 and w.max() <= 1
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-9)
    bov = hinfo["bone_of_vertex"]
    for k in range(w.shape[1]):
        np.testing.assert_array_equal(w[bov == k, k], 1.0)
    v, t = knee_mesh.vertices.astype(np.float64), knee_mesh.tets.astype(np.int64)
    lap = igl.cotmatrix(v, t)
    mass = igl.massmatrix(v, t)
    q = lap.T @ sp_.diags(1.0 / mass.diagonal()) @ lap
    harm = np.clip(hinfo["raw"], 0.0, 1.0)
    for k in range(w.shape[1]):
        col = np.clip(info["raw"][:, k], 0.0, 1.0)
        e_bbw, e_harm = float(col @ (q @ col)), float(harm[:, k] @ (q @ harm[:, k]))
        assert e_bbw <= e_harm * (1 + 1e-6), (k, e_bbw, e_harm)
