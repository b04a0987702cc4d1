"""Fitting a mesh to a scan's surface with its connectivity kept (Kurihara & Miyata 2004, §4, Fig. 5).

Kurihara builds, for every measured pose ``i``, a mesh ``S^f_i`` with the base
mesh ``S_0``'s connectivity: ``S_0`` deformed by SSD (Kurihara Eqs. 2–3), then
by RBF feature points (Kurihara Eqs. 4–5,
:class:`deformation.fields.splines.RBFDeformation`), then each vertex moved to its
nearest point on the scan's surface (the paper used PQP).  Here:

* :func:`closest_points`: Open3D's ``RaycastingScene`` closest-point query on
  a triangle mesh (exact point-to-triangle, not to its vertices);
* :func:`fit_nearest`: the paper's fit, every vertex onto its closest point;
* :func:`fit_regularised`: our addition for scans where the nearest point is
  wrong (where fingers touch, the skin between them is missing from the
  scan's isosurface: Kurihara's Pose 4, which its fit could not handle): only
  confident targets pull, and every vertex keeps the shape of the mesh it
  started from through its Laplacian coordinates (Sorkine et al. 2004).

References
----------
Sorkine O, Cohen-Or D, Lipman Y, Alexa M, Rössl C, Seidel H-P. Laplacian
surface editing. SGP 2004. https://doi.org/10.1145/1057432.1057456
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from deformation.meshes.mesh import SurfaceMesh

__all__ = [
    "closest_points",
    "vertex_normals",
    "fit_nearest",
    "fit_regularised",
    "FitResult",
    "umbrella_laplacian",
    "farthest_points",
    "consistent_mesh",
    "landmark_sites",
    "on_mesh",
    "FEATURE_SOURCES",
    "FITS",
    "confident_targets",
    "raycasting_scene",
    "triangle_normals",
]

FEATURE_SOURCES = ("registration", "closest", "landmarks")  #: where the RBF feature points' targets come from
FITS = ("regularised", "nearest")


def raycasting_scene(mesh: SurfaceMesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.array(mesh.vertices, np.float32)), o3d.core.Tensor(np.array(mesh.triangles, np.uint32))
    )
    return scene


def closest_points(mesh: SurfaceMesh, points, *, scene=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For world ``points (n, 3)``: the closest point on ``mesh``'s triangles, its distance (mm) and the
    triangle's index (Open3D ``RaycastingScene``, float32 inside: ~1e-5 mm at 100 mm)."""
    import open3d as o3d

    if mesh.n_triangles == 0:
        raise ValueError("closest points on a mesh with no triangles")
    scene = scene or raycasting_scene(mesh)
    q = np.ascontiguousarray(np.asarray(points, float).reshape(-1, 3), dtype=np.float32)
    ans = scene.compute_closest_points(o3d.core.Tensor(q))
    p = ans["points"].numpy().astype(np.float64)
    return p, np.linalg.norm(p - q, axis=1), ans["primitive_ids"].numpy().astype(np.int64)


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals of the triangles (the winding's right-hand rule)."""
    p = np.asarray(vertices, float)[np.asarray(triangles)]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (the sum of the adjacent triangles' cross products)."""
    v = np.asarray(vertices, float)
    t = np.asarray(triangles)
    p = v[t]
    c = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # twice the area times the unit normal
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], c)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def umbrella_laplacian(n_vertices: int, triangles: np.ndarray) -> sp.csr_matrix:
    """``L = I − D⁻¹A`` of the mesh's vertex graph (uniform weights): ``(L x)_j`` is vertex ``j`` minus the
    mean of its neighbours (an isolated vertex has a zero row)."""
    t = np.asarray(triangles)
    rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
    cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
    a = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n_vertices, n_vertices)).tocsr()
    a.data[:] = 1.0  # an edge shared by two triangles counts once
    deg = np.asarray(a.sum(axis=1)).ravel()
    inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)
    return (sp.diags((deg > 0).astype(float)) - sp.diags(inv) @ a).tocsr()


