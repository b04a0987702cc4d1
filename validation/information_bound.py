"""How well can a bone's rigid pose be known from one scan?  Cramér–Rao bounds.

Rhee §3.1 (Rhee Eq. 1) registers each bone by the intensities of its
(slightly dilated) region; the noise in the scan limits how well those
intensities fix the six rigid parameters.  For a scan ``S(x) = I(T⁻¹x) + n``
with white noise of standard deviation ``σ`` and a noise-free template ``I``,
the Fisher information of the bone's small motion ``θ = (ω, t)`` (rotation
vector about a point ``c``, then translation) is::

    F = (1/σ²) Σ_v g_v g_vᵀ,   g_v = [ (x_v − c) × ∇S(x_v) ,  ∇S(x_v) ],

summed over the scan voxels ``v`` of the bone's region; any unbiased
estimator has covariance ``≥ F⁻¹`` (Cramér–Rao), and one with a Gaussian
prior of covariance ``P`` (the polish's weak kinematic prior) mean squared
error ``≥ (F + P⁻¹)⁻¹`` (van Trees).

The bounds are optimistic, hence true lower bounds: the template is taken
noise-free, the region exactly the truth's and exactly rigid, Rician noise
as Gaussian of the same ``σ`` (it carries at most as much information), and
the MRI bias field is ignored.  ``∇S(x) = R ∇I(T⁻¹x)`` with ``∇I`` by central
differences of the phantom's analytic template intensity
(:class:`~validation.phantoms.generate.Phantom`): the bound is that of the
phantom's own image model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "RigidBound",
    "rigid_information",
    "rigid_bound",
    "phantom_pose_bounds",
    "median_error_norm",
    "template_gradient",
]

GRADIENT_STEP_MM = 0.05  # central-difference step of the template gradient (edges are ≥ 0.8 voxel wide)


@dataclass
class RigidBound:
    """Lower bound on one bone's rigid pose error in one scan."""

    bone: str
    n_voxels: int
    rotation_cov_deg2: np.ndarray  # 3x3, rotation vector error (degrees²), world axes
    translation_cov_mm2: np.ndarray  # 3x3, translation error at the reference point (mm²)
    weakest_axis: np.ndarray  # unit world axis of the least-determined rotation
    weakest_sd_deg: float  # its standard deviation

    @property
    def rotation_rms_deg(self) -> float:
        """RMS of the rotation error's magnitude (√ trace)."""
        return float(np.sqrt(max(np.trace(self.rotation_cov_deg2), 0.0)))

    @property
    def translation_rms_mm(self) -> float:
        return float(np.sqrt(max(np.trace(self.translation_cov_mm2), 0.0)))


def rigid_information(points: np.ndarray, gradients: np.ndarray, center, sigma: float) -> np.ndarray:
    """Fisher information (6x6; rad, mm) of a rigid motion from samples with intensity gradients.

    ``points`` (n, 3) world mm where the scan is sampled, ``gradients`` (n, 3)
    the scan's intensity gradient there (per mm), ``center`` the rotation's
    reference point, ``sigma`` the noise standard deviation.
    """
    points = np.asarray(points, float)
    gradients = np.asarray(gradients, float)
    if points.shape != gradients.shape or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points and gradients must both be (n, 3), got {points.shape} and {gradients.shape}")
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma!r}")
    r = points - np.asarray(center, float)
    g = np.hstack([np.cross(r, gradients), gradients])
    return g.T @ g / float(sigma) ** 2


def rigid_bound(
    information: np.ndarray,
    *,
    bone: str = "",
    n_voxels: int = 0,
    prior_deg: float | None = None,
    prior_mm: float | None = None,
) -> RigidBound:
    """Covariance bound from a 6x6 information matrix, optionally with an isotropic Gaussian prior.

    Without a prior the bound is ``F⁻¹`` (Cramér–Rao; directions the data do
    not see at all get an infinite variance); with ``prior_deg`` /
    ``prior_mm`` (standard deviations per axis) it is ``(F + P⁻¹)⁻¹`` (van
    Trees).
    """
    f = np.array(information, float)
    if f.shape != (6, 6):
        raise ValueError(f"information must be 6x6, got {f.shape}")
    p = np.zeros(6)
    if prior_deg is not None:
        p[:3] = 1.0 / np.deg2rad(prior_deg) ** 2
    if prior_mm is not None:
        p[3:] = 1.0 / float(prior_mm) ** 2
    f = f + np.diag(p)
    w, v = np.linalg.eigh(f)
    tiny = w.max() * 1e-12 if w.max() > 0 else 1.0
    inv_w = np.where(w > tiny, 1.0 / np.where(w > tiny, w, 1.0), np.inf)
    # Infinite variance along unseen directions: keep them out of the matrix product (inf·0 = nan).
    finite = np.isfinite(inv_w)
    cov = (v[:, finite] * inv_w[finite]) @ v[:, finite].T
    if not finite.all():
        unseen = v[:, ~finite]
        cov = cov + np.where(np.abs(unseen @ unseen.T) > 1e-9, np.inf, 0.0)
    deg = np.rad2deg(1.0)
    rot = cov[:3, :3] * deg**2
    # The weakest rotation: the rotation block's largest-variance direction.
    if np.all(np.isfinite(rot)):
        rw, rv = np.linalg.eigh(rot)
        axis, sd = rv[:, -1], float(np.sqrt(max(rw[-1], 0.0)))
    else:  # the rotation part of the first unseen direction
        axis, sd = v[:3, np.flatnonzero(~finite)[0]], np.inf
        axis = axis / max(np.linalg.norm(axis), 1e-12)
    return RigidBound(bone, int(n_voxels), rot, cov[3:, 3:], axis, sd)


