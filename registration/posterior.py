"""The dense registration's correction as inference: a Gaussian prior on it, the images' information, the posterior.

:func:`registration.dense.register_dense` finds a correction ``u`` of the start ``φ₀`` (``φ = φ₀ ∘ (id + u)``)
that raises the images' local correlation.  Where the tissue carries structure above the noise, that correction
is measured; where it is flat, the steps fit the noise and move the map away from a start that may have been
right.  This module treats the registration's ``u`` as a measurement and weighs it against the start:

* **Likelihood.**  Near the registered map, the scan is the template through it plus noise, with a local
  affine intensity change (what the local correlation allows): ``F(x) = a(x) S(x + δ(x)) + b(x) + ε``.  A
  displacement ``δ`` of the map costs ``δᵀ g gᵀ δ / σ_ε²`` per independent sample, ``g`` the signal's gradient.
  Its expected outer product is estimated without the noise's bias by the *cross* structure tensor
  ``sym(∇F ⊗ a ∇W)`` (``W`` the template through the map: the two images' noises are independent, so their
  gradients' product has no noise term), ``a`` the local regression slope of ``F`` on ``W`` in the LNCC window,
  and ``σ_ε²`` the window's residual variance after that affine fit (the noise, and whatever the map does not
  explain), at least the scan's own noise variance (:func:`registration.dense.voxel_noise_variance`).
* **Pooling.**  The correction has the resolution of the registration's smoothing (its steps are smoothed by a
  Gaussian of ``pool`` voxels): its value at ``x`` is measured by every sample in that kernel, counted once per
  independent noise sample (``per_sample`` voxels: :func:`registration.dense.noise_correlation_factor`).  The
  precision at ``x`` is the information summed over the kernel (a Gaussian of peak 1).
* **Prior.**  ``u ~ N(0, σ_p² I)`` at each voxel: its mean is the start.  ``σ_p²`` is chosen by the data, as
  the value that makes the registration's own corrections most probable (type-II maximum likelihood, the
  evidence: ``u(x) ~ N(0, σ_p² I + P(x)⁻¹)``) over the scan's soft tissue — in effect the size of the
  corrections where the images measure them.
* **Posterior.**  Per voxel, ``C = (P + I/σ_p²)⁻¹`` and ``û = C P u``: where the images speak (``P ≫ 1/σ_p²``)
  the registration's correction stands, where they are silent it vanishes and the start stands.  The map's
  expected error at a voxel is ``σ = √tr C`` (mm).  On a bone held rigid, the correction is the bone's rigid
  motion and stays: its ``σ`` is that of the bone's rigid pose, from the Fisher information of its six
  parameters over its voxels and one voxel around (``(Σ Jᵀ I J + Λ)⁻¹``, ``J`` the rigid motion's Jacobian,
  ``Λ`` the refinement's bounds as a prior), and the two blend over the bone's fade.

References
----------
Simpson IJA, Schnabel JA, Groves AR, Andersson JLR, Woolrich MW. Probabilistic inference of regularisation in
non-rigid registration. NeuroImage 59 (2012) 2438–2451. https://doi.org/10.1016/j.neuroimage.2011.09.074
Le Folgoc L, Delingette H, Criminisi A, Ayache N. Quantifying registration uncertainty with sparse Bayesian
modelling. IEEE Trans Med Imaging 36 (2017) 607–617. https://doi.org/10.1109/TMI.2016.2623608
Ashburner J, Neelin P, Collins DL, Evans A, Friston K. Incorporating prior knowledge into image registration.
NeuroImage 6 (1997) 344–352. https://doi.org/10.1006/nimg.1997.0299
MacKay DJC. Bayesian interpolation. Neural Comput 4 (1992) 415–447 (the evidence for a prior's variance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from deformation.filters import smooth

__all__ = [
    "PosteriorResult",
    "information",
    "pooled_precision",
    "prior_variance",
    "prior_variance_with_motion",
    "posterior_correction",
    "rigid_jacobian",
    "rigid_pose_variance",
]

#: the Gaussians here are the dense registration's (``registration.dense.GAUSSIAN``): edge values continued, cut at 3 σ
GAUSSIAN = {"mode": "nearest", "truncate": 3.0}

#: the six components of a symmetric 3×3 tensor field, in this order (array axes z, y, x)
PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


@dataclass
class PosteriorResult:
    u: np.ndarray  #: the posterior mean of the correction (3, …) mm along the array axes
    sigma: np.ndarray  #: the expected error √tr C at each voxel (mm), float32
    gain: np.ndarray  #: the share of the registration's correction kept, tr(C P) / 3 (0: the start, 1: all)
    prior_sd: float  #: σ_p (mm per axis)


def _full(t: np.ndarray) -> np.ndarray:
    """(6, …) components → (…, 3, 3) symmetric matrices."""
    m = np.empty(t.shape[1:] + (3, 3), np.float64)
    for k, (i, j) in enumerate(PAIRS):
        m[..., i, j] = t[k]
        m[..., j, i] = t[k]
    return m


def information(f, w, sp, window, noise_var: float, per_sample: float = 1.0, mask=None) -> np.ndarray:
    """The Fisher information about a displacement of the map at each voxel (6, …; 1/mm², components ``PAIRS``
    along the array axes): ``sym(∇F ⊗ a ∇W) / σ_ε² / per_sample`` (module docstring).  ``f`` the scan, ``w`` the
    template through the map (same grid, spacing ``sp`` mm along the array axes), ``window`` the LNCC window's σ
    (voxels), ``noise_var`` the scan's noise
    variance (``f``'s units), ``mask`` (or None) the voxels that count (0 elsewhere)."""
    f = np.asarray(f, np.float32)
    w = np.asarray(w, np.float32)
    mf, mw, sfw, sww, sff = (smooth(a, window, **GAUSSIAN) for a in (f, w, f * w, w * w, f * f))
    vw = np.maximum(sww - mw * mw, np.float32(1e-12))
    cfw = sfw - mf * mw
    a = cfw / vw  # the local regression slope of F on W
    # the window's residual variance, at least the noise's (and above 0 for a noiseless image)
    resid = np.maximum(sff - mf * mf - a * cfw, np.float32(max(noise_var, 1e-10)))
    gf = [g / np.float32(h) for g, h in zip(np.gradient(f), sp)]
    gw = [g / np.float32(h) for g, h in zip(np.gradient(w), sp)]
    scale = a / (resid * np.float32(max(per_sample, 1.0)))
    out = np.empty((6,) + f.shape, np.float32)
    for k, (i, j) in enumerate(PAIRS):
        out[k] = 0.5 * (gf[i] * gw[j] + gf[j] * gw[i]) * scale
    if mask is not None:
        out *= np.asarray(mask, np.float32)[None]
    return out


def pooled_precision(info: np.ndarray, pool, sp, z: float = 2.0, *, eig: bool = False):
    """``info`` summed over a Gaussian of ``pool`` voxels (σ per axis) with peak 1 (the smoothed field times the
    kernel's sum, ``(2π)^{3/2} Π σ``), each eigenvalue lowered by ``z`` standard errors of that sum.

    The cross tensor of two noises has mean 0 but not value 0: summed over the kernel it keeps a fluctuation whose
    positive eigenvalues would claim information where the images carry none.  Its standard error follows from
    the model: each image carries half the residual variance ``σ_ε²`` (:func:`information` divides by it), so a
    central difference along axis ``i`` (spacing ``h_i``) carries noise of variance ``σ_ε² / (4 h_i²)`` (white
    noise; a correlated one has less, so this errs towards less information), and a component ``(i, j)`` of
    ``gᶠ gʷ / σ_ε²`` has variance ``(I_ii / h_j² + I_jj / h_i²) / 4 + 1 / (16 h_i² h_j²)`` about its mean
    (signal × noise and noise × noise; ``I`` the information without its noise, estimated by the kernel's mean).
    Summed with the kernel's weights its variance is ``Σ K²`` (``π^{3/2} Π σ``) times that; the eigenvalues are
    lowered by ``z`` times the Frobenius norm of those standard errors (a one-sided bound: the information that
    stands ``z`` standard errors above chance).  With ``eig`` the result is ``(λ, V)``, the eigenvalues (≥ 0)
    and vectors of ``P`` instead of ``P``, which :func:`prior_variance`, :func:`prior_variance_with_motion` and
    :func:`posterior_correction` take (``eig=``, their ``precision`` then None)."""
    pool = np.broadcast_to(np.asarray(pool, float), (3,))
    n = float((2.0 * np.pi) ** 1.5 * np.prod(pool))
    n2 = float(np.pi**1.5 * np.prod(pool))
    mean = np.stack([smooth(c, pool, **GAUSSIAN) for c in info])
    diag = np.maximum(mean[:3], 0.0)
    inv_h2 = [np.float32(1.0 / float(h) ** 2) for h in sp]
    var = np.zeros(info.shape[1:], np.float32)
    for i in range(3):
        for j in range(3):
            var += (diag[i] * inv_h2[j] + diag[j] * inv_h2[i]) * np.float32(0.25) + np.float32(
                inv_h2[i] * inv_h2[j] / 16.0
            )
    floor = np.float32(z) * np.sqrt(var * np.float32(n2))
    lam, vec = np.linalg.eigh(_full(mean * np.float32(n)))
    lam = np.clip(lam - floor[..., None].astype(np.float64), 0.0, None)
    if eig:
        return lam, vec
    full = np.einsum("...ik,...k,...jk->...ij", vec, lam, vec)
    return np.stack([full[..., i, j] for i, j in PAIRS]).astype(np.float32)


def _eig(p: np.ndarray, eig=None, idx=None):
    """Eigenvalues (clipped at 0: the cross tensor of misaligned edges can be negative) and vectors of (6, …) ``p``
    at the voxels ``idx`` (a tuple of index arrays; None: all), or those of ``eig`` (``(λ, V)`` of the whole
    of ``p``, :func:`pooled_precision`'s) there."""
    if eig is not None:
        lam, vec = eig
        return (lam, vec) if idx is None else (lam[idx], vec[idx])
    lam, vec = np.linalg.eigh(_full(p if idx is None else p[(slice(None),) + idx]))
    return np.clip(lam, 0.0, None), vec


#: the range (mm²) the evidence's prior variance is searched in: 0.01 mm to 10 mm SD
PRIOR_VARIANCE_BOUNDS = (1e-4, 100.0)


def prior_variance(
    u: np.ndarray,
    precision: np.ndarray,
    where: np.ndarray,
    *,
    lo=PRIOR_VARIANCE_BOUNDS[0],
    hi=PRIOR_VARIANCE_BOUNDS[1],
    eig=None,
) -> float:
    """σ_p² (mm²) that maximises the evidence of the corrections ``u`` (3, …) at the voxels ``where``:
    ``u(x) ~ N(0, σ_p² I + P(x)⁻¹)``, ``P`` the pooled ``precision`` (6, …).  In ``P``'s eigenbasis each component
    ``v_k`` has variance ``σ_p² + 1/λ_k``; up to terms free of ``σ_p²`` the negative log evidence is
    ``Σ log(1 + λ σ_p²) + λ v² / (1 + λ σ_p²)`` (a direction with ``λ = 0`` tells nothing).  Searched on
    ``log σ_p²`` within ``[lo, hi]``.  ``eig``: ``precision``'s ``(λ, V)`` (:func:`pooled_precision`)."""
    got = _evidence_terms(u, precision, where, eig)
    if got is None:  # nothing measured: the evidence is flat, and the lower bound says so
        return float(lo)
    return _best_prior_variance(*got[:2], lo, hi)


def _evidence_terms(u, precision, where, eig):
    """``(λ, v², idx)`` at the voxels ``where``: the eigenvalues of ``precision`` there and the squared components
    of ``u`` along its eigenvectors; None when nothing is measured there."""
    idx = np.nonzero(where)
    if not len(idx[0]):
        return None
    lam, vec = _eig(precision, eig, idx)
    if not np.any(lam > 0):
        return None
    uu = np.stack([c[idx] for c in u], axis=-1).astype(np.float64)
    return lam, np.einsum("nij,ni->nj", vec, uu) ** 2, idx


def _best_prior_variance(lam, v2, lo, hi) -> float:
    """:func:`prior_variance`'s search on ``log σ_p²`` within ``[lo, hi]``."""

    def neg(log_s):
        s = np.exp(log_s)
        d = 1.0 + lam * s
        return float(np.sum(np.log(d) + lam * v2 / d))

    r = minimize_scalar(neg, bounds=(np.log(lo), np.log(hi)), method="bounded", options={"xatol": 1e-3})
    return float(np.exp(r.x))


def prior_variance_with_motion(
    u: np.ndarray, precision: np.ndarray, where: np.ndarray, motion2: np.ndarray, *, eig=None
) -> tuple[float, float]:
    """``(σ₀², β²)`` that maximise the evidence of ``u`` under a prior whose variance grows with the motion so far,
    ``σ_p²(x) = σ₀² + β² m(x)`` (``m`` = ``motion2``, mm²: the squared correction the coarser levels made): a
    finer level's change is larger where a larger motion was being corrected.  The same evidence as
    :func:`prior_variance`, searched on ``(log σ₀², log β²)`` (Nelder–Mead) within ``PRIOR_VARIANCE_BOUNDS`` and
    ``β² ∈ [1e-6, 1]``."""
    from scipy.optimize import minimize

    lo, hi = PRIOR_VARIANCE_BOUNDS
    got = _evidence_terms(u, precision, where, eig)
    if got is None:  # nothing measured (see prior_variance)
        return float(lo), 1e-6
    lam, v2, idx = got
    m = np.asarray(motion2, np.float64)[idx][:, None]

    def unpack(x):
        return float(np.exp(np.clip(x[0], np.log(lo), np.log(hi)))), float(np.exp(np.clip(x[1], np.log(1e-6), 0.0)))

    def neg(x):
        s0, b = unpack(x)
        d = 1.0 + lam * (s0 + b * m)
        return float(np.sum(np.log(d) + lam * v2 / d))

    s_first = _best_prior_variance(lam, v2, lo, hi)  # the motion-free evidence's, a start
    best = min(
        (
            minimize(neg, np.log([s_first, b0]), method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-6})
            for b0 in (1e-3, 0.1)
        ),
        key=lambda r: r.fun,
    )
    return unpack(best.x)


