"""Clamped plate spline (Rhee et al. 2011, §4.2) and RBF feature-point deformation (Kurihara 2004, Kurihara Eq. 4–5)."""

from __future__ import annotations

from decimal import Decimal, localcontext

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from deformation.fields import splines
from deformation.fields.splines import KURIHARA_D_MM, ClampedPlateSpline, RBFDeformation, cps_green, cps_green_gradient

EPS = np.finfo(np.float64).eps

# A ball in world mm with a non-unit centre and radius: a missing world → unit-ball map cannot hide.
CENTER = np.array([12.5, -30.0, 47.0])
RADIUS = 37.5


def _printed_green(x, y):
    """Rhee §4.2 exactly as printed: G = |x−y| (A + 1/A − 2), A = sqrt(|x|²|y|² − 2xᵀy + 1) / |x−y|."""
    r = cdist(x, y)
    s2 = np.sum(x * x, 1)[:, None] * np.sum(y * y, 1)[None, :] - 2.0 * (x @ y.T) + 1.0
    a = np.sqrt(s2) / r
    return r * (a + 1.0 / a - 2.0)


def _decimal_green(x, y, digits: int = 60) -> float:
    """The printed formula in 60-digit decimal arithmetic from the exact float inputs: a reference."""
    with localcontext() as ctx:
        ctx.prec = digits
        xd = [Decimal(float(v)) for v in x]
        yd = [Decimal(float(v)) for v in y]
        r = sum((a - b) ** 2 for a, b in zip(xd, yd)).sqrt()
        xx = sum(a * a for a in xd)
        yy = sum(b * b for b in yd)
        xy = sum(a * b for a, b in zip(xd, yd))
        s = (xx * yy - 2 * xy + 1).sqrt()
        a = s / r
        return float(r * (a + 1 / a - 2))


def _random_in_ball(rng: np.random.Generator, n: int, rmax: float) -> np.ndarray:
    """``n`` points uniformly distributed in the ball of radius ``rmax`` around 0 (unit-ball coordinates)."""
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    return u * rmax * rng.uniform(0.0, 1.0, (n, 1)) ** (1.0 / 3.0)


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1)[:, None]


def _rhee_spline(rng: np.random.Generator):
    """Rhee's 8 control points (2×2×2, jittered) in the world ball, and random displacements in mm."""
    a = 0.35
    grid = np.array([[i, j, k] for i in (-a, a) for j in (-a, a) for k in (-a, a)])
    unit = grid + rng.normal(0.0, 0.03, grid.shape)
    cps = ClampedPlateSpline(CENTER + RADIUS * unit, center=CENTER, radius=RADIUS)
    d = rng.normal(0.0, 2.0, (8, 3))
    return cps, d


def _laplacian(fun, h: float):
    """7-point finite-difference Laplacian of ``fun`` (points (m, 3) → values (m, k)) with step ``h``."""
    e = np.eye(3) * h

    def lap(u):
        f0 = fun(u)
        return sum(fun(u + e[i]) - 2.0 * f0 + fun(u - e[i]) for i in range(3)) / h**2

    return lap


# -- the Green's function ---------------------------------------------------------------------------


def test_green_matches_printed_form_where_that_is_well_conditioned():
    rng = np.random.default_rng(101)
    x = _random_in_ball(rng, 300, 0.95)
    y = _random_in_ball(rng, 200, 0.95)
    g = cps_green(x, y)
    r = cdist(x, y)
    a = np.sqrt(r**2 + (1 - np.sum(x * x, 1))[:, None] * (1 - np.sum(y * y, 1))[None, :]) / r
    # The printed form computes A + 1/A − 2 = (A − 1)²/A by cancellation: its relative rounding error is
    # ~ a few eps × (A + 1/A + 2)/(A + 1/A − 2), which is ≤ 25 for A ≥ 1.5, i.e. ≲ 1e-13.  1e-12 has margin.
    ok = a >= 1.5
    assert ok.sum() > 1000
    np.testing.assert_allclose(g[ok], _printed_green(x, y)[ok], rtol=1e-12, atol=0)