def _cg(a, b, x0, inv_diag, *, rtol: float = 1e-10, maxiter: int = 5000):
    """Jacobi-preconditioned conjugate gradients for the SPD ``a`` and the columns of ``b`` at once, from ``x0``:
    ``(x, iterations, converged)``.  Written out (not SciPy's ``cg``) because its dot products go to BLAS,
    which splits vectors of more than 10 000 values across threads and rounds differently with their
    number; NumPy's own sums and SciPy's sparse product give the same bits for any thread count."""
    x = np.array(x0, dtype=np.float64)
    r = b - a @ x
    z = inv_diag[:, None] * r
    p = z.copy()
    rz = np.sum(r * z, axis=0)
    stop = rtol * np.sqrt(np.sum(b * b, axis=0))
    for it in range(1, maxiter + 1):
        if np.all(np.sqrt(np.sum(r * r, axis=0)) <= stop):
            return x, it - 1, True
        ap = a @ p
        pap = np.sum(p * ap, axis=0)
        alpha = np.divide(rz, pap, out=np.zeros_like(rz), where=pap > 0)
        x += alpha * p
        r -= alpha * ap
        z = inv_diag[:, None] * r
        rz_new = np.sum(r * z, axis=0)
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0)
        p = z + beta * p
        rz = rz_new
    return x, maxiter, bool(np.all(np.sqrt(np.sum(r * r, axis=0)) <= stop))


def confident_targets(
    x, normals, target: SurfaceMesh, scene, target_normals, max_distance_mm: float, cos_max: float
) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of ``x`` on ``target`` and which count: near, facing the same way, and found along the
    vertex's normal (a hidden vertex's nearest point lies sideways, on the seam where touching surfaces
    merge); within a tenth of a mm the direction means nothing and the point counts."""
    p, d, tri = closest_points(target, x, scene=scene)
    along = np.abs(np.einsum("ij,ij->i", normals, p - x)) >= cos_max * d
    ok = (d <= max_distance_mm) & (np.einsum("ij,ij->i", normals, target_normals[tri]) >= cos_max) & (along | (d < 0.1))
    return p, ok


def farthest_points(points, n: int, *, candidates=None) -> np.ndarray:
    """Indices of ``n`` of ``points`` (among ``candidates``, default all) spread by farthest-point sampling,
    starting from the candidate nearest the points' centroid (deterministic: no random choice)."""
    pts = np.asarray(points, float)
    cand = (
        np.arange(len(pts))
        if candidates is None
        else np.flatnonzero(np.asarray(candidates, bool))
        if np.asarray(candidates).dtype == bool
        else np.asarray(candidates, np.int64)
    )
    if len(cand) == 0:
        return np.zeros(0, np.int64)
    c = pts[cand]
    first = int(np.argmin(np.linalg.norm(c - pts.mean(axis=0), axis=1)))
    chosen = [first]
    d = np.linalg.norm(c - c[first], axis=1)
    for _ in range(min(int(n), len(cand)) - 1):
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(c - c[k], axis=1))
    return cand[np.asarray(chosen, np.int64)]


@dataclass
class FitResult:
    """A fitted mesh (the start's connectivity) and how far its vertices are from the target surface."""

    mesh: SurfaceMesh
    distance_mm: np.ndarray  #: each vertex's distance to the target surface after the fit
    confident: np.ndarray  #: the vertices whose last target counted (bool)
    iterations: int
    info: dict = field(default_factory=dict)


def fit_nearest(start: SurfaceMesh, target: SurfaceMesh) -> FitResult:
    """Kurihara §4's fit: every vertex of ``start`` moved to its closest point on ``target``."""
    scene = raycasting_scene(target)
    p, _, _ = closest_points(target, start.vertices, scene=scene)
    return FitResult(SurfaceMesh(p, start.triangles), np.zeros(len(p)), np.ones(len(p), bool), 1, {"method": "nearest"})


