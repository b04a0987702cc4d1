"""Tetrahedral meshes of the body: lattice tetrahedralisation of a mask, rasterisation, point location.

The skinning weights (:mod:`deformation.models.harmonic`) are solved on a mesh of
the body mask made on its own voxel grid:

1. :func:`lattice_step` — the lattice step in voxels along each axis: from an
   edge length in mm, or the mask's own resolution unless that makes more
   than :data:`MAX_LATTICE_VERTICES` vertices;
2. :func:`lattice_tetmesh` — the cubes of the lattice of voxel centres that
   are mostly body (:func:`lattice_cubes`), each split into the 6 Kuhn
   (Freudenthal) tetrahedra about its main diagonal: a conforming,
   positively oriented :class:`TetMesh` whose P1 stiffness matrix is the
   7-point finite-difference Laplacian, an M-matrix.  The mesh is a function
   of the mask and the step alone: the same bits for any number of threads.

Then, for any tet mesh — the template's, or a *deformed* one:

* :func:`rasterize` — for every voxel centre of a grid, the tetrahedron that
  contains it and its barycentric coordinates, plus the number of tetrahedra
  that contain it (> 1 where a deformed mesh folds);
* :func:`locate` — the same for arbitrary points; points outside the mesh
  get the boundary face nearest to them.

Points on a face are decided exactly (:data:`TIE_DIRECTION`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _graph_components

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.mesh import SurfaceMesh, checked_cells

__all__ = [
    "TetMesh",
    "TIE_DIRECTION",
    "MAX_LATTICE_VERTICES",
    "lattice_nodes",
    "lattice_cubes",
    "lattice_step",
    "lattice_tetmesh",
    "rasterize",
    "locate",
]


#: Generic direction (world mm, unit length) deciding points that lie on a face.  A point is in a
#: tetrahedron when all four barycentric coordinates are positive.  Within ``1e-6`` of zero the side is
#: decided by the sign of the face's plane equation evaluated with the face's vertices in ascending index
#: order: the two tetrahedra sharing the face evaluate the identical floating-point expression, so they never
#: both (or neither) claim the point.  A point on a face, edge or vertex to within round-off (voxel centres on
#: regular meshes, a mesh's own vertices) goes where an infinitesimal step along this direction takes it
#: (simulation of simplicity).  So in a conforming, non-folded mesh every interior point is covered exactly
#: once; where several tetrahedra claim a voxel, the one with the lowest index is reported.  Rasterisation
#: bounds each tetrahedron in continuous index space (any orthonormal direction and anisotropic spacing).
TIE_DIRECTION = np.array([0.5896, 0.5463, 0.5949]) / np.linalg.norm([0.5896, 0.5463, 0.5949])
_BAND = 1e-6  # |barycentric| below this: decide the side by the exact-order face test

# Faces of a tetrahedron (a, b, c, d), each oriented outward for a positively oriented tet,
# listed opposite vertex 0, 1, 2, 3.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A tetrahedral mesh.

    Parameters
    ----------
    vertices : (n, 3) array_like
        Vertex positions ``(x, y, z)`` in world mm; stored as float64.
    tets : (m, 4) array_like
        Vertex indices of each tetrahedron; stored as int64.  A mesh made by
        :func:`lattice_tetmesh` is positively oriented (``det[b−a, c−a, d−a] > 0``);
        the class itself accepts any orientation, because a *deformed* mesh may
        hold inverted tetrahedra (see :meth:`signed_volumes`, :meth:`oriented`).

    Raises
    ------
    ValueError
        Wrong shapes, non-finite vertices, or indices outside ``[0, n)``.

    Notes
    -----
    The arrays are read-only; :meth:`with_vertices` makes a deformed copy.
    """

    vertices: np.ndarray
    tets: np.ndarray

    def __post_init__(self):
        v, t = checked_cells(self.vertices, self.tets, 4, "tets")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "tets", t)

    # -- sizes ----------------------------------------------------------------------------
    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def __repr__(self) -> str:
        return f"TetMesh(n_vertices={self.n_vertices}, n_tets={self.n_tets})"

    # -- derived quantities -----------------------------------------------------------------
    def signed_volumes(self) -> np.ndarray:
        """Signed volume of every tetrahedron (mm³), positive for positive orientation."""
        p = self.vertices[self.tets]
        return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0

    def oriented(self) -> TetMesh:
        """The same mesh with every negatively oriented tetrahedron flipped (vertices 2 and 3 swapped)."""
        neg = self.signed_volumes() < 0
        if not np.any(neg):
            return self
        t = self.tets.copy()
        t[neg, 2], t[neg, 3] = self.tets[neg, 3], self.tets[neg, 2]
        return TetMesh(self.vertices, t)

    def with_vertices(self, vertices) -> TetMesh:
        """The same connectivity on new vertex positions (e.g. a deformed mesh)."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.shape != self.vertices.shape:
            raise ValueError(f"need {self.vertices.shape} vertex positions, got {v.shape}")
        return TetMesh(v, self.tets)

    def centroids(self) -> np.ndarray:
        """Centroid of every tetrahedron ``(m, 3)`` mm."""
        return self.vertices[self.tets].mean(axis=1)

    def _cached(self, key: str, compute):
        """Connectivity-derived arrays, computed once per mesh (read-only; the mesh is immutable)."""
        cache = self.__dict__.setdefault("_cache", {})
        if key not in cache:
            value = compute()
            for a in value if isinstance(value, tuple) else (value,):
                a.flags.writeable = False
            cache[key] = value
        return cache[key]

    def edges(self) -> np.ndarray:
        """Unique edges ``(e, 2)`` int64, each with the lower vertex index first, sorted (read-only)."""

        def compute():
            t = self.tets
            pairs = np.concatenate([t[:, [a, b]] for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
            pairs.sort(axis=1)
            n = np.int64(max(self.n_vertices, 1))
            key = np.unique(pairs[:, 0] * n + pairs[:, 1])  # one int64 per edge: sorted as (lower, higher)
            return np.stack([key // n, key % n], axis=1)

        return self._cached("edges", compute)

    def edge_graph(self) -> sp.csr_matrix:
        """Symmetric vertex adjacency ``(n, n)`` of the mesh edges (CSR, int8 ones)."""
        e = self.edges()
        n = self.n_vertices
        rows = np.concatenate([e[:, 0], e[:, 1]])
        cols = np.concatenate([e[:, 1], e[:, 0]])
        return sp.csr_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n, n))

    def boundary_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """Faces used by exactly one tetrahedron (read-only arrays, computed once).

        Returns
        -------
        faces : (f, 3) int64
            Vertex indices, oriented outward when the tetrahedra are positively
            oriented; sorted by their owning tetrahedron, then face.
        owner : (f,) int64
            The tetrahedron each face belongs to.
        """

        def compute():
            faces = self.tets[:, _TET_FACES].reshape(-1, 3)  # (4m, 3) in tet-major order
            key = np.sort(faces, axis=1)
            _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
            once = counts[inverse.reshape(-1)] == 1
            owner = np.repeat(np.arange(self.n_tets, dtype=np.int64), 4)
            return faces[once], owner[once]

        return self._cached("boundary_faces", compute)

    def boundary_vertices(self) -> np.ndarray:
        """Sorted indices of the vertices on the boundary surface (read-only)."""
        return self._cached("boundary_vertices", lambda: np.unique(self.boundary_faces()[0]))

    def boundary_surface(self) -> SurfaceMesh:
        """The boundary faces as a :class:`~deformation.meshes.mesh.SurfaceMesh` over all vertices (interior ones
        unused)."""
        faces, _ = self.boundary_faces()
        return SurfaceMesh(self.vertices, faces)

    def edge_lengths(self) -> np.ndarray:
        """Length of every unique edge (mm)."""
        e = self.edges()
        return np.linalg.norm(self.vertices[e[:, 1]] - self.vertices[e[:, 0]], axis=1)


# ---------------------------------------------------------------------------------------------
# Tetrahedralisation of a mask: the Kuhn (Freudenthal) triangulation of a lattice of voxel centres
# ---------------------------------------------------------------------------------------------

#: Default vertex budget of :func:`lattice_step` (above it the lattice is coarsened): the harmonic weights'
#: sparse LU grows about as the square of the vertex count; at this size it takes some tens of seconds on 2 cores.
MAX_LATTICE_VERTICES = 150_000

# The 6 tetrahedra of a cube whose corners are numbered by bits (x + 2y + 4z): the paths 0 → a → a+b → 7
# along the cube's edges, for the 6 orders of the unit steps a, b, c ∈ {1 (x), 2 (y), 4 (z)}.  All six share
# the main diagonal 0–7.
_KUHN_TETS = np.array([[0, a, a + b, 7] for a, b in ((1, 2), (1, 4), (2, 1), (2, 4), (4, 1), (4, 2))], dtype=np.int64)


def _checked_step(step) -> tuple[int, int, int]:
    """``(sx, sy, sz)`` from one whole number of voxels or three."""
    s = np.asarray(step)
    if s.ndim == 0:
        s = np.repeat(s, 3)
    if s.shape != (3,) or s.dtype.kind not in "iuf" or not np.all(s == np.round(s)) or np.any(s < 1):
        raise ValueError(f"the lattice step must be whole numbers of voxels ≥ 1 (one, or x, y, z), got {step!r}")
    return tuple(int(v) for v in s)


def lattice_nodes(n: int, step: int) -> np.ndarray:
    """Voxel indices of the lattice nodes along an axis of ``n`` voxels: ``0, s, 2s, …`` and ``n − 1``.

    The last voxel is a node even when ``n − 1`` is not a multiple of ``step`` (the last cube is then
    shorter), so that the lattice spans the whole grid.
    """
    nodes = np.arange(0, int(n), int(step), dtype=np.int64)
    return nodes if nodes[-1] == n - 1 else np.append(nodes, n - 1)


def _window_sums(a: np.ndarray, nodes: np.ndarray, axis: int, dtype) -> np.ndarray:
    """Sums of ``a`` along ``axis`` over the inclusive windows ``[nodes[c], nodes[c + 1]]`` (which overlap by
    one plane)."""
    half = np.add.reduceat(a, nodes[:-1], axis=axis, dtype=dtype)  # [nodes[c], nodes[c+1]); the last to the end
    ends = np.take(a, nodes[1:-1], axis=axis).astype(dtype)  # the closing plane of every window but the last
    index = [slice(None)] * a.ndim
    index[axis] = slice(0, len(nodes) - 2)
    half[tuple(index)] += ends
    return half


def lattice_cubes(mask: Volume, step=1) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Which cubes of the lattice of voxel centres with ``step`` voxels per axis are body.

    A cube is body when strictly more than half of the mask's voxels in its block — the voxel centres it
    spans, its corners included, ``(s + 1)³`` of them (its 8 corners for ``step=1``) — are non-zero.

    Returns
    -------
    cubes : (Nz − 1, Ny − 1, Nx − 1) bool
        Indexed ``[z, y, x]`` like the mask; cube ``(c, b, a)`` spans the nodes ``a, a + 1`` along x etc.
    nodes : (x, y, z) tuple of int64 arrays
        The lattice nodes' voxel indices along each axis (:func:`lattice_nodes`).
    """
    if mask.is_vector:
        raise ValueError("a lattice tetrahedralisation needs a scalar mask volume")
    sx, sy, sz = _checked_step(step)
    g = mask.geometry
    nodes = tuple(lattice_nodes(n, s) for n, s in zip(g.size, (sx, sy, sz)))
    m = np.asarray(mask.data) != 0
    if min(len(n) for n in nodes) < 2:
        raise ValueError(f"the mask's grid {g.describe()} is one voxel thin along an axis: no lattice cube fits in it")
    # counts are at most (s+1)³: the smallest unsigned type that holds them keeps the passes light on big grids
    dtype = np.min_scalar_type((sx + 1) * (sy + 1) * (sz + 1))
    count = m
    for axis, nd in ((2, nodes[0]), (1, nodes[1]), (0, nodes[2])):
        count = _window_sums(count, nd, axis, dtype)
    wx, wy, wz = (np.diff(n).astype(dtype) + 1 for n in nodes)
    voxels = np.multiply.outer(np.multiply.outer(wz, wy), wx)  # voxel centres in each block
    return count > voxels // 2, nodes  # strictly more than half (integer counts)


