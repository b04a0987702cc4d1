"""The lattice tetrahedralisation of a mask (deformation.meshes.tetmesh.lattice_tetmesh: Kuhn / Freudenthal) and the
harmonic weights on it (deformation.models.harmonic): geometry, the majority rule, conformity, the M-matrix stiffness,
exact linear weights, the maximum principle, and the same bytes from two processes."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.tetmesh import lattice_cubes, lattice_nodes, lattice_step, lattice_tetmesh
from deformation.models.harmonic import harmonic_voxel_weights, harmonic_weights, stiffness_matrix

SPACING = (0.7, 1.3, 2.1)  # anisotropic: 1 : 1.9 : 3
DIRECTIONS = {
    "identity": np.eye(3),
    "permuted-flipped": np.array([[0.0, -1, 0], [0, 0, 1], [1, 0, 0]]),  # det −1: a reflection
    "rotated": Rotation.from_euler("zyx", [31.0, -17.0, 52.0], degrees=True).as_matrix(),
}


def _grid(size, direction="rotated", spacing=SPACING) -> GridGeometry:
    return GridGeometry(size, spacing, (3.0, -2.0, 5.0), DIRECTIONS[direction].reshape(-1))


def _blob(g: GridGeometry) -> Volume:
    """An ellipsoid with a box-shaped arm (in index space), one piece."""
    k, j, i = np.indices(g.array_shape, dtype=float)
    nx, ny, nz = g.size
    ell = ((i - 0.4 * nx) / (0.33 * nx)) ** 2 + ((j - 0.5 * ny) / (0.4 * ny)) ** 2 + ((k - 0.5 * nz) / (0.42 * nz)) ** 2
    arm = (i >= 0.5 * nx) & (i <= nx - 2) & (np.abs(j - 0.5 * ny) <= 1.5) & (np.abs(k - 0.5 * nz) <= 1.5)
    return Volume((ell <= 1.0) | arm, g)


def _cube_sides(g: GridGeometry, nodes):
    """Side lengths (mm) of the lattice cubes along x, y, z."""
    return tuple(np.diff(n) * h for n, h in zip(nodes, g.spacing))


def _faces(tets: np.ndarray) -> np.ndarray:
    return np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)


@pytest.mark.parametrize("direction", list(DIRECTIONS))
@pytest.mark.parametrize("step", [1, (2, 1, 3)])
def test_lattice_mesh_geometry_volume_and_conformity(direction, step):
    g = _grid((16, 13, 11), direction)
    mask = _blob(g)
    mesh = lattice_tetmesh(mask, step=step, keep_largest_component=False)
    s = np.broadcast_to(step, (3,))
    nodes = tuple(lattice_nodes(n, si) for n, si in zip(g.size, s))
    # Vertices: exactly the world positions of voxel centres at lattice nodes.
    ijk = g.world_to_index(mesh.vertices)
    ijk_int = np.rint(ijk)
    assert np.abs(ijk - ijk_int).max() < 1e-9
    for a in range(3):
        assert np.isin(ijk_int[:, a], nodes[a]).all()
    np.testing.assert_array_equal(mesh.vertices, g.index_to_world(ijk_int))  # the same bits
    kk, jj, ii = ijk_int[:, 2].astype(int), ijk_int[:, 1].astype(int), ijk_int[:, 0].astype(int)
    np.testing.assert_allclose(mesh.vertices, g.world_coordinates()[kk, jj, ii], atol=1e-9, rtol=0)
    # The majority rule, brute force: a cube is in when strictly more than half of its block is body.
    cubes, _ = lattice_cubes(mask, step)
    want = np.zeros_like(cubes)
    for c in np.ndindex(cubes.shape):
        (z0, z1), (y0, y1), (x0, x1) = ((nodes[2 - a][c[a]], nodes[2 - a][c[a] + 1]) for a in range(3))
        block = mask.data[z0 : z1 + 1, y0 : y1 + 1, x0 : x1 + 1]
        want[c] = 2 * block.sum() > block.size
    np.testing.assert_array_equal(cubes, want)
    assert 0 < cubes.sum() < cubes.size
    # Every tetrahedron positive and a sixth of its cube; the total is the cubes' volume (summation round-off).
    hx, hy, hz = _cube_sides(g, nodes)
    cube_mm3 = np.multiply.outer(np.multiply.outer(hz, hy), hx)
    vol = mesh.signed_volumes()
    assert mesh.n_tets == 6 * cubes.sum() and vol.min() > 0
    np.testing.assert_allclose(np.sort(vol), np.sort(np.repeat(cube_mm3[cubes] / 6, 6)), rtol=1e-12)
    assert vol.sum() == pytest.approx(cube_mm3[cubes].sum(), rel=1e-12)
    # Conforming: no face in more than two tets, and the faces in one tet make up exactly the surface of the
    # union of the cubes (a cube cut along another diagonal than its neighbour's would leave both halves of
    # their shared face on the boundary, adding its area).
    key, counts = np.unique(_faces(mesh.tets), axis=0, return_counts=True)
    assert counts.max() == 2
    bf = key[counts == 1]
    p = mesh.vertices[bf]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    want_area = 0.0
    for axis, face_mm2 in (
        (2, np.multiply.outer(hz, hy)[:, :, None]),
        (1, np.multiply.outer(hz, hx)[:, None, :]),
        (0, np.multiply.outer(hy, hx)[None, :, :]),
    ):
        padded = np.pad(cubes, [(1, 1) if a == axis else (0, 0) for a in range(3)])
        exposed = np.diff(padded.astype(np.int8), axis=axis) != 0  # between a cube and a non-cube
        want_area += (exposed * face_mm2).sum()
    assert area == pytest.approx(want_area, rel=1e-12)


def test_stiffness_of_a_lattice_is_the_seven_point_stencil():
    """On an anisotropic, rotated box the P1 stiffness is an M-matrix: no positive off-diagonal beyond
    round-off; with round-off zeros dropped, interior rows are exactly 7-point: −H_y H_z / H_x to each x
    neighbour (and so on), 2 Σ on the diagonal, with H = step × spacing."""
    for step in (1, (2, 1, 3)):
        g = _grid((11, 9, 13), "rotated")
        mesh = lattice_tetmesh(Volume(np.ones(g.array_shape, bool), g), step=step)
        raw = stiffness_matrix(mesh, drop_tol=0.0).tocoo()
        off = raw.row != raw.col
        diag = raw.tocsr().diagonal()
        # round-off of exact zeros (face and body diagonals): float64 products of ~1/H² terms, ≲ 1e-15 relative
        assert raw.data[off].max() <= 1e-12 * diag.max(), raw.data[off].max() / diag.max()
        L = stiffness_matrix(mesh).tocsr()
        Lc = L.tocoo()
        assert Lc.data[Lc.row != Lc.col].max() < 0  # every stored off-diagonal strictly negative
        np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0.0, atol=1e-12 * diag.max())
        H = np.broadcast_to(step, (3,)) * np.asarray(g.spacing)
        ijk = np.rint(g.world_to_index(mesh.vertices)).astype(int)
        nodes = [lattice_nodes(n, s) for n, s in zip(g.size, np.broadcast_to(step, (3,)))]
        # interior: the node and its 6 neighbours inside, every cube around it a full step
        interior = np.ones(mesh.n_vertices, bool)
        for a in range(3):
            pos = np.searchsorted(nodes[a], ijk[:, a])
            interior &= (pos >= 1) & (pos <= len(nodes[a]) - 3)  # not the first, last, or next-to-last node
        assert interior.sum() > 10
        want_off = {a: -np.prod(np.delete(H, a)) / H[a] for a in range(3)}
        for v in np.flatnonzero(interior):
            cols = L.indices[L.indptr[v] : L.indptr[v + 1]]
            vals = L.data[L.indptr[v] : L.indptr[v + 1]]
            assert cols.size == 7, cols.size  # itself and 6 axis neighbours
            for c, x in zip(cols, vals):
                d = ijk[c] - ijk[v]
                if c == v:
                    assert x == pytest.approx(-2 * sum(want_off.values()), rel=1e-12)
                else:
                    (a,) = np.flatnonzero(d)
                    assert abs(d[a]) == H[a] / g.spacing[a]
                    assert x == pytest.approx(want_off[a], rel=1e-12)


@pytest.mark.parametrize("direction", ["permuted-flipped", "rotated"])
def test_harmonic_weights_between_two_slabs_are_linear(direction):
    """Bones at x = 0, 1 and x = 10, 11 of a box: the harmonic weight is linear in x (its Laplacian is 0 and
    its normal derivative on the sides is 0), and P1 elements reproduce linear functions exactly: round-off
    of a direct solve on ~600 unknowns (≲ 1e-13) is all that is left."""
    g = _grid((12, 7, 6), direction)
    labels = np.zeros(g.array_shape, np.uint8)
    labels[:, :, :2] = 1
    labels[:, :, 10:] = 2
    body = Volume(np.ones(g.array_shape, bool), g)
    mesh = lattice_tetmesh(body, step=(1, 2, 2))
    w, info = harmonic_weights(mesh, Volume(labels, g), {"a": 1, "b": 2})
    i = np.rint(g.world_to_index(mesh.vertices)[:, 0])
    want_a = np.clip((10 - i) / 9, 0, 1)
    np.testing.assert_allclose(w[:, 0], want_a, atol=1e-12, rtol=0)
    np.testing.assert_allclose(w[:, 1], 1 - want_a, atol=1e-12, rtol=0)
    assert info["clipped_max"] == 0.0 and 0 < info["raw_min"] and info["raw_max"] < 1


@pytest.mark.parametrize("step", [1, 2])
def test_weights_on_an_irregular_body_stay_in_0_1_without_clipping(step):
    """Three bones in the blob on a rotated, anisotropic grid: the discrete maximum principle holds, so the
    raw solution is in [0, 1] up to round-off and clipping changes nothing more; the voxel weights are a
    partition of unity."""
    g = _grid((16, 13, 11), "rotated")
    body = _blob(g)
    labels = np.zeros(g.array_shape, np.uint8)
    k, j, i = np.indices(g.array_shape)
    labels[body.data & (np.abs(i - 3) <= 1) & (np.abs(j - 6) <= 1) & (np.abs(k - 5) <= 1)] = 1
    labels[body.data & (i >= 12) & (i <= 13)] = 2  # the arm's end
    labels[body.data & (np.abs(i - 6) <= 1) & (j >= 9) & (np.abs(k - 5) <= 1)] = 3
    r = harmonic_voxel_weights(
        Volume(labels, g), {"a": 1, "b": 2, "c": 3}, body, mesh=lattice_tetmesh(body, step=step), snap_missing=True
    )
    info = r.info
    # exact arithmetic keeps [0, 1]; the LU solve's round-off (a few ulp, e.g. 1 + 7e-16 at a free vertex whose
    # neighbours are all one bone's) is all that clipping may remove
    assert info["clipped_max"] <= 1e-12
    assert -1e-12 <= info["raw_min"] and info["raw_max"] <= 1.0 + 1e-12
    assert info["sum_error_raw"] < 1e-12  # Σ_k w_k = 1 up to the solve's round-off
    np.testing.assert_allclose(r.weights.value.astype(np.float64).sum(axis=1), 1.0, atol=1e-6)


def test_a_one_voxel_gap_is_not_bridged():
    """Two blocks one voxel of air apart along x: each cube across the gap has exactly half of its corners in
    the body, which is not more than half, so the blocks stay two pieces; the larger is kept."""
    g = GridGeometry((14, 7, 7), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    m = np.zeros(g.array_shape, bool)
    m[1:6, 1:6, 1:7] = True  # x 1..6: 6 planes
    m[1:6, 1:6, 8:13] = True  # x 8..12: 5 planes; x = 7 is air
    cubes, _ = lattice_cubes(Volume(m, g), 1)
    assert not cubes[:, :, 6:8].any() and cubes[:, :, 1:6].any() and cubes[:, :, 8:12].any()
    both = lattice_tetmesh(Volume(m, g), keep_largest_component=False)
    x = np.rint(g.world_to_index(both.vertices)[:, 0])
    assert connected_components(both.edge_graph(), directed=False)[0] == 2
    assert not np.any(x == 7)
    kept = lattice_tetmesh(Volume(m, g))
    x = np.rint(g.world_to_index(kept.vertices)[:, 0])
    assert x.min() == 1 and x.max() == 6 and kept.n_tets == 6 * 4 * 4 * 5
    # at a step of 2 voxels the cube across the gap is mostly body: a gap narrower than the step is bridged
    assert (
        connected_components(
            lattice_tetmesh(Volume(m, g), step=2, keep_largest_component=False).edge_graph(), directed=False
        )[0]
        == 1
    )


def test_lattice_step_and_input_checks():
    g = _grid((16, 13, 11), "rotated")
    mask = _blob(g)
    assert lattice_step(mask, edge_length_mm=2.0) == (3, 2, 1)  # 2/0.7 = 2.9, 2/1.3 = 1.5, 2/2.1 = 0.95
    assert lattice_step(mask, edge_length_mm=0.1) == (1, 1, 1)
    n1 = lattice_tetmesh(mask, step=1).n_vertices
    assert lattice_step(mask) == (1, 1, 1) and lattice_step(mask, max_vertices=n1) == (1, 1, 1)
    s = lattice_step(mask, max_vertices=n1 - 1)[0]
    assert s > 1 and lattice_tetmesh(mask, step=s).n_vertices <= n1 - 1
    assert lattice_tetmesh(mask, step=s - 1).n_vertices > n1 - 1  # the smallest step that fits
    np.testing.assert_array_equal(lattice_nodes(11, 3), [0, 3, 6, 9, 10])
    np.testing.assert_array_equal(lattice_nodes(10, 3), [0, 3, 6, 9])
    for bad in (0, 1.5, (1, 2), -1):
        with pytest.raises(ValueError, match="whole numbers of voxels"):
            lattice_tetmesh(mask, step=bad)
    with pytest.raises(ValueError, match="edge_length_mm must be positive"):
        lattice_step(mask, edge_length_mm=0)
    with pytest.raises(ValueError, match="no lattice cube"):
        lattice_tetmesh(Volume(np.zeros(g.array_shape, bool), g))
    with pytest.raises(ValueError, match="one voxel thin"):
        lattice_tetmesh(Volume(np.ones((1, 5, 5), bool), GridGeometry((5, 5, 1), (1, 1, 1), (0, 0, 0))))


_SCRIPT = textwrap.dedent("""
    import sys
    from pathlib import Path
    import numpy as np
    sys.path.insert(0, {tests!r})
    from test_lattice_tetmesh import _blob, _grid
    from deformation.geometry import Volume
    from deformation.models.harmonic import harmonic_voxel_weights
    from workbench.io.tetmeshes import weight_arrays, write_tetmesh
    from workbench.io.weights import write_voxel_weights

    out = Path(sys.argv[1])
    g = _grid((16, 13, 11), "rotated")
    body = _blob(g)
    labels = np.zeros(g.array_shape, np.uint8)
    labels[..., 2:4] = 1
    labels[..., 12:14] = 2
    labels *= body.data
    r = harmonic_voxel_weights(Volume(labels, g), {{"a": 1, "b": 2}}, body)
    write_tetmesh(r.mesh, out / "tetmesh.vtu", point_data=weight_arrays(r.bones, r.vertex_weights))
    write_voxel_weights(r.weights, g, out / "weights.json", **r.info)
""")


def test_the_same_bytes_from_two_processes(tmp_path):
    """Mesh and weights written by two processes with different thread counts and hash seeds: the same files,
    byte for byte."""
    script = tmp_path / "run.py"
    script.write_text(_SCRIPT.format(tests=str(Path(__file__).parent)))
    digests = []
    for k, threads in enumerate(("1", "2")):
        out = tmp_path / f"run{k}"
        out.mkdir()
        env = dict(os.environ, PYTHONHASHSEED=str(k), NUMBA_NUM_THREADS=threads, OMP_NUM_THREADS=threads)
        subprocess.run([sys.executable, str(script), str(out)], check=True, env=env, cwd=tmp_path, timeout=600)
        digests.append({p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(out.iterdir())})
    assert set(digests[0]) == {"tetmesh.vtu", "weights.json", "weights_index.mha", "weights_value.mha"}
    assert digests[0] == digests[1]