def test_green_is_accurate_where_the_printed_form_cancels():
    # Near the sphere A → 1 and the printed form loses most of its digits; the stable form does not.
    rng = np.random.default_rng(102)
    for gap in (1e-3, 1e-5, 1e-7):
        x = _unit_vectors(rng, 4) * (1.0 - gap)
        y = _unit_vectors(rng, 4) * (1.0 - 2.0 * gap)
        g = cps_green(x, y)
        ref = np.array([[_decimal_green(xi, yj) for yj in y] for xi in x])
        assert np.all(ref > 0)
        # Each step of G = P²/(S(S+r)²) adds ≤ 1 ulp; P = (1−|x|²)(1−|y|²) inherits the relative error of
        # 1 − |x|² computed from |x|² ≈ 1, ~ eps / gap.  So the error is ≲ 10 eps (1 + 1/gap).
        np.testing.assert_allclose(g, ref, rtol=10 * EPS * (1 + 1 / gap), atol=0)
    # ... while the printed form is visibly off there (this is why the stable form exists).
    x = _unit_vectors(rng, 4) * (1.0 - 1e-7)
    y = _unit_vectors(rng, 4) * (1.0 - 2e-7)
    ref = np.array([[_decimal_green(xi, yj) for yj in y] for xi in x])
    assert np.max(np.abs(_printed_green(x, y) / ref - 1)) > 1e-3


def test_green_diagonal_limit():
    rng = np.random.default_rng(103)
    x = _random_in_ball(rng, 50, 0.99)
    g = cps_green(x, x)
    # On the diagonal r = 0, S = 1 − |x|², G = S⁴/S³: a few relative roundings (8 eps), plus the rounding of
    # |x|² ≤ 1 (a few eps absolute, summation order differs from ours) carried into 1 − |x|².
    np.testing.assert_allclose(np.diag(g), 1.0 - np.sum(x * x, 1), rtol=8 * EPS, atol=4 * EPS)


def test_printed_form_tends_to_the_diagonal_limit():
    rng = np.random.default_rng(104)
    x = _random_in_ball(rng, 20, 0.8)
    u = _unit_vectors(rng, 20)
    limit = 1.0 - np.sum(x * x, 1)
    for delta in (1e-2, 1e-4, 1e-6):
        y = x + delta * u
        printed = np.diag(_printed_green(x, y))
        stable = np.diag(cps_green(x, y))
        # G(x, x + δu) = (1 − |x|²) − 2δ + O(δ²): the Green's function has the cone |x − y| of the 3-D
        # biharmonic fundamental solution, so the difference from the limit is ≈ 2δ (≤ 3δ for δ ≤ 1e-2).
        assert np.all(np.abs(printed - limit) <= 3 * delta)
        assert np.all(np.abs(printed - limit) >= 1 * delta)
        # Near the diagonal A = S/r is large, the printed form does not cancel: both agree to rounding.
        np.testing.assert_allclose(printed, stable, rtol=1e-13, atol=0)


def test_green_is_symmetric_non_negative_and_zero_outside_the_ball():
    rng = np.random.default_rng(105)
    x = _random_in_ball(rng, 40, 1.3)  # about half outside
    y = _random_in_ball(rng, 30, 1.3)
    g = cps_green(x, y)
    # Every step is symmetric in (x, y) in floating point ((a − b)² = (b − a)², p_x p_y = p_y p_x): exact.
    np.testing.assert_array_equal(g, cps_green(y, x).T)
    assert np.all(g >= 0)
    outside_x = np.sum(x * x, 1) >= 1
    outside_y = np.sum(y * y, 1) >= 1
    assert outside_x.any() and outside_y.any() and (~outside_x).any()
    assert np.all(g[outside_x, :] == 0) and np.all(g[:, outside_y] == 0)
    # On the sphere exactly, and for the same point outside (0/0 in the formula): 0, without warnings.
    s = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [2.0, 0.0, 0.0]])
    np.testing.assert_array_equal(cps_green(s, s), np.zeros((3, 3)))


def test_green_is_the_same_when_computed_in_chunks(monkeypatch):
    # Large (m, n) matrices are built in row chunks to bound the temporaries; chunking must not change a bit.
    rng = np.random.default_rng(106)
    x = _random_in_ball(rng, 1000, 1.1)
    y = _random_in_ball(rng, 7, 0.9)
    whole = cps_green(x, y)
    monkeypatch.setattr(splines, "_CHUNK_ELEMENTS", 50)  # 7 rows per chunk, the last one partial
    np.testing.assert_array_equal(cps_green(x, y), whole)


