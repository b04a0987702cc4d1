"""The registration's correction as inference (registration.posterior): information, evidence, posterior, rigid pose.

Each piece against an analytic reference: the cross structure tensor of a noisy ramp against ``c² / σ²`` (its
noises are independent, so no noise term), the evidence's σ_p on draws of known variance, the posterior's
limits (silent: the start and the prior's error; speaking: the correction), a rigid body's pointwise error
against ``J C Jᵀ`` written out.
"""

from __future__ import annotations

import numpy as np

from registration.posterior import (
    information,
    pooled_precision,
    posterior_correction,
    prior_variance,
    rigid_pose_variance,
)


def test_information_of_a_noisy_ramp_is_its_slope_squared_over_the_noise():
    """F and W the same ramp along x (slope c per mm, anisotropic voxels) with independent noise of SD σ: the
    information along x is c² / σ_ε², σ_ε² the window's residual variance after the affine fit (both noises,
    2σ², as F − a W carries both with a = 1), and nothing along y, z (their gradients' noises are
    independent: the cross product's mean is 0).  Tolerance: the mean over 24·20·16 voxels of a product of
    noisy gradients, whose relative SD there is about 1 %; 5 % allowed."""
    rng = np.random.default_rng(0)
    shape, sp, c, sd = (16, 20, 24), (2.0, 1.5, 1.0), 3.0, 0.5
    x = np.indices(shape)[2] * sp[2]
    f = (c * x + sd * rng.normal(size=shape)).astype(np.float32)
    w = (c * x + sd * rng.normal(size=shape)).astype(np.float32)
    info = information(f, w, sp, 3.0, sd * sd)
    inner = (slice(4, -4), slice(4, -4), slice(4, -4))
    ref = c * c / (2 * sd * sd)
    assert abs(float(info[2][inner].mean()) / ref - 1.0) < 0.05
    for k in (0, 1, 3, 4, 5):  # zz, yy and the cross terms: noise only
        assert abs(float(info[k][inner].mean())) < 0.05 * ref


def test_pooled_precision_sums_the_kernel():
    """A constant information field, pooled over a Gaussian of σ = (1, 2, 1.5) voxels with peak 1, becomes that
    constant times (2π)^{3/2}·3 (the kernel's sum; 3e-3: the discrete Gaussian cut at 3 σ and normalised
    per axis differs from the continuous one's sum by under 0.3 % at σ ≥ 1)."""
    info = np.ones((6, 20, 20, 20), np.float32)
    p = pooled_precision(info, (1.0, 2.0, 1.5), (1.0, 1.0, 1.0), z=0.0)
    assert abs(float(p[0, 10, 10, 10]) / ((2 * np.pi) ** 1.5 * 3.0) - 1.0) < 3e-3


def test_the_evidence_finds_the_prior_variance_of_the_draws():
    """Corrections drawn as the model says, u ~ N(0, σ_p² I + P⁻¹) with P random per voxel (a third of the voxels
    silent, λ = 0): the evidence's σ_p² is within 5 % of the drawn 0.25 mm² (30 000 voxels: its sampling error is
    about 1 %)."""
    rng = np.random.default_rng(1)
    n = 30000
    a = rng.normal(size=(n, 3, 3))
    p = np.einsum("nij,nkj->nik", a, a) * rng.uniform(0.0, 20.0, size=(n, 1, 1))
    p[: n // 3] = 0.0
    cov = 0.25 * np.eye(3) + np.linalg.pinv(p + 1e-12 * np.eye(3))
    cov[: n // 3] = 0.25 * np.eye(3)  # silent voxels: the prior alone
    u = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, 3)))
    prec = np.stack([p[:, 0, 0], p[:, 1, 1], p[:, 2, 2], p[:, 0, 1], p[:, 0, 2], p[:, 1, 2]]).reshape(6, n, 1, 1)
    est = prior_variance(u.T.reshape(3, n, 1, 1), prec, np.ones((n, 1, 1), bool))
    assert abs(est / 0.25 - 1.0) < 0.05


def test_posterior_keeps_a_measured_correction_and_drops_a_silent_one():
    """Where P ≫ 1/σ_p² the correction stands and σ → 0; where P = 0 the start stands (û = 0) and σ = √3 σ_p; a
    voxel informed along x only keeps x and drops y, z.  Exact up to the gain λσ²/(1 + λσ²) (1e-6 at λ = 1e8)."""
    u = np.ones((3, 3, 1, 1), np.float32)
    prec = np.zeros((6, 3, 1, 1), np.float32)
    prec[:3, 0] = 1e8  # voxel 0: all three directions measured
    prec[2, 2] = 1e8  # voxel 2: along the last array axis only
    post = posterior_correction(u, prec, 0.04)
    assert np.allclose(post.u[:, 0, 0, 0], 1.0, atol=1e-5) and post.sigma[0, 0, 0] < 1e-3
    assert np.allclose(post.u[:, 1, 0, 0], 0.0) and abs(post.sigma[1, 0, 0] - np.sqrt(3 * 0.04)) < 1e-6
    assert np.allclose(post.u[:, 2, 0, 0], [0.0, 0.0, 1.0], atol=1e-5)
    assert abs(post.sigma[2, 0, 0] - np.sqrt(2 * 0.04)) < 1e-4


def test_a_rigid_bodys_pointwise_error_is_its_pose_covariance_through_the_jacobian():
    """rigid_pose_variance: the covariance is (Σ Jᵀ I J + Λ)⁻¹ and the error at a voxel √tr(J C Jᵀ), against both
    written out with explicit matrices at a few voxels (float64 round-off: 1e-6 relative)."""
    rng = np.random.default_rng(2)
    shape = (6, 7, 5)
    grid = [g * s for g, s in zip(np.indices(shape, dtype=np.float64), (1.2, 0.9, 2.0))]
    a = rng.normal(size=shape + (3, 3))
    m = np.einsum("...ij,...kj->...ik", a, a)
    info = np.stack([m[..., 0, 0], m[..., 1, 1], m[..., 2, 2], m[..., 0, 1], m[..., 0, 2], m[..., 1, 2]])
    mask = np.zeros(shape, bool)
    mask[1:5, 2:6, 1:4] = True
    centre = [3.0, 4.0, 5.0]
    prior = np.r_[np.full(3, 4.0), np.full(3, 0.1)]
    cov, sd = rigid_pose_variance(info, mask, grid, centre, prior)

    def jac(idx):
        r = np.array([g[idx] for g in grid]) - centre
        cross = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
        return np.hstack([np.eye(3), -cross])

    fisher = sum(jac(i).T @ m[i] @ jac(i) for i in zip(*np.nonzero(mask)))
    ref = np.linalg.inv(fisher + np.diag(1 / prior**2))
    assert np.allclose(cov, ref, rtol=1e-6, atol=1e-12)
    for idx in [(0, 0, 0), (3, 4, 2), (5, 6, 4)]:
        j = jac(idx)
        assert abs(sd[idx] - np.sqrt(np.trace(j @ ref @ j.T))) < 1e-6 * sd[idx]
