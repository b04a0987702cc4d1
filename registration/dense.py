"""Articulated dense registration: diffeomorphic local-correlation steps with the bones kept rigid.

Rhee's Algorithm 1 (:mod:`registration.adaptive`, Rhee §4.3) moves one block at a
time and keeps a step only when it pays; this method moves every voxel at every
iteration, in the manner of ANTs SyN's greedy cross-correlation registration,
and keeps what an articulated body needs.  From a one-to-one start ``φ₀``
(scan → template, the polyrigid flow of :mod:`deformation.models.polyrigid`) it finds
``U = id + u`` on the scan grid with ``F ≈ M ∘ φ₀ ∘ U`` and returns
``φ = φ₀ ∘ U``: local normalised cross-correlation (LNCC) in a Gaussian
window, its gradient smoothed ("fluid") and composed into ``U`` within a trust
radius, ``U`` smoothed ("elastic"), every step one-to-one, the bones held
rigid at the pose stage's placement (their poses refined on the same
objective), coarse to fine.  :func:`register_dense` describes each part;
:class:`DenseSettings` holds the settings, whose measurements are in
``docs/measurements/registration-settings.md``.

References
----------
Avants BB, Epstein CL, Grossman M, Gee JC. Symmetric diffeomorphic image
registration with cross-correlation. Med Image Anal 12 (2008) 26–41.
https://doi.org/10.1016/j.media.2007.06.004
Vercauteren T, Pennec X, Perchant A, Ayache N. Diffeomorphic demons.
NeuroImage 45 (2009) S61–S72. https://doi.org/10.1016/j.neuroimage.2008.10.040
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field

import numba
import numpy as np
from scipy import ndimage

from deformation.fields.displacement import folding_statistics, jacobian_determinant_components, unfold
from deformation.fields.interpolate import sample_array, sample_displaced_array, sample_shifted
from deformation.filters import smooth
from deformation.geometry import GridGeometry, Volume

from . import posterior as bayes
from .metrics import air_level, cc, similarity, warp_template

__all__ = [
    "DenseSettings",
    "DenseResult",
    "register_dense",
    "TemplateSampler",
    "bone_fit_improves",
    "fission",
    "jacobian_min",
    "kernel_noise",
    "membrane_energy",
    "noise_correlation_factor",
    "penalties",
    "refine_bone",
    "share_of_air_around",
    "voxel_in_voxels",
    "voxel_noise_variance",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DenseSettings:
    """Settings of :func:`register_dense` (lengths in mm, so that they mean the same on any grid).

    The measurements behind the defaults are in ``docs/measurements/registration-settings.md``.
    """

    shrink: tuple = (4, 2, 1)  #: subsampling per level, coarse to fine
    #: trials per level, at most: a cap for safety; a level stops on convergence (tolerance, max_halvings)
    iterations: tuple = (200, 200, 200)
    #: LNCC Gaussian window σ: about the size of the soft tissue's structure (septa, vessels), so that the
    #: correlation follows it rather than the skin's edge (registration-settings.md, "window_mm")
    window_mm: float = 3.0
    fluid_mm: float = 4.0  #: σ of the smoothing of each step, when fluid_voxels is None
    step_mm: float = 0.5  #: the trust radius's upper bound: a voxel's largest move in one step (see step_voxels)
    step_voxels: bool = True  #: step_mm is in voxels of the level (True) or mm (False)
    radius_growth: float = 1.25  #: the trust radius grows by this factor after a taken step (up to step_mm)
    max_halvings: int = 5  #: a level stops when a step of radius step_mm·2⁻ᵏ does not raise its objective
    min_jacobian: float = 0.2  #: every step keeps det(I + ∇f) above this
    #: "fixed" (U = id on the bones: the pose stage placed them), "rigid" (each moves rigidly), "free"
    bones: str = "fixed"
    bone_margin_mm: float = 4.0  #: the bones' motion fades into the smooth step over this distance
    #: with bones="fixed": each held bone's pose refined as a rigid body on the level's objective, the soft tissue
    #: held (:func:`register_dense`, Notes)
    refine_bones: bool = True
    refine_deg: float = 8.0  #: the refinement's bound on each rotation-vector component from the start's pose
    refine_mm: float = 4.0  #: ... and on each axis of the translation: the estimate is corrected, not replaced
    refine_evaluations: int = 150  #: objective evaluations per bone and round, at most (NLopt BOBYQA)
    #: rounds of the bones' refinement per level, at most: one before the steps, then one each time they stop
    refine_rounds: int = 3
    refine_margin_voxels: float | None = 1.0  #: a refined bone's motion fades over this many level voxels
    #: a bone's pose is first changed only when the refinement moves one of its voxels by more than this many
    #: scan voxels (the LNCC's optimum sits a few tenths of a mm from the bone's own fit)
    refine_min_move_voxels: float = 0.5
    #: a bone not moved so far is tested on a level only where it is at least this many level voxels thick
    refine_min_voxels: float = 3.0
    #: ... and moved only when its own fit rises by more than this many standard errors (Fisher's z of its NCC:
    #: ``bone_fit_improves``); 0 accepts any rise
    refine_significance: float = 2.0
    elastic_mm: float = 2.0  #: σ of the smoothing of the field after each step (0: none), when elastic_voxels is None
    #: fluid σ in voxels of each level (None: fluid_mm), as ANTs SyN's: each level regularises at its own scale
    #: (registration-settings.md, "fluid_voxels")
    fluid_voxels: float | None = 3.0
    elastic_voxels: float | None = 0.8  #: elastic σ in voxels of each level (None: elastic_mm)
    #: a level stops when 10 taken steps gain less than this much of its objective
    tolerance: float = 1e-4
    #: the LNCC windows and both smoothings keep to the scan's tissue (when air surrounds its body), so that the
    #: skin's motion is not averaged with the air's, which no image drives (registration-settings.md, "tissue_only")
    tissue_only: bool = True
    air_weight: float = 0.05  #: the air's weight in U's normalised smoothing when tissue_only (1: a plain Gaussian)
    #: with tissue_only, the weight of the skin's term (the bodies' smoothed masks' squared difference near the
    #: scan's skin), which holds the registered body's outline on the scan's; 0: off
    #: (registration-settings.md, "skin_weight and stiffness")
    skin_weight: float = 1.0
    #: the weight of the membrane energy of the correction ``u``, each voxel weighed by the noise's share of the
    #: scan's local variance: the start stands where the scan shows only noise; 0: off
    stiffness: float = 3.0
    body_only: bool = True  #: forces only inside the two images' bodies grown by 2 windows (air has no anatomy)
    unfold: bool = (
        True  #: remove the result's grid-level folds inside the body (deformation.fields.displacement.unfold)
    )
    #: the LNCC's template variance evened out over the positions trilinear sampling reads the template at
    #: (``interpolation_noise_variance``); off by default (registration-settings.md, "interpolation_noise")
    interpolation_noise: bool = False
    #: data fission (Leiner et al. 2023): each level returns the map its held-out copy of the noise scores
    #: highest (``fission``); off by default (registration-settings.md, "holdout")
    holdout: bool = False
    #: ``a``: the steps' images carry (1 + a²) times the image's noise variance, the held-out copy (1 + 1/a²) times
    holdout_share: float = 0.35
    holdout_patience: int = 10  #: a level stops after this many taken steps without a new highest held-out LNCC
    holdout_seed: int = 0  #: the draw of the fission's noise (same inputs and seed, same bits)
    #: each level's change weighed against its input by what the images measure (:mod:`registration.posterior`):
    #: the result carries its expected error at each voxel (``DenseResult.uncertainty``); False: none
    posterior: bool = True
    #: σ (voxels of each level) of the kernel over which a level's change is measured (the resolution of the
    #: field); None: the level's fluid smoothing (``fluid_voxels``, or ``fluid_mm`` in its voxels)
    posterior_pool_voxels: float | None = None
    #: the registration's own error (its smoothing's bias, a motion it recovered in part) as a share of the
    #: correction it made, added to the posterior's σ in quadrature: the noise alone leaves σ several times too
    #: small where a large motion was corrected (registration-settings.md, "posterior")
    posterior_relative_error: float = 0.4
    #: each level keeps the posterior mean of its change (True: where the images are silent the level's input
    #: stands) or the steps' own change, the posterior then giving the expected error only (False, the default:
    #: on the tuning draws the posterior mean cost the large bends more than it gave the small-residual cases,
    #: dense-registration.md, "The correction as inference")
    posterior_mean: bool = False
    #: with posterior_mean False, σ counts how far the steps' change sits from the posterior mean: the expected
    #: squared error of an estimate Δ under the posterior N(û, C) is ``tr C + |Δ − û|²`` (False: ``tr C`` alone)
    posterior_offset: bool = True
    #: the whole correction from the start weighed too, on the finest level against the start (its prior's
    #: variance the evidence's): in the soft tissue σ² is at least that posterior's expected squared error, so a
    #: direction the images never measured keeps the error a start typically has, not a level's change's
    #: (dense-registration.md, "The whole correction against the start")
    posterior_total: bool = True

    def __post_init__(self):
        if len(self.shrink) != len(self.iterations) or not self.shrink:
            raise ValueError("shrink and iterations need one entry per level")
        if any(int(s) < 1 for s in self.shrink):
            raise ValueError(f"shrink factors must be ≥ 1, got {self.shrink}")
        if self.bones not in ("fixed", "rigid", "free"):
            raise ValueError(f"bones must be 'fixed', 'rigid' or 'free', got {self.bones!r}")
        if self.window_mm <= 0 or self.fluid_mm < 0 or self.step_mm <= 0 or not 0 <= self.min_jacobian < 1:
            raise ValueError("window_mm > 0, fluid_mm ≥ 0, step_mm > 0 and 0 ≤ min_jacobian < 1 are required")
        if any(v is not None and not v >= 0 for v in (self.fluid_voxels, self.elastic_voxels)):
            raise ValueError(
                f"fluid_voxels and elastic_voxels must be ≥ 0 or None, got {self.fluid_voxels}, {self.elastic_voxels}"
            )
        for name in ("skin_weight", "stiffness"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be ≥ 0, got {getattr(self, name)}")
        if not self.radius_growth >= 1 or not isinstance(self.max_halvings, int) or self.max_halvings < 0:
            raise ValueError(
                f"radius_growth must be ≥ 1 and max_halvings ≥ 0, got {self.radius_growth}, {self.max_halvings}"
            )
        whole = [isinstance(v, int) and not isinstance(v, bool) for v in (self.refine_evaluations, self.refine_rounds)]
        if not (
            self.refine_deg > 0
            and self.refine_mm > 0
            and all(whole)
            and self.refine_evaluations >= 13
            and self.refine_rounds >= 1
        ):
            raise ValueError(
                f"refine_deg and refine_mm must be > 0, refine_evaluations a whole number ≥ 13 "
                f"(BOBYQA's first model needs 2·6 + 1) and refine_rounds ≥ 1, got {self.refine_deg}, "
                f"{self.refine_mm}, {self.refine_evaluations}, {self.refine_rounds}"
            )
        if not (
            self.refine_min_move_voxels >= 0
            and self.refine_min_voxels >= 1
            and self.bone_margin_mm > 0
            and self.refine_significance >= 0
            and (self.refine_margin_voxels is None or self.refine_margin_voxels > 0)
        ):
            raise ValueError(
                f"refine_min_move_voxels ≥ 0, refine_min_voxels ≥ 1, bone_margin_mm > 0, "
                f"refine_significance ≥ 0 (got {self.refine_significance}) and "
                f"refine_margin_voxels > 0 (or None) are required, got {self.refine_min_move_voxels}, "
                f"{self.refine_min_voxels}, {self.bone_margin_mm}, {self.refine_margin_voxels}"
            )
        if not (self.holdout_share > 0 and isinstance(self.holdout_patience, int) and self.holdout_patience >= 1):
            raise ValueError(
                f"holdout_share must be > 0 and holdout_patience a whole number ≥ 1, got "
                f"{self.holdout_share}, {self.holdout_patience}"
            )
        if not (np.isfinite(self.posterior_relative_error) and self.posterior_relative_error >= 0):
            raise ValueError(f"posterior_relative_error must be ≥ 0, got {self.posterior_relative_error}")
        if self.posterior_pool_voxels is not None and not self.posterior_pool_voxels > 0:
            raise ValueError(f"posterior_pool_voxels must be > 0 or None, got {self.posterior_pool_voxels}")
        if not 0 < self.air_weight <= 1:
            raise ValueError(f"air_weight must be in (0, 1], got {self.air_weight}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class DenseResult:
    correspondence: Volume  #: scan_to_template (mm) on the scan grid: φ₀ ∘ U
    registered: Volume  #: the template resampled through it
    seconds: float
    levels: list = field(default_factory=list)  #: per level: shape, iterations, LNCC before/after, halvings, s
    settings: dict = field(default_factory=dict)
    similarity_before: dict = field(default_factory=dict)  #: SSD/CC/MI of the scan and the start's template
    similarity_after: dict = field(default_factory=dict)  #: … and the registered template
    #: det statistics of the result over the scan's body (deformation.fields.displacement.folding_statistics;
    #: ``over`` says which voxels) and ``n_folded_u``, the folds of U alone (0: every step was one-to-one)
    folding: dict = field(default_factory=dict)
    unfold: dict | None = (
        None  #: what the final repair changed (deformation.fields.displacement.unfold), None if nothing
    )
    #: settings.posterior: the expected error at each scan voxel (mm), ``σ = √(Σ_levels (tr C + |Δu − û|²) + (α|u|)²)``,
    #: None when off: each level's posterior variance, how far its kept change Δu sits from the posterior mean û
    #: (settings.posterior_offset; 0 with posterior_mean), in the soft tissue at least the whole correction's posterior
    #: against the start (settings.posterior_total), and a share α of the correction (the registration's own error)
    uncertainty: Volume | None = None
    #: settings.posterior: the prior's SD, the noise, the pooling and the share of the correction kept
    posterior: dict | None = None


#: the bones' significance test compares images smoothed by at least this σ in scan voxels and in template voxels
#: (the larger in mm): trilinear interpolation between the template's voxel centres then changes its noise variance
#: by at most ~1.5× (against 8× unsmoothed), so a candidate's NCC hardly rises by sampling its noise more thinly
TEST_SMOOTH_VOXELS = 1.0


#: the dense registration's Gaussians (:func:`deformation.filters.smooth`, SciPy's, σ in voxels of the level):
#: the edge values continued (a level's box ends in the air), the kernel cut at 3 σ
GAUSSIAN = {"mode": "nearest", "truncate": 3.0}


#: arrays smaller than this (voxels) are smoothed serially: handing a bone's box to the threads costs more than
#: it saves (32³, as the interpolation's serial threshold)
SMOOTH_SERIAL_BELOW = 32768
POOLS: dict = {}  # one thread pool per thread count, kept: starting threads at every step cost ~1 s a run
POOLS_LOCK = threading.Lock()
# a forked child inherits the pools without their threads, and map() on one would wait forever
os.register_at_fork(after_in_child=POOLS.clear)


def smooth_all(arrays, sigma_vox) -> list:
    """Each array smoothed by the dense Gaussian (``GAUSSIAN``), on as many threads as numba's setting
    allows (SciPy's filters release the GIL; arrays of fewer than ``SMOOTH_SERIAL_BELOW`` voxels serially).
    Whole arrays go to the threads in turn; the ones left over (the third of three on two threads) are cut into one slab
    per thread along their longest axis, each with a halo of the kernel's reach: a Gaussian is a 1-D filter per axis,
    and every output voxel of a slab is computed from the same inputs in the same order as on the whole array, so the
    bits do not depend on the thread count."""
    n = min(len(arrays), max(int(numba.get_num_threads()), 1))
    # small arrays (a bone's box in the refinement) serially: handing them to the threads costs more than it saves
    if n <= 1 or not np.any(np.asarray(sigma_vox) > 0) or max(a.size for a in arrays) < SMOOTH_SERIAL_BELOW:
        return [smooth(a, sigma_vox, **GAUSSIAN) for a in arrays]
    with POOLS_LOCK:
        if n not in POOLS:
            POOLS[n] = ThreadPoolExecutor(n, thread_name_prefix="dense-smooth")
    n_whole = len(arrays) - len(arrays) % n
    out = [None] * len(arrays)
    jobs = [(i, None, None) for i in range(n_whole)]
    sig = np.broadcast_to(np.asarray(sigma_vox, float), (arrays[0].ndim,))
    for i in range(n_whole, len(arrays)):
        a = arrays[i]
        ax = int(np.argmax(a.shape))
        reach = int(GAUSSIAN["truncate"] * float(sig[ax]) + 0.5)  # SciPy's kernel radius
        cuts = np.linspace(0, a.shape[ax], n + 1).astype(int)
        out[i] = np.empty_like(a)
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            jobs.append((i, ax, (int(lo), int(hi), max(int(lo) - reach, 0), min(int(hi) + reach, a.shape[ax]))))

    def run(job):
        i, ax, cut = job
        if ax is None:
            out[i] = smooth(arrays[i], sigma_vox, **GAUSSIAN)
            return
        lo, hi, lo_h, hi_h = cut
        take = [slice(None)] * arrays[i].ndim
        take[ax] = slice(lo_h, hi_h)
        sm = smooth(arrays[i][tuple(take)], sigma_vox, **GAUSSIAN)
        keep = [slice(None)] * arrays[i].ndim
        keep[ax] = slice(lo - lo_h, hi - lo_h)
        dest = [slice(None)] * arrays[i].ndim
        dest[ax] = slice(lo, hi)
        out[i][tuple(dest)] = sm[tuple(keep)]

    list(POOLS[n].map(run, jobs))
    return out


def local_stats(f, sig, mask=None):
    """The fixed image's local mean and variance in the LNCC window (the same at every step of a level), and
    the window's mask, its local weight and mask·f (``None`` without a mask)."""
    if mask is None:
        mf, sff = smooth_all([f, f * f], sig)
        return mf, sff - mf * mf, None
    masked_f = mask * f  # kept: every step's f·w term uses it
    sm, smf, smff = smooth_all([mask, masked_f, masked_f * f], sig)
    sm = np.maximum(sm, 1e-3)
    mf = smf / sm
    return mf, smff / sm - mf * mf, (mask, sm, masked_f)


def lncc_force(f, w, sig, f_stats, region=None, v=None):
    """LNCC of ``f`` and ``w`` (mean over the voxels where ``region`` > 0, or all) and its gradient with
    respect to ``w`` (Avants 2008, Eq. 5); ``f_stats`` = :func:`local_stats` of ``f``.  With a window mask
    the local statistics are over the mask's voxels only, and the gradient is 0 outside it (the smoothed force
    still reaches into the air from the tissue).  ``v`` (or ``None``): a variance added to ``w``'s at each
    voxel (``interpolation_noise_variance``), in its local second moment, times the share of a voxel's noise
    variance a window's variance holds: the variance of independent samples about their weighted mean is
    ``1 − Σ K²`` of theirs, ``K`` the window's weights (its discrete kernel; ~0 for a window under a voxel, as on
    the coarse levels, where there is then nothing to even out; the level's samples are nearly independent, the
    pre-smoothing's σ being under half a level voxel; a tissue-only window's mask is left out of it).  The
    factor ignores that sampling between centres also correlates neighbouring samples' noise, which a window of
    about a voxel or less feels: there the term over-corrects (docs/measurements/dense-registration.md)."""
    mf, sff, masked = f_stats
    if v is not None:
        v = v * np.float32(
            1.0 - np.prod([kernel_noise(float(x))[0] for x in np.broadcast_to(np.asarray(sig, float), (3,))])
        )
    if masked is None:
        mw, sww, sfw = smooth_all([w, w * w if v is None else w * w + v, f * w], sig)
    else:
        mask, sm, masked_f = masked
        mask_w = mask * w
        ww = mask_w * w if v is None else mask_w * w + mask * v
        mw, sww, sfw = (a / sm for a in smooth_all([mask_w, ww, masked_f * w], sig))
    sww = sww - mw * mw
    sfw = sfw - mf * mw
    # A floor on the local variances (intensities are normalised to ~[0, 1]): flat air or marrow has no
    # correlation to follow.  A constant, not a mean over the image: float32 reductions round differently
    # with the arrays' memory alignment, and the result must be the same bits on every run.
    eps = 1e-5
    sff = np.maximum(sff, eps)
    sww = np.maximum(sww, eps)
    cc = sfw * sfw / (sff * sww)
    dcc = 2.0 * sfw / (sff * sww) * ((f - mf) - sfw / sww * (w - mw))
    if masked is not None:
        dcc = dcc * masked[0]
    return float(np.mean(cc if region is None else cc[region > 0], dtype=np.float64)), dcc


def _pseudo_residual_variance(d: np.ndarray, where: np.ndarray | None) -> float:
    """Gasser et al.'s pseudo-residual ``(2 I_k − I_{k−1} − I_{k+1}) / √6`` along each axis (white noise's
    variance; a smooth signal cancels), its robust scale (1.4826 × the median absolute value) squared, averaged
    over the axes, over the voxels of ``where`` (or all).  Runs of three equal voxels are left out: a constant
    fill (a CT's outside of its reconstruction circle, a zero-filled background) has no noise to measure, and
    would pull the median to 0.  An axis with fewer than 100 stencils is skipped; 0 when none is left.
    Gasser T, Sroka L, Jennen-Steinmetz C. Residual variance and residual pattern in nonlinear regression.
    Biometrika 73 (1986) 625–633."""
    var = []
    for a in range(3):
        if d.shape[a] < 3:
            continue
        c = [slice(1, -1) if b == a else slice(None) for b in range(3)]
        lo = [slice(0, -2) if b == a else slice(None) for b in range(3)]
        hi = [slice(2, None) if b == a else slice(None) for b in range(3)]
        e = (2.0 * d[tuple(c)] - d[tuple(lo)] - d[tuple(hi)]) / np.sqrt(6.0)
        keep = (d[tuple(c)] != d[tuple(lo)]) | (d[tuple(c)] != d[tuple(hi)])
        if where is not None:
            keep &= where[tuple(c)] & where[tuple(lo)] & where[tuple(hi)]
        e = e[keep]
        if e.size >= 100:  # a median over fewer is no measure
            var.append((1.4826 * float(np.median(np.abs(e)))) ** 2)
    return float(np.mean(var)) if var else 0.0


#: the air (beyond the body grown by this many voxels) gives the noise when it has at least AIR_NOISE_VOXELS
AIR_NOISE_GROW, AIR_NOISE_VOXELS = 2, 1000


def voxel_noise_variance(data: np.ndarray, body: np.ndarray | None) -> tuple[float, float]:
    """The variance of an image's voxel-to-voxel (white) noise in its tissue and in its air, measured in the air
    where there is enough of it: there is no anatomy there, so the pseudo-residual
    (``_pseudo_residual_variance``) is the noise's alone.  A magnitude image's air (no value below 0, mean
    over SD within 1.6-2.3 of the Rayleigh's 1.91 and median over mean within 0.03 of its 0.939) holds
    Rayleigh noise, whose variance is (2 − π/2) of the tissue's Gaussian σ² (Gudbjartsson & Patz 1995); any
    other air's noise is the tissue's (CT, a Gaussian MRI).  Without enough air that is not a constant fill (or
    ``body`` None): the pseudo-residual over the body a voxel inside its edge (which the tissue's voxel-scale
    texture inflates) for both.  The noise is taken as white: a correlated one (a reconstruction kernel,
    zero-filling) is measured low, and the correction then does less than it could.  Gudbjartsson H, Patz S.
    The Rician distribution of noisy MRI data. Magn Reson Med 34 (1995) 910–914."""
    d = np.asarray(data, np.float32)
    if body is not None:
        air = ~ndimage.binary_dilation(body, iterations=AIR_NOISE_GROW)
        if int(air.sum()) >= AIR_NOISE_VOXELS:
            x = d[air].astype(np.float64)
            values, counts = np.unique(x, return_counts=True)
            if counts.max() > 0.05 * x.size:  # a constant fill is no noise: its statistics are the rest's
                x = x[x != values[counts.argmax()]]
            var = _pseudo_residual_variance(d, air)
            if var > 0 and x.size >= AIR_NOISE_VOXELS:
                sd = float(x.std())
                rayleigh = (
                    x.min() >= 0
                    and sd > 0
                    and 1.6 <= x.mean() / sd <= 2.3
                    and abs(float(np.median(x)) / x.mean() - np.sqrt(np.log(4.0) / (np.pi / 2.0))) < 0.03
                )
                if rayleigh:
                    return var / (2.0 - np.pi / 2.0), var
                return var, var
        inner = ndimage.binary_erosion(body, iterations=1)
        if int(inner.sum()) >= 100:
            var = _pseudo_residual_variance(d, inner)
            return var, var
    var = _pseudo_residual_variance(d, None)
    return var, var


def fission(f: np.ndarray, body: np.ndarray | None, moving: Volume, m_body: np.ndarray | None, st) -> tuple:
    """Data fission of both images (settings.holdout): ``x + a z`` for the steps and ``x − z / a`` held out,
    ``z`` Gaussian white noise of each image's own noise SD (its tissue's, measured in its air where there is
    enough: :func:`voxel_noise_variance`; a magnitude image's noise is Gaussian in the tissue), so that the two
    copies' noises are independent where the image's noise is Gaussian and white (Leiner J, Duan B, Wasserman
    L, Ramdas A. Data fission: splitting a single data point. J Am Stat Assoc (2023)).  ``f`` is the scan's
    array, ``body`` its body and ``m_body`` the template's (None: the noise measured over every voxel).  Returns
    ``((f_held_out, template_held_out, sds), f_steps, template_steps)``: new arrays and volumes, the inputs
    untouched."""
    a = np.float32(st.holdout_share)
    rng = np.random.default_rng(st.holdout_seed)
    m = np.asarray(moving.data, np.float32)
    sd_f = np.float32(np.sqrt(voxel_noise_variance(f, body)[0]))
    sd_m = np.float32(np.sqrt(voxel_noise_variance(m, m_body)[0]))
    z = rng.standard_normal(f.shape, dtype=np.float32) * sd_f
    f_steps, f_held = (f + a * z).astype(np.float32), (f - z / a).astype(np.float32)
    z = rng.standard_normal(m.shape, dtype=np.float32) * sd_m
    m_steps = Volume((m + a * z).astype(np.float32), moving.geometry)
    m_held = Volume((m - z / a).astype(np.float32), moving.geometry)
    return (f_held, m_held, (float(sd_f), float(sd_m))), f_steps, m_steps


def kernel_noise(sigma: float) -> tuple[float, float]:
    """White noise smoothed by the dense Gaussian (``GAUSSIAN``) of ``sigma`` voxels along one axis: its variance
    (as a share of the unsmoothed one) and the correlation of neighbouring voxels."""
    if sigma <= 0:
        return 1.0, 0.0
    delta = np.zeros(2 * int(3.0 * sigma + 0.5) + 3)
    delta[len(delta) // 2] = 1.0
    k = ndimage.gaussian_filter1d(delta, sigma, mode="constant", truncate=3.0)
    return float((k * k).sum()), float((k[1:] * k[:-1]).sum() / (k * k).sum())


def interpolation_noise_variance(p: np.ndarray, var: float, rho) -> np.ndarray:
    """What evens out the template's noise variance over the positions trilinear sampling reads it at: for
    index positions ``p`` (3, ...) of a template whose noise has variance ``var`` and neighbour correlation
    ``rho[a]`` along index axis ``a``, the variance the noise keeps on average over positions less the one it
    keeps at ``p``.

    Sampling between voxel centres averages neighbours: at fraction ``t`` along an axis the noise keeps
    ``(1 − t)² + t² + 2 t (1 − t) ρ = 1 − 2 t (1 − t)(1 − ρ)`` of its variance (the three axes multiply), down
    to 1/8 for white noise midway on all three.  A map that falls between centres lowers the sampled template's
    local variance and the LNCC rises with it: the registration is drawn to such positions wherever the tissue
    is flat (the interpolation artefact Pluim et al. 2000 describe for mutual information).  Added to the
    sampled template's local variance, this leaves every position with the noise of the average position
    (``Π (1 − (1 − ρ_a) / 3)``, fractions spread evenly): the artefact is gone, and the windows' noise weighs
    on the correlation as much as it does on average without the correction (the whole noise, as at a voxel
    centre, would favour maps that bring more of the template's signal variance into a window, such as its
    skin's edge into the scan's body).  Negative at and near the centres.  Pluim JPW, Maintz JBA, Viergever
    MA. Interpolation artefacts in mutual information-based image registration. Comput Vis Image Underst 77
    (2000) 211–232."""
    f = np.ones(p.shape[1:], np.float32)
    mean = 1.0
    for a in range(3):
        t = p[a] - np.floor(p[a])
        f *= 1.0 - 2.0 * (1.0 - rho[a]) * t * (1.0 - t)
        mean *= 1.0 - (1.0 - rho[a]) / 3.0  # fractions spread evenly: the mean of 2 t (1 − t) is 1/3
    return (np.float32(var) * (np.float32(mean) - f)).astype(np.float32)


def weighted_smooth(arrays, weight, norm, sigma_vox) -> np.ndarray:
    """Normalised convolution of each array with weights ``weight``: ``G∗(w·a) / G∗w``, ``norm`` = 1 / G∗w
    (the same for every step of a level).  A voxel's value is its neighbours' weighted mean: where the weight
    is 1 in the tissue and small in the air, the skin's value is (almost) the tissue's alone."""
    return np.stack(smooth_all([a * weight for a in arrays], sigma_vox)) * norm[None]


def _body_region(fixed: Volume, moving: Volume, grow_mm: float):
    """The scan's body (:func:`registration.segmentation.segment_body`) and the voxels inside either image's
    body or within ``grow_mm`` of it (float32 0/1), where the force acts.

    ``(None, None)`` when the segmentation finds no tissue (then every voxel takes part).  On an image without
    air (a field of view inside the limb) the "body" is the brighter tissue: see :func:`share_of_air_around`.
    """
    from .segmentation import segment_body

    try:
        body_f = segment_body(fixed).data > 0
        body = body_f | (segment_body(moving).data > 0)
    except ValueError:
        return None, None
    d = ndimage.distance_transform_edt(~body, sampling=np.asarray(fixed.geometry.spacing, float)[::-1])
    return body_f, (d <= grow_mm).astype(np.float32)


#: settings.tissue_only applies when at least this share of the grid's faces lies outside the scan's body (air
#: surrounds it): without air the segmentation's "body" is the brighter tissue, and keeping to it would drop the
#: rest of the tissue (registration-settings.md, "tissue_only")
AIR_AROUND = 0.75


def share_of_air_around(body: np.ndarray) -> float:
    """The share of the grid's face voxels outside ``body``."""
    faces = [body[0], body[-1], body[:, 0], body[:, -1], body[:, :, 0], body[:, :, -1]]
    return float(sum(int((~f).sum()) for f in faces) / sum(f.size for f in faces))


def _crop_box(region: np.ndarray | None, shape, margin_vox, align: int) -> tuple:
    """The array box (slices) holding ``region``'s voxels grown by ``margin_vox`` per axis, its low corner
    rounded down to a multiple of ``align`` (so every level samples the same voxels as on the whole grid);
    the whole grid when there is no region."""
    if region is None or not np.any(region):
        return tuple(slice(0, n) for n in shape)
    box = []
    for ax, n in enumerate(shape):
        hit = np.nonzero(np.any(region, axis=tuple(a for a in range(len(shape)) if a != ax)))[0]
        lo = max(int(hit[0]) - int(margin_vox[ax]), 0) // align * align
        box.append(slice(lo, min(int(hit[-1]) + 1 + int(margin_vox[ax]), n)))
    return tuple(box)


def _bone_cores(labels: np.ndarray, peel: int, sp) -> np.ndarray:
    """Each bone's voxels deeper than ``peel`` voxels inside it — or its deepest ones, so no bone is freed whole.

    Depth is measured per bone (within its own bounding box grown by one voxel) in voxels of the smallest
    spacing; the grid's edge does not count as a surface (a limb cut by the field of view stays frozen there).
    """
    out = np.zeros(labels.shape, bool)
    unit = float(np.min(sp))
    for lab, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        box = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        m = labels[box] == lab
        d = ndimage.distance_transform_edt(m, sampling=sp) / unit  # to the nearest non-bone voxel of the box
        out[box] |= m & (d > min(float(peel), float(d.max()) - 1e-6))
    return out


def _bone_weights(lab: np.ndarray, bones, sp, margin_mm: float) -> list:
    """Per bone of ``lab`` (≥ 4 voxels): ``(label, box, mask, weight)`` on the bone's bounding box grown by the
    margin — ``weight`` 1 on the bone, falling linearly to 0 at ``margin_mm`` (mm, spacing ``sp``) — so that
    the distance maps cost the bones' neighbourhoods, not the grid (21 bones on a hand)."""
    out = []
    reach = [int(np.ceil(margin_mm / v)) + 1 for v in sp]
    objs = ndimage.find_objects(lab)
    for b in bones:
        if b > len(objs) or objs[b - 1] is None:
            continue
        box = tuple(slice(max(o.start - r, 0), min(o.stop + r, n)) for o, r, n in zip(objs[b - 1], reach, lab.shape))
        m = lab[box] == b
        if m.sum() < 4:
            continue
        d = ndimage.distance_transform_edt(~m, sampling=sp)
        out.append((b, box, m, np.clip(1.0 - d / margin_mm, 0.0, 1.0).astype(np.float32)))
    return out


def _sample(a, coords, order=1):
    return ndimage.map_coordinates(a, coords, order=order, mode="nearest")


def jacobian_min(u, sp):
    """Smallest det(I + ∇u) of a displacement ``u`` (3, nz, ny, nx) in mm along the array axes (spacing ``sp``)."""
    return float(jacobian_determinant_components(u, sp).min())


def _rigid_project(f, mask, grid_mm, weight):
    """Replace ``f`` (3, …, mm, array axes) near ``mask`` by its least-squares rigid motion over ``mask``.

    The motion ``t + ω × (x − c)`` (linearised rotation) is fitted to ``f`` on
    the mask's voxels; ``weight`` (1 on the mask, falling to 0 outside) blends
    it into ``f``.
    """
    idx = np.nonzero(mask)
    if len(idx[0]) < 4:
        return f
    x = np.stack([g[idx] for g in grid_mm], axis=1)  # (n, 3)
    c = x.mean(axis=0)
    r = x - c
    y = np.stack([f[a][idx] for a in range(3)], axis=1)
    # f ≈ t + ω × r:  rows [I | -[r]×]  — solve the 6×6 normal equations
    a = bayes.rigid_jacobian(r)
    ata = np.einsum("nij,nik->jk", a, a)
    aty = np.einsum("nij,ni->j", a, y)
    try:
        p = np.linalg.solve(ata, aty)
    except np.linalg.LinAlgError:
        return f
    t, om = p[:3], p[3:]
    near = weight > 0
    xr = [g[near] - c[a_] for a_, g in enumerate(grid_mm)]
    rig = [
        t[0] + om[1] * xr[2] - om[2] * xr[1],
        t[1] + om[2] * xr[0] - om[0] * xr[2],
        t[2] + om[0] * xr[1] - om[1] * xr[0],
    ]
    wn = weight[near]
    for a_ in range(3):
        f[a_][near] = (1.0 - wn) * f[a_][near] + wn * rig[a_]
    return f


def _rigid_displacement(p, centre, grid_mm, box) -> np.ndarray:
    """``T(x) − x`` on ``box`` (3, …; mm along the array axes) for the rigid motion ``T(y) = R (y − c) + c + t``,
    ``p`` = (rotation vector in degrees, ``t`` in mm), ``c`` = ``centre``."""
    from scipy.spatial.transform import Rotation

    r = Rotation.from_rotvec(np.deg2rad(np.asarray(p[:3], float))).as_matrix()
    x = [g[box] - np.float32(c) for g, c in zip(grid_mm, centre)]
    return np.stack([r[a, 0] * x[0] + r[a, 1] * x[1] + r[a, 2] * x[2] - x[a] + p[3 + a] for a in range(3)]).astype(
        np.float32
    )


class TemplateSampler:
    """The template seen through ``φ₀ ∘ U`` on each level: ``w(x) = M(x + u(x) + φ₀(x + u(x)))``, the template
    itself sampled once (trilinear) at every trial, its intensities divided by ``scale``.

    The template resampled through ``φ₀`` once and then through ``U`` (``M₀ ∘ U``) is interpolated twice:
    ``U = 0`` reads ``M₀``'s grid values and every other ``U`` averages neighbours, which lowers the variance of
    the template's noise in ``w``, and the LNCC rises with it (an interpolation artefact, as Pluim et al. 2000
    describe for mutual information).  The steps then climb towards shifts of a fraction of a voxel wherever the
    tissue is flat.  Sampled once, through the composed map, ``U = 0`` is no longer privileged: the start's
    positions fall at any fraction of the template's voxels.  The artefact is not gone: a position at a template
    voxel's centre still carries more of its noise than one between centres, so the LNCC still favours some
    sub-voxel positions, now in a pattern that varies with ``φ₀`` rather than one shift everywhere.

    Each level's template is smoothed on its own grid by the level's pre-smoothing (a Gaussian of ``sig_pre``
    scan voxels along each scan axis, its variance projected onto the template's axes).  Beyond the template's
    grid ``w`` is the template's air (or ``outside``); ``φ₀`` continues by its edge values beyond the scan's box."""

    def __init__(
        self, moving: Volume, initial: Volume, scale: float, crop: tuple, noise_body=False, outside: float | None = None
    ):
        self.geometry = moving.geometry
        self.data = np.asarray(moving.data, np.float32) / np.float32(scale)
        # the template's voxel noise variance (settings.interpolation_noise) in its tissue and its air, measured
        # with its body (``noise_body``: a mask on its grid, None: every voxel); False: not counted.  Where the two
        # differ (a magnitude image's Rayleigh air) a map of it on the template's grid, the body's value inside
        self.noise_var = self.noise_air = self.noise_map = None
        if noise_body is not False:
            self.noise_var, self.noise_air = voxel_noise_variance(self.data, noise_body)
            if noise_body is not None and abs(self.noise_air - self.noise_var) > 0.05 * self.noise_var:
                self.noise_map = np.where(noise_body, np.float32(self.noise_var), np.float32(self.noise_air))
        # read beyond the template's grid: its air (``outside`` None), else ``outside``
        self.air = float(air_level(moving)) / scale if outside is None else float(outside)
        self.phi = np.moveaxis(np.asarray(initial.data, np.float32)[crop], -1, 0)  # (3, box): world mm
        self.scan = initial.geometry
        self.corner = np.array([crop[2].start, crop[1].start, crop[0].start], float)  # the box's first (i, j, k)

    def level(self, s: int, sig_pre: float, shape: tuple):
        """``(warp, sample)`` on the level of shrink ``s`` (grid ``shape``): ``warp(u)`` is ``w`` on the whole
        level for ``u`` ``(3, *shape)`` mm along the array axes; ``sample(coords)`` is ``w`` at fractional level
        indices ``coords`` (z, y, x arrays of any one shape), through ``φ₀`` there.  Both read the template
        trilinearly; ``warp(u, order=0)`` at its nearest voxel."""
        g, tg = self.scan, self.geometry
        m = self.data
        sigma = np.zeros(3)
        if sig_pre > 0:
            dg, dt = g.direction_matrix, tg.direction_matrix
            cov = dg @ np.diag((sig_pre * np.asarray(g.spacing, float)) ** 2) @ dg.T  # world mm²
            sigma = np.sqrt(np.einsum("ia,ij,ja->a", dt, cov, dt)) / np.asarray(tg.spacing, float)  # i, j, k
            m = smooth(m, sigma[::-1], **GAUSSIAN)
        # the level's template noise: its variance and neighbours' correlation along i, j, k after the smoothing
        kn = [kernel_noise(float(v)) for v in sigma]
        kappa = kn[0][0] * kn[1][0] * kn[2][0]
        noise_var = None if self.noise_var is None else self.noise_var * kappa
        noise_map = None
        if self.noise_map is not None:  # the tissue's and the air's, smoothed as the template (its mean: the map's)
            noise_map = (
                smooth(self.noise_map, sigma[::-1], **GAUSSIAN) if sig_pre > 0 else self.noise_map
            ) * np.float32(kappa)
        rho = [k[1] for k in kn]
        phi = np.ascontiguousarray(self.phi[:, ::s, ::s, ::s])
        lg = GridGeometry(
            size=tuple(int(v) for v in shape[::-1]),
            spacing=tuple(float(v) * s for v in g.spacing),
            origin=tuple(float(v) for v in g.index_to_world(self.corner)),
            direction=g.direction,
        )
        d = g.direction_matrix
        inv_sp = 1.0 / (np.asarray(g.spacing, float)[::-1] * s)
        w2i, i2w = tg.world_to_index_matrix, lg.index_to_world_matrix
        air = self.air

        def warp(u, order=1):
            """``(w, v)``: the template through the map and the variance that evens out its noise over the
            sampled positions (``interpolation_noise_variance``; None when not counted)."""
            ph = sample_shifted(phi, u, inv_sp)
            # u along the array axes (z, y, x) → world, written out (no BLAS: the same bits on every run)
            disp = np.stack([d[r, 0] * u[2] + d[r, 1] * u[1] + d[r, 2] * u[0] + ph[r] for r in range(3)], axis=-1)
            w = sample_displaced_array(m, w2i, lg, disp, order, air).astype(np.float32)
            if noise_var is None or order == 0:
                return w, None
            pos = xw + disp
            p = np.stack(
                [
                    w2i[r, 0] * pos[..., 0] + w2i[r, 1] * pos[..., 1] + w2i[r, 2] * pos[..., 2] + w2i[r, 3]
                    for r in range(3)
                ]
            ).astype(np.float32)
            v = interpolation_noise_variance(p, noise_var, rho)
            if noise_map is not None:  # the variance at the sampled place over the body's (the map's there)
                v *= sample_displaced_array(noise_map, w2i, lg, disp, 1, self.noise_air * kappa).astype(
                    np.float32
                ) / np.float32(noise_var)
            return w, v

        phi_last = np.ascontiguousarray(np.moveaxis(phi, 0, -1))  # (nz, ny, nx, 3) for sample_array
        lw2i = lg.world_to_index_matrix

        def world(ijk):  # level index (i, j, k arrays) → world mm (N, 3), written out as warp's
            return np.stack(
                [i2w[r, 0] * ijk[0] + i2w[r, 1] * ijk[1] + i2w[r, 2] * ijk[2] + i2w[r, 3] for r in range(3)], axis=-1
            )

        # the level's world positions (nz, ny, nx, 3), for the template positions of warp's noise
        xw = (
            None
            if noise_var is None
            else world(np.indices(shape[::-1], dtype=np.float32).transpose(0, 3, 2, 1)).astype(np.float32)
        )

        def sample(coords):
            ijk = [np.ravel(coords[2 - r]) for r in range(3)]  # array axes (z, y, x) → index axes (i, j, k)
            # φ₀ continues by its edge values (as sample_shifted's): read at the indices clamped to the grid
            at = world([np.clip(ijk[r], 0, shape[2 - r] - 1) for r in range(3)])
            points = world(ijk) + sample_array(phi_last, lw2i, at, 1, 0.0)
            return sample_array(m, w2i, points, 1, air).reshape(np.shape(coords[0])).astype(np.float32)

        return warp, sample


def voxel_in_voxels(a: GridGeometry, b: GridGeometry) -> float:
    """Grid ``a``'s voxel in voxels of grid ``b``, along the axis of ``b`` where it is the most: the voxel's
    extent along each of ``b``'s axes (its edges, world mm, projected through both directions) over ``b``'s
    spacing there."""
    cosines = np.abs(np.asarray(a.direction_matrix).T @ np.asarray(b.direction_matrix))  # [axis of a, axis of b]
    return float(np.max(np.asarray(a.spacing, float) @ cosines / np.asarray(b.spacing, float)))


def noise_correlation_factor(f, w, air, shape_voxels: float, w_fill: float | None = None) -> float:
    """How many voxels of the level carry one independent sample of the noise, for a correlation between ``f``
    and ``w``: Bartlett's (1935) variance of a correlation between two autocorrelated fields, the product over
    the axes of ``Σ_k ρ_f(k) ρ_w(k)`` (exact for uncorrelated fields; for a bone's NCC of 0.9 a heuristic), each
    image's autocorrelation taken as a Gaussian of the lag, ``ρ(k) = ρ₁^(k²)`` (white noise smoothed by a
    Gaussian), with ``ρ₁`` its lag-1 autocorrelation measured in the ``air`` (no anatomy: noise alone; ``w``'s
    voxels equal to ``w_fill``, beyond the template's grid, left out; a magnitude image's Rayleigh air shows
    about ρ² of its noise's correlation, so this then errs towards more samples).  An image whose air is
    constant, or with fewer than 1000 air voxels: white noise smoothed by a Gaussian of ``shape_voxels`` level
    voxels, ``ρ₁ = exp(−1 / (4 σ²))``.  At least 1."""
    model = float(np.exp(-1.0 / (4.0 * shape_voxels**2))) if shape_voxels > 0 else 0.0
    factor = 1.0
    k = np.arange(-12, 13, dtype=float) ** 2
    for a in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[a], hi[a] = slice(0, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        rho = []
        for img, fill in ((f, None), (w, w_fill)):
            r = model
            if air is not None:
                ok = air if fill is None else air & (img != np.float32(fill))
                both = ok[lo] & ok[hi]
                if int(both.sum()) >= 1000:
                    x, y = img[lo][both].astype(np.float64), img[hi][both].astype(np.float64)
                    x, y = x - x.mean(), y - y.mean()
                    den = np.sqrt((x * x).sum() * (y * y).sum())
                    if den > 0:
                        r = float((x * y).sum() / den)
            rho.append(float(np.clip(r, 0.0, 0.99)))
        r = rho[0] * rho[1]
        factor *= float((r**k).sum()) if r > 0 else 1.0
    return max(factor, 1.0)


def bone_fit_improves(p, b, box, m, wgt, u, fl, sample_w, centre, grid_mm, sp, st, per_sample: float = 1.0) -> bool:
    """Whether the bone's own fit shows its pose off: the NCC of the scan and the template over the bone's voxels
    and one voxel around (``m`` dilated, on the level), with the bone at pose ``p`` against ``u`` as it is,
    compared by Fisher's z-transform: True when ``atanh(r₁) − atanh(r₀)`` exceeds ``st.refine_significance``
    standard errors ``√(2 / (n_eff − 3))``, that of two independent correlations over ``n_eff = n / per_sample``
    independent samples (``per_sample``: :func:`noise_correlation_factor`).  The candidate is the one the
    refinement's search found best on the same noise, which no error of a fixed comparison accounts for; the
    independent correlations' error is the larger one (Steiger's 1980 test of correlations sharing the scan
    would pass smaller gains), and is kept for that, not because it corrects the search's selection.  ``fl``
    and ``sample_w`` are the level's images smoothed for the test (``register_dense``: at least one scan and
    one template voxel), so that a candidate between the template's voxel centres hardly lowers its noise
    (``TemplateSampler``'s artefact).
    The refinement's own objective spans the soft tissue around the bone, whose map is still being fitted; a
    thin bone's roll is barely seen by its own voxels, and the noise of a CT-like scan can then pay for a wrong
    one.  (A constant image: NaN, not significant.)"""
    idx = np.meshgrid(*[np.arange(o.start, o.stop, dtype=np.float32) for o in box], indexing="ij")
    inv = 1.0 / np.asarray(sp, float)
    ub = u[(slice(None),) + box]
    mask = ndimage.binary_dilation(m)
    r = []
    for q in (None, p):
        uc = ub if q is None else ub + wgt[None] * (_rigid_displacement(q, centre, grid_mm, box) - ub)
        r.append(cc(fl[box], sample_w([idx[a] + uc[a] * inv[a] for a in range(3)]), mask))
    n = int(mask.sum()) / max(float(per_sample), 1.0)
    if n <= 3.0:  # too few independent samples to tell anything
        return False
    z = (np.arctanh(min(r[1], 0.999999)) - np.arctanh(min(r[0], 0.999999))) * np.sqrt((n - 3.0) / 2.0)
    log.debug(
        "bone %d first move: own NCC %.4f -> %.4f over %d voxels (%.0f independent), z %.2f",
        b,
        r[0],
        r[1],
        int(mask.sum()),
        n,
        z,
    )
    return z > st.refine_significance


def refine_bone(p0, centre, box, wgt, u, fl, sample_w, win, tissue, region, grid_mm, sp, st):
    """One held bone's rigid pose refined on the LNCC, the soft tissue held.

    The candidate field is ``u`` moved towards the bone's rigid displacement by its weight (exactly rigid on
    the bone, fading over its margin); its objective is the LNCC's mean over the voxels whose value the bone's
    motion can change (its box grown by the windows' reach), computed on a box grown by that reach again so
    that the windows' statistics there are the whole grid's (the same template samples as the level's:
    ``TemplateSampler``).  The skin's term and the membrane energy are left out of it: the round is taken
    only when the whole level's objective, which has them, rises.
    Derivative-free (NLopt BOBYQA, Powell 2009) within the bounds ``st.refine_deg`` /
    ``st.refine_mm`` of the start.  Returns ``(p, gain, evaluations)``, ``gain`` the best candidate's objective
    less the objective of ``u`` as it is (≤ 0: keep ``u``).
    """
    import nlopt

    shape = fl.shape
    reach = np.ceil(3.0 * np.asarray(win, float)).astype(int) + 1
    inner = tuple(slice(max(b.start - r, 0), min(b.stop + r, n)) for b, r, n in zip(box, reach, shape))
    outer = tuple(slice(max(b.start - 2 * r, 0), min(b.stop + 2 * r, n)) for b, r, n in zip(box, reach, shape))

    def rel(bx):
        return tuple(slice(b.start - o.start, b.stop - o.start) for b, o in zip(bx, outer))

    fo = fl[outer]
    stats = local_stats(fo, win, None if tissue is None else tissue[outer])
    reg = np.zeros(fo.shape, np.float32)
    reg[rel(inner)] = 1.0 if region is None else region[inner]
    uo = u[(slice(None),) + outer]
    rb = (slice(None),) + rel(box)
    wb = wgt[None]
    go = [g[outer] for g in grid_mm]
    base = [np.arange(o.start, o.stop, dtype=np.float32) for o in outer]
    idx = np.meshgrid(*base, indexing="ij")
    inv = (1.0 / np.asarray(sp, float)).astype(np.float32)

    # the candidates keep U one-to-one as every step does: det(I + ∇u) on the box grown by a voxel above
    # min_jacobian (or not below its value as u is, where it already was); one that does not is never the best
    # (the LNCC can rise by crushing the tissue between two bones into the fade)
    grown = (slice(None),) + tuple(slice(max(r.start - 1, 0), min(r.stop + 1, n)) for r, n in zip(rel(box), fo.shape))
    det_floor = min(st.min_jacobian, jacobian_min(uo[grown], sp))

    def objective(p, grad=None):
        uc = uo.copy()
        uc[rb] += wb * (_rigid_displacement(p, centre, go, rel(box)) - uc[rb])
        # strictly below: where u already is at or under min_jacobian, a candidate that leaves that voxel as it is
        # is one-to-one as u is (with ≤ every candidate would be refused)
        if jacobian_min(uc[grown], sp) < det_floor:
            return f_now - 1.0  # below every LNCC a one-to-one candidate can reach from here (it is ≤ 1)
        w = w_now.copy()  # only the bone's box changes
        w[rbox] = sample_w([idx[a][rbox] + uc[a][rbox] * inv[a] for a in range(3)])
        return lncc_force(fo, w, win, stats, reg)[0]

    rbox = rel(box)
    w_now = sample_w([idx[a] + uo[a] * inv[a] for a in range(3)])
    f_now = lncc_force(fo, w_now, win, stats, reg)[0]  # the objective as u is now
    x0 = np.asarray(p0, float)
    bound = np.r_[np.full(3, st.refine_deg), np.full(3, st.refine_mm)]
    x0 = np.clip(x0, -bound, bound)
    best = [x0.copy(), objective(x0), 2]  # u moved to p0's rigid motion with this fade: not quite u

    def tracked(x, grad):
        f = objective(x)
        best[2] += 1
        if f > best[1]:
            best[0], best[1] = np.array(x, float), f
        return f

    opt = nlopt.opt(nlopt.LN_BOBYQA, 6)
    opt.set_lower_bounds(-bound)
    opt.set_upper_bounds(bound)
    # first trial moves: 1° and half a level voxel (a voxel's worth at 30 mm from the centre for the rotation)
    opt.set_initial_step(np.minimum(np.r_[np.full(3, 1.0), np.full(3, 0.5 * float(np.min(sp)))], bound))
    opt.set_xtol_abs(np.full(6, 0.01))  # 0.01° and 0.01 mm: far below a voxel
    opt.set_maxeval(int(st.refine_evaluations))
    opt.set_max_objective(tracked)
    try:
        opt.optimize(x0)
    except (nlopt.RoundoffLimited, RuntimeError, ValueError):
        pass  # the best point seen is still valid
    return best[0], best[1] - f_now, best[2]


def membrane_energy(u: np.ndarray, weight: np.ndarray, sp) -> tuple[float, np.ndarray]:
    """The membrane energy ``Σ m |∇u|²`` of ``u`` (``(3, *shape)``, mm along the array axes) by forward differences,
    each pair of neighbours weighed by the product of their ``weight`` (``m``), and its derivative with respect to
    ``u`` (``(3, *shape)``): exact for this discrete energy, so that a step along its negative lowers it."""
    energy = 0.0
    grad = np.zeros_like(u)
    for b in range(3):
        lo = [slice(None)] * 4
        hi = [slice(None)] * 4
        lo[b + 1], hi[b + 1] = slice(None, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        pair = weight[lo[1:]] * weight[hi[1:]]
        d = (u[hi] - u[lo]) / u.dtype.type(sp[b])
        wd = pair[None] * d
        energy += float(np.sum(wd * d, dtype=np.float64))
        g = wd * u.dtype.type(2.0 / sp[b])
        grad[hi] += g
        grad[lo] -= g
    return energy, grad


def penalties(b, s, band, region, skin_weight: float, u, membrane_w, sp, stiffness: float, n_region: float):
    """The level's objective is the LNCC's mean less the returned penalties: ``skin_weight`` times the mean over
    the region of ``band (b − s)²`` (``b``: the template's smoothed body through the map, ``s`` the scan's; ``b``
    None: no skin term) plus ``stiffness`` times the membrane energy of ``u`` weighed by ``membrane_w``
    (:func:`membrane_energy`; None: none) over ``n_region``.  Returns ``(penalty, skin, membrane)``: the objective's
    ascent along ``b`` and along ``u`` times ``n_region`` (as the LNCC's force is: the derivative of its sum),
    None where the term is off.  ``penalty`` is ``(membrane's, skin's)``, subtracted in that order."""
    skin_penalty = membrane_penalty = 0.0
    skin = membrane = None
    if b is not None:
        diff = b - s
        wdiff = band * diff
        sq = wdiff * diff
        skin_penalty = skin_weight * float(np.mean(sq if region is None else sq[region > 0], dtype=np.float64))
        skin = np.float32(-2.0 * skin_weight) * wdiff
    if membrane_w is not None:
        energy, membrane = membrane_energy(u, membrane_w, sp)
        membrane_penalty = stiffness * energy / n_region
        membrane *= u.dtype.type(-stiffness)
    return (membrane_penalty, skin_penalty), skin, membrane


def _posterior(
    u, fl, w, sp, win, noise_var, per_sample, pool, labl, regl, tissue, st, u_in=None, finest=True, u_total=None
) -> tuple:
    """settings.posterior on a level (:mod:`registration.posterior`): ``(û, σ, record, keep, var_total)`` for the
    level's change ``u`` of its input ``u_in`` (``var_total``: with ``u_total``, the whole correction's expected
    squared error against the start, settings.posterior_total; else None).  The soft tissue's change is weighed
    against the input by the information pooled at the level's scale; the prior's variance, ``σ₀² + β² |u_in|²``,
    is the evidence's over the scan's tissue away from the bones (every 2nd voxel along each axis); a bone
    (``labl`` pulled through ``u_in + u``) keeps its rigid motion, its ``σ`` that of its rigid pose, blended into
    the tissue's over its fade (``bone_margin_mm``, as the steps hold it)."""
    shape = fl.shape
    mask = None if regl is None else regl > 0
    # the local intensity fit over at least 2 voxels of the level (a coarse level's LNCC window is under one)
    info = bayes.information(fl, w, sp, np.maximum(win, 2.0), noise_var, per_sample, mask)
    eig = bayes.pooled_precision(info, pool, sp, eig=True)  # one decomposition for the evidence and the posterior
    keep = np.ones(shape, np.float32)  # 1 − the nearest bone's weight (1 away from every bone)
    bone_w = []
    if labl is not None:
        u_all = u if u_in is None else u_in + u
        lab_now = sample_shifted(labl.astype(np.float32), u_all, 1.0 / sp, order=0).astype(np.int32)
        bones = [int(b) for b in np.unique(lab_now) if b != 0]
        bone_w = _bone_weights(lab_now, bones, sp, st.bone_margin_mm)
        for _, box, _, wgt in bone_w:
            keep[box] = np.minimum(keep[box], 1.0 - wgt)
    soft = keep >= 1.0
    if tissue is not None:
        soft &= tissue > 0.5
    elif mask is not None:
        soft &= mask
    sub = np.zeros(shape, bool)
    sub[::2, ::2, ::2] = True
    # the prior of the level's change: its variance grows with the correction the coarser levels made (none on the
    # first level), both parts chosen by the evidence
    motion_share = None
    if u_in is not None and np.any(u_in):
        m2 = (u_in**2).sum(axis=0)
        s0, b = bayes.prior_variance_with_motion(u, None, soft & sub, m2, eig=eig)
        prior_var = s0 + b * m2
        motion_share = float(np.sqrt(b))
    else:
        prior_var = bayes.prior_variance(u, None, soft & sub, eig=eig)
    post = bayes.posterior_correction(u, None, prior_var, eig=eig)
    k = keep[None]
    u_new = (k * post.u + (1.0 - k) * u).astype(np.float32)
    var_total = None
    if u_total is not None:  # settings.posterior_total: the whole correction against the start, the same information
        if st.posterior_mean:  # the map the level keeps: its input and the posterior mean of its change
            u_total = u_new if u_in is None else u_in + u_new
        post_t = bayes.posterior_correction(
            u_total, None, bayes.prior_variance(u_total, None, soft & sub, eig=eig), eig=eig
        )
        var_total = post_t.sigma.astype(np.float32) ** 2 + ((u_total - post_t.u) ** 2).sum(axis=0)
    del eig

    var = post.sigma.astype(np.float64) ** 2
    if bone_w and not finest:  # a held bone's pose is judged once, on the finest level
        var = keep * var
    elif bone_w:
        grid_mm = [g * np.float32(h) for g, h in zip(np.indices(shape, dtype=np.float32), sp)]
        prior_sd = np.r_[np.full(3, st.refine_mm), np.full(3, np.deg2rad(st.refine_deg))]
        nearest = np.zeros(shape, np.float32)  # the largest bone weight so far
        bone_var = np.zeros(shape, np.float64)
        bone_sd = {}
        for b, box, m, wgt in bone_w:
            g_box = [g[box] for g in grid_mm]
            centre = [float(g[m].mean()) for g in g_box]
            grown = ndimage.binary_dilation(m)
            cov, sd = bayes.rigid_pose_variance(info[(slice(None),) + box], grown, g_box, centre, prior_sd)
            take = wgt > nearest[box]
            bone_var[box][take] = sd[take].astype(np.float64) ** 2
            nearest[box][take] = wgt[take]
            bone_sd[str(b)] = [
                round(float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:]).max()))), 4),
                round(float(np.sqrt(np.linalg.eigvalsh(cov[:3, :3]).max())), 4),
            ]
        var = keep * var + (1.0 - keep) * bone_var
    sigma = np.sqrt(var).astype(np.float32)
    tis = soft if soft.any() else np.ones(shape, bool)
    rec = {
        "prior_sd_mm": round(post.prior_sd, 4),
        "prior_motion_share": None if motion_share is None else round(motion_share, 4),
        # the evidence found no correction the images measure: σ_p at its lower bound (σ then says little)
        "prior_at_bound": bool(post.prior_sd**2 <= 1.01 * bayes.PRIOR_VARIANCE_BOUNDS[0]),
        "pool_voxels": [round(float(v), 3) for v in np.broadcast_to(np.asarray(pool, float), (3,))],
        # the share of the correction kept over the tissue away from the bones (0: the start, 1: the steps' own)
        "kept": round(float(post.gain[tis].mean(dtype=np.float64)), 4),
        "correction_mm": [
            round(float(np.linalg.norm(u[:, tis], axis=0).mean(dtype=np.float64)), 4),
            round(float(np.linalg.norm(u_new[:, tis], axis=0).mean(dtype=np.float64)), 4),
        ],
        "sigma_median_mm": round(float(np.median(sigma[tis])), 4),
        # each bone's largest rotation SD (°) and translation SD (mm) of its rigid pose
        "bone_sd": bone_sd if (bone_w and finest) else None,
    }
    return u_new, sigma, rec, keep, var_total