def test_green_shape_errors():
    with pytest.raises(ValueError, match=r"x must be an array of points \(m, 3\)"):
        cps_green(np.zeros((4, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="y must be finite"):
        cps_green(np.zeros((4, 3)), [[0.0, np.nan, 0.0]])


# -- the clamped plate spline ---------------------------------------------------------------------


def test_cps_interpolates_the_control_displacements():
    rng = np.random.default_rng(201)
    for n in (1, 8, 40):
        ctrl = CENTER + RADIUS * _random_in_ball(rng, n, 0.9)
        cps = ClampedPlateSpline(ctrl, center=CENTER, radius=RADIUS)
        d = rng.normal(0.0, 3.0, (n, 3))
        w = cps.solve(d)
        # Cholesky is backward stable: |G w − d| ≲ n eps cond(G) |d|.  cond(G) is ≲ 1e3 for these seeded
        # points (checked), |d| ≲ 10 mm, so the error is ≲ 1e-10 mm; 1e-9 mm leaves margin.
        assert cps.condition_number < 1e3
        np.testing.assert_allclose(cps.evaluate(ctrl, w), d, rtol=0, atol=1e-9)
        np.testing.assert_allclose(cps.displacement(ctrl, d), d, rtol=0, atol=1e-9)


def test_cps_world_to_unit_ball_mapping():
    rng = np.random.default_rng(202)
    unit = _random_in_ball(rng, 8, 0.8)
    d = rng.normal(0.0, 2.0, (8, 3))
    pts_unit = _random_in_ball(rng, 100, 1.2)
    world = ClampedPlateSpline(CENTER + RADIUS * unit, center=CENTER, radius=RADIUS)
    plain = ClampedPlateSpline(unit)
    # The same spline in the unit ball: only the affine map's rounding (~1e-15 relative) differs.
    np.testing.assert_allclose(
        world.displacement(CENTER + RADIUS * pts_unit, d), plain.displacement(pts_unit, d), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(world.gram, cps_green(unit, unit), rtol=1e-13, atol=1e-15)


def test_cps_evaluate_keeps_the_leading_shape():
    rng = np.random.default_rng(203)
    cps, d = _rhee_spline(rng)
    pts = CENTER + RADIUS * _random_in_ball(rng, 24, 0.9).reshape(2, 3, 4, 3)
    w = cps.solve(d)
    out = cps.evaluate(pts, w)
    assert out.shape == (2, 3, 4, 3)
    np.testing.assert_array_equal(out.reshape(-1, 3), cps.evaluate(pts.reshape(-1, 3), w))


def test_cps_is_zero_on_and_outside_the_sphere():
    rng = np.random.default_rng(204)
    cps, d = _rhee_spline(rng)
    w = cps.solve(d)
    n = _unit_vectors(rng, 200)
    on = cps.evaluate(CENTER + RADIUS * n, w)
    # Mapping back gives |u| = 1 ± a few eps, where G ∝ (1 − |u|²)² ~ 1e-31: zero to far below 1e-12 mm.
    assert np.max(np.abs(on)) <= 1e-12
    outside = CENTER + RADIUS * n * rng.uniform(1.0 + 1e-9, 3.0, (200, 1))
    np.testing.assert_array_equal(cps.evaluate(outside, w), 0.0)
    np.testing.assert_array_equal(cps.basis(outside), 0.0)


def test_cps_green_gradient_matches_central_differences():
    rng = np.random.default_rng(11)
    x = rng.uniform(-1.1, 1.1, (3000, 3))  # inside and (some) outside the ball
    y = rng.uniform(-0.6, 0.6, (12, 3))
    x[:4] = y[:4]  # coincident points: the cone singularity of r, where the symmetric value is used
    g, dg = cps_green_gradient(x, y)
    np.testing.assert_allclose(g, cps_green(x, y), rtol=0, atol=8 * EPS)  # same formula, another summation
    h = 1e-6
    num = np.stack([(cps_green(x + h * e, y) - cps_green(x - h * e, y)) / (2 * h) for e in np.eye(3)], axis=-1)
    # central differences: truncation O(h² G‴) plus round-off O(eps G / h), measured 3e-10 against a gradient
    # scale of ~2; 1e-8 leaves margin, while a wrong term of the derivative is off by O(0.1-1)
    assert np.abs(num).max() > 0.5
    np.testing.assert_allclose(dg, num, rtol=0, atol=1e-8)
    outside = np.linalg.norm(x, axis=1) >= 1
    assert outside.any() and np.all(dg[outside] == 0) and np.all(g[outside] == 0)


def test_cps_gradient_vanishes_on_the_sphere():
    rng = np.random.default_rng(205)
    cps, d = _rhee_spline(rng)
    w = cps.solve(d)
    n = _unit_vectors(rng, 100)

    def f(s):  # the field (mm) at depth s (unit-ball units) inside the sphere along each normal
        return cps.evaluate(CENTER + RADIUS * (1.0 - s) * n, w)

    # The value is 0 on the whole sphere, so the tangential derivatives vanish and the gradient there is the
    # normal derivative.  Outside the field is 0, inside it is ≈ a s² + b s³ (G ∝ (1 − |x|²)²): C¹, not C².
    # The one-sided second-order difference (−3 f(0) + 4 f(h) − f(2h)) / 2h is exact for a s², so it gives
    # ∂f/∂s(0) + O(h²) — and it is O(h²) only if the true derivative is 0.
    def normal_derivative(h):
        return (-3.0 * f(0.0) + 4.0 * f(h) - f(2.0 * h)) / (2.0 * h) / RADIUS  # mm per mm

    gradient_scale = np.max(np.abs(cps.evaluate(CENTER + RADIUS * _random_in_ball(rng, 500, 0.6), w))) / RADIUS
    coarse, fine = normal_derivative(2e-3), normal_derivative(1e-3)
    # Measured: |b| ≲ 60 mm in unit-ball units, so |2 b h²| / R ≲ 1e-4 mm/mm at h = 1e-3 — four orders below
    # the field's interior gradient scale (~0.1 mm/mm); 1e-3 × that scale leaves margin.
    assert np.max(np.abs(fine)) <= 1e-3 * gradient_scale
    # Second-order convergence to 0: halving h divides the estimate by ≈ 4 (a non-zero derivative would
    # make the ratio → 1).  Rounding is negligible: f(2h) ~ 1e-4 mm, eps f / h ~ 1e-17.
    ratio = np.max(np.abs(fine)) / np.max(np.abs(coarse))
    assert 0.2 <= ratio <= 0.3
    # The same estimator does see a non-zero normal derivative inside the ball (the test can fail).
    inner = cps.evaluate(CENTER + RADIUS * 0.6 * n, w)
    inner_h = cps.evaluate(CENTER + RADIUS * (0.6 - 1e-3) * n, w)
    assert np.max(np.abs(inner - inner_h)) / (1e-3 * RADIUS) > 10 * np.max(np.abs(fine))


def test_cps_is_biharmonic_away_from_the_control_points():
    rng = np.random.default_rng(206)
    cps, d = _rhee_spline(rng)
    w = cps.solve(d)
    ctrl = cps.control_points_unit
    pts = _random_in_ball(rng, 4000, 0.8)
    delta = 0.25  # distance (unit-ball units) kept from every control point
    pts = pts[np.min(cdist(pts, ctrl), axis=1) > delta][:60]
    assert len(pts) == 60

    def cps_field(u):
        return cps.evaluate(CENTER + RADIUS * u, w)

    # A non-biharmonic field through the same data: the Gaussian RBF interpolant (σ = 0.5).
    kernel = np.exp(-cdist(ctrl, ctrl, "sqeuclidean") / 0.25)
    wg = np.linalg.solve(kernel, d)

    def gauss_field(u):
        return np.exp(-cdist(u, ctrl, "sqeuclidean") / 0.25) @ wg

    h = 5e-3

    def relative_bilaplacian(fun, step):
        lap = _laplacian(fun, step)
        return np.max(np.abs(_laplacian(lap, step)(pts))) / np.max(np.abs(lap(pts)))

    # Truncation error of the 7-point Laplacian applied twice: L_h² = Δ² + (h²/6) Δ Σ_i ∂_i⁴ + O(h⁴), so for a
    # biharmonic f the result is (h²/6) Σ_i ∂_i⁴ Δf.  Δf behaves like 1/r around each control point (Δ|x−y| =
    # 2/|x−y|), whose Σ_i ∂_i⁴ is 42/r⁵ = (42/r⁴)(1/r): the error is ≈ 7 h²/δ⁴ |Δf| ≈ 0.045 |Δf| here; we
    # allow twice that for the regular part of G and the neighbouring control points.  Rounding: eps |f| × ~100
    # / h⁴ ~ 1e-4, negligible against |Δf| ~ 60.  (Measured: 0.03.)
    tol = 2 * 7 * h**2 / delta**4
    assert relative_bilaplacian(cps_field, h) <= tol
    # It is truncation error, not a true bilaplacian: halving h divides it by ≈ 4.
    ratio = relative_bilaplacian(cps_field, h / 2) / relative_bilaplacian(cps_field, h)
    assert 0.2 <= ratio <= 0.3
    # The test can fail: the Gaussian field's bilaplacian is O(1/σ⁴) ≈ 30 |Δf|, far above tol.
    assert relative_bilaplacian(gauss_field, h) > 100 * tol


def test_basis_for_values_equals_solve_then_evaluate():
    rng = np.random.default_rng(207)
    cps, d = _rhee_spline(rng)
    pts = CENTER + RADIUS * _random_in_ball(rng, 2000, 1.1)
    b = cps.basis_for_values(pts)
    assert b.shape == (2000, 8) and b.flags.c_contiguous
    # Both are K G⁻¹ d in a different association, cond(G) ≈ 2 and |d| ~ 5 mm: rounding ~1e-14 mm.
    np.testing.assert_allclose(b @ d, cps.evaluate(pts, cps.solve(d)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cps.basis(pts) @ cps.solve(d), cps.evaluate(pts, cps.solve(d)), rtol=0, atol=1e-13)
    # B reproduces the identity at the control points (interpolation), to the same rounding.
    np.testing.assert_allclose(cps.basis_for_values(cps.control_points), np.eye(8), rtol=0, atol=1e-12)


def test_cps_rejects_bad_input():
    inside = CENTER + np.array([[1.0, 2.0, 3.0], [-5.0, 0.0, 4.0]])
    with pytest.raises(ValueError, match="lies on or outside the ball"):
        ClampedPlateSpline(np.vstack([inside, CENTER + [RADIUS, 0.0, 0.0]]), center=CENTER, radius=RADIUS)
    with pytest.raises(ValueError, match="lies on or outside the ball"):
        ClampedPlateSpline([[2.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="control points 0 and 2 coincide"):
        ClampedPlateSpline(np.vstack([inside, inside[:1]]), center=CENTER, radius=RADIUS)
    with pytest.raises(ValueError, match="radius must be a positive"):
        ClampedPlateSpline(inside, center=CENTER, radius=0.0)
    with pytest.raises(ValueError, match="center must be 3 finite"):
        ClampedPlateSpline(inside, center=(0.0, 1.0), radius=RADIUS)
    with pytest.raises(ValueError, match=r"control_points must be an array of points \(m, 3\)"):
        ClampedPlateSpline(np.zeros(3))
    cps = ClampedPlateSpline(inside, center=CENTER, radius=RADIUS)
    with pytest.raises(ValueError, match=r"displacements must have shape \(2, 3\)"):
        cps.solve(np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"weights must have shape \(2, 3\)"):
        cps.evaluate(inside, np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"points must be an array of points \(m, 3\)"):
        cps.basis_for_values(np.zeros((4, 2)))


# -- Kurihara's RBF deformation -------------------------------------------------------------------


def _features(rng: np.random.Generator, n: int = 100):
    """``n`` feature points spread over a 200 mm cube, and targets a few mm away (Kurihara: 70–150 points)."""
    q = rng.uniform(-100.0, 100.0, (n, 3)) + [300.0, -50.0, 20.0]
    return q, q + rng.normal(0.0, 3.0, (n, 3))


@pytest.mark.parametrize("D", [KURIHARA_D_MM, 20.0])
def test_rbf_moves_feature_points_onto_their_targets(D):
    rng = np.random.default_rng(301)
    q, r = _features(rng)
    rbf = RBFDeformation(q, r, D=D)
    assert rbf.method == "cholesky"
    # With D = 1600 mm Φ ≈ all-ones: cond(Φ) ≈ 3e4 (≈ 14 for D = 20).  A backward-stable solve leaves a residual
    # ≲ n eps cond |R − Q| ≈ 1e-8 mm at worst (measured 1e-12), and evaluating Σ φ C with Σ|C_j| ≈ 4e4 mm rounds
    # to ~1e-11 mm: 1e-6 mm is a safe bound that still catches a wrong solve (errors would be ~mm).
    assert rbf.condition_number < 1e6
    np.testing.assert_allclose(rbf(q), r, rtol=0, atol=1e-6)
    assert rbf.fit_residual_mm <= 1e-6
    np.testing.assert_allclose(rbf.displacement(q), r - q, rtol=0, atol=1e-6)


def test_rbf_single_scalar_reading_is_recovered_when_it_exists():
    # If all features move by the same vector t, Kurihara Eq. 5 has a scalar solution c (Φ c = 1); our per-component
    # coefficients are then C_j = c_j t.  Same Φ, cond ≈ 3e4: agreement to ~1e-9 relative.
    rng = np.random.default_rng(302)
    q, _ = _features(rng)
    t = np.array([5.0, -2.0, 1.0])
    rbf = RBFDeformation(q, q + t)
    c = np.linalg.solve(np.exp(-cdist(q, q) / KURIHARA_D_MM), np.ones(len(q)))
    np.testing.assert_allclose(rbf.coefficients, np.outer(c, t), rtol=1e-8, atol=1e-8 * np.abs(c).max())


def test_rbf_blend_between_and_away_from_the_features():
    rng = np.random.default_rng(303)
    q, r = _features(rng)
    centre = np.array([300.0, -50.0, 20.0])
    t = np.array([5.0, -2.0, 1.0])
    inner = centre + rng.uniform(-80.0, 80.0, (500, 3))
    # Kurihara's large D makes the blend nearly rigid: a uniform translation of the features moves the points
    # in between by almost the same translation (measured 0.4 % of |t| for D = 1600; 2 % bound), whereas with
    # D = 20 mm, far below the feature spacing, it does not (measured 60 %) — the check can fail.
    dev_big = np.max(np.linalg.norm(RBFDeformation(q, q + t).displacement(inner) - t, axis=1))
    dev_small = np.max(np.linalg.norm(RBFDeformation(q, q + t, D=20.0).displacement(inner) - t, axis=1))
    assert dev_big <= 0.02 * np.linalg.norm(t) < dev_small

    for D in (KURIHARA_D_MM, 20.0):
        rbf = RBFDeformation(q, r, D=D)
        coef_sum = np.sum(np.linalg.norm(rbf.coefficients, axis=1))
        # Smooth: |φ'| ≤ 1/D, so the displacement is Lipschitz with constant Σ_j |C_j| / D along any line.
        step = 0.5
        line = centre + np.outer(np.arange(-600.0, 600.0, step), [0.36, 0.48, 0.8])
        disp = rbf.displacement(line)
        assert np.all(np.linalg.norm(np.diff(disp, axis=0), axis=1) <= coef_sum / D * step * (1 + 1e-9))
        # Far away (distance d ≫ spread): |v − q_j| = d − û·q_j + O(spread²/d), so each step s outward
        # multiplies the displacement by exp(−s/D) up to a relative s spread²/(2 d² D) ≲ 1e-3 at d ≥ 2000 mm.
        far = centre + np.outer(np.arange(2000.0, 2100.0, 10.0), [0.6, 0.8, 0.0])
        mag = np.linalg.norm(rbf.displacement(far), axis=1)
        np.testing.assert_allclose(mag[1:] / mag[:-1], np.exp(-10.0 / D), rtol=2e-3)
        # ... and is bounded by exp(−d_min/D) Σ_j |C_j| (every φ ≤ exp(−d_min/D)).
        dmin = np.min(cdist(far, q), axis=1)
        assert np.all(mag <= np.exp(-dmin / D) * coef_sum * (1 + 1e-9))


def test_rbf_call_keeps_shape_and_adds_displacement():
    rng = np.random.default_rng(304)
    q, r = _features(rng, 20)
    rbf = RBFDeformation(q, r, D=200.0)
    pts = rng.uniform(150.0, 450.0, (2, 5, 3))
    out = rbf(pts)
    assert out.shape == (2, 5, 3)
    np.testing.assert_array_equal(out, pts + rbf.displacement(pts))
    np.testing.assert_allclose(
        rbf.displacement(pts).reshape(-1, 3), rbf.basis(pts.reshape(-1, 3)) @ rbf.coefficients, rtol=0, atol=1e-12
    )


def test_rbf_rejects_bad_input():
    rng = np.random.default_rng(305)
    q, r = _features(rng, 10)
    with pytest.raises(ValueError, match="target_points must match source_points"):
        RBFDeformation(q, r[:-1])
    with pytest.raises(ValueError, match=r"source_points must be an array of points \(m, 3\)"):
        RBFDeformation(q[:, :2], r[:, :2])
    with pytest.raises(ValueError, match="feature points 3 and 10 coincide"):
        RBFDeformation(np.vstack([q, q[3]]), np.vstack([r, r[3]]))
    for bad_d in (0.0, -5.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="D .* must be a positive number of mm"):
            RBFDeformation(q, r, D=bad_d)
    with pytest.raises(ValueError, match="target_points must be finite"):
        RBFDeformation(q, np.where(np.arange(10)[:, None] == 4, np.nan, r))
    rbf = RBFDeformation(q, r)
    with pytest.raises(ValueError, match=r"points must be points \(\.\.\., 3\)"):
        rbf(np.zeros((4, 2)))