def posterior_correction(u: np.ndarray, precision: np.ndarray, prior_var, *, eig=None) -> PosteriorResult:
    """Per voxel ``C = (P + I/σ_p²)⁻¹``, the posterior mean ``û = C P u`` and ``σ = √tr C``; in ``P``'s eigenbasis
    the gain along ``λ`` is ``λ σ_p² / (1 + λ σ_p²)`` and the variance ``σ_p² / (1 + λ σ_p²)``.  ``eig``:
    ``precision``'s ``(λ, V)`` (:func:`pooled_precision`)."""
    lam, vec = _eig(precision, eig)
    pv = np.asarray(prior_var, np.float64)
    pv = pv[..., None] if pv.ndim else pv  # a variance per voxel, or one for all
    d = 1.0 + lam * pv
    gain = lam * pv / d
    uu = np.moveaxis(u, 0, -1).astype(np.float64)
    v = np.einsum("...ij,...i->...j", vec, uu) * gain
    post = np.einsum("...ij,...j->...i", vec, v)
    return PosteriorResult(
        u=np.moveaxis(post, -1, 0).astype(np.float32),
        sigma=np.sqrt((pv / d).sum(axis=-1)).astype(np.float32),
        gain=(gain.mean(axis=-1)).astype(np.float32),
        prior_sd=float(np.sqrt(np.min(pv))),
    )