def median_error_norm(cov, *, seed: int = 0, n: int = 20000) -> float:
    """Median of ``|e|`` for ``e ~ N(0, cov)`` (Monte Carlo, seeded).

    ``cov`` may be a list of covariances: the median is then that of the
    pooled errors, ``n`` draws from each (the expected median error over a
    set of bone fits whose errors have these covariances).
    """
    covs = [np.asarray(cov, float)] if np.ndim(cov) == 2 else [np.asarray(c, float) for c in cov]
    rng = np.random.default_rng(seed)
    norms = []
    for c in covs:
        if not np.all(np.isfinite(c)):
            norms.append(np.full(n, np.inf))
            continue
        w, v = np.linalg.eigh(c)
        z = rng.standard_normal((n, len(w))) * np.sqrt(np.clip(w, 0, None))
        norms.append(np.linalg.norm(z @ v.T, axis=1))
    return float(np.median(np.concatenate(norms)))


def template_gradient(phantom, p: np.ndarray, h: float) -> np.ndarray:
    """``∇I`` at template points ``p (n, 3)``: central differences of step ``h`` mm of the phantom's noise-free
    analytic template intensity (per mm, ``(n, 3)``)."""
    g = np.empty_like(p)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        g[:, k] = (phantom.render(p + e) - phantom.render(p - e)) / (2 * h)
    return g


def phantom_pose_bounds(
    phantom,
    angles: dict,
    regions: dict,
    *,
    sigma: float | None = None,
    prior_deg: float | None = None,
    prior_mm: float | None = None,
    step_mm: float = GRADIENT_STEP_MM,
) -> dict[str, RigidBound]:
    """Every bone's bound in the phantom posed by ``angles``.

    ``regions`` are the template's bone regions
    (:func:`registration.rigid.bone_regions`); each is carried into the scan
    by the bone's true transform, and its scan voxels are the samples.
    ``sigma`` defaults to the phantom modality's noise.  The translation
    bound is at the bone's centroid, where the accuracy report measures
    translation errors.
    """
    sigma = float(phantom.contrast.noise_sigma if sigma is None else sigma)
    pose = phantom.pose_of(angles)
    x_all = phantom.geometry.world_coordinates().reshape(-1, 3)
    out = {}
    for name, region in regions.items():
        t = np.asarray(pose[name], float)
        r, tr = t[:3, :3], t[:3, 3]
        g = region.crop.geometry
        # Scan voxels whose template position lies in the region (nearest crop voxel).
        corners = g.index_to_world(
            np.array(
                [[i, j, k] for i in (0, g.size[0] - 1) for j in (0, g.size[1] - 1) for k in (0, g.size[2] - 1)], float
            )
        )
        posed = corners @ r.T + tr
        near = np.all((x_all >= posed.min(0) - 1e-6) & (x_all <= posed.max(0) + 1e-6), axis=1)
        x = x_all[near]
        p = (x - tr) @ r  # template positions
        ijk = np.rint(g.world_to_index(p)).astype(int)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(g.size)), axis=1)
        sel = np.zeros(len(x), bool)
        sel[inside] = region.mask[ijk[inside, 2], ijk[inside, 1], ijk[inside, 0]]
        x, p = x[sel], p[sel]
        grad = template_gradient(phantom, p, step_mm) @ r.T  # ∇S(x) = R ∇I(T⁻¹x)
        centre = r @ np.asarray(region.centroid, float) + tr
        info = rigid_information(x, grad, centre, sigma)
        out[name] = rigid_bound(info, bone=name, n_voxels=len(x), prior_deg=prior_deg, prior_mm=prior_mm)
    return out
