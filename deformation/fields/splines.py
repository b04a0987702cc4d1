"""Interpolating splines for sparse displacements: the clamped plate spline and Kurihara's RBF.

* :func:`cps_green` — the Green's function of the 3-D biharmonic clamped
  plate spline on the unit ball (Rhee et al. 2011, §4.2, after Wahba/Boggio;
  Rhee's footnote 1: the function listed as triharmonic is the biharmonic
  one), evaluated in a cancellation-free form.
* :class:`ClampedPlateSpline` — a displacement field through a few control
  points, localised to a ball given in world millimetres: zero value and zero
  gradient on the sphere, zero outside it (the local deformation of Rhee's
  locally adaptive registration, Algorithm 1).
* :class:`RBFDeformation` — Kurihara & Miyata 2004, §4.2, Kurihara Eq. 4–5: feature
  point deformation of mesh vertices with the basis ``φ(r) = exp(−r/D)``.

Every position and displacement is in world millimetres, points as arrays
``(..., 3)`` in ``(x, y, z)`` order.  Both classes factorise their small
``n × n`` system once (Cholesky) and share it between the x, y and z
components.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import scipy.linalg
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

__all__ = ["cps_green", "cps_green_gradient", "ClampedPlateSpline", "RBFDeformation", "KURIHARA_D_MM"]

#: Kurihara & Miyata 2004, §4.2: "we used D = 1600 [mm] for our experiment".
KURIHARA_D_MM = 1600.0

# Rows of the (m, n) evaluation matrices computed per chunk: bounds the
# temporaries of cdist & co. to ~2**21 doubles (16 MB) whatever m is.
_CHUNK_ELEMENTS = 1 << 21


# -- helpers ------------------------------------------------------------------------------------------


def _as_points(value, name: str, *, n: int | None = None) -> np.ndarray:
    """``value`` as a finite float64 array ``(m, 3)`` (``(n, 3)`` if ``n`` is given)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be an array of points (m, 3) in (x, y, z) order, got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} must have one row per control/feature point, i.e. shape ({n}, 3); got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.argmax(~np.all(np.isfinite(arr), axis=1)))
        raise ValueError(f"{name} must be finite; row {bad} is {arr[bad].tolist()}")
    return arr