def fit_regularised(
    start: SurfaceMesh,
    target: SurfaceMesh,
    *,
    stiffness: float = 1.0,
    max_distance_mm: float = 5.0,
    max_angle_deg: float = 60.0,
    iterations: int = 10,
    tolerance_mm: float = 1e-3,
) -> FitResult:
    """The smoothness-regularised fit: the nearest points that can be trusted, the mesh's shape kept.

    Where fingers touch, the skin between them is missing from the scan's
    isosurface, and the nearest point of a vertex on one finger's side lies on
    the merged surface or on the other finger.  A vertex's target counts only
    when it is near (``max_distance_mm``), its surface faces the same way
    (normals within ``max_angle_deg``) and it lies along the vertex's normal
    (within the same angle: a hidden vertex's nearest point lies sideways, on
    the seam where the two skins merge); every vertex keeps the shape of the
    mesh it started from through its Laplacian (umbrella) coordinates::

        min_x  Σ_j c_j |x_j − p_j|² + λ Σ_j |L x − L x₀|²_j

    with ``p_j`` the closest point of the current ``x_j``, ``c_j`` ∈ {0, 1} its
    confidence and ``x₀`` the start; a sparse symmetric positive definite
    system (conjugate gradients, warm-started from the current vertices, for
    the three coordinates at once), repeated as the closest points move.
    Vertices with no confident target are carried by their neighbours (the
    Laplacian) rather than pulled onto a wrong surface.

    ``stiffness`` is λ (relative to the data term's unit weight per confident vertex): 1 keeps the
    start's local shape about as strongly as it follows the surface; the Laplacian of a smooth region is
    small, so a region with confident targets still lands on the surface within a fraction of a mm.
    Stops after ``iterations`` or when no vertex moved more than ``tolerance_mm``.
    """
    if stiffness <= 0:
        raise ValueError(f"stiffness must be positive, got {stiffness}")
    x0 = np.asarray(start.vertices, float)
    n = len(x0)
    lap = umbrella_laplacian(n, start.triangles)
    ltl = (lap.T @ lap).tocsc()
    rhs_shape = ltl @ x0  # λ Lᵀ L x₀: the start's Laplacian coordinates kept
    scene = raycasting_scene(target)
    tn = triangle_normals(target.vertices, target.triangles)
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    x = x0.copy()
    conf = np.zeros(n, bool)
    it, cg_iters, cg_ok = 0, 0, True
    moved = np.inf
    for _ in range(1, int(iterations) + 1):
        p, conf = confident_targets(x, vertex_normals(x, start.triangles), target, scene, tn, max_distance_mm, cos_max)
        c = conf.astype(float)
        # a vertex with no confident target in a component that has none either would leave A singular:
        # a tiny pull towards where it is now keeps it there
        a = (sp.diags(c + 1e-9) + stiffness * ltl).tocsr()
        b = c[:, None] * p + stiffness * rhs_shape + 1e-9 * x
        # A is symmetric positive definite: conjugate gradients from the current vertices (which move little
        # from one pass to the next), Jacobi-preconditioned.  A sparse LU of A cost 0.35 s a pass on an
        # 8 k-vertex knee skin (the bi-Laplacian fills in) and grows faster than the mesh; CG takes ~5 ms
        x_new, cg_iters, cg_ok = _cg(a, b, x, 1.0 / a.diagonal())
        moved = float(np.linalg.norm(x_new - x, axis=1).max())
        x = x_new
        if moved < tolerance_mm:
            break
    _, d, _ = closest_points(target, x, scene=scene)
    return FitResult(
        SurfaceMesh(x, start.triangles),
        d,
        conf,
        it,
        {
            "method": "regularised",
            "stiffness": stiffness,
            "max_distance_mm": max_distance_mm,
            "max_angle_deg": max_angle_deg,
            "last_move_mm": moved,
            "confident_fraction": float(conf.mean()),
            "cg_iterations": cg_iters,
            "cg_converged": cg_ok,
        },
    )