def _used_nodes(cubes: np.ndarray) -> np.ndarray:
    """Nodes ``(Nz, Ny, Nx)`` that are a corner of at least one cube."""
    nz, ny, nx = cubes.shape
    used = np.zeros((nz + 1, ny + 1, nx + 1), dtype=bool)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                used[dz : dz + nz, dy : dy + ny, dx : dx + nx] |= cubes
    return used


def lattice_step(
    mask: Volume, *, edge_length_mm: float | None = None, max_vertices: int | None = MAX_LATTICE_VERTICES
) -> tuple[int, int, int]:
    """The lattice step ``(sx, sy, sz)`` in voxels for :func:`lattice_tetmesh`.

    Parameters
    ----------
    mask : Volume
        The body mask.
    edge_length_mm : float, optional
        The lattice spacing in mm: ``round(edge_length_mm / spacing)`` voxels along each axis, at least 1.
    max_vertices : int or None
        Without ``edge_length_mm``: step 1 (the mask's own resolution) unless the mesh would have more
        vertices than this (counted as the nodes of the body cubes, before other components are dropped);
        then the smallest step ``s`` (the same along every axis) whose mesh has at most that many.
        ``None``: always 1.
    """
    g = mask.geometry
    if edge_length_mm is not None:
        if not edge_length_mm > 0:
            raise ValueError(f"edge_length_mm must be positive, got {edge_length_mm}")
        return tuple(max(1, int(round(float(edge_length_mm) / h))) for h in g.spacing)
    if max_vertices is None:
        return (1, 1, 1)
    if not max_vertices >= 8:
        raise ValueError(f"max_vertices must be at least 8 (one cube), got {max_vertices}")
    # the vertex count falls about as 1/s³: start at the step that estimate gives, not at 1 (each try is a pass
    # over the whole mask)
    body = int(np.count_nonzero(mask.data))
    s = max(1, int(np.floor((body / max_vertices) ** (1.0 / 3.0))))
    while True:
        cubes, _ = lattice_cubes(mask, s)
        if int(_used_nodes(cubes).sum()) <= max_vertices or s >= max(g.size):
            return (s, s, s)
        s += 1


