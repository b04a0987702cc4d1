"""Automatic skinning weights: harmonic functions on a tetrahedral mesh of the body.

Kurihara & Miyata set their skinning weights by hand and name automatic
weights as future work; Rhee et al. do not say how theirs were made.  Here
the weight of bone ``k`` is the harmonic function on the body's tet mesh (the
Kuhn lattice of :func:`~deformation.meshes.tetmesh.lattice_tetmesh`) that is 1 on
bone ``k`` and 0 on every other bone::

    Δ w_k = 0 in the soft tissue,   w_k = δ_kl on bone l.

The boundary values sum to one, so ``Σ_k w_k = 1`` everywhere
(Kurihara Eq. 3), and by the maximum principle ``0 ≤ w_k ≤ 1`` with no
island of influence away from the bone.  :func:`harmonic_weights` solves it with P1
finite elements (the cotangent Laplacian, one sparse LU for all bones); on a
Kuhn lattice that is the 7-point stencil, an M-matrix, so the discrete
maximum principle holds (Ciarlet & Raviart 1973).  A vertex is on bone ``k``
when its nearest voxel carries bone ``k``'s label
(:func:`constrained_vertices`).  :func:`weights_on_grid` and
:func:`weights_at_points` carry the vertex weights to voxels and skin
vertices by barycentric interpolation (a partition of unity, so
Kurihara Eq. 3 still holds).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _graph_components
from scipy.sparse.linalg import splu

from deformation.geometry import GridGeometry, Volume
from deformation.meshes.tetmesh import MAX_LATTICE_VERTICES, TIE_DIRECTION, TetMesh, locate, rasterize
from deformation.models.skinning import MAX_INFLUENCES, SkinningWeights

__all__ = [
    "stiffness_matrix",
    "constrained_vertices",
    "harmonic_weights",
    "bbw_weights",
    "weights_on_grid",
    "weights_at_points",
    "harmonic_voxel_weights",
    "VoxelWeights",
]


# ---------------------------------------------------------------------------------------------
# The P1 stiffness matrix
# ---------------------------------------------------------------------------------------------


def stiffness_matrix(mesh: TetMesh, *, drop_tol: float = 1e-12) -> sp.csr_matrix:
    """P1 finite-element stiffness matrix ``L (n, n)`` of a tet mesh (the cotangent Laplacian).

    ``L_ij = Σ_t |t| ∇φ_i·∇φ_j`` over the tets ``t`` holding both vertices,
    with ``φ`` the piecewise-linear hat functions.  Symmetric positive
    semi-definite, rows sum to zero; off-diagonals are ``−(1/6) Σ l_e cot θ_e``
    over the edges opposite ``ij`` and turn positive at obtuse dihedral
    angles (never on a Kuhn lattice, :func:`~deformation.meshes.tetmesh.lattice_tetmesh`,
    where they are the 7-point stencil's and exactly 0 on the face and body
    diagonals).  Units: mm (volume / length²).

    Off-diagonal entries with ``|L_ij| ≤ drop_tol · max(L_ii, L_jj)`` — round-off
    of an exact zero, such as a lattice's diagonals — are removed from the
    matrix, so that its sparse LU does not fill them in (0 keeps every entry).

    Raises
    ------
    ValueError
        A degenerate (zero-volume) tetrahedron.
    """
    p = mesh.vertices[mesh.tets]  # (m, 4, 3)
    d = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # columns b-a, c-a, d-a
    det = np.linalg.det(d)
    scale = np.abs(mesh.vertices).max() + 1.0
    tiny = np.abs(det) <= 1e-14 * scale**3
    if np.any(tiny):
        raise ValueError(
            f"stiffness_matrix: {int(tiny.sum())} degenerate tetrahedra (zero volume), e.g. tet {int(np.argmax(tiny))}"
        )
    inv = np.linalg.inv(d)  # rows: gradients of barycentric coordinates 1..3
    grads = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)  # (m, 4, 3)
    ke = (np.abs(det) / 6.0)[:, None, None] * np.einsum("mik,mjk->mij", grads, grads)
    rows = np.repeat(mesh.tets, 4, axis=1).ravel()
    cols = np.tile(mesh.tets, (1, 4)).ravel()
    n = mesh.n_vertices
    L = sp.coo_matrix((ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    if drop_tol > 0:
        diag = L.diagonal()
        r = np.repeat(np.arange(n), np.diff(L.indptr))
        tiny = (r != L.indices) & (np.abs(L.data) <= drop_tol * np.maximum(diag[r], diag[L.indices]))
        if np.any(tiny):
            L.data[tiny] = 0.0
            L.eliminate_zeros()
    return L


def _dissection_order(points: np.ndarray, graph: sp.csr_matrix, leaf: int = 64) -> np.ndarray:
    """A nested-dissection elimination order of a mesh's vertices, by coordinate bisection (George 1973).

    The vertices are split at the median of their longest extent; those on the lower side with a
    neighbour (in ``graph``, symmetric) on the upper side are the separator, numbered after both sides,
    each of which is dissected the same way down to ``leaf`` vertices (both sides are never empty: the
    median lies between the extremes).  On an axis-aligned lattice the separators are lattice planes; the
    sparse LU of the Laplacian in this order runs faster than in SuperLU's own minimum-degree orderings.
    Deterministic: a function of the points and the graph.

    George A. Nested dissection of a regular finite element mesh. SIAM J Numer Anal 10(2) (1973) 345–363.
    https://doi.org/10.1137/0710032
    """
    pattern = graph.tocsr(copy=True)
    pattern.data = np.ones(pattern.nnz)
    out = []

    def dissect(idx):
        p = points[idx]
        extent = p.max(axis=0) - p.min(axis=0) if idx.size else np.zeros(3)
        axis = int(np.argmax(extent))
        if idx.size <= leaf or extent[axis] == 0:
            out.append(idx)
            return
        v = p[:, axis]
        low = v <= np.median(v)
        if low.all():
            low = v < np.median(v)
        sub = pattern[idx][:, idx]
        sep = low & (sub @ (~low).astype(np.float64) > 0)
        dissect(idx[low & ~sep])
        dissect(idx[~low])
        out.append(idx[sep])

    dissect(np.arange(points.shape[0]))
    return np.concatenate(out)


# ---------------------------------------------------------------------------------------------
# Dirichlet vertices
# ---------------------------------------------------------------------------------------------


def _bone_lut(bone_labels: dict, labels: Volume) -> tuple[tuple, np.ndarray]:
    """Bone names and a label → bone-index lookup table (−1: not a bone)."""
    bones = tuple(str(b) for b in bone_labels)
    if not bones:
        raise ValueError("bone_labels is empty: give {bone name: label id}")
    ids = []
    for b, lab in bone_labels.items():
        if isinstance(lab, bool) or int(lab) != lab or int(lab) < 1:
            raise ValueError(f"bone {b!r}: label id must be a positive integer, got {lab!r}")
        ids.append(int(lab))
    if len(set(ids)) != len(ids):
        raise ValueError(f"bone label ids must be distinct, got {dict(bone_labels)}")
    data = np.asarray(labels.data)
    if labels.is_vector:
        raise ValueError("the label map must be a scalar volume")
    if data.dtype.kind not in "iub" and not np.all(data == np.round(data)):
        raise ValueError("the label map holds non-integer values")
    if data.size and data.min() < 0:
        raise ValueError(f"the label map holds negative ids (minimum {data.min()})")
    top = int(max(max(ids), data.max() if data.size else 0))
    lut = np.full(top + 1, -1, dtype=np.int64)
    for k, lab in enumerate(ids):
        lut[lab] = k
    return bones, lut


def _label_at_points(labels: Volume, points: np.ndarray) -> np.ndarray:
    """Label of the voxel nearest to each world point (ITK rounding); 0 outside the grid."""
    ijk = np.floor(labels.geometry.world_to_index(points) + 0.5).astype(np.int64)
    size = np.asarray(labels.geometry.size)
    ok = np.all((ijk >= 0) & (ijk < size), axis=1)
    out = np.zeros(len(points), dtype=np.int64)
    i, j, k = ijk[ok].T
    out[ok] = np.asarray(labels.data)[k, j, i]
    return out


def constrained_vertices(mesh: TetMesh, labels: Volume, bone_labels: dict, *, snap_missing: bool = False):
    """The bone each mesh vertex is fixed to (−1: free), by the label of its nearest voxel.

    Parameters
    ----------
    mesh : TetMesh
        Body mesh (world mm).
    labels : Volume
        Bone label map (integer ids).
    bone_labels : dict
        ``{bone name: label id}``; the order gives the bone index.
    snap_missing : bool
        A bone that contains no vertex constrains instead the free vertex
        nearest to one of its voxel centres (otherwise: an error).

    Returns
    -------
    bone_of_vertex : (n_vertices,) int64
    snapped : list of str
        The bones that were snapped.

    Raises
    ------
    ValueError
        A bone with no voxel in the label map, or (without ``snap_missing``)
        a bone that contains no mesh vertex.
    """
    bones, lut = _bone_lut(bone_labels, labels)
    lab = _label_at_points(labels, mesh.vertices)
    bone_of_vertex = lut[np.clip(lab, 0, len(lut) - 1)]
    bone_of_vertex[(lab < 0) | (lab >= len(lut))] = -1
    counts = np.bincount(bone_of_vertex[bone_of_vertex >= 0], minlength=len(bones))
    snapped = []
    missing = [k for k in range(len(bones)) if counts[k] == 0]
    if missing:
        data = np.asarray(labels.data)
        voxel_counts = {k: int(np.count_nonzero(data == bone_labels[bones[k]])) for k in missing}
        empty = [bones[k] for k in missing if voxel_counts[k] == 0]
        if empty:
            raise ValueError(
                f"bones {empty} have no voxels in the label map; check bone_labels "
                f"{dict(bone_labels)} against the label map's ids"
            )
        if not snap_missing:
            med = float(np.median(mesh.edge_lengths())) if mesh.n_tets else float("nan")
            g = labels.geometry
            details = ", ".join(
                f"{bones[k]!r} ({voxel_counts[k]} voxels ≈ {voxel_counts[k] * float(np.prod(g.spacing)):.0f} mm³)"
                for k in missing
            )
            raise ValueError(
                f"no tet-mesh vertex lies inside bone(s) {details}; the mesh's median edge is {med:.2f} mm. "
                "Mesh with a smaller lattice step (lattice_tetmesh(..., step=...)), "
                "or pass snap_missing=True to fix the vertex nearest to each such bone."
            )
        from scipy.spatial import cKDTree

        free = np.flatnonzero(bone_of_vertex < 0)
        tree = cKDTree(mesh.vertices[free])
        data = np.asarray(labels.data)
        for k in missing:
            kji = np.argwhere(data == bone_labels[bones[k]])
            centres = labels.geometry.index_to_world(kji[:, ::-1].astype(float))
            # the nearest vertex no other snapped bone took (two tiny bones near one vertex must not share it)
            dist, idx = tree.query(centres, k=min(8, len(free)))
            dist, idx = dist.reshape(len(centres), -1).ravel(), idx.reshape(len(centres), -1).ravel()
            order = np.lexsort((idx, dist))  # nearest first; ties to the lower vertex
            pick = next((int(idx[o]) for o in order if bone_of_vertex[free[idx[o]]] < 0), None)
            if pick is None:
                raise ValueError(
                    f"bone {bones[k]!r} has no mesh vertex and every free vertex near it is taken by "
                    "another snapped bone; mesh with a smaller lattice step"
                )
            bone_of_vertex[free[pick]] = k
            snapped.append(bones[k])
    return bone_of_vertex, snapped


# ---------------------------------------------------------------------------------------------
# Harmonic weights
# ---------------------------------------------------------------------------------------------


def _check_domain(mesh: TetMesh, bone_of_vertex: np.ndarray) -> None:
    """Every vertex in a tetrahedron and every connected piece of the mesh holding a bone, or the weights
    are undetermined there."""
    used = np.zeros(mesh.n_vertices, dtype=bool)
    used[mesh.tets.ravel()] = True
    if not np.all(used):
        raise ValueError(f"the mesh has {int((~used).sum())} vertices used by no tetrahedron; remove them first")
    n_comp, comp = _graph_components(mesh.edge_graph(), directed=False)
    has_bone = np.zeros(n_comp, dtype=bool)
    has_bone[comp[bone_of_vertex >= 0]] = True
    if not np.all(has_bone):
        bad = np.flatnonzero(~has_bone)
        raise ValueError(
            f"{bad.size} connected component(s) of the mesh ({int(np.isin(comp, bad).sum())} vertices) "
            "contain no bone vertex, so their weights are undetermined; keep only the body's main "
            "component (lattice_tetmesh(..., keep_largest_component=True))"
        )


def harmonic_weights(
    mesh: TetMesh,
    labels: Volume,
    bone_labels: dict,
    *,
    max_influences: int = MAX_INFLUENCES,
    snap_missing: bool = False,
):
    """Harmonic skinning weights of every tet-mesh vertex, each bone a Dirichlet boundary.

    Parameters
    ----------
    mesh : TetMesh
        Body mesh in world mm (e.g. :func:`~deformation.meshes.tetmesh.lattice_tetmesh`).
    labels : Volume
        Bone label map (integer ids); any grid.
    bone_labels : dict
        ``{bone name: label id}``; its order is the column order of the result.
    max_influences : int
        Only recorded in ``info`` (the dense vertex weights keep every bone;
        :func:`weights_on_grid` and :func:`weights_at_points` truncate).
    snap_missing : bool
        See :func:`constrained_vertices`.

    Returns
    -------
    vertex_dense : (n_vertices, n_bones) float64
        Weights in [0, 1], rows summing to one; exactly one-hot on
        constrained vertices.
    info : dict
        ``bones`` (tuple), ``bone_of_vertex`` ((n,) int64, −1 free),
        ``n_constrained`` ({bone: count}), ``n_free``, ``snapped`` (bones
        snapped), ``raw`` (the unclipped solution, (n, n_bones)), ``raw_min`` and
        ``raw_max`` (over the free vertices), ``clipped_max`` (largest change by clipping),
        ``clipped_fraction`` (of free entries changed), ``sum_error_raw``
        (``max |Σ_k w_k − 1|`` before clipping), ``residual`` (max-norm of
        ``L_ii W_i + L_ib W_b`` relative to ``L_ib W_b``), ``max_influences``,
        and ``seconds`` ({assemble, factorize, solve}).

    Raises
    ------
    ValueError
        A bone without constrained vertices (see :func:`constrained_vertices`),
        a mesh component with no bone in it, or a degenerate tetrahedron.
    """
    t0 = time.perf_counter()
    bones = tuple(str(b) for b in bone_labels)
    n_bones = len(bones)
    bone_of_vertex, snapped = constrained_vertices(mesh, labels, bone_labels, snap_missing=snap_missing)
    _check_domain(mesh, bone_of_vertex)
    L = stiffness_matrix(mesh)
    t1 = time.perf_counter()
    free = np.flatnonzero(bone_of_vertex < 0)
    fixed = np.flatnonzero(bone_of_vertex >= 0)
    wb = np.zeros((fixed.size, n_bones))
    wb[np.arange(fixed.size), bone_of_vertex[fixed]] = 1.0
    raw = np.zeros((mesh.n_vertices, n_bones))
    raw[fixed] = wb
    residual = 0.0
    t2 = t3 = t1
    if free.size:
        lf = L[free]
        lii = lf[:, free].tocsr()
        rhs = -(lf[:, fixed] @ wb)
        # L_ii is symmetric positive definite: diagonal pivots in a symmetric nested-dissection order
        # (SuperLU keeps it: "NATURAL" on the permuted matrix).
        order = _dissection_order(mesh.vertices[free], lii)
        lu = splu(
            lii[order][:, order].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        t2 = time.perf_counter()
        wi = np.empty_like(rhs)
        wi[order] = lu.solve(np.asfortranarray(rhs[order]))
        t3 = time.perf_counter()
        raw[free] = wi
        scale = max(float(np.abs(rhs).max()), 1e-300)
        residual = float(np.abs(lii @ wi - rhs).max() / scale)
    w = np.clip(raw, 0.0, 1.0)
    clipped = np.abs(w - raw)
    w /= w.sum(axis=1, keepdims=True)  # Kurihara Eq. 3: Σ_k w_k = 1 (exact for the solve, restored after clipping)
    info = {
        "bones": bones,
        "bone_of_vertex": bone_of_vertex,
        "n_constrained": {b: int(np.sum(bone_of_vertex == k)) for k, b in enumerate(bones)},
        "n_free": int(free.size),
        "snapped": snapped,
        "raw": raw,
        "raw_min": float(raw[free].min()) if free.size else 0.0,
        "raw_max": float(raw[free].max()) if free.size else 1.0,
        "clipped_max": float(clipped.max()),
        "clipped_fraction": float(np.count_nonzero(clipped[free] > 0) / max(clipped[free].size, 1)),
        "sum_error_raw": float(np.abs(raw.sum(axis=1) - 1.0).max()),
        "residual": residual,
        "max_influences": int(max_influences),
        "seconds": {"assemble": t1 - t0, "factorize": t2 - t1, "solve": t3 - t2},
    }
    return w, info


def bbw_weights(mesh: TetMesh, labels: Volume, bone_labels: dict, *, snap_missing: bool = False):
    """Bounded biharmonic weights (Jacobson et al. 2011) of every tet-mesh vertex, by libigl's ``igl.bbw``.

    The same domain and boundary conditions as :func:`harmonic_weights` (each
    bone's vertices one-hot, :func:`constrained_vertices`), but each weight
    minimises the Laplacian energy ``∫ (Δw)²`` subject to ``0 ≤ w ≤ 1``
    (libigl's active-set solver), then rows are normalised to sum to one, as
    libigl's ``normalize_row_sums``.  Smoother than harmonic weights at the
    constraints, with no local extrema.  Needs the optional ``libigl`` package
    (``pip install -e '.[bench]'``).  Returns ``(vertex_dense, info)`` with
    ``info``: ``bones``, ``n_free``, ``raw`` (libigl's solution), ``sum_error_raw`` and ``seconds``.

    Jacobson A, Baran I, Popović J, Sorkine O. Bounded biharmonic weights for
    real-time deformation. ACM Trans Graph 30(4) (2011) 78.
    https://doi.org/10.1145/2010324.1964973
    """
    try:
        import igl
    except ImportError as e:
        raise ImportError("bounded biharmonic weights need libigl: pip install -e '.[bench]'") from e
    t0 = time.perf_counter()
    bones = tuple(str(b) for b in bone_labels)
    bone_of_vertex, _ = constrained_vertices(mesh, labels, bone_labels, snap_missing=snap_missing)
    _check_domain(mesh, bone_of_vertex)
    fixed = np.flatnonzero(bone_of_vertex >= 0)
    bc = np.zeros((fixed.size, len(bones)))
    bc[np.arange(fixed.size), bone_of_vertex[fixed]] = 1.0
    raw = igl.bbw(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64),
        np.ascontiguousarray(mesh.tets, dtype=np.int64),
        fixed.astype(np.int64),
        bc,
        partition_unity=False,
        max_iter=100,
    )
    w = np.clip(raw, 0.0, 1.0)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    info = {
        "bones": bones,
        "n_free": int(np.count_nonzero(bone_of_vertex < 0)),
        "raw": raw,
        "sum_error_raw": float(np.abs(raw.sum(axis=1) - 1.0).max()),
        "seconds": time.perf_counter() - t0,
    }
    return w, info


# ---------------------------------------------------------------------------------------------
# Weights on a voxel grid
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, inline="always")
def _top_k(acc, k_max, idx_row, val_row, used):
    """Keep the ``k_max`` largest of ``acc`` (ties: lower bone), renormalise; returns the kept sum."""
    n_b = acc.shape[0]
    for b in range(n_b):
        used[b] = False
    total = 0.0
    n_kept = 0
    for s in range(k_max):
        best = -1
        bv = 0.0
        for b in range(n_b):
            if not used[b] and acc[b] > bv:
                bv = acc[b]
                best = b
        if best < 0:
            break
        used[best] = True
        idx_row[s] = best
        val_row[s] = bv
        total += bv
        n_kept += 1
    if n_kept == 0:
        return 0.0
    for s in range(n_kept, k_max):
        idx_row[s] = idx_row[0]
        val_row[s] = 0.0
    for s in range(n_kept):
        val_row[s] = val_row[s] / total
    return total


@nb.njit(cache=True, parallel=True)
def _grid_weights_kernel(bone_of_voxel, tet_index, bary, nearest_vertex, tets, W, k_max, out_idx, out_val, n_bad):
    n = bone_of_voxel.shape[0]
    n_b = W.shape[1]
    chunk = 4096
    n_chunks = (n + chunk - 1) // chunk
    for ch in nb.prange(n_chunks):
        acc = np.empty(n_b)
        used = np.empty(n_b, dtype=np.bool_)
        idx_row = np.empty(k_max, dtype=np.int64)
        val_row = np.empty(k_max)
        bad = 0
        for p in range(ch * chunk, min(n, (ch + 1) * chunk)):
            b = bone_of_voxel[p]
            if b >= 0:
                for s in range(k_max):
                    out_idx[p, s] = b
                    out_val[p, s] = 0.0
                out_val[p, 0] = 1.0
                continue
            t = tet_index[p]
            if t >= 0:
                for q in range(n_b):
                    acc[q] = 0.0
                for c in range(4):
                    lam = np.float64(bary[p, c])
                    if lam != 0.0:
                        v = tets[t, c]
                        for q in range(n_b):
                            acc[q] += lam * W[v, q]
            else:
                v = nearest_vertex[p]
                for q in range(n_b):
                    acc[q] = W[v, q]
            if _top_k(acc, k_max, idx_row, val_row, used) <= 0.0:
                bad += 1
                for s in range(k_max):
                    out_idx[p, s] = 0
                    out_val[p, s] = 0.0
                out_val[p, 0] = 1.0
                continue
            for s in range(k_max):
                out_idx[p, s] = idx_row[s]
                out_val[p, s] = val_row[s]
        n_bad[ch] = bad


def _check_dense(mesh: TetMesh, vertex_dense, bones) -> tuple[tuple, np.ndarray]:
    bones = tuple(str(b) for b in bones)
    w = np.ascontiguousarray(vertex_dense, dtype=np.float64)
    if w.shape != (mesh.n_vertices, len(bones)):
        raise ValueError(
            f"vertex_dense must be (n_vertices, n_bones) = ({mesh.n_vertices}, {len(bones)}), got {w.shape}"
        )
    if not np.all(np.isfinite(w)) or w.min() < -1e-9:
        raise ValueError("vertex_dense must be finite and non-negative")
    return bones, w


def weights_on_grid(
    mesh: TetMesh,
    vertex_dense,
    bones,
    geometry: GridGeometry,
    labels: Volume,
    bone_labels: dict,
    *,
    max_influences: int = MAX_INFLUENCES,
    outside: str = "nearest",
) -> SkinningWeights:
    """Skinning weights of every voxel of a grid, in array order (``[z, y, x]`` flattened).

    Parameters
    ----------
    mesh : TetMesh
        The body mesh the vertex weights live on.
    vertex_dense : (n_vertices, n_bones) array
        Vertex weights (e.g. :func:`harmonic_weights`).
    bones : sequence of str
        Bone names of the columns of ``vertex_dense``.
    geometry : GridGeometry
        The voxel grid (usually the template's).
    labels : Volume
        Bone label map on ``geometry`` (checked).
    bone_labels : dict
        ``{bone name: label id}``; every name must be in ``bones``.
    max_influences : int
        Bones kept per voxel (the largest), renormalised.
    outside : {"nearest", "raise"}
        Voxels outside the tet mesh (not in a bone) take the weights of the
        nearest boundary vertex of the mesh (``"nearest"``: exact Euclidean
        nearest in world mm, SciPy cKDTree — the dominant cost on a large grid
        that is mostly air; a voxel centre equidistant from several vertices,
        common on a lattice mesh, takes the one nearest to it moved by
        ``1e-6`` of the smallest spacing along
        :data:`~deformation.meshes.tetmesh.TIE_DIRECTION`), or raise ``ValueError``.

    Returns
    -------
    SkinningWeights
        ``geometry.n_voxels`` points: bone voxels exactly one-hot on their
        bone; voxels in the mesh the barycentric interpolation of the vertex
        weights (Kurihara Eq. 3 holds because barycentric coordinates are a
        partition of unity); others by ``outside``.
    """
    from scipy.spatial import cKDTree

    bones, w = _check_dense(mesh, vertex_dense, bones)
    if outside not in ("nearest", "raise"):
        raise ValueError(f"outside must be 'nearest' or 'raise', got {outside!r}")
    geometry.check_same(
        labels.geometry,
        names=("grid", "label map"),
        remedy="resample the label map onto the grid with nearest-neighbour interpolation",
    )
    unknown = [b for b in bone_labels if b not in bones]
    if unknown:
        raise ValueError(f"bones {unknown} of bone_labels have no weight column; the weights are over {bones}")
    lut_names, lut = _bone_lut(bone_labels, labels)
    col = np.array([bones.index(b) for b in lut_names] + [-1], dtype=np.int64)  # label-order → column
    lut = col[lut]  # −1 stays −1 through col[-1]
    k_max = int(min(max_influences, len(bones)))
    if k_max < 1:
        raise ValueError("max_influences must be at least 1")
    lab = np.asarray(labels.data).reshape(-1)
    bone_of_voxel = lut[lab.astype(np.int64)]
    tet_index, bary = rasterize(mesh, geometry, return_count=False)
    tet_index = tet_index.reshape(-1)
    bary = bary.reshape(-1, 4)
    nearest = np.full(geometry.n_voxels, -1, dtype=np.int64)
    need = np.flatnonzero((tet_index < 0) & (bone_of_voxel < 0))
    if need.size:
        if outside == "raise":
            raise ValueError(
                f"{need.size} voxels (not in a bone) lie outside the tet mesh; "
                "use outside='nearest' or mesh a larger body region"
            )
        bverts = mesh.boundary_vertices()
        # An unbalanced tree is faster on these lattice-aligned points (same exact answer).
        tree = cKDTree(mesh.vertices[bverts], balanced_tree=False, compact_nodes=False)
        a = geometry.index_to_world_matrix
        tie = 1e-6 * min(geometry.spacing) * TIE_DIRECTION  # ties decided by the point, not by the tree
        nx, ny, _ = geometry.size
        step = 1 << 20
        for s in range(0, need.size, step):
            flat = need[s : s + step]
            i = flat % nx
            j = (flat // nx) % ny
            k = flat // (nx * ny)
            ijk = np.stack([i, j, k], axis=1).astype(np.float64)
            _, q = tree.query(ijk @ a[:3, :3].T + (a[:3, 3] + tie), workers=-1)
            nearest[flat] = bverts[q]
    dtype = np.int16 if len(bones) > 255 else np.uint8
    out_idx = np.empty((geometry.n_voxels, k_max), dtype=dtype)
    out_val = np.empty((geometry.n_voxels, k_max), dtype=np.float32)
    n_bad = np.zeros((geometry.n_voxels + 4095) // 4096, dtype=np.int64)
    _grid_weights_kernel(bone_of_voxel, tet_index, bary, nearest, mesh.tets, w, k_max, out_idx, out_val, n_bad)
    if n_bad.sum():
        raise ValueError(f"{int(n_bad.sum())} voxels got no positive weight on any bone (vertex weights all zero?)")
    return SkinningWeights(bones, out_idx, out_val)


def weights_at_points(
    mesh: TetMesh, vertex_dense, bones, points, *, max_influences: int = MAX_INFLUENCES
) -> SkinningWeights:
    """Skinning weights at arbitrary points (e.g. skin-mesh vertices) by barycentric interpolation.

    Points outside the tet mesh (a skin mesh's vertices may lie slightly
    outside it) take the weights at their closest point on the mesh boundary
    (:func:`~deformation.meshes.tetmesh.locate`).  At most ``max_influences`` bones per
    point, renormalised.
    """
    bones, w = _check_dense(mesh, vertex_dense, bones)
    tet, bary, _ = locate(mesh, points)
    dense = np.einsum("nc,ncb->nb", bary, w[mesh.tets[tet]])
    return SkinningWeights.from_dense(dense, bones, max_influences=max_influences)


@dataclass
class VoxelWeights:
    """Skinning weights of every voxel of a grid, with the mesh they were solved on."""

    weights: SkinningWeights  #: per voxel, array order
    mesh: TetMesh  #: the body's tetrahedral mesh
    vertex_weights: np.ndarray  #: (n_vertices, n_bones) harmonic weights, columns in ``bones`` order
    bones: tuple
    info: dict  #: solver statistics and the lattice step (JSON values)


def harmonic_voxel_weights(
    labels: Volume,
    bone_labels: dict,
    body: Volume,
    *,
    mesh: TetMesh | None = None,
    edge_length_mm: float | None = None,
    max_vertices: int | None = MAX_LATTICE_VERTICES,
    progress=None,
    kind: str = "harmonic",
    snap_missing: bool = False,
) -> VoxelWeights:
    """Harmonic (or bounded biharmonic, ``kind="bbw"``) skinning weights (Kurihara Eq. 3's w) of every voxel.

    The body (``body``, a mask on the same grid) is meshed with the Kuhn
    tetrahedra of a lattice of its voxel centres
    (:func:`~deformation.meshes.tetmesh.lattice_tetmesh`, with the step of
    :func:`~deformation.meshes.tetmesh.lattice_step` for ``edge_length_mm`` and
    ``max_vertices``) unless ``mesh`` is given; each bone's weight is the
    harmonic function that is 1 on that bone's vertices and 0 on the other
    bones' (:func:`harmonic_weights`), and every voxel takes the barycentric
    interpolation of its tetrahedron's vertex weights (bones one-hot, at most
    :data:`~deformation.models.skinning.MAX_INFLUENCES` influences;
    :func:`weights_on_grid`).  ``progress(message)`` is told each step.
    ``kind="bbw"`` solves bounded biharmonic weights on the same mesh instead
    (:func:`bbw_weights`, libigl).  ``snap_missing`` (harmonic): a bone
    with no lattice vertex inside (smaller than the lattice step) fixes the
    vertex nearest to it instead (:func:`constrained_vertices`; the bones are
    named in ``info["snapped"]``).  ``info["lattice_step"]`` is the step
    ``[sx, sy, sz]`` in voxels of a mesh made here (``None`` for a given mesh).
    """
    if kind not in ("harmonic", "bbw"):
        raise ValueError(f"kind must be 'harmonic' or 'bbw', got {kind!r}")
    from deformation.meshes.tetmesh import lattice_step, lattice_tetmesh

    say = progress or (lambda message: None)
    labels.geometry.check_same(body.geometry, names=("labels", "body mask"))
    step = None
    if mesh is None:
        step = lattice_step(body, edge_length_mm=edge_length_mm, max_vertices=max_vertices)
        say(f"meshing the body: Kuhn tetrahedra on a lattice of {'×'.join(map(str, step))}-voxel steps ...")
        mesh = lattice_tetmesh(body, step=step)
    say(f"{kind} weights on {mesh.n_vertices} vertices ...")
    if kind == "harmonic":
        dense, hinfo = harmonic_weights(mesh, labels, bone_labels, snap_missing=snap_missing)
    else:
        dense, hinfo = bbw_weights(mesh, labels, bone_labels)
    if hinfo.get("snapped"):
        say(
            f"no mesh vertex inside {', '.join(hinfo['snapped'])} (smaller than the lattice step): the nearest "
            "vertex of each was fixed to it"
        )
    say("weights of every voxel (barycentric; one-hot in bones) ...")
    bones = tuple(bone_labels)
    weights = weights_on_grid(mesh, dense, bones, labels.geometry, labels, bone_labels)
    info = {k: v for k, v in hinfo.items() if isinstance(v, (int, float, str, bool))}
    info["snapped"] = ", ".join(hinfo.get("snapped") or [])
    info.update(
        n_vertices=int(mesh.n_vertices),
        n_tets=int(mesh.n_tets),
        kind=kind,
        lattice_step=list(step) if step is not None else None,
    )
    return VoxelWeights(weights, mesh, dense, bones, info)