def rigid_jacobian(r: np.ndarray) -> np.ndarray:
    """The Jacobian ``[I | −[r]×]`` (``(n, 3, 6)``) of a small rigid motion ``t + ω × r`` at the points ``r``
    (``(n, 3)``, from the centre) with respect to ``(t, ω)``."""
    jac = np.zeros((len(r), 3, 6))
    jac[:, 0, 0] = jac[:, 1, 1] = jac[:, 2, 2] = 1.0
    # ω × r, rows: (ω₁ r₂ − ω₂ r₁, ω₂ r₀ − ω₀ r₂, ω₀ r₁ − ω₁ r₀)
    jac[:, 0, 4], jac[:, 0, 5] = r[:, 2], -r[:, 1]
    jac[:, 1, 3], jac[:, 1, 5] = -r[:, 2], r[:, 0]
    jac[:, 2, 3], jac[:, 2, 4] = r[:, 1], -r[:, 0]
    return jac


def rigid_pose_variance(info: np.ndarray, mask: np.ndarray, grid_mm, centre, prior_sd) -> tuple[np.ndarray, np.ndarray]:
    """A rigid body's pose covariance (6×6: translation mm, rotation rad about ``centre``) from the information
    of its voxels ``mask`` (``info``: (6, …) per voxel), ``(Σ Jᵀ I J + diag(1/prior_sd²))⁻¹``, ``J = [I | −[r]×]``
    (``r`` = x − centre, mm along the array axes, ``grid_mm`` the voxels' positions); and the expected error
    ``√tr(J C Jᵀ)`` (mm) at every voxel of ``grid_mm``'s arrays."""
    idx = np.nonzero(mask)
    r = np.stack([g[idx] - c for g, c in zip(grid_mm, centre)], axis=-1).astype(np.float64)
    ii = _full(info[(slice(None),) + idx])
    jac = rigid_jacobian(r)
    fisher = np.einsum("nia,nij,njb->ab", jac, ii, jac)
    cov = np.linalg.pinv(fisher + np.diag(1.0 / np.asarray(prior_sd, float) ** 2))
    # tr(J C Jᵀ) at every voxel: the translation block, plus the rotation block's |r|² I − r rᵀ part and the
    # cross terms, written out for the arrays
    rr = [g - c for g, c in zip(grid_mm, centre)]
    ct, cr, cx = cov[:3, :3], cov[3:, 3:], cov[:3, 3:]
    tr = np.full(rr[0].shape, np.trace(ct))
    # J_rot = −[r]×: tr([r]× C_r [r]×ᵀ) = |r|² tr C_r − rᵀ C_r r
    r2 = rr[0] ** 2 + rr[1] ** 2 + rr[2] ** 2
    tr = tr + r2 * np.trace(cr) - sum(cr[a, b] * rr[a] * rr[b] for a in range(3) for b in range(3))
    # 2 tr(C_tr [r]×ᵀ): [r]×ᵀ = −[r]×, tr(C_x(−[r]×)) with [r]× = [[0, −r2, r1], [r2, 0, −r0], [−r1, r0, 0]]
    tr = tr - 2.0 * (
        cx[0, 1] * (-rr[2])
        + cx[0, 2] * rr[1]
        + cx[1, 0] * rr[2]
        + cx[1, 2] * (-rr[0])
        + cx[2, 0] * (-rr[1])
        + cx[2, 1] * rr[0]
    )
    return cov, np.sqrt(np.clip(tr, 0.0, None)).astype(np.float32)