def lattice_tetmesh(mask: Volume, *, step=1, keep_largest_component: bool = True) -> TetMesh:
    """Fill a body mask with tetrahedra: the Kuhn (Freudenthal) triangulation of a lattice of voxel centres.

    The lattice's nodes are the voxel centres at index multiples of ``step`` along each axis, and the last
    voxel of each axis (:func:`lattice_nodes`); its cubes that are mostly body (:func:`lattice_cubes`:
    strictly more than half of the voxel centres they span are in the mask — so two fingers one voxel of air
    apart, at ``step=1``, stay apart) are each split into the 6 tetrahedra of the Kuhn triangulation, all
    about the cube's diagonal from its lowest-index to its highest-index corner.  Neighbouring cubes then cut
    their shared face along the same diagonal, so the mesh is conforming (Freudenthal 1942; Kuhn 1960).

    With this triangulation the P1 stiffness matrix (:func:`deformation.models.harmonic.stiffness_matrix`) is the
    7-point finite-difference Laplacian times the cube volume, for any box ``h_x × h_y × h_z``: in the
    tetrahedron ``0 → h_a e_a → … + h_b e_b → … + h_c e_c`` the barycentric coordinates are
    ``1 − x_a/h_a, x_a/h_a − x_b/h_b, x_b/h_b − x_c/h_c, x_c/h_c``, so ``∇λ_i·∇λ_j`` is ``−1/h_a²`` (and so
    on) for the three edges along an axis and exactly 0 for the others; the 6 tetrahedra around an edge
    along ``a`` sum to ``−h_x h_y h_z / h_a²``, the face and body diagonals to 0.  Rotations and reflections
    (the grid's direction matrix) keep dot products.  No off-diagonal entry is positive, the matrix is an
    M-matrix, and harmonic weights obey the discrete maximum principle (Ciarlet & Raviart 1973).

    Parameters
    ----------
    mask : Volume
        Body mask (non-zero = body) on any grid: anisotropic spacing and any orthonormal direction.
    step : int or (sx, sy, sz)
        Lattice step in voxels (:func:`lattice_step`).  A gap in the mask narrower than about a step may be
        bridged, and a structure thinner than that may be left out.
    keep_largest_component : bool
        Keep only the tetrahedra of the largest vertex-connected component (a floating fragment has no bone
        and so no harmonic weights).

    Returns
    -------
    TetMesh
        Positively oriented tetrahedra; the vertices are the used lattice nodes in ``[z, y, x]`` array order,
        at their voxel centres' world positions (``mask.geometry.index_to_world``); the tetrahedra follow
        their cubes in the same order.  A function of the mask and the step alone: the same bits in any
        process.

    Raises
    ------
    ValueError
        No cube of the lattice is body (an empty or too thin mask, or too large a step).

    References
    ----------
    Freudenthal H. Simplizialzerlegungen von beschränkter Flachheit. Ann Math 43(3) (1942) 580–582.
    https://doi.org/10.2307/1968813

    Kuhn HW. Some combinatorial lemmas in topology. IBM J Res Dev 4(5) (1960) 518–524.
    https://doi.org/10.1147/rd.45.0518

    Ciarlet PG, Raviart PA. Maximum principle and uniform convergence for the finite element method.
    Comput Methods Appl Mech Eng 2(1) (1973) 17–31. https://doi.org/10.1016/0045-7825(73)90019-4
    """
    cubes, (ndx, ndy, ndz) = lattice_cubes(mask, step)
    g = mask.geometry
    if not cubes.any():
        raise ValueError(
            f"no lattice cube (step {_checked_step(step)} voxels) is mostly body in the mask on "
            f"{g.describe()}: is the mask empty or thinner than two steps? Use a smaller step"
        )
    nx, ny = len(ndx), len(ndy)
    cz, cy, cx = np.nonzero(cubes)  # C order: the cubes in [z, y, x] array order
    base = (cz * ny + cy) * nx + cx  # node id of each cube's corner 0
    corner = np.array([((b >> 2) & 1) * ny * nx + ((b >> 1) & 1) * nx + (b & 1) for b in range(8)], dtype=np.int64)
    tets = (base[:, None, None] + corner[_KUHN_TETS][None]).reshape(-1, 4)
    n_nodes = nx * ny * len(ndz)
    if keep_largest_component:
        tets = _largest_component(tets, n_nodes)
    used = np.unique(tets)
    remap = np.full(n_nodes, -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    kz, rest = np.divmod(used, ny * nx)
    ky, kx = np.divmod(rest, nx)
    ijk = np.stack([ndx[kx], ndy[ky], ndz[kz]], axis=1).astype(np.float64)
    return TetMesh(g.index_to_world(ijk), remap[tets]).oriented()


def _largest_component(tets: np.ndarray, n_vertices: int) -> np.ndarray:
    """The tetrahedra of the largest vertex-connected component."""
    rows = np.repeat(tets[:, :1], 3, axis=1).ravel()
    cols = tets[:, 1:].ravel()
    g = sp.coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    n, lab = _graph_components(g, directed=False)
    if n == 1:
        return tets
    tet_lab = lab[tets[:, 0]]
    counts = np.bincount(tet_lab, minlength=n)
    return tets[tet_lab == int(np.argmax(counts))]


# ---------------------------------------------------------------------------------------------
# Compiled kernels: barycentric coordinates and containment
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def _tet_inverse(V, tets, t, minv):
    """``minv`` ← inverse of [b−a, c−a, d−a] (columns) of tet ``t``; returns the determinant."""
    a = tets[t, 0]
    b = tets[t, 1]
    c = tets[t, 2]
    d = tets[t, 3]
    m00 = V[b, 0] - V[a, 0]
    m10 = V[b, 1] - V[a, 1]
    m20 = V[b, 2] - V[a, 2]
    m01 = V[c, 0] - V[a, 0]
    m11 = V[c, 1] - V[a, 1]
    m21 = V[c, 2] - V[a, 2]
    m02 = V[d, 0] - V[a, 0]
    m12 = V[d, 1] - V[a, 1]
    m22 = V[d, 2] - V[a, 2]
    c00 = m11 * m22 - m12 * m21
    c01 = m02 * m21 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    det = m00 * c00 + m10 * c01 + m20 * c02
    if det == 0.0:
        return 0.0
    inv = 1.0 / det
    minv[0, 0] = c00 * inv
    minv[0, 1] = c01 * inv
    minv[0, 2] = c02 * inv
    minv[1, 0] = (m12 * m20 - m10 * m22) * inv
    minv[1, 1] = (m00 * m22 - m02 * m20) * inv
    minv[1, 2] = (m02 * m10 - m00 * m12) * inv
    minv[2, 0] = (m10 * m21 - m11 * m20) * inv
    minv[2, 1] = (m01 * m20 - m00 * m21) * inv
    minv[2, 2] = (m00 * m11 - m01 * m10) * inv
    return det


@nb.njit(cache=True)
def _face_pass(V, tets, t, c, x, y, z, tie):
    """Is point (x, y, z) on the inner side of the face of tet ``t`` opposite its vertex ``c``?

    The side is the sign of ``n·(p − a)`` with ``n = (b − a) × (c' − a)`` over the face's three
    vertices *sorted by vertex index*: the two tets sharing a face evaluate the very same
    floating-point expression, so they can never both (or neither) claim a point near it.  A point
    on the plane to within round-off (relative 1e-10) goes to the side ``tie`` points into
    (simulation of simplicity), so a point at a shared edge or vertex is claimed by the one tet an
    infinitesimal step along ``tie`` enters.
    """
    i0 = tets[t, (c + 1) % 4]
    i1 = tets[t, (c + 2) % 4]
    i2 = tets[t, (c + 3) % 4]
    if i0 > i1:
        i0, i1 = i1, i0
    if i1 > i2:
        i1, i2 = i2, i1
    if i0 > i1:
        i0, i1 = i1, i0
    ux = V[i1, 0] - V[i0, 0]
    uy = V[i1, 1] - V[i0, 1]
    uz = V[i1, 2] - V[i0, 2]
    wx = V[i2, 0] - V[i0, 0]
    wy = V[i2, 1] - V[i0, 1]
    wz = V[i2, 2] - V[i0, 2]
    nx = uy * wz - uz * wy
    ny = uz * wx - ux * wz
    nz = ux * wy - uy * wx
    o = tets[t, c]
    so = nx * (V[o, 0] - V[i0, 0]) + ny * (V[o, 1] - V[i0, 1]) + nz * (V[o, 2] - V[i0, 2])
    if so == 0.0:
        return False
    px = x - V[i0, 0]
    py = y - V[i0, 1]
    pz = z - V[i0, 2]
    sp_ = nx * px + ny * py + nz * pz
    # On the plane up to round-off (e.g. p is a vertex of the face): the tie direction decides.
    # The test uses only the sorted face and p, so both tets of the face agree on it too.
    if abs(sp_) <= 1e-10 * math.sqrt((nx * nx + ny * ny + nz * nz) * (px * px + py * py + pz * pz)):
        sp_ = nx * tie[0] + ny * tie[1] + nz * tie[2]
        if sp_ == 0.0:
            return False
    return (sp_ > 0.0) == (so > 0.0)


@nb.njit(cache=True)
def _bary(V, a, minv, x, y, z, lam):
    dx = x - V[a, 0]
    dy = y - V[a, 1]
    dz = z - V[a, 2]
    lam[1] = minv[0, 0] * dx + minv[0, 1] * dy + minv[0, 2] * dz
    lam[2] = minv[1, 0] * dx + minv[1, 1] * dy + minv[1, 2] * dz
    lam[3] = minv[2, 0] * dx + minv[2, 1] * dy + minv[2, 2] * dz
    lam[0] = 1.0 - lam[1] - lam[2] - lam[3]


@nb.njit(cache=True)
def _contains(V, tets, t, lam, x, y, z, tie, band):
    """Containment: clear-cut from the barycentric coordinates, else by :func:`_face_pass`."""
    for c in range(4):
        if lam[c] < -band:
            return False
    for c in range(4):
        if lam[c] <= band and not _face_pass(V, tets, t, c, x, y, z, tie):
            return False
    return True


@nb.njit(cache=True)
def _clamp_bary(lam):
    """Round-off on a face can leave −1e-17: clamp to ≥ 0 and renormalise."""
    s = 0.0
    for c in range(4):
        if lam[c] < 0.0:
            lam[c] = 0.0
        s += lam[c]
    for c in range(4):
        lam[c] = lam[c] / s


@nb.njit(cache=True)
def _rasterize_kernel(V, Vidx, tets, a_mat, nx, ny, nz, tie, band, tet_index, bary, count):
    """Serial over tets (deterministic: the lowest tet index wins a voxel claimed twice)."""
    minv = np.empty((3, 3))
    lam = np.empty(4)
    for t in range(tets.shape[0]):
        lo0 = np.inf
        lo1 = np.inf
        lo2 = np.inf
        hi0 = -np.inf
        hi1 = -np.inf
        hi2 = -np.inf
        for c in range(4):
            v = tets[t, c]
            lo0 = min(lo0, Vidx[v, 0])
            hi0 = max(hi0, Vidx[v, 0])
            lo1 = min(lo1, Vidx[v, 1])
            hi1 = max(hi1, Vidx[v, 1])
            lo2 = min(lo2, Vidx[v, 2])
            hi2 = max(hi2, Vidx[v, 2])
        i0 = max(0, int(np.ceil(lo0 - 1e-7)))
        i1 = min(nx - 1, int(np.floor(hi0 + 1e-7)))
        j0 = max(0, int(np.ceil(lo1 - 1e-7)))
        j1 = min(ny - 1, int(np.floor(hi1 + 1e-7)))
        k0 = max(0, int(np.ceil(lo2 - 1e-7)))
        k1 = min(nz - 1, int(np.floor(hi2 + 1e-7)))
        if i0 > i1 or j0 > j1 or k0 > k1:
            continue  # no voxel centre in the bounding box (or outside the grid)
        if _tet_inverse(V, tets, t, minv) == 0.0:
            continue  # degenerate
        a = tets[t, 0]
        for k in range(k0, k1 + 1):
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    x = a_mat[0, 0] * i + a_mat[0, 1] * j + a_mat[0, 2] * k + a_mat[0, 3]
                    y = a_mat[1, 0] * i + a_mat[1, 1] * j + a_mat[1, 2] * k + a_mat[1, 3]
                    z = a_mat[2, 0] * i + a_mat[2, 1] * j + a_mat[2, 2] * k + a_mat[2, 3]
                    _bary(V, a, minv, x, y, z, lam)
                    if _contains(V, tets, t, lam, x, y, z, tie, band):
                        count[k, j, i] += 1
                        if tet_index[k, j, i] < 0:
                            tet_index[k, j, i] = t
                            _clamp_bary(lam)
                            for c in range(4):
                                bary[k, j, i, c] = lam[c]


def rasterize(mesh: TetMesh, geometry: GridGeometry, *, dtype=np.float32, return_count: bool = True):
    """The tetrahedron containing every voxel centre of a grid, with barycentric coordinates.

    Parameters
    ----------
    mesh : TetMesh
        Any tet mesh in world mm (positively oriented or not; a deformed mesh
        may fold).  Degenerate (zero-volume) tetrahedra are skipped.
    geometry : GridGeometry
        The grid; any spacing and orthonormal direction.
    dtype : numpy dtype
        Of the barycentric coordinates: float32 (default, memory) or float64
        (exact to round-off).
    return_count : bool
        Also return the cover count.

    Returns
    -------
    tet_index : (nz, ny, nx) int64
        Containing tetrahedron (lowest index if several), −1 outside the mesh.
    barycentric : (nz, ny, nx, 4) ``dtype``
        Barycentric coordinates with respect to ``mesh.tets[tet_index]``'s
        four vertices (zero outside): ``voxel centre = Σ_c λ_c v_c``.
    count : (nz, ny, nx) int32
        Number of tetrahedra containing the voxel centre (only with
        ``return_count``): 1 inside a valid mesh, 0 outside, ≥ 2 where the
        mesh overlaps itself (folds).  Ties on shared faces are broken as
        described in the module docstring, so a conforming mesh never counts 2.
    """
    nx, ny, nz = geometry.size
    a_mat = np.ascontiguousarray(geometry.index_to_world_matrix)
    vidx = np.ascontiguousarray(geometry.world_to_index(mesh.vertices))
    tet_index = np.full((nz, ny, nx), -1, dtype=np.int64)
    bary = np.zeros((nz, ny, nx, 4), dtype=dtype)
    count = np.zeros((nz, ny, nx), dtype=np.int32)
    if mesh.n_tets:
        _rasterize_kernel(
            mesh.vertices, vidx, mesh.tets, a_mat, nx, ny, nz, TIE_DIRECTION, _BAND, tet_index, bary, count
        )
    if return_count:
        return tet_index, bary, count
    return tet_index, bary


# ---------------------------------------------------------------------------------------------
# Point location
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def _bucket_tets(V, tets, lo, h, dims):
    """CSR of the tets whose bounding box overlaps each cell of a regular bucket grid."""
    m = tets.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    counts = np.zeros(ncell + 1, dtype=np.int64)
    rng = np.empty((m, 6), dtype=np.int64)
    for t in range(m):
        for ax in range(3):
            mn = np.inf
            mx = -np.inf
            for c in range(4):
                q = V[tets[t, c], ax]
                mn = min(mn, q)
                mx = max(mx, q)
            c0 = int(np.floor((mn - lo[ax]) / h - 1e-9))
            c1 = int(np.floor((mx - lo[ax]) / h + 1e-9))
            rng[t, 2 * ax] = min(max(c0, 0), dims[ax] - 1)
            rng[t, 2 * ax + 1] = min(max(c1, 0), dims[ax] - 1)
        for cz in range(rng[t, 4], rng[t, 5] + 1):
            for cy in range(rng[t, 2], rng[t, 3] + 1):
                for cx in range(rng[t, 0], rng[t, 1] + 1):
                    counts[(cz * dims[1] + cy) * dims[0] + cx + 1] += 1
    for c in range(ncell):
        counts[c + 1] += counts[c]
    items = np.empty(counts[ncell], dtype=np.int64)
    fill = counts[:-1].copy()
    for t in range(m):
        for cz in range(rng[t, 4], rng[t, 5] + 1):
            for cy in range(rng[t, 2], rng[t, 3] + 1):
                for cx in range(rng[t, 0], rng[t, 1] + 1):
                    cell = (cz * dims[1] + cy) * dims[0] + cx
                    items[fill[cell]] = t
                    fill[cell] += 1
    return counts, items


@nb.njit(cache=True, parallel=True)
def _locate_kernel(V, tets, points, lo, h, dims, offsets, items, tie, band, out_tet, out_bary):
    n = points.shape[0]
    for p in nb.prange(n):
        minv = np.empty((3, 3))
        lam = np.empty(4)
        x = points[p, 0]
        y = points[p, 1]
        z = points[p, 2]
        out_tet[p] = -1
        fx = (x - lo[0]) / h
        fy = (y - lo[1]) / h
        fz = (z - lo[2]) / h
        if not (fx >= 0.0 and fy >= 0.0 and fz >= 0.0):  # also catches NaN
            continue
        cx = int(fx)
        cy = int(fy)
        cz = int(fz)
        if cx >= dims[0] or cy >= dims[1] or cz >= dims[2]:
            continue
        cell = (cz * dims[1] + cy) * dims[0] + cx
        for s in range(offsets[cell], offsets[cell + 1]):  # tets in increasing index order
            t = items[s]
            if _tet_inverse(V, tets, t, minv) == 0.0:
                continue
            _bary(V, tets[t, 0], minv, x, y, z, lam)
            if _contains(V, tets, t, lam, x, y, z, tie, band):
                _clamp_bary(lam)
                out_tet[p] = t
                for c in range(4):
                    out_bary[p, c] = lam[c]
                break


@nb.njit(cache=True)
def _closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz, out):
    """Closest point to p on triangle abc (Ericson, Real-Time Collision Detection §5.1.5); returns d²."""
    abx = bx - ax
    aby = by - ay
    abz = bz - az
    acx = cx - ax
    acy = cy - ay
    acz = cz - az
    apx = px - ax
    apy = py - ay
    apz = pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz = ax, ay, az
    else:
        bpx = px - bx
        bpy = py - by
        bpz = pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx = px - cx
        cpy = py - cy
        cpz = pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz = bx, by, bz
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz = cx, cy, cz
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            s = d1 / (d1 - d3)
            qx, qy, qz = ax + s * abx, ay + s * aby, az + s * abz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            s = d2 / (d2 - d6)
            qx, qy, qz = ax + s * acx, ay + s * acy, az + s * acz
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx, qy, qz = bx + s * (cx - bx), by + s * (cy - by), bz + s * (cz - bz)
        else:
            den = 1.0 / (va + vb + vc)
            v = vb * den
            w = vc * den
            qx = ax + abx * v + acx * w
            qy = ay + aby * v + acy * w
            qz = az + abz * v + acz * w
    out[0] = qx
    out[1] = qy
    out[2] = qz
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2