def _held_out_score(flv, warp_v, win, fv_stats, regl, u_now) -> float:
    """settings.holdout: the held-out copy's LNCC of the map ``u_now`` (the template at its nearest voxel)."""
    return lncc_force(flv, warp_v(u_now, order=0)[0], win, fv_stats, regl)[0]


@dataclass
class _Registration:
    """What every level of :func:`register_dense` shares: the settings, the scan on the force's box (``f0``,
    normalised by ``scale``), the template's sampler, the masks, the bones (their labels on the box, centroids and
    refined poses ``params``, which the levels carry on), the held-out copy and the noise."""

    st: DenseSettings
    f0: np.ndarray
    template: TemplateSampler
    tissue0: np.ndarray | None
    skin: tuple | None
    lab0: np.ndarray | None
    region: np.ndarray | None
    centres: dict
    params: dict
    tested: set
    held_out: tuple | None
    noise_var: float | None
    air_around: bool
    template_voxel: float
    scale: float
    sp_full: np.ndarray
    crop: tuple
    var_post: np.ndarray | None = None  #: settings.posterior: the expected squared error of u so far
    var_total: np.ndarray | None = None  #: settings.posterior_total: the whole correction's, on the finest level


class _Level:
    """One level of :func:`register_dense`: its images and masks, the map ``u`` (mm along the array axes) and what
    the steps keep of it, and the level's parts as methods: the objective (:meth:`score`), a step's direction and
    candidate, the bones' hold and refinement (:meth:`bone_hold`, :meth:`refine`, :meth:`bone_round`), and the
    trust region with the posterior (:meth:`run`)."""

    def __init__(self, reg, lv, s, u, prev_s):
        """Level ``lv`` of shrink ``s`` of the registration ``reg`` (:class:`_Registration`), from the map ``u`` of
        the previous level (of shrink ``prev_s``; None on the first)."""
        self.reg, self.st, self.lv = reg, reg.st, lv
        sp_full, skin, held_out, template, lab0, region, st, tissue0, noise_var, f0 = (
            reg.sp_full,
            reg.skin,
            reg.held_out,
            reg.template,
            reg.lab0,
            reg.region,
            reg.st,
            reg.tissue0,
            reg.noise_var,
            reg.f0,
        )
        var_post = reg.var_post
        t_level = time.perf_counter()
        s = int(s)
        sp = sp_full * s
        sig_pre = 0.5 * (s - 1) if s > 1 else 0.0
        fl = smooth(f0, sig_pre, **GAUSSIAN)[::s, ::s, ::s].astype(np.float32)
        shape = fl.shape
        warp_w, sample_w = template.level(s, sig_pre, shape)
        grid = np.indices(shape, dtype=np.float32)
        grid_mm = [grid[a] * sp[a] for a in range(3)]
        if u is None:
            u = np.zeros((3,) + shape, np.float32)
        else:  # carry u up: coarse index = fine index · (s_fine / s_coarse)
            ratio = s / prev_s
            coords = grid * ratio
            coords = [np.minimum(coords[a], u.shape[a + 1] - 1) for a in range(3)]
            u = np.stack([_sample(u[a], coords) for a in range(3)]).astype(np.float32)
            if var_post is not None:
                var_post = _sample(var_post, coords).astype(np.float32)
        u_in = u.copy()  # settings.posterior weighs this level's change of u
        labl = lab0[::s, ::s, ::s] if lab0 is not None else None
        regl = None if region is None else ndimage.maximum_filter(region, size=s)[::s, ::s, ::s]
        win = st.window_mm / sp
        # the scan's tissue on this level (a fraction where the pre-smoothing mixes it with air)
        tissue = None if tissue0 is None else smooth(tissue0, sig_pre, **GAUSSIAN)[::s, ::s, ::s].astype(np.float32)
        f_stats = local_stats(fl, win, tissue)
        # settings.stiffness: each voxel's weight in the membrane energy (the share of the scan's local variance its
        # noise makes up, the bones and beyond the region 0) and the mean's denominator (the LNCC's: the region)
        membrane_w = None
        n_region = float(np.count_nonzero(regl > 0)) if regl is not None else float(np.prod(shape))
        if st.stiffness > 0 and noise_var is not None and noise_var > 0:
            level_noise = np.float32(noise_var * kernel_noise(sig_pre)[0] ** 3)  # the pre-smoothing thins it
            membrane_w = np.clip(level_noise / np.maximum(f_stats[1], np.float32(1e-12)), 0.0, 1.0).astype(np.float32)
            if regl is not None:
                membrane_w *= regl > 0
            if labl is not None:
                membrane_w[labl > 0] = 0.0
        skin_warp = skin_l = skin_band = None
        if skin is not None:
            skin_warp = skin[0].level(s, sig_pre, shape)[0]
            skin_l = smooth(skin[1], sig_pre, **GAUSSIAN)[::s, ::s, ::s].astype(np.float32)
            # the term counts where the scan shows an outline: 1 at its skin, falling to 0 a few windows inside and
            # outside.  Deep in the scan's body the template's air is a crease whose skins touch in the scan
            # (contact), which no map of one outline onto the other can mend
            skin_band = (4.0 * skin_l * (1.0 - skin_l)).astype(np.float32)
        held_score = None  # settings.holdout: the held-out LNCC of a map (the template at its nearest voxel)
        if held_out is not None:
            flv = smooth(held_out[0], sig_pre, **GAUSSIAN)[::s, ::s, ::s].astype(np.float32)
            fv_stats = local_stats(flv, win, tissue)
            warp_v = held_out[1].level(s, sig_pre, shape)[0]

            held_score = functools.partial(_held_out_score, flv, warp_v, win, fv_stats, regl)

        fluid = st.fluid_mm / sp if st.fluid_voxels is None else np.full(3, float(st.fluid_voxels))
        elastic = st.elastic_mm / sp if st.elastic_voxels is None else np.full(3, float(st.elastic_voxels))
        force_norm = u_weight = u_norm = None
        if tissue is not None:  # the normalised convolutions' denominators (settings.tissue_only)
            force_norm = 1.0 / np.maximum(smooth(tissue, fluid, **GAUSSIAN), 0.5)
            u_weight = tissue + np.float32(st.air_weight) * (1.0 - tissue)
            u_norm = 1.0 / smooth(u_weight, elastic, **GAUSSIAN)
        step = st.step_mm * (float(sp.min()) if st.step_voxels else 1.0)
        bones = [int(b) for b in np.unique(labl) if b != 0] if labl is not None else []
        inv_sp = 1.0 / sp
        reg.var_post = var_post
        self.u = u
        self.t_level = t_level
        self.sp = sp
        self.sig_pre = sig_pre
        self.fl = fl
        self.shape = shape
        self.grid = grid
        self.grid_mm = grid_mm
        self.u_in = u_in
        self.labl = labl
        self.regl = regl
        self.win = win
        self.tissue = tissue
        self.f_stats = f_stats
        self.membrane_w = membrane_w
        self.n_region = n_region
        self.skin_warp = skin_warp
        self.skin_l = skin_l
        self.skin_band = skin_band
        self.held_score = held_score
        self.fluid = fluid
        self.elastic = elastic
        self.force_norm = force_norm
        self.u_weight = u_weight
        self.u_norm = u_norm
        self.step = step
        self.bones = bones
        self.inv_sp = inv_sp
        self.warp_w = warp_w
        self.sample_w = sample_w
        self.s = s
        self.test = None  # the bones' significance test's images (bone_fit_improves), made when first needed
        self.bone_w = []  # the bones' weights: (label, box, mask, weight) each
        self.hold = (None, None)  # bone_hold() of the current bone_w

    def bone_hold(self):
        """Where U is held (0 on a bone, rising to 1 past its margin) and the held value there: each
        refined bone's rigid displacement (the nearest bone's where margins meet), None before any."""
        keep = np.ones(self.shape, np.float32)
        held = np.zeros((3,) + self.shape, np.float32) if self.reg.params else None
        for b, box, _, wgt in self.bone_w:
            kb = 1.0 - wgt
            if held is not None:  # where this bone is the nearest: its rigid displacement, or 0 if not refined
                take = kb < keep[box]
                hb = held[(slice(None),) + box]
                hb[:, take] = (
                    _rigid_displacement(self.reg.params[b], self.reg.centres[b], self.grid_mm, box)[:, take]
                    if b in self.reg.params
                    else 0.0
                )
            keep[box] = np.minimum(keep[box], kb)
        return keep, held

    def refine(self, u_now, test_all):
        """settings.refine_bones: each held bone's pose refined in turn (:func:`refine_bone`), only those
        already moved unless ``test_all``; returns the new ``u`` (``u_now`` untouched) and the record."""
        u_now = u_now.copy()
        lab_now = sample_shifted(self.labl.astype(np.float32), u_now, self.inv_sp, order=0).astype(np.int32)
        # the candidate's fade: refine_margin_voxels of the level's largest spacing (at least that many voxels
        # along every axis)
        margin = (
            self.st.bone_margin_mm
            if self.st.refine_margin_voxels is None
            else self.st.refine_margin_voxels * float(self.sp.max())
        )
        self.bone_w = _bone_weights(lab_now, self.bones, self.sp, margin)
        evaluations, moved, folded, unseen = 0, {}, 0, 0
        finest = self.lv == len(self.st.shrink) - 1
        for b, box, m, wgt in self.bone_w:
            if b not in self.reg.centres:
                continue
            if b not in self.reg.params:  # not moved so far: tested on a level's first round where it is thick enough
                # voxels across at its thickest (a single voxel: 1): a pose is read from two opposite edges
                thick = 2.0 * float(ndimage.distance_transform_edt(m).max()) - 1.0
                if not test_all or thick < self.st.refine_min_voxels or (finest and b in self.reg.tested):
                    continue
                self.reg.tested.add(b)
            lb = lab_now[box]
            wgt = np.where((lb == 0) | (lb == b), wgt, np.float32(0.0))  # a bone's move moves no other bone
            p, gain, n = refine_bone(
                self.reg.params.get(b, np.zeros(6)),
                self.reg.centres[b],
                box,
                wgt,
                u_now,
                self.fl,
                self.sample_w,
                self.win,
                self.tissue,
                self.regl,
                self.grid_mm,
                self.sp,
                self.st,
            )
            evaluations += n
            if gain > 0 and b not in self.reg.params:  # the start's pose stands unless the image shows it off
                with np.errstate(invalid="ignore"):
                    move = np.sqrt(
                        (_rigid_displacement(p, self.reg.centres[b], self.grid_mm, box)[:, m] ** 2).sum(axis=0)
                    ).max()
                if move <= self.st.refine_min_move_voxels * float(self.reg.sp_full.min()):
                    continue
                if self.test is None:  # smoothed by at least one scan voxel: see bone_fit_improves
                    # at least a scan voxel and a template voxel (in mm, as scan voxels)
                    sig_t = max(self.sig_pre, TEST_SMOOTH_VOXELS, TEST_SMOOTH_VOXELS * self.reg.template_voxel)
                    fl_t, sample_t = self.fl, self.sample_w
                    if sig_t > self.sig_pre:
                        fl_t = smooth(self.reg.f0, sig_t, **GAUSSIAN)[:: self.s, :: self.s, :: self.s].astype(
                            np.float32
                        )
                        warp_t, sample_t = self.reg.template.level(self.s, sig_t, self.shape)
                    else:
                        warp_t = self.warp_w
                    # the air: beyond the bodies grown by two windows, where air surrounds the scan's body
                    air = self.regl == 0 if (self.regl is not None and self.reg.air_around) else None
                    self.test = (
                        fl_t,
                        sample_t,
                        noise_correlation_factor(fl_t, warp_t(u_now)[0], air, sig_t / self.s, self.reg.template.air),
                    )
                if not bone_fit_improves(
                    p,
                    b,
                    box,
                    m,
                    wgt,
                    u_now,
                    self.test[0],
                    self.test[1],
                    self.reg.centres[b],
                    self.grid_mm,
                    self.sp,
                    self.st,
                    self.test[2],
                ):
                    unseen += 1
                    continue
            if gain > 0:
                # the move must keep U one-to-one as every step does: det(I + ∇u) on the box (grown by a
                # voxel) above min_jacobian, or not below its value before where it already was
                grown = (slice(None),) + tuple(
                    slice(max(c.start - 1, 0), min(c.stop + 1, n)) for c, n in zip(box, self.shape)
                )
                det_before = jacobian_min(u_now[grown], self.sp)
                sub = u_now[(slice(None),) + box]  # a view
                kept_sub = sub.copy()
                sub += wgt[None] * (_rigid_displacement(p, self.reg.centres[b], self.grid_mm, box) - sub)
                if jacobian_min(u_now[grown], self.sp) < min(self.st.min_jacobian, det_before):
                    sub[...] = kept_sub
                    folded += 1
                    continue
                self.reg.params[b] = p
                moved[b] = p
        return u_now, {
            "evaluations": evaluations,
            "bones_moved": len(moved),
            "refused_folding": folded,
            "refused_not_significant": unseen,
        }

    def score(self, u_now):
        """``(w, objective, (dcc, skin, membrane))`` at ``u_now``: the template through the map, the level's
        objective (the mean LNCC over the region, less settings.skin_weight times the bodies' weighted mean
        squared difference and settings.stiffness times the membrane energy's mean) and its derivatives: the
        LNCC's with respect to ``w``; with the skin's term ``(b, d)``, the template's smoothed body through the
        map and the term's derivative with respect to it; with the energy, its ascent along ``u``."""
        w_now, v_now = self.warp_w(u_now)
        cc_now, dcc_now = lncc_force(self.fl, w_now, self.win, self.f_stats, self.regl, v_now)
        b = None
        if self.skin_warp is not None:
            # beyond the template's grid (its body unknown there: a limb leaving the field of view; any
            # trilinear share of it reads far below 0) the template's body is taken as the scan's: no cost
            b = self.skin_warp(u_now)[0]
            b = np.where(b >= 0.0, b, self.skin_l)
        penalty, skin_d, membrane = penalties(
            b,
            self.skin_l,
            self.skin_band,
            self.regl,
            self.st.skin_weight,
            u_now,
            self.membrane_w,
            self.sp,
            self.st.stiffness,
            self.n_region,
        )
        return w_now, cc_now - penalty[0] - penalty[1], (dcc_now, None if b is None else (b, skin_d), membrane)

    def direction(self, u_now, dcc, w, refresh_bones):
        """The smoothed gradient of the level's objective at ``u_now`` (mm, array axes; ``dcc`` is
        :func:`score`'s derivatives: the LNCC's, the skin's term's and the membrane energy's) and its largest
        magnitude (the trust
        radius bounds every voxel's move).  The interpolation's noise term (settings.interpolation_noise)
        enters through ``dcc`` (the local variance it is added to) but its own derivative with respect to
        the map is left out: the central differences of ``w`` are uncorrelated with the noise ``w`` keeps at
        the voxel itself (with trilinear sampling on a grid aligned with the template's, the two
        neighbours' shares of it cancel; approximately on a rotated one), so the force carries no pull
        towards any sub-voxel position for a derivative to undo; the term corrects the objective that
        decides whether a step is taken."""
        dcc, skin, membrane = dcc
        gw = np.gradient(w)
        parts = [dcc * gw[a] / self.sp[a] for a in range(3)]
        if skin is not None:  # the skin's term: its derivative times the template body's gradient
            gm = np.gradient(skin[0])
            parts = [parts[a] + skin[1] * gm[a] / self.sp[a] for a in range(3)]
        if membrane is not None:  # settings.stiffness: the energy's descent, on u itself
            parts = [parts[a] + membrane[a] for a in range(3)]
        if self.regl is not None:
            parts = [p * self.regl for p in parts]
        force = np.stack(smooth_all(parts, self.fluid))
        if self.tissue is not None:
            force *= self.force_norm[None]
        if self.bones and (refresh_bones or not self.bone_w):  # the bones' regions follow the map
            lab_now = sample_shifted(self.labl.astype(np.float32), u_now, self.inv_sp, order=0).astype(np.int32)
            self.bone_w = _bone_weights(lab_now, self.bones, self.sp, self.st.bone_margin_mm)
            self.hold = self.bone_hold() if self.st.bones == "fixed" else (None, None)
        return force, float(np.sqrt((force**2).sum(axis=0)).max())

    def candidate(self, u_now, force, fmax, radius):
        """``u_now`` after one step of at most ``radius`` mm per voxel along ``force`` (composed, smoothed,
        bones held), and the number of halvings that kept the step one-to-one."""
        fstep = force * np.float32(radius / fmax)
        for _, box, m, wgt in self.bone_w:
            sub = fstep[(slice(None),) + box]  # a view: changed in place
            if self.st.bones == "rigid":
                _rigid_project(sub, m, [gm[box] for gm in self.grid_mm], wgt)
            else:
                sub *= (1.0 - wgt)[None]
        halved = 0
        for _ in range(60):  # 2⁻⁶⁰: a step that still folds is then nothing
            if jacobian_min(fstep, self.sp) > self.st.min_jacobian:
                break
            fstep *= 0.5
            halved += 1
        # compose: u ← f + u ∘ (id + f)
        u_new = (fstep + sample_shifted(u_now, fstep, self.inv_sp)).astype(np.float32)
        # U's smoothing and the bones' self.hold act in proportion to the step: a step of half the radius is half
        # of a full one (the composed update and the regularisation alike), so a small enough step follows
        # the ascent direction and the level's objective can rise until a real balance is reached
        share = np.float32(radius / self.step)
        if np.any(self.elastic > 0):
            if self.tissue is not None:
                smoothed = weighted_smooth(list(u_new), self.u_weight, self.u_norm, self.elastic)
            else:
                smoothed = np.stack(smooth_all(list(u_new), self.elastic))
            u_new = u_new + share * (smoothed - u_new) if share < 1 else smoothed
            if self.bone_w and self.st.bones == "fixed":
                keep, held = self.hold
                # the bones themselves are held at every step (at their refined rigid motion, 0 before any
                # refinement); their margins fade in proportion
                factor = np.where(keep > 0, 1.0 - share * (1.0 - keep), 0.0).astype(np.float32)[None]
                u_new = u_new * factor if held is None else held + (u_new - held) * factor
            elif self.bone_w:  # smoothing bent the bones: back to each one's rigid motion
                for _, box, m, wgt in self.bone_w:
                    _rigid_project(u_new[(slice(None),) + box], m, [gm[box] for gm in self.grid_mm], wgt)
        return u_new, halved

    def bone_round(self, u, w, cc, dcc, rounds):
        """The held bones refined as rigid bodies, each on its own part of the objective; the round is taken
        only if the level's objective rises.  Returns ``(taken, u, w, cc, dcc)``, the map and its objective after
        the round; its record goes to ``rounds``."""
        t_b = time.perf_counter()
        kept = dict(self.reg.params)
        # a level's first recorded round tests the bones not moved so far (refine() says which); every round
        # refines the bones already moved
        u_b, rec_b = self.refine(u, test_all=not rounds)
        if not rec_b["evaluations"]:  # no bone to test or refine on this round
            self.bone_w = []  # refine() made them with its own margin: recomputed at the next step
            return False, u, w, cc, dcc
        w_b, cc_b, dcc_b = self.score(u_b)
        rec_b.update(
            lncc_before=cc, lncc_after=cc_b, taken=bool(cc_b > cc), seconds=round(time.perf_counter() - t_b, 2)
        )
        if not rec_b["taken"]:
            rec_b["bones_moved"] = 0
        if cc_b > cc:
            u, w, cc, dcc = u_b, w_b, cc_b, dcc_b
        else:
            self.reg.params.clear()
            self.reg.params.update(kept)
        self.bone_w = []  # recomputed (with the hold) from the map at the next step
        # each bone's rotation (°) and shift (mm) from the start's pose, so far
        rec_b["poses"] = {
            str(b): [round(float(np.linalg.norm(p[:3])), 3), round(float(np.linalg.norm(p[3:])), 3)]
            for b, p in sorted(self.reg.params.items())
        }
        rounds.append(rec_b)
        return rec_b["taken"], u, w, cc, dcc

    def weigh(self) -> dict:
        """settings.posterior: the level's change of ``u`` weighed against its input (:func:`_posterior`,
        :mod:`registration.posterior`), the information pooled at the level's own scale: a coarse level measures
        the smooth part of the correction over a large region, the finest the detail; with posterior_mean the
        level keeps the posterior mean of its change.  Adds the level's posterior variance to ``reg.var_post``
        and returns its record."""
        w_last = self.warp_w(self.u)[0]
        level_noise = float(self.reg.noise_var or 0.0) * kernel_noise(self.sig_pre)[0] ** 3
        air = self.regl == 0 if (self.regl is not None and self.reg.air_around) else None
        per_sample = noise_correlation_factor(self.fl, w_last, air, self.sig_pre / self.s, self.reg.template.air)
        pool = (
            self.st.posterior_pool_voxels
            if self.st.posterior_pool_voxels is not None
            else (float(self.st.fluid_voxels) if self.st.fluid_voxels is not None else self.st.fluid_mm / self.sp)
        )
        finest = self.lv == len(self.st.shrink) - 1
        du, sigma_l, post_rec, self.keep, var_total = _posterior(
            self.u - self.u_in,
            self.fl,
            w_last,
            self.sp,
            self.win,
            level_noise,
            per_sample,
            pool,
            self.labl,
            self.regl,
            self.tissue,
            self.st,
            self.u_in,
            finest=finest,
            u_total=self.u if (finest and self.st.posterior_total) else None,
        )
        self.reg.var_total = var_total
        var_l = sigma_l.astype(np.float32) ** 2
        if self.st.posterior_mean:
            self.u = self.u_in + du
        elif self.st.posterior_offset:  # the map keeps the steps' change Δ: E|Δ − u_true|² = tr C + |Δ − û|²
            var_l += ((self.u - self.u_in - du) ** 2).sum(axis=0)
        self.reg.var_post = var_l if self.reg.var_post is None else self.reg.var_post + var_l
        post_rec.update(
            noise_sd=round(float(np.sqrt(level_noise)) * self.reg.scale, 6),
            per_sample=round(per_sample, 3),
        )
        log.info(
            "dense posterior: prior SD %.3f mm, %.0f %% of the correction kept in the tissue, median sigma %.3f mm",
            post_rec["prior_sd_mm"],
            100.0 * post_rec["kept"],
            post_rec["sigma_median_mm"],
        )
        return post_rec

    def run(self, iters):
        """The level's trust region, the bones' rounds, the held-out copy and the posterior; returns the level's
        record and leaves the map in ``self.u``."""
        # A trust region on the level's objective (score()): a step is taken only when it
        # raises the objective; otherwise the radius (each voxel's largest move) halves and the step is tried
        # again from the same direction; after a taken step the radius grows by radius_growth, up to ``step``.
        # The level stops when no step of radius step·2⁻ᵏ (k = settings.max_halvings) raises the objective, or
        # when the last 10 taken steps together gained less than settings.tolerance; ``iterations`` only caps
        # the trials.  With settings.holdout it also stops after holdout_patience taken steps without a new highest
        # held-out LNCC, and returns the map of that highest (possibly an earlier one).
        w, cc, dcc = self.score(self.u)
        rounds = []  # the bones' refinements (settings.refine_bones)

        # Block-coordinate ascent: the held bones as rigid bodies, then the dense steps until they stop, then
        # the bones again, ... until a round of the bones no longer raises the objective (or refine_rounds).
        refining = bool(self.bones and self.reg.centres)

        if refining:
            _, self.u, w, cc, dcc = self.bone_round(self.u, w, cc, dcc, rounds)
        history = [cc]
        # settings.holdout: (held-out LNCC, taken steps, u, w, cc, dcc, bone poses, bones tested, bones' rounds) of
        # the best map; step 0 is the level's input after its first bones' round (which no held-out score judges)
        held_best = None

        def snapshot(held_lncc):  # the map as it is now, with its held-out LNCC (settings.holdout)
            return (
                held_lncc,
                len(history),
                self.u,
                w,
                cc,
                dcc,
                dict(self.reg.params),
                set(self.reg.tested),
                len(rounds),
            )

        if self.held_score is not None:
            held = [self.held_score(self.u)]
            held_best = snapshot(held[0])
            since = len(history)  # the patience counts from the best map or the last bones' round
        radius = self.step
        halvings = rejected = 0
        stop = "cap"
        force = None
        trials = 0
        while trials < int(iters):
            trials += 1
            if force is None:
                force, fmax = self.direction(self.u, dcc, w, refresh_bones=len(history) % 5 == 1)
                if fmax <= 0:
                    stop = "no force"
                    break
            u_c, halved = self.candidate(self.u, force, fmax, radius)
            halvings += halved
            w_c, cc_c, dcc_c = self.score(u_c)
            stopped = None
            if cc_c > cc:  # taken
                self.u, w, cc, dcc = u_c, w_c, cc_c, dcc_c
                history.append(cc)
                force = None
                radius = min(self.st.radius_growth * radius, self.step)
                if len(history) > 10 and history[-1] - history[-11] < self.st.tolerance:
                    stopped = "converged"
                if held_best is not None:
                    held.append(self.held_score(self.u))
                    if held[-1] > held_best[0]:
                        held_best = snapshot(held[-1])
                    elif len(history) - max(held_best[1], since) >= self.st.holdout_patience:
                        stopped = "held-out"
            else:
                rejected += 1
                radius *= 0.5
                if radius < self.step * 0.5**self.st.max_halvings:
                    stopped = "no better step"
            if stopped:
                stop = stopped
                taken = False
                if refining and len(rounds) < self.st.refine_rounds:
                    taken, self.u, w, cc, dcc = self.bone_round(self.u, w, cc, dcc, rounds)
                if taken:
                    history.append(cc)  # the bones' round raised the objective: the steps go on from there
                    if held_best is not None:
                        held.append(self.held_score(self.u))
                        since = len(history)
                        if held[-1] > held_best[0]:
                            held_best = snapshot(held[-1])
                    force, radius, stop = None, self.step, "cap"
                    continue
                break
        held_rec = None
        if held_best is not None:
            if held_best[2] is not self.u:  # back to the map the held-out copy scored highest
                self.u, w, cc, dcc = held_best[2:6]
                self.reg.params.clear()
                self.reg.params.update(held_best[6])
                self.reg.tested.clear()  # a bone first tested after the best map may be tested again
                self.reg.tested.update(held_best[7])
                for r in rounds[held_best[8] :]:  # the bones' rounds after it are undone with it
                    r["discarded"] = True
            held_rec = {
                "lncc": [round(float(h), 6) for h in held],
                "best_step": held_best[1] - 1,
                "noise_sd": [round(self.reg.held_out[2][0] * self.reg.scale, 6), round(self.reg.held_out[2][1], 6)],
            }
        post_rec = self.weigh() if self.st.posterior else None
        before = rounds[0]["lncc_before"] if rounds else history[0]
        rec = {
            "level": self.lv,
            "shrink": self.s,
            "shape": list(self.shape),
            "iterations": len(history) - 1,
            "lncc_before": before,
            "lncc_after": cc,
            "input_kept": cc == before and not any(r["taken"] and not r.get("discarded") for r in rounds),
            "rejected": rejected,
            "stop": stop,
            "halvings": halvings,
            # the level's objective (the LNCC, less the skin's term when "skin_term" and the membrane energy when
            # "noise_share") per taken step (and bones' round): never falls; lncc_before / lncc_after are its
            "lncc": [round(float(h), 6) for h in history],
            "tissue_only": self.tissue is not None,  # the windows and smoothing kept to the scan's tissue
            "skin_term": self.skin_warp is not None,  # settings.skin_weight: the objective less the bodies' difference
            # settings.stiffness: the membrane energy's mean weight over the region (the noise's share of the
            # scan's local variance), None when off
            "noise_share": None
            if self.membrane_w is None
            else round(float(self.membrane_w.sum(dtype=np.float64) / self.n_region), 4),
            # settings.interpolation_noise: the template's noise SD in its tissue (its units), None when off
            "template_noise_sd": None
            if self.reg.template.noise_var is None
            else float(np.sqrt(self.reg.template.noise_var) * self.reg.scale),
            "bone_refinement": rounds or None,  # settings.refine_bones: each round's record, None when off
            # settings.holdout: the held-out LNCC per taken step, the step returned (0: the level's input, after
            # its first bones' round) and the two images' noise SDs (their units), None when off
            "held_out": held_rec,
            "posterior": post_rec,  # settings.posterior: the level's change weighed against its input, None when off
            "seconds": round(time.perf_counter() - self.t_level, 2),
        }
        return rec