def landmark_sites(base: SurfaceMesh, template_points, *, max_snap_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Where landmarks picked on the template's skin lie on ``base`` (S0): each point's closest point on its
    triangles as ``(triangle index (k,), barycentric coordinates (k, 3))``, so that any mesh with S0's
    connectivity carries the landmark (the SSD mesh: the RBF's centres).  A point farther than
    ``max_snap_mm`` from S0, or two within 0.1 mm of each other (the RBF's system would be singular), is
    refused."""
    from scipy.spatial import cKDTree

    tp = np.asarray(template_points, float).reshape(-1, 3)
    p, d, tri = closest_points(base, tp)
    far = np.flatnonzero(d > max_snap_mm)
    if len(far):
        raise ValueError(
            f"landmark {int(far[0])} lies {d[far[0]]:.1f} mm from the template's skin mesh (more than "
            f"{max_snap_mm:g} mm): pick it on the skin"
        )
    pairs = cKDTree(p).query_pairs(0.1, output_type="ndarray")
    if len(pairs):
        raise ValueError(
            f"landmarks {int(pairs[0][0])} and {int(pairs[0][1])} are within 0.1 mm of each other on "
            "the skin: drop one of them"
        )
    v = base.vertices[base.triangles[tri]]  # (k, 3 corners, 3)
    e0, e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], p - v[:, 0]
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    d20, d21 = (e2 * e0).sum(1), (e2 * e1).sum(1)
    den = np.where(np.abs(d00 * d11 - d01**2) > 0, d00 * d11 - d01**2, 1.0)
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    return tri.astype(np.int64), np.stack([1.0 - b1 - b2, b1, b2], axis=1)


def on_mesh(mesh_vertices: np.ndarray, triangles: np.ndarray, sites: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The points ``sites`` (triangle, barycentric; :func:`landmark_sites`) on a mesh with these vertices."""
    tri, bary = sites
    return np.einsum("kc,kcd->kd", bary, np.asarray(mesh_vertices, float)[triangles[tri]])


def consistent_mesh(
    base: SurfaceMesh,
    weights,
    transforms,
    target: SurfaceMesh,
    *,
    feature_targets=None,
    landmarks=None,
    n_features: int = 150,
    fit: str = "regularised",
    rbf_length_mm: float | None = None,
    max_distance_mm: float = 5.0,
    max_angle_deg: float = 60.0,
    stiffness: float = 1.0,
) -> dict:
    """Kurihara §4 for one scan: ``S_0`` (``base``, its vertices' skinning ``weights``) → SSD with the scan's
    bone ``transforms`` (Kurihara Eqs. 2–3) → RBF feature-point deformation (Kurihara Eqs. 4–5) → fit to the
    scan's surface ``target`` (:func:`fit_regularised` or the paper's :func:`fit_nearest`).

    Feature points: ``landmarks`` ``(sites, scan points)`` — points picked on the template's skin
    (:func:`landmark_sites` on S0) and where they are in the scan, every one a feature point (Kurihara's
    hand-picked points) — or ``n_features`` vertices spread over the mesh (:func:`farthest_points`) among
    those with a target: ``feature_targets`` ``(n_vertices, 3)`` world mm (e.g. where the volume registration
    puts each base vertex in the scan; NaN rows: none), or, when None, the confident closest points of the
    SSD mesh on ``target`` (near, facing the same way, along the normal).  Returns the ``ssd``, ``rbf`` and
    ``fitted`` meshes, the :class:`FitResult`, the feature indices (for landmarks: the corner of its triangle
    with the largest barycentric weight) and their targets.
    """
    from deformation.fields.splines import KURIHARA_D_MM, RBFDeformation
    from deformation.models.skinning import lbs

    if fit not in FITS:
        raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
    if landmarks is not None and feature_targets is not None:
        raise ValueError("give landmarks or feature_targets, not both")
    ssd = SurfaceMesh(lbs(base.vertices, weights, transforms), base.triangles)  # S^s_i, Kurihara Eq. 2
    if landmarks is not None:
        sites, tgt = landmarks[0], np.asarray(landmarks[1], float).reshape(-1, 3)
        if len(tgt) != len(sites[0]) or len(tgt) < 4:
            raise ValueError(f"{len(sites[0])} landmark sites and {len(tgt)} scan points: one each, at least 4")
        centres = on_mesh(ssd.vertices, base.triangles, sites)
        corner = np.argmax(sites[1], axis=1)
        idx = base.triangles[sites[0], corner]
        source = "landmarks"
    else:
        if feature_targets is not None:
            tgt = np.asarray(feature_targets, float).reshape(-1, 3)
            if len(tgt) != base.n_vertices:
                raise ValueError(f"{len(tgt)} feature targets for a base mesh of {base.n_vertices} vertices")
            has = np.isfinite(tgt).all(axis=1)
            source = "given targets"
        else:
            scene = raycasting_scene(target)
            tgt, has = confident_targets(
                ssd.vertices,
                vertex_normals(ssd.vertices, ssd.triangles),
                target,
                scene,
                triangle_normals(target.vertices, target.triangles),
                max_distance_mm,
                np.cos(np.deg2rad(max_angle_deg)),
            )
            source = "confident closest points"
        idx = farthest_points(base.vertices, n_features, candidates=has)
        if len(idx) < 4:
            raise ValueError(
                f"only {len(idx)} vertices have a feature target ({source}); at least 4 are needed "
                "(try the other --features source)"
            )
        centres, tgt = ssd.vertices[idx], tgt[idx]
    rbf = RBFDeformation(centres, tgt, D=KURIHARA_D_MM if rbf_length_mm is None else rbf_length_mm)  # Kurihara Eq. 5
    rbf_mesh = SurfaceMesh(rbf(ssd.vertices), base.triangles)  # S^r_i, Kurihara Eq. 4
    if fit == "nearest":
        res = fit_nearest(rbf_mesh, target)
    else:
        res = fit_regularised(
            rbf_mesh, target, stiffness=stiffness, max_distance_mm=max_distance_mm, max_angle_deg=max_angle_deg
        )
    return {
        "ssd": ssd,
        "rbf": rbf_mesh,
        "fitted": res.mesh,
        "fit": res,
        "features": idx,
        "feature_targets": tgt,
        "info": {
            "features": int(len(idx)),
            "feature_source": source,
            "fit": fit,
            "rbf_residual_mm": float(rbf.fit_residual_mm),
            **{k: v for k, v in res.info.items() if k != "method"},
        },
    }