@nb.njit(cache=True, parallel=True)
def _nearest_face_kernel(V, tets, faces, owner, points, cand, out_tet, out_bary, out_dist):
    """For each point, the candidate boundary face nearest to it; barycentrics of the closest point."""
    n = points.shape[0]
    for p in nb.prange(n):
        q = np.empty(3)
        best_q = np.empty(3)
        minv = np.empty((3, 3))
        lam = np.empty(4)
        best = np.inf
        best_f = -1
        for s in range(cand.shape[1]):
            f = cand[p, s]
            if f < 0:
                continue
            a = faces[f, 0]
            b = faces[f, 1]
            c = faces[f, 2]
            d2 = _closest_on_triangle(
                points[p, 0],
                points[p, 1],
                points[p, 2],
                V[a, 0],
                V[a, 1],
                V[a, 2],
                V[b, 0],
                V[b, 1],
                V[b, 2],
                V[c, 0],
                V[c, 1],
                V[c, 2],
                q,
            )
            if d2 < best or (d2 == best and f < best_f):
                best = d2
                best_f = f
                best_q[0] = q[0]
                best_q[1] = q[1]
                best_q[2] = q[2]
        t = owner[best_f]
        out_tet[p] = t
        out_dist[p] = np.sqrt(best)
        if _tet_inverse(V, tets, t, minv) == 0.0:
            for c in range(4):
                out_bary[p, c] = 0.25
            continue
        _bary(V, tets[t, 0], minv, best_q[0], best_q[1], best_q[2], lam)
        s_ = 0.0
        for c in range(4):
            lam[c] = max(lam[c], 0.0)
            s_ += lam[c]
        for c in range(4):
            out_bary[p, c] = lam[c] / s_