def _as_point_cloud(value, name: str) -> tuple[np.ndarray, tuple[int, ...]]:
    """Points ``(..., 3)`` → finite ``(m, 3)`` float64 array and the leading shape."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise ValueError(f"{name} must be points (..., 3) in (x, y, z) order, got shape {arr.shape}")
    lead = arr.shape[:-1]
    flat = arr.reshape(-1, 3)
    if not np.all(np.isfinite(flat)):
        raise ValueError(
            f"{name} must be finite; {int(np.sum(~np.all(np.isfinite(flat), axis=1)))} "
            "point(s) have NaN or infinite coordinates"
        )
    return flat, lead


def _nearest_pair(points: np.ndarray) -> tuple[float, int, int]:
    """Smallest distance between two rows of ``points (n, 3)`` and the pair (n ≥ 2), in O(n log n)."""
    dist, idx = cKDTree(points).query(points, k=2)
    i = int(np.argmin(dist[:, 1]))
    # With exact duplicates the point itself may come back second: its partner is then the first hit.
    j = int(idx[i, 0]) if int(idx[i, 1]) == i else int(idx[i, 1])
    i, j = min(i, j), max(i, j)
    return float(np.linalg.norm(points[i] - points[j])), i, j


def _row_chunks(m: int, n: int):
    step = max(1, _CHUNK_ELEMENTS // max(n, 1))
    for start in range(0, m, step):
        yield slice(start, min(m, start + step))


# -- the clamped plate spline's Green's function --------------------------------------------------


def cps_green(x, y) -> np.ndarray:
    """Green's function of the 3-D biharmonic clamped plate spline on the unit ball.

    Rhee et al. 2011, §4.2 (after Wahba; Boggio's formula)::

        G(x, y) = |x − y| (A + 1/A − 2),   A = sqrt(|x|²|y|² − 2xᵀy + 1) / |x − y|

    for ``|x|, |y| < 1`` and ``G = 0`` outside the unit ball (up to Boggio's
    constant factor, which the spline weights absorb; Rhee's footnote 1: this
    is the biharmonic ``Δ²`` case, not the triharmonic one).

    The printed form cancels catastrophically where ``A → 1`` (near the
    sphere, where ``G`` is tiny) and is ``0·∞`` at ``x = y``.  With
    ``r = |x − y|`` and ``S = sqrt(|x|²|y|² − 2xᵀy + 1) = r A`` it equals
    ``(S − r)² / S``, and since ``S² − r² = (1 − |x|²)(1 − |y|²) =: P``::

        G = P² / (S (S + r)²),    S = sqrt(r² + P)

    which has only sums of non-negative terms (``r`` is computed from the
    coordinate differences, not from ``|x|² + |y|² − 2xᵀy``), so it is
    accurate to a few ulps everywhere inside the ball — near the sphere, to
    the unavoidable rounding of ``1 − |x|²``, ``~eps / (1 − |x|)`` — and
    at ``x = y`` gives the diagonal limit ``G(x, x) = 1 − |x|²``.  The factor
    ``(1 − |x|²)²`` gives zero value and zero gradient on the sphere.
    ``1 − |x|²`` is clamped to 0 for ``|x| ≥ 1``, which makes ``G = 0``
    there (the formula itself is not zero outside the ball).

    Parameters
    ----------
    x : (n, 3) array-like
        Points in unit-ball coordinates.
    y : (m, 3) array-like
        Points in unit-ball coordinates.

    Returns
    -------
    (n, m) float64 array
        ``G[i, j] = G(x_i, y_j)``, symmetric in its arguments, non-negative.
    """
    x = _as_points(x, "x")
    y = _as_points(y, "y")
    px = np.clip(1.0 - np.einsum("ij,ij->i", x, x), 0.0, None)
    py = np.clip(1.0 - np.einsum("ij,ij->i", y, y), 0.0, None)
    out = np.empty((x.shape[0], y.shape[0]), dtype=np.float64)
    for rows in _row_chunks(x.shape[0], y.shape[0]):
        r2 = cdist(x[rows], y, "sqeuclidean")
        r = np.sqrt(r2)
        p = px[rows, None] * py[None, :]
        s = np.sqrt(r2 + p)
        den = s * (s + r) ** 2
        # den = 0 only where r = 0 and P = 0 (the same point on/outside the sphere): G = 0 there.
        np.divide(p * p, den, out=out[rows], where=den > 0)
        out[rows][den <= 0] = 0.0
    return out


def cps_green_gradient(x, y) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cps_green` and its gradient in the first argument, ``∂G(x_i, y_j)/∂x_i``.

    Differentiating ``G = P² / (S (S + r)²)`` (notation of :func:`cps_green`),
    with ``∂P/∂x = −2x (1 − |y|²)``, ``∂r/∂x = (x − y)/r`` and
    ``∂S/∂x = ((x − y) + ½ ∂P/∂x) / S``::

        ∂G = 2P ∂P / (S (S + r)²) − G ∂S / S − 2G (∂S + ∂r) / (S + r)

    — from the same well-conditioned ``P``, ``S`` and ``r`` as ``G`` (tested against
    central differences to 1e-8 of a gradient scale of ~2); one pass
    instead of the six extra evaluations of central differences (the fold
    check of every local step of :mod:`registration.adaptive` needs it on
    every voxel of the step's ball).  At ``x = y`` the biharmonic kernel has
    the cone singularity of ``r``; there ``∂r/∂x`` is taken as 0, the
    symmetric (central-difference) value.  Zero outside the ball.

    Returns ``(G (n, m), dG (n, m, 3))``.
    """
    x = np.ascontiguousarray(_as_points(x, "x"), dtype=np.float64)
    y = np.ascontiguousarray(_as_points(y, "y"), dtype=np.float64)
    g = np.empty((x.shape[0], y.shape[0]), dtype=np.float64)
    dg = np.empty((x.shape[0], y.shape[0], 3), dtype=np.float64)
    _cps_green_gradient(x, y, g, dg)
    return g, dg


@nb.njit(cache=True, nogil=True)
def _cps_green_gradient(x, y, g, dg):
    for i in range(x.shape[0]):
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        px = 1.0 - (x0 * x0 + x1 * x1 + x2 * x2)
        inside = px > 0.0
        if not inside:
            px = 0.0
        for j in range(y.shape[0]):
            py = 1.0 - (y[j, 0] * y[j, 0] + y[j, 1] * y[j, 1] + y[j, 2] * y[j, 2])
            if py < 0.0:
                py = 0.0
            d0, d1, d2 = x0 - y[j, 0], x1 - y[j, 1], x2 - y[j, 2]
            r = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            p = px * py
            s = np.sqrt(r * r + p)
            if not s > 0.0:  # r = 0 and P = 0: the same point on/outside the sphere, G = 0
                g[i, j] = 0.0
                dg[i, j, 0] = dg[i, j, 1] = dg[i, j, 2] = 0.0
                continue
            sr = s + r
            q = p / (s * sr * sr)
            gg = p * q
            g[i, j] = gg
            c = -2.0 * py if inside else 0.0  # ∂P/∂x = c x
            ir = 1.0 / r if r > 0.0 else 0.0
            for a in range(3):
                xa = x0 if a == 0 else (x1 if a == 1 else x2)
                da = d0 if a == 0 else (d1 if a == 1 else d2)
                dp = c * xa
                ds = (da + 0.5 * dp) / s
                dg[i, j, a] = 2.0 * q * dp - gg * ds / s - 2.0 * gg * (ds + da * ir) / sr


# -- the clamped plate spline ----------------------------------------------------------------------


class ClampedPlateSpline:
    """Biharmonic clamped plate spline displacement through control points in a ball (world mm).

    Rhee et al. 2011, §4.2: the ``x`` component of the displacement at ``p``
    is ``d_x(p) = Σ_k w_k G(p, c_k)`` (likewise ``y``, ``z``), with ``G`` the
    clamped plate Green's function (:func:`cps_green`) and the weights the
    solution of the linear system ``G w = d`` (``G_jk = G(c_j, c_k)``) — one
    matrix for the three components, factorised once (Cholesky: ``G`` is a
    reproducing kernel of the clamped plate energy, positive definite for
    distinct control points).  The field is biharmonic away from the control
    points, has zero value and zero gradient on the sphere and is zero outside
    it, so a local deformation never leaks out of its region (the locality
    Rhee's locally adaptive registration, Algorithm 1, relies on).

    World points ``p`` are mapped to unit-ball coordinates ``(p − center) / radius``.

    Hot path (Rhee Algorithm 1: a simplex over the 24 displacement values of
    8 control points, thousands of cost evaluations on 10⁴–10⁵ voxels):
    precompute ``B = spline.basis_for_values(points)`` once, then each
    evaluation is a single ``(m, n) @ (n, 3)`` product ``B @ d`` — do not
    call :meth:`evaluate` inside the optimiser loop.

    Parameters
    ----------
    control_points : (n, 3) array-like
        Control point positions in world mm, strictly inside the ball and
        pairwise distinct.
    center : (3,) array-like, optional
        Centre of the ball in world mm.
    radius : float, optional
        Radius of the ball in mm (the displacement is zero beyond it).

    Raises
    ------
    ValueError
        For a control point on or outside the ball, coincident control
        points, a non-positive radius, or non-finite input.
    """

    #: Control points closer than this (in unit-ball units, i.e. × radius mm) are coincident.
    COINCIDENT_TOL = 1e-9

    def __init__(self, control_points, *, center=(0.0, 0.0, 0.0), radius: float = 1.0):
        c = np.asarray(center, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(f"center must be 3 finite coordinates (x, y, z) in mm, got {center!r}")
        radius = float(radius)
        if not np.isfinite(radius) or radius <= 0:
            raise ValueError(f"radius must be a positive number of mm, got {radius!r}")
        pts = _as_points(control_points, "control_points")
        if pts.shape[0] < 1:
            raise ValueError("control_points must hold at least one point")
        self.center = c
        self.radius = radius
        self.control_points = pts
        self.control_points_unit = self.to_unit(pts)
        norm = np.linalg.norm(self.control_points_unit, axis=1)
        if np.any(norm >= 1.0):
            k = int(np.argmax(norm))
            raise ValueError(
                f"control point {k} at {pts[k].tolist()} mm lies on or outside the ball "
                f"(|p − center| / radius = {norm[k]:.6g} ≥ 1; center {c.tolist()} mm, radius {radius:g} mm): "
                "the clamped plate spline is zero there. Enlarge the radius or move the point inside."
            )
        if pts.shape[0] > 1:
            dmin, i, j = _nearest_pair(self.control_points_unit)
            if dmin <= self.COINCIDENT_TOL:
                raise ValueError(
                    f"control points {i} and {j} coincide ({pts[i].tolist()} mm and {pts[j].tolist()} mm, "
                    f"{dmin * radius:.3g} mm apart): the system G w = d is singular. Merge or remove duplicates."
                )
        self.gram = cps_green(self.control_points_unit, self.control_points_unit)
        try:
            self._cho = scipy.linalg.cho_factor(self.gram, lower=True, check_finite=False)
        except np.linalg.LinAlgError as exc:
            raise ValueError(
                f"the clamped plate spline matrix G of the {pts.shape[0]} control points is numerically singular "
                f"(nearly coincident control points, or points very close to the sphere): {exc}. "
                "Space the control points further apart or move them away from the boundary."
            ) from None

    # -- properties -------------------------------------------------------------------------------
    @property
    def n_controls(self) -> int:
        return int(self.control_points.shape[0])

    @property
    def condition_number(self) -> float:
        """2-norm condition number of ``G`` (eigenvalues of the symmetric matrix)."""
        ev = np.linalg.eigvalsh(self.gram)
        return float(ev[-1] / ev[0])

    def __repr__(self) -> str:
        return (
            f"ClampedPlateSpline({self.n_controls} control points, center={self.center.tolist()} mm, "
            f"radius={self.radius:g} mm)"
        )

    # -- maps -------------------------------------------------------------------------------------
    def to_unit(self, points) -> np.ndarray:
        """World points ``(..., 3)`` mm → unit-ball coordinates ``(p − center) / radius``."""
        return (np.asarray(points, dtype=np.float64) - self.center) / self.radius

    def _check_values(self, values, name: str) -> np.ndarray:
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (self.n_controls, 3):
            raise ValueError(
                f"{name} must have shape ({self.n_controls}, 3) — one (dx, dy, dz) row per control "
                f"point — got {v.shape}"
            )
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite")
        return v

    def solve(self, displacements) -> np.ndarray:
        """Weights ``w (n, 3)`` with ``G w = d`` (Rhee et al. 2011, §4.2), one factorisation for x, y, z.

        Parameters
        ----------
        displacements : (n, 3) array-like
            Displacement (mm) wanted at each control point.

        Returns
        -------
        (n, 3) float64 array
            Weights in mm (``G`` is dimensionless).
        """
        d = self._check_values(displacements, "displacements")
        return scipy.linalg.cho_solve(self._cho, d, check_finite=False)

    def basis(self, points) -> np.ndarray:
        """The matrix ``K (m, n)``, ``K_ik = G(p_i, c_k)``, so that the field at ``points`` is ``K @ weights``.

        Rows of points outside the ball are zero.

        Parameters
        ----------
        points : (m, 3) array-like
            World points in mm.
        """
        p = _as_points(points, "points")
        return cps_green(self.to_unit(p), self.control_points_unit)

    def basis_for_values(self, points) -> np.ndarray:
        """The matrix ``B = K G⁻¹ (m, n)``: the field at ``points`` is ``B @ d`` for control displacements ``d``.

        This is the precomputation for an optimiser that varies the control
        displacements (Rhee Algorithm 1): one ``(m, n) @ (n, 3)`` product per
        cost evaluation, no solve.

        Parameters
        ----------
        points : (m, 3) array-like
            World points in mm.

        Returns
        -------
        (m, n) C-contiguous float64 array
        """
        k = self.basis(points)
        # G is symmetric, so (K G⁻¹)ᵀ = G⁻¹ Kᵀ.
        return np.ascontiguousarray(scipy.linalg.cho_solve(self._cho, k.T, check_finite=False).T)

    def evaluate(self, points, weights) -> np.ndarray:
        """Displacement (mm) at world ``points (..., 3)`` for ``weights (n, 3)`` from :meth:`solve`.

        Zero outside the ball.  Returns an array of the shape of ``points``.
        For repeated evaluation on fixed points use :meth:`basis_for_values`.
        """
        w = self._check_values(weights, "weights")
        flat, lead = _as_point_cloud(points, "points")
        return (self.basis(flat) @ w).reshape(lead + (3,))

    def displacement(self, points, displacements) -> np.ndarray:
        """Displacement (mm) at world ``points (..., 3)`` interpolating ``displacements (n, 3)``."""
        return self.evaluate(points, self.solve(displacements))


# -- Kurihara's RBF feature-point deformation -----------------------------------------------------


class RBFDeformation:
    """Feature-point deformation with radial basis functions (Kurihara §4.2, Kurihara Eq. 4–5).

    Kurihara Eq. 4 moves a vertex ``v`` to ``v' = v + Σ_j c_j φ(|v − q_j|)(r_j − q_j)``
    with ``φ(r) = exp(−r/D)``, ``q_j`` the feature points on the approximate
    mesh and ``r_j`` their targets on the measured mesh.  Kurihara Eq. 5 as printed,
    ``r_j − q_j = Σ_i c_i φ(|q_j − q_i|)(r_i − q_i)``, has one scalar ``c_i``
    per feature point: 3n equations in n unknowns, which in general have no
    solution (the three components of a feature's displacement would have to
    be blended with the same coefficients).  We implement the per-component
    reading — the standard RBF interpolant of each displacement component —
    with an independent coefficient per feature point and per component::

        Φ C = R − Q,   Φ_ji = φ(|q_j − q_i|),   v' = v + Σ_j φ(|v − q_j|) C_j

    ``C_jc / (r_j − q_j)_c`` is Kurihara's ``c_j`` for component ``c``; when
    one scalar per feature does satisfy Kurihara Eq. 5, both readings coincide.  Each
    feature point then moves exactly onto its target.

    The exponential kernel is positive definite in 3-D (Matérn ν = ½), so
    ``Φ`` is factorised by Cholesky, once for the three components.  With the
    paper's ``D = 1600 mm`` and features within ~200 mm, ``Φ`` is close to the
    all-ones matrix (condition number ~10⁴ for 100 features); if Cholesky
    fails numerically the solve falls back to least squares
    (``scipy.linalg.lstsq``), and either way the residual at the feature
    points is checked (``fit_residual_mm``).

    Parameters
    ----------
    source_points : (n, 3) array-like
        Feature points ``q_j`` on the mesh being deformed, world mm, distinct.
    target_points : (n, 3) array-like
        Their target positions ``r_j``, world mm.
    D : float, optional
        Length scale of ``φ(r) = exp(−r/D)`` in mm (default 1600, Kurihara's value).
    max_residual_mm : float, optional
        Largest acceptable distance between a deformed feature point and its
        target; a larger residual of the solve is an error.
    """

    #: Feature points closer than ``COINCIDENT_TOL × D`` are duplicates.
    COINCIDENT_TOL = 1e-9

    def __init__(self, source_points, target_points, *, D: float = KURIHARA_D_MM, max_residual_mm: float = 1e-6):
        D = float(D)
        if not np.isfinite(D) or D <= 0:
            raise ValueError(f"D (the length scale of φ(r) = exp(−r/D)) must be a positive number of mm, got {D!r}")
        q = _as_points(source_points, "source_points")
        if q.shape[0] < 1:
            raise ValueError("source_points must hold at least one feature point")
        r = _as_points(target_points, "target_points")
        if r.shape != q.shape:
            raise ValueError(f"target_points must match source_points one to one: shapes {r.shape} and {q.shape}")
        if q.shape[0] > 1:
            dmin, i, j = _nearest_pair(q)
            if dmin <= self.COINCIDENT_TOL * D:
                raise ValueError(
                    f"feature points {i} and {j} coincide ({q[i].tolist()} mm, {dmin:.3g} mm apart): "
                    "Φ is singular. Merge or remove duplicate feature points."
                )
        self.D = D
        self.source_points = q
        self.target_points = r
        self.kernel = np.exp(-cdist(q, q) / D)  # Kurihara Eq. 5's φ(|q_j − q_i|), φ(r) = e^(−r/D)
        rhs = r - q  # Kurihara Eq. 5's r_j − q_j
        try:
            cho = scipy.linalg.cho_factor(self.kernel, lower=True, check_finite=False)
            # Kurihara Eq. 5 as printed has one scalar c_i per feature (3n equations, n unknowns); here per
            # component, Φ C = R − Q, with C_ic = c_i (r_i − q_i)_c (class docstring)
            coef = scipy.linalg.cho_solve(cho, rhs, check_finite=False)
            # One step of iterative refinement: cheap, and tightens the residual when Φ is ill-conditioned.
            coef += scipy.linalg.cho_solve(cho, rhs - self.kernel @ coef, check_finite=False)
            self.method = "cholesky"
        except np.linalg.LinAlgError:
            coef = scipy.linalg.lstsq(self.kernel, rhs, check_finite=False)[0]  # Kurihara Eq. 5 (per component)
            self.method = "lstsq"
        self.coefficients = coef
        self.fit_residual_mm = float(np.max(np.linalg.norm(self.kernel @ coef - rhs, axis=1)))
        if not self.fit_residual_mm <= max_residual_mm:
            raise ValueError(
                f"the RBF system is too ill-conditioned to move the feature points onto their targets: residual "
                f"{self.fit_residual_mm:.3g} mm > max_residual_mm={max_residual_mm:g} ({self.method} solve, "
                f"D = {D:g} mm). Use a smaller D or remove near-duplicate feature points."
            )

    @property
    def n_features(self) -> int:
        return int(self.source_points.shape[0])

    @property
    def condition_number(self) -> float:
        """2-norm condition number of ``Φ``."""
        ev = np.linalg.eigvalsh(self.kernel)
        return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")

    def __repr__(self) -> str:
        return f"RBFDeformation({self.n_features} feature points, D={self.D:g} mm, {self.method})"

    def basis(self, points) -> np.ndarray:
        """``Φ_v (m, n)`` with ``Φ_v[i, j] = φ(|p_i − q_j|)``: ``displacement = Φ_v @ coefficients``."""
        p = _as_points(points, "points")
        return np.exp(-cdist(p, self.source_points) / self.D)

    def displacement(self, points) -> np.ndarray:
        """``v' − v`` (mm) at world ``points (..., 3)`` (Kurihara Eq. 4), same shape as ``points``."""
        flat, lead = _as_point_cloud(points, "points")
        out = np.empty_like(flat)
        for rows in _row_chunks(flat.shape[0], self.n_features):
            # Kurihara Eq. 4: v' − v = Σ_j c_j φ(|v − q_j|)(r_j − q_j), c_j (r_j − q_j) the rows of C
            out[rows] = np.exp(-cdist(flat[rows], self.source_points) / self.D) @ self.coefficients
        return out.reshape(lead + (3,))

    def __call__(self, points) -> np.ndarray:
        """Deformed positions ``v' = v + displacement(v)`` (mm) of ``points (..., 3)``."""
        p = np.asarray(points, dtype=np.float64)
        return p + self.displacement(p)  # Kurihara Eq. 4: v' = v + Σ_j c_j φ(|v − q_j|)(r_j − q_j)