def register_dense(
    fixed: Volume,
    moving: Volume,
    *,
    initial: Volume | None = None,
    moving_labels: Volume | None = None,
    settings: DenseSettings | None = None,
    progress=None,
) -> DenseResult:
    """Register the template ``moving`` to the scan ``fixed`` from ``initial`` (``φ₀``, scan → template).

    ``moving_labels`` (the template's bone label map) makes every bone move
    rigidly or stay fixed (``settings.bones``).  Returns the ``scan_to_template``
    field ``φ₀ ∘ U`` on the scan grid.  ``progress(dict)`` is called once per
    level with its record.

    Notes
    -----
    * **Start**: ``φ₀`` (scan → template), one-to-one (the polyrigid flow of
      :mod:`deformation.models.polyrigid`); the registration finds ``U = id + u`` on the
      scan grid with ``F ≈ M ∘ φ₀ ∘ U``, the template sampled once through the
      composed map at every trial (``TemplateSampler``: resampling an
      already resampled template rewards sub-voxel shifts that smooth its noise);
      the result is ``φ = φ₀ ∘ U`` (composed, not added).
    * **Similarity**: local normalised cross-correlation in a Gaussian window
      (LNCC), insensitive to the MRI bias field and to contrast differences
      between scans; its gradient is that of Avants et al. (ANTs SyN's CC).
    * **Steps**: the gradient, smoothed by a Gaussian ("fluid" regularisation),
      scaled so that no voxel moves more than the trust radius, then *composed*
      into ``U`` (``u ← f + u ∘ (id + f)``) and ``U`` smoothed ("elastic"
      regularisation, in proportion to the step: half the radius, half the
      smoothing).  A step with ``det(I + ∇f) ≤ min_jacobian`` anywhere is halved
      until it has none, so every step is one-to-one and so is their
      composition: no fold is created.
    * **Convergence** (a trust region on each level's objective, the mean LNCC
      over the voxels where the force acts less the skin's term and the membrane
      energy below): a step is taken only when it raises
      the objective; otherwise the radius halves and the step is tried again from
      the same direction; after a taken step the radius grows (``radius_growth``,
      up to ``step_mm``).  A level stops when no step of radius
      ``step_mm · 2^-max_halvings`` raises its objective, or when 10 taken steps
      together gained less than ``tolerance``; ``iterations`` only caps the
      trials.  Each level's record holds its objective per taken step (it never
      falls), the rejected trials and why it stopped.
    * **Bones** (the template's labels pulled through the current map):
      ``bones="fixed"`` (default) holds each bone at a rigid motion — ``U = id``,
      where the pose stage's rigid intensity registration placed it, more
      precisely than a dense force can — fading into the smooth step over
      ``bone_margin_mm``; ``"rigid"`` replaces the step (and the smoothed field)
      on each bone by its least-squares rigid motion; ``"free"`` ignores the
      labels.
    * **Held bones refined** (``refine_bones``, with ``"fixed"``): a pose stage
      that erred leaves a held bone where it put it, so the bones' poses are
      refined too, by block-coordinate ascent on the same objective: before a
      level's steps, and each time they stop, each bone's rigid motion (six
      parameters about its centroid) is optimised with the soft tissue held
      (NLopt BOBYQA, derivative-free; the candidate moves the bone and fades over
      ``refine_margin_voxels``; the objective is the LNCC over the voxels that
      motion can change, against its value as ``U`` is; a candidate that would
      bring ``det(I + ∇u)`` below ``min_jacobian`` scores below every one-to-one
      one), and the round is taken only if the level's objective rises; the
      steps then go on.
      The pose stage's estimate stands unless the image moves a bone past
      ``refine_min_move_voxels`` (half a scan voxel: the LNCC's windows reach
      into the soft tissue, and its optimum sits a few tenths of a mm from the
      bone's own fit) and the bone's own fit rises significantly with it
      (``refine_significance``, ``bone_fit_improves``: the images smoothed
      by a scan voxel, the noise's correlation counted); a bone is tested on a
      level only where it is at least ``refine_min_voxels`` across (a pose is read from opposite edges), once on
      the finest level if no coarser one could, and once moved it is refined on
      every later round.
    * **Multi-resolution**: the images are smoothed and subsampled by
      ``shrink`` per level, coarse to fine; ``u`` is carried up by trilinear
      interpolation.  The smoothing σ are in voxels of each level by default
      (``fluid_voxels``, ``elastic_voxels``), as ANTs SyN's.
    * **Body only**: the force acts inside the two images' bodies
      (:func:`registration.segmentation.segment_body`) grown by two windows: in
      air the noise alone moves the map, and nothing anatomical holds it.  The levels
      compute on the box around that region grown by the LNCC statistics' reach
      (less time where the body fills a small part of the grid), and U takes
      its edge values beyond the box.
    * **Tissue only** (``tissue_only``, when air surrounds the scan's body):
      the LNCC windows are over the scan's body only, the smoothed force is
      divided by the tissue's share of the kernel (at least 1/2), and ``U`` is
      smoothed by a normalised convolution (Knutsson & Westin 1993) weighing the
      air by ``air_weight``, so the skin's motion is not averaged with the air's,
      which no image drives, and the correlation at the skin follows the
      tissue's texture rather than the body/air step; as sliding-motion
      registration smooths each region on its own (Risser et al. 2013,
      piecewise-diffeomorphic registration).
    * **The skin** (``skin_weight``, with the tissue-only windows): those windows
      do not see the skin, and in flat tissue (soft tissue in CT) nothing else
      does, so a step driven elsewhere could pull the registered body's outline
      inside the scan's.  The level's objective is the LNCC less ``skin_weight``
      times the mean squared difference of the two bodies' masks, each smoothed
      by the window (the template's sampled through the same map; unknown beyond
      its grid, where the term is left out), counted near the scan's skin only
      (deep in its body the template's air is a crease whose skins touch in the
      scan): a force across the skin, not along it.
    * **Where the scan shows only noise** (``stiffness``): a step that moves
      tissue there raises the LNCC by fitting the noise, and nothing in the
      images holds the start.  The level's objective also subtracts a membrane
      energy of the correction ``u``, each voxel weighed by the share of the
      scan's local variance (in the LNCC's window) its noise makes up: near 1 in
      flat tissue, near 0 where structure rises above the noise, so a correction
      the images support costs little and one they do not support costs.
    * **Expected error** (``posterior``, :mod:`registration.posterior`): after each
      level, its change of ``U`` is weighed as a measurement against a Gaussian
      prior (the images' information pooled at the level's scale, the prior's
      variance by the evidence); ``DenseResult.uncertainty`` is the expected
      error σ at each voxel.  With ``posterior_mean`` the level keeps the
      posterior mean of its change (where the scan is silent its input stands);
      by default the map is the steps' own.
    * **Result**: ``φ₀`` is sampled at ``U(x)`` with its edge values beyond the
      grid.  The sampled ``φ₀ ∘ U`` can show ``det ≤ 0`` at a few voxels where the
      start compresses a crease below the voxel size or curled fingers touch;
      those voxels of the scan's body are smoothed locally
      (:func:`deformation.fields.displacement.unfold`) around the bones' interiors (their
      deepest voxels frozen, then fewer; as a last resort none, which is tried
      second as a probe: when it leaves folds, freezing more is not tried),
      every smoothed voxel then going back towards the registered value as far as the
      determinant allows (unfold's restoring passes: the smoothing replaces
      patches, a fold needs a few voxels), and the repair is taken only when it
      removes every fold (``DenseResult.unfold`` says which attempt,
      ``bone_layers_released`` None for the last resort).
    """
    st = settings or DenseSettings()
    t0 = time.perf_counter()
    g = fixed.geometry
    if initial is None:
        initial = Volume(np.zeros(g.array_shape + (3,), np.float32), g)
    g.check_same(initial.geometry, names=("fixed image", "initial correspondence"))
    m0 = warp_template(moving, initial).data  # a new array
    f0 = np.array(fixed.data, np.float32, copy=True)  # normalised in place below: never the caller's array
    lab0 = None
    if st.bones != "free" and moving_labels is not None:
        lab0 = sample_displaced_array(
            np.asarray(moving_labels.data), moving_labels.geometry.world_to_index_matrix, g, initial.data, 0, 0
        ).astype(np.int32)
    # Normalise intensities so that step sizes do not depend on the scanner's units.
    scale = float(np.percentile(np.abs(f0), 99.5)) or 1.0
    f0 /= scale
    m0 /= scale
    sp_full = np.asarray(g.spacing, float)[::-1]  # array axes (z, y, x)
    scan_body, region = _body_region(Volume(f0, g), Volume(m0, g), 2.0 * st.window_mm) if st.body_only else (None, None)
    # The levels work on the box around the force's region only: a region voxel's force reads the LNCC
    # statistics within 3 windows of it (truncate 3), rounded to a level voxel, and beyond the region the
    # force is zero, so padding the box's edges by their values (the filters' "nearest") smooths the force
    # as the whole grid would.  Near the box's edge, in the air, the result is not the whole grid's: U's
    # smoothing and composition there see U continued flat (on the whole grid it decays), and the levels'
    # pre-smoothing sees the edge continued (registration-settings.md, "body_only").
    crop = _crop_box(
        region,
        g.array_shape,
        np.ceil((3.0 * st.window_mm + max(st.shrink) * sp_full.max()) / sp_full),
        int(np.lcm.reduce([int(v) for v in st.shrink])),
    )
    del m0  # the steps sample the template itself (TemplateSampler), not this resampled copy
    # the template's body, where its noise is measured (settings.interpolation_noise, settings.holdout): a mask on
    # its grid, None where none is found (every voxel then); False: not needed
    template_body = False
    if st.interpolation_noise or st.holdout:
        from .segmentation import segment_body

        try:
            template_body = segment_body(moving).data > 0
        except (ValueError, RuntimeError):  # no tissue found; SimpleITK's smoothing on an axis under 4 voxels
            template_body = None
    held_out = None  # settings.holdout: (scan's held-out copy on the box, its template sampler, noise SDs)
    moving_steps = moving
    if st.holdout:  # on the whole scan, before the crop: its noise is measured in all of its air
        held_out, f0, moving_steps = fission(f0, scan_body, moving, template_body, st)
        held_out = (held_out[0][crop], TemplateSampler(held_out[1], initial, scale, crop), held_out[2])
    # settings.stiffness: the voxel noise variance of the scan the steps see (normalised; with holdout, its steps'
    # copy), measured in its air
    noise_var = voxel_noise_variance(f0, scan_body)[0] if (st.stiffness > 0 or st.posterior) else None
    f0 = f0[crop]
    template = TemplateSampler(moving_steps, initial, scale, crop, template_body if st.interpolation_noise else False)
    tissue0 = None  # the scan's tissue (settings.tissue_only), when air surrounds the body
    air_around = scan_body is not None and share_of_air_around(scan_body) >= AIR_AROUND
    template_voxel = voxel_in_voxels(moving.geometry, g)  # the bones' test smooths by at least one of each
    if st.tissue_only and air_around:
        tissue0 = scan_body[crop].astype(np.float32)
    skin = None  # settings.skin_weight: (the template body's sampler, the scan's body on the box), both smoothed
    if tissue0 is not None and st.skin_weight > 0:
        if template_body is False:
            from .segmentation import segment_body

            try:
                template_body = segment_body(moving).data > 0
            except (ValueError, RuntimeError):
                template_body = None
        if template_body is not None:
            t_sig = st.window_mm / np.asarray(moving.geometry.spacing, float)[::-1]
            # beyond the template's grid its body is unknown: read as far below 0, which score() leaves out
            skin = (
                TemplateSampler(
                    Volume(smooth(template_body.astype(np.float32), t_sig, **GAUSSIAN), moving.geometry),
                    initial,
                    1.0,
                    crop,
                    outside=-1e4,
                ),
                smooth(tissue0, st.window_mm / sp_full, **GAUSSIAN),
            )
    lab_full = lab0  # the fold repair below works on the whole grid
    if lab0 is not None:
        lab0 = lab0[crop]
    if region is not None:
        region = region[crop]
    # the held bones' rigid corrections (settings.refine_bones): label → (rotation vector °, t mm) about the
    # bone's centroid on the scan (mm along the array axes of the box, the same on every level)
    centres, params, tested = {}, {}, set()
    if lab0 is not None and st.bones == "fixed" and st.refine_bones:
        for b, sl in enumerate(ndimage.find_objects(lab0), start=1):
            if sl is not None:
                centres[b] = np.array(
                    [(np.nonzero(lab0[sl] == b)[a] + sl[a].start).mean() * sp_full[a] for a in range(3)]
                )
    u = None  # (3, nz, ny, nx) mm along array axes, on the current level's grid
    prev_s = None  # the previous level's shrink factor
    levels = []
    reg = _Registration(
        st,
        f0,
        template,
        tissue0,
        skin,
        lab0,
        region,
        centres,
        params,
        tested,
        held_out,
        noise_var,
        air_around,
        template_voxel,
        scale,
        sp_full,
        crop,
    )
    for lv, (s, iters) in enumerate(zip(st.shrink, st.iterations)):
        level = _Level(reg, lv, int(s), u, prev_s)
        rec = level.run(iters)
        u = level.u
        levels.append(rec)
        log.info(
            "dense level %d (shrink %d): %d steps taken, %d refused, stopped: %s; objective %.4f -> %.4f",
            lv,
            int(s),
            rec["iterations"],
            rec["rejected"],
            rec["stop"],
            rec["lncc_before"] or 0,
            rec["lncc_after"] or 0,
        )
        if progress is not None:
            progress(rec)
        prev_s = int(s)
    var_post = reg.var_post
    sigma = post_rec = None
    if var_post is not None:
        # σ: the levels' posteriors and, in the soft tissue, the registration's own error, a share of the correction
        # it made (a held bone's error is its rigid pose's, in the finest level's posterior)
        own = (st.posterior_relative_error * np.linalg.norm(u, axis=0)) ** 2
        if reg.var_total is not None:  # settings.posterior_total: in the soft tissue at least the whole correction's
            var_post = var_post + level.keep * np.maximum(reg.var_total - var_post, 0.0)
        sigma = np.sqrt(var_post + level.keep * own).astype(np.float32)
        post_rec = dict(levels[-1]["posterior"])
        post_rec.update(
            prior_sd_levels_mm=[lv_["posterior"]["prior_sd_mm"] for lv_ in levels if lv_["posterior"]],
            kept_levels=[lv_["posterior"]["kept"] for lv_ in levels if lv_["posterior"]],
        )
    # u (array axes, mm) → world displacement on the scan grid, then φ = φ₀ ∘ U
    box_shape = f0.shape
    if u.shape[1:] != box_shape:
        grid = np.indices(box_shape, dtype=np.float32)
        coords = [np.minimum(grid[a] / prev_s, u.shape[a + 1] - 1) for a in range(3)]
        u = np.stack([_sample(u[a], coords) for a in range(3)])
        if sigma is not None:
            sigma = _sample(sigma, coords).astype(np.float32)
    if sigma is not None:  # its median over the scan's body (the levels' records hold their own parts)
        inside = scan_body[crop] if scan_body is not None else np.ones(box_shape, bool)
        post_rec["sigma_median_mm"] = round(float(np.median(sigma[inside])), 4) if inside.any() else None
    if box_shape != g.array_shape:  # beyond the box (air), U's edge values: the levels' "nearest" padding
        pad = [(c.start, n - c.stop) for c, n in zip(crop, g.array_shape)]
        u = np.pad(u, [(0, 0)] + pad, mode="edge")
        if sigma is not None:  # beyond the box the images say nothing: the prior's expected error
            outside = np.sqrt(3.0 * sum(v**2 for v in post_rec["prior_sd_levels_mm"]))
            sigma = np.pad(sigma, pad, constant_values=np.float32(outside))
    lab0 = lab_full
    u_ijk = (u[2], u[1], u[0])  # along index axes i, j, k
    d = np.asarray(g.direction_matrix)
    # written out, not a matrix product: BLAS kernels may round differently with the arrays' alignment
    u_world = np.stack(
        [d[r, 0] * u_ijk[0] + d[r, 1] * u_ijk[1] + d[r, 2] * u_ijk[2] for r in range(3)], axis=-1
    ).astype(np.float32)
    # φ = φ₀ ∘ U: φ₀ sampled at x + u(x), extended by its edge values beyond the grid as the images were
    # in every step (deformation.fields.displacement.compose takes φ₀ as zero there, which tears a limb cut by the edge)
    phi0 = np.moveaxis(
        sample_shifted(np.moveaxis(np.asarray(initial.data, np.float32), -1, 0), u, 1.0 / sp_full), 0, -1
    )
    corr = Volume((u_world + phi0).astype(np.float32), g)
    u_folds = folding_statistics(Volume(u_world, g), scan_body)["n_folded"]
    repair = None
    if st.unfold:
        # Every step was one-to-one on its level's grid (the smoothing of U between steps is not checked); φ₀ ∘ U,
        # sampled on the scan grid, can show det ≤ 0 where the start compresses the crease below the voxel size (as the
        # phantoms' exact fields do) or where trilinear sampling of a steep φ₀ meets U's shift.  Those voxels are
        # smoothed locally, inside the body only (air carries no anatomy).
        mask = scan_body
        lab_now = (
            None
            if lab0 is None
            else sample_shifted(lab0.astype(np.float32), u, 1.0 / sp_full, order=0).astype(np.int32)
        )
        n_folded = folding_statistics(corr, mask)["n_folded"]
        if n_folded:
            # the bones keep the start's rigid motion: the repair works around their interiors, and a fold
            # pressed against a bone frees one more voxel layer of it at a time (up to 3, a bone's deepest
            # voxels staying, _bone_cores); nothing frozen is the last choice, though it runs second as a probe
            # (the smoothing stays local to the folds, but may then bend a bone next to one).  Only a complete
            # repair is taken: a failing one smooths an ever larger region, so then the folds stay, reported in
            # ``folding`` (registration-settings.md, "unfold").
            # Each attempt first smooths only the folded voxels with a narrow kernel (σ 0.7 voxel, no margin):
            # on the hand the folds sit where curled fingers touch, where neighbouring voxels map to different
            # fingers and a wider average lands between them; the knee's crease folds need the defaults (σ 1,
            # one voxel of margin).
            best = None

            def attempt(peel):
                """Both kernels with the bones' cores less ``peel`` layers frozen (None: nothing frozen), until
                one leaves no fold: the better ``(field, info)``."""
                frozen = None if peel is None else _bone_cores(lab_now, peel, sp_full)
                out = None
                for kernel in ({"sigma": 0.7, "margin": 0}, {}):
                    fixed_c, info = unfold(corr, mask=mask, frozen=frozen, **kernel)
                    info["bone_layers_released"] = peel
                    info["kernel"] = kernel or "unfold's defaults"
                    if out is None or info["n_folded_after"] < out[1]["n_folded_after"]:
                        out = (fixed_c, info)
                    if not info["n_folded_after"]:
                        break
                return out

            # the first attempt that leaves no fold in the order 1, 2, 3 layers, nothing frozen; else the one that
            # leaves the fewest (not taken).  Nothing frozen runs second, as a probe: freezing voxels only takes
            # freedom from the smoothing, so when it leaves folds the attempts that freeze more are not run (each
            # would spend unfold's whole iteration budget in vain; the record then describes the best of the two
            # attempts run, not of all four)
            order = [None] if lab_now is None else [1, None, 2, 3]
            tried = {}
            for peel in order:
                tried[peel] = attempt(peel)
                if best is None or tried[peel][1]["n_folded_after"] < best[1]["n_folded_after"]:
                    best = tried[peel]
                if (peel is None) == bool(tried[peel][1]["n_folded_after"]):  # None failed, or a freezing one did it
                    break
            done = [peel for peel in (1, 2, 3, None) if peel in tried and not tried[peel][1]["n_folded_after"]]
            if done:
                best = tried[done[0]]
            repair = best[1]
            repair["taken"] = repair["n_folded_after"] == 0
            # every attempt run, in order: bone layers released (None: nothing frozen) and the folds it left
            repair["attempts"] = [[peel, info["n_folded_after"]] for peel, (_, info) in tried.items()]
            if repair["taken"]:
                corr = Volume(best[0].data.astype(np.float32), g)
    registered = warp_template(moving, corr)
    seconds = time.perf_counter() - t0
    return DenseResult(
        corr,
        registered,
        seconds,
        levels,
        st.to_dict(),
        similarity_before=similarity(fixed.data, warp_template(moving, initial).data),
        similarity_after=similarity(fixed.data, registered.data),
        folding={
            **folding_statistics(corr, scan_body),
            "over": "all voxels" if scan_body is None else "the scan's body",
            "n_folded_u": u_folds,
        },
        unfold=repair,
        uncertainty=None if sigma is None else Volume(sigma, g),
        posterior=post_rec,
    )