def locate(mesh: TetMesh, points, *, n_candidates: int = 32):
    """The tetrahedron containing each point, its barycentric coordinates, and whether it is inside.

    Parameters
    ----------
    mesh : TetMesh
        The mesh (world mm).
    points : (n, 3) array_like
        World points (mm).
    n_candidates : int
        For points outside the mesh: how many boundary faces (nearest by
        centroid, SciPy cKDTree) are tested exactly for the closest point.

    Returns
    -------
    tet_index : (n,) int64
        Containing tetrahedron (the same tie rule and choice as :func:`rasterize`);
        for a point outside, the tetrahedron owning the nearest boundary face.
    barycentric : (n, 4) float64
        Barycentric coordinates of the point (inside) or of its closest point on
        the boundary (outside), clamped to ≥ 0 and renormalised to sum to one —
        so interpolating with them extends values constantly along the surface
        normal.
    inside : (n,) bool
        Whether the point lies in the mesh.
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (n, 3) world mm, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points must be finite")
    pts = np.ascontiguousarray(pts)
    n = pts.shape[0]
    tet_index = np.full(n, -1, dtype=np.int64)
    bary = np.zeros((n, 4))
    if mesh.n_tets == 0:
        raise ValueError("locate: the mesh has no tetrahedra")
    if n == 0:
        return tet_index, bary, np.zeros(0, dtype=bool)
    V = mesh.vertices
    lo = V.min(axis=0) - 1e-6
    hi = V.max(axis=0) + 1e-6
    vol = float(np.abs(mesh.signed_volumes()).sum())
    h = max((vol / mesh.n_tets) ** (1.0 / 3.0) * 2.0, 1e-9)
    dims = np.maximum(1, np.ceil((hi - lo) / h).astype(np.int64))
    while np.prod(dims) > 8 * mesh.n_tets + 64:  # bound the bucket memory
        h *= 1.25
        dims = np.maximum(1, np.ceil((hi - lo) / h).astype(np.int64))
    offsets, items = _bucket_tets(V, mesh.tets, lo, h, dims)
    _locate_kernel(V, mesh.tets, pts, lo, h, dims, offsets, items, TIE_DIRECTION, _BAND, tet_index, bary)
    inside = tet_index >= 0
    out = np.flatnonzero(~inside)
    if out.size:
        faces, owner = mesh.boundary_faces()
        cent = mesh.vertices[faces].mean(axis=1)
        k = int(min(n_candidates, len(faces)))
        _, cand = cKDTree(cent).query(pts[out], k=k)
        cand = np.ascontiguousarray(np.asarray(cand, dtype=np.int64).reshape(out.size, k))
        t_out = np.empty(out.size, dtype=np.int64)
        b_out = np.empty((out.size, 4))
        d_out = np.empty(out.size)
        _nearest_face_kernel(V, mesh.tets, faces, owner, pts[out], cand, t_out, b_out, d_out)
        tet_index[out] = t_out
        bary[out] = b_out
    return tet_index, bary, inside
