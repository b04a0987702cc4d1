"""Rigid registration of one bone, template → scan (Rhee et al. 2011, §3.1, Rhee Eq. 1; Kurihara & Miyata 2004, §3).

Rhee §3.1 finds each bone's rigid transform ``T`` by minimising the sum of
squared differences over the bone's voxels (Rhee Eq. 1)::

    E(T) = Σ_{x ∈ bone} (I_scan(T x) − I_template(x))²

"with trilinear interpolation", initialised down the skeleton from the
parent bone's result.  Kurihara §3 instead aligns bone isosurfaces by ICP.
This module holds both refinements plus the shared pieces:
:class:`BoneRegion` (a bone's dilated region in the template, each dilation
voxel given to its nearest bone only), :class:`Sampler` (a scan interpolated
at world points after a light Gaussian smoothing),
:func:`coarse_rotation_search` (our addition: rotations of a child bone about
its joint centre on a grid, since its parent's transform alone can start it
far outside any local optimiser's capture range), :func:`refine_intensity`
(Rhee Eq. 1 through SimpleITK's registration framework, then
:func:`polish_with_prior`: the same cost to convergence by least squares with
a weak prior towards the kinematic initialisation, and the posterior
uncertainty) and :func:`refine_surface` (Kurihara's ICP of VTK isosurfaces by
Open3D, :mod:`registration.icp`).

Every transform maps template world points to scan world points (4x4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from deformation.fields.interpolate import sample_spline
from deformation.filters import smooth
from deformation.geometry import Volume
from deformation.kinematics.transforms import apply, compose, rotation_angle_deg
from deformation.meshes.isosurface import isosurface

__all__ = [
    "BoneRegion",
    "BoneFit",
    "Sampler",
    "bone_regions",
    "polish_with_prior",
    "surface_prior",
    "ssd",
    "ncc",
    "PRIOR_MM",
    "coarse_rotation_search",
    "refine_intensity",
    "refine_surface",
    "auto_iso_level",
]


#: voxels per independent sample of the residual in the polish's data term: each voxel counts, so the reported
#: standard deviations are optimistic by about the residual's correlation length's square root
#: (registration-settings.md, "NOISE_CORRELATION")
NOISE_CORRELATION = 1.0

#: the polish's robust loss (scipy.optimize.least_squares) and its threshold in units of the residual's robust
#: scale (1.4826 × its MAD): Huber at 2σ bounds the pull of the soft tissue in a bone's region that does not move
#: with the bone (registration-settings.md, "ROBUST_LOSS and ROBUST_SCALE")
ROBUST_LOSS = "huber"
ROBUST_SCALE = 2.0
PRIOR_MM = 2.0  # the polish's translation prior (the rotation prior is the callers' prior_deg)


@dataclass
class BoneRegion:
    """A bone's (dilated) region in the template, cropped, with world points and intensities."""

    name: str
    label: int
    crop: Volume  # template intensities on the crop grid (float32)
    mask: np.ndarray  # bool, crop array shape [z, y, x]: the dilated bone region
    bone: np.ndarray  # bool, crop array shape: the bone's own labelled voxels
    points: np.ndarray  # (n, 3) world mm of the mask voxels
    values: np.ndarray  # (n,) template intensities at ``points``
    centroid: np.ndarray  # centroid of the bone's labelled voxels, world mm


@dataclass
class BoneFit:
    """One bone's registration in one scan."""

    bone: str
    transform: np.ndarray
    method: str
    status: str  # "ok", "not_converged", "poor_match", "outside_field_of_view", "joint_detached", "joint_outlier"
    # or "parent_flagged"
    ssd_before: float  # mean squared difference over the region at the initialisation
    ssd_after: float
    ncc: float  # normalised cross-correlation of template and scan over the region, after
    inside_fraction: float  # fraction of the region that maps inside the scan
    iterations: int = 0
    stop: str = ""
    seconds: float = 0.0
    init: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_dict(self) -> dict:
        return {
            "bone": self.bone,
            "method": self.method,
            "status": self.status,
            "transform": np.asarray(self.transform).tolist(),
            "ssd_before": float(self.ssd_before),
            "ssd_after": float(self.ssd_after),
            "ncc": float(self.ncc),
            "inside_fraction": float(self.inside_fraction),
            "iterations": int(self.iterations),
            "stop": self.stop,
            "seconds": round(float(self.seconds), 4),
            "init": self.init,
            **self.extra,
        }


# -- regions ------------------------------------------------------------------------------------------
def bone_regions(
    template: Volume,
    labels: Volume,
    skeleton,
    *,
    margin_mm: float | None = None,
    crop_margin_mm: float | None = None,
    exclusion_mm: float | None = None,
) -> dict[str, BoneRegion]:
    """Every skeleton bone's region in the template.

    Parameters
    ----------
    margin_mm : dilation of each bone's label (Rhee: "slightly dilated"), so
        that the bone's edge, where the image information is, lies inside the
        region; default one voxel (the largest spacing) but at least 2 mm.
        Each voxel of the dilation belongs to its nearest bone only.
    crop_margin_mm : extra room around the region in the crop (for the
        smoothing of the coarse levels); default 3 voxels.
    exclusion_mm : dilation voxels this close to another bone are left out
        (default: ``margin_mm``): near a joint the partner bone moves into
        them in a posed scan, and its cortex would pull on this bone.
    """
    g = labels.geometry
    template.geometry.check_same(
        g, names=("template", "template labels"), remedy="the label map must be on the template's grid"
    )
    spacing = np.asarray(g.spacing, float)
    if margin_mm is None:
        margin_mm = max(2.0, float(spacing.max()))
    if crop_margin_mm is None:
        crop_margin_mm = 3.0 * float(spacing.max())
    lab = np.asarray(labels.data)
    known = {b.label for b in skeleton.bones}
    bone_voxels = np.isin(lab, list(known))
    # Nearest bone voxel of every voxel (distances in mm; the array axes are [z, y, x]).
    dist, idx = ndimage.distance_transform_edt(~bone_voxels, sampling=spacing[::-1], return_indices=True)
    nearest = lab[tuple(idx)]
    img = np.asarray(template.data, dtype=np.float32)
    out = {}
    for b in skeleton.bones:
        own = lab == b.label
        n = int(own.sum())
        if n < 4:
            raise ValueError(
                f"bone {b.name!r} (label {b.label}) has {n} voxels in the template label map (at least "
                "4 needed); check the label ids in skeleton.json against the label map, or, for a "
                "segmented template, move or add seeds for this bone"
            )
        region = (nearest == b.label) & (dist <= margin_mm)
        others = bone_voxels & ~own
        if others.any():
            excl = margin_mm if exclusion_mm is None else exclusion_mm
            d_other = ndimage.distance_transform_edt(~others, sampling=spacing[::-1])
            region &= own | (d_other > excl)
        zz, yy, xx = np.nonzero(region)
        pad = np.ceil(crop_margin_mm / spacing).astype(int)  # (x, y, z)
        lo = np.array([xx.min(), yy.min(), zz.min()]) - pad  # voxel index (i, j, k); Volume.crop clips
        hi = np.array([xx.max(), yy.max(), zz.max()]) + pad + 1
        crop = Volume(img, g).crop(lo, hi)
        m = Volume(region, g).crop(lo, hi).data
        k, j, i = np.nonzero(m)
        pts = crop.geometry.index_to_world(np.column_stack([i, j, k]).astype(float))
        bk, bj, bi = np.nonzero(own)
        centroid = g.index_to_world(np.column_stack([bi, bj, bk]).astype(float)).mean(axis=0)
        out[b.name] = BoneRegion(
            b.name, b.label, crop, m, Volume(own, g).crop(lo, hi).data, pts, crop.data[m].astype(np.float64), centroid
        )
    return out


# -- sampling and metrics ------------------------------------------------------------------------------
class Sampler:
    """Interpolates one scan at world points: trilinear (``order=1``, Rhee's choice) or cubic B-spline
    (``order=3``, the default: on coarse grids trilinear interpolation of a rotated bone leaves a residual
    that biases the SSD minimum, several times the cubic one's; docs/measurements/pose-and-initialisation.md).
    The B-spline coefficients are computed once per scan.  Points outside the grid give NaN."""

    def __init__(self, image: Volume, order: int = 3, smooth_voxels: float = 0.0):
        if order not in (1, 3):
            raise ValueError(f"interpolation order must be 1 (linear) or 3 (cubic B-spline), got {order}")
        image = smooth(image, smooth_voxels, dtype=np.float32)  # SciPy's kernel in voxels, edges reflected
        self.image = image
        self.order = order
        data = np.asarray(image.data, dtype=np.float64)
        self.coeffs = ndimage.spline_filter(data, order=3, mode="mirror") if order == 3 else data

    def sitk_image(self):
        if getattr(self, "_sitk", None) is None:
            self._sitk = Volume(np.asarray(self.image.data, dtype=np.float32), self.image.geometry).to_sitk()
        return self._sitk

    def __call__(self, points: np.ndarray, transforms: np.ndarray | None = None) -> np.ndarray:
        """The scan at world ``points`` ``(n, 3)``; with ``transforms`` ``(k, 4, 4)``, at each transform of the
        points, ``(k, n)``."""
        return sample_spline(
            self.coeffs, self.image.geometry.world_to_index_matrix, points, order=self.order, transforms=transforms
        )


def ssd(a: np.ndarray, b: np.ndarray) -> float:
    """Mean squared difference over the finite pairs (NaN when none)."""
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.mean((a[ok] - b[ok]) ** 2)) if ok.any() else math.nan


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation over the finite pairs."""
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3:
        return math.nan
    x, y = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    den = math.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y / den) if den > 0 else math.nan


def _evaluate(region: BoneRegion, sampler: Sampler, t: np.ndarray, *, min_inside: float = 0.5) -> tuple[float, float]:
    """(SSD, inside fraction) of the region mapped by ``t`` into the scan; inf when too little is inside."""
    vals = sampler(apply(t, region.points))
    inside = float(np.isfinite(vals).mean())
    if inside < min_inside:
        return math.inf, inside
    return ssd(vals, region.values), inside  # Rhee Eq. 1 at T, divided by the voxel count


# -- coarse initialisation -----------------------------------------------------------------------------
def _batch_ssd(
    region_pts,
    region_vals,
    sampler: Sampler,
    transforms: np.ndarray,
    min_inside: float = 0.5,
    metric: str = "ssd",
    outside_unmatched: bool = False,
):
    """Cost of the region under each of ``transforms`` (k, 4, 4), one interpolation call per batch.

    ``metric="ssd"``: mean squared difference (Rhee Eq. 1).  ``metric="ncc"``: the
    mean squared difference left after the best linear intensity map
    ``a·I_scan + b`` per candidate, ``var(I_template)·(1 − ρ²)`` with ρ the
    correlation — Rhee Eq. 1 made blind to a bone-wide gain and offset (an MRI
    bias field, a different window).
    """
    n = len(region_pts)
    v = sampler(region_pts, transforms)  # (k, n)
    ok = np.isfinite(v)
    cnt = ok.sum(axis=1)
    if metric == "ssd":
        d2 = np.where(ok, (v - region_vals) ** 2, 0.0)  # Rhee Eq. 1's (I_scan(T x) − I_template(x))² per candidate
        out = d2.sum(axis=1) / np.maximum(cnt, 1)
    else:
        w = ok.astype(float)
        m = np.maximum(cnt, 1)
        t = np.broadcast_to(region_vals, v.shape)
        vz = np.where(ok, v, 0.0)
        mv, mt = vz.sum(1) / m, (t * w).sum(1) / m
        cv = (vz - mv[:, None]) * w
        ct = (t - mt[:, None]) * w
        sxy, sxx, syy = (cv * ct).sum(1), (cv * cv).sum(1), (ct * ct).sum(1)
        rho2 = np.where(sxx * syy > 0, sxy**2 / np.maximum(sxx * syy, 1e-300), 0.0)
        out = syy / m * (1.0 - rho2)
        if outside_unmatched:
            # the region's points outside the scan count as matched by nothing (ρ = 0: the template's variance),
            # not as absent: otherwise a candidate that turns half the bone out of the field of view is scored on
            # the half next to its joint, which moves least, and wins
            var_all = float(np.var(region_vals))
            out = (cnt * out + (n - cnt) * var_all) / n
    out[cnt < min_inside * n] = np.inf
    return out


def coarse_rotation_search(
    region: BoneRegion,
    sampler: Sampler,
    parent_transform: np.ndarray,
    joint,
    *,
    flex_range=(-120.0, 120.0),
    abd_range=(-20.0, 20.0),
    twist_range=(-20.0, 20.0),
    max_points: int = 400,
    top: int = 12,
    metric: str = "ncc",
    center=None,
    seed: int = 0,
    runners_up: list | None = None,
    outside_unmatched: bool = True,
) -> tuple[np.ndarray, float, int, np.ndarray]:
    """Best child transform among rotations about the joint centre (our initialisation step).

    The cost is ``metric`` (see ``_batch_ssd``): SSD, or by default the
    SSD left after the best linear intensity map.

    Candidates are ``T_parent ∘ M(θ)`` with ``M`` the joint's rotation
    (intrinsic x, y, z about the joint's template axes) about ``center``
    (default: the skeleton's joint centre), on a grid over flexion, abduction
    and twist.  The grid step follows the bone's geometry: a rotation by the
    step moves the far end of the bone by half its thickness, so the SSD basin
    of a thin bone far from its joint (the knee phantom's fibula, 45 mm out;
    a 5° error there already misses the bone) is never stepped over.  Finer
    3x3x3 grids around the winner halve the step down to ≤ 1°.  To keep the
    count down, a first grid at twice that step keeps its ``top`` candidates
    and only their neighbourhoods are searched at the full step.  The SSD uses
    ``max_points`` seeded random points of the region and evaluates a batch of
    candidates per interpolation call.  Returns ``(transform, cost,
    evaluations, angles)`` with ``angles`` the winning (flexion, abduction,
    twist) in degrees.

    With ``outside_unmatched`` (default; ``metric="ncc"``) stages 1 and 2 count
    the region's points that a candidate puts outside the scan as matched by
    nothing (their share of the template's variance), not as absent: otherwise
    a pose that turns half of a bone out of the scan is scored on its inside
    half alone and can win (a distal phalanx placed hyperextended, half out of
    view: docs/measurements/pose-and-initialisation.md).

    ``runners_up`` (optional list) receives ``(cost, angles, transform)`` of
    the other local winners of stage 2 (cost as stage 2 scored it), best first, each more than two steps
    (a rotation that moves the bone's far end by its thickness) from the
    winner and from each other: the blur that widens the basin
    can rank a wrong pose of a thin bone first (a curled distal phalanx next
    to its neighbours), and a caller whose refined fit is then flagged can
    refine these at the fine scale instead (:func:`registration.pose.register_scan`).
    """
    c = np.asarray(joint.center if center is None else center, float)
    a = joint.axes
    pts, vals = region.points, region.values
    if len(pts) > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))
        pts, vals = pts[pick], vals[pick]
    lever = float(np.linalg.norm(region.points - c, axis=1).max())
    bone_pts = region.points[region.bone[region.mask]]
    thickness = 2.0 * math.sqrt(max(float(np.linalg.eigvalsh(np.cov(bone_pts.T))[0]), 1e-6))
    step = float(np.clip(np.degrees(0.5 * thickness / max(lever, 1e-6)), 2.0, 15.0))

    def axis_values(lo, hi, st):
        v = np.arange(0.0, hi + 1e-9, st)
        return np.unique(np.concatenate([-np.arange(0.0, -lo + 1e-9, st)[::-1], v]))

    def transforms(angles):
        r = np.einsum("ij,kjl,ml->kim", a, Rotation.from_euler("XYZ", angles, degrees=True).as_matrix(), a)
        m = np.tile(np.eye(4), (len(angles), 1, 1))
        m[:, :3, :3] = r
        m[:, :3, 3] = c - r @ c
        return np.einsum("ij,kjl->kil", parent_transform, m)

    # Stage 1: a grid at twice the geometric step; keep the best ``top`` candidates.
    coarse_step = min(2.0 * step, 15.0)
    grid = (
        np.array(
            np.meshgrid(
                axis_values(*flex_range, coarse_step),
                axis_values(*abd_range, coarse_step),
                axis_values(*twist_range, coarse_step),
                indexing="ij",
            )
        )
        .reshape(3, -1)
        .T
    )
    e = np.concatenate(
        [
            _batch_ssd(pts, vals, sampler, transforms(chunk), metric=metric, outside_unmatched=outside_unmatched)
            for chunk in np.array_split(grid, max(1, len(grid) // 256))
        ]
    )
    n = len(grid)
    order = np.argsort(e)[:top]
    if not np.isfinite(e[order[0]]):
        return parent_transform.copy(), math.inf, n, np.zeros(3)
    # Stage 2: the geometric step around each of them.
    half = max(1, int(round(coarse_step / step)))
    ticks = np.arange(-half, half + 1) * step  # symmetric about the stage-1 winner, which is scored again
    local = np.array(np.meshgrid(ticks, ticks, ticks, indexing="ij")).reshape(3, -1).T
    best, best_angles = math.inf, np.zeros(3)
    local_winners = []
    for i in order:
        if not np.isfinite(e[i]):
            break
        cand = grid[i] + local
        ec = _batch_ssd(pts, vals, sampler, transforms(cand), metric=metric, outside_unmatched=outside_unmatched)
        n += len(cand)
        w = int(np.argmin(ec))
        if np.isfinite(ec[w]):
            local_winners.append((float(ec[w]), cand[w].copy()))
        if ec[w] < best:
            best, best_angles = float(ec[w]), cand[w].copy()
    offsets = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T
    # Stage 3 polishes inside the chosen basin on the points inside the scan alone, the cost the refinement then
    # minimises: counting the outside ones as unmatched is there to choose the basin
    if outside_unmatched:
        best = float(_batch_ssd(pts, vals, sampler, transforms(best_angles[None]), metric=metric)[0])
    h = step / 2
    while True:
        cand = best_angles + h * offsets
        e = _batch_ssd(pts, vals, sampler, transforms(cand), metric=metric)
        n += len(cand)
        i = int(np.argmin(e))
        if e[i] < best:
            best, best_angles = float(e[i]), cand[i].copy()
        if h <= 1.0:
            break
        h /= 2
    if runners_up is not None:
        kept = [best_angles]
        for cost, ang in sorted(local_winners, key=lambda t: t[0]):
            if all(np.linalg.norm(ang - k) > 2.0 * step for k in kept):  # the far end moved by ≥ the bone's thickness
                kept.append(ang)
                runners_up.append((cost, ang, transforms(ang[None])[0]))
    return transforms(best_angles[None])[0], best, n, best_angles


# -- Rhee Eq. 1 through SimpleITK ---------------------------------------------------------------------------
def _euler_from_matrix(t: np.ndarray, center: np.ndarray):
    import SimpleITK as sitk

    tx = sitk.Euler3DTransform()
    tx.SetCenter([float(v) for v in center])
    tx.SetMatrix([float(v) for v in t[:3, :3].ravel()], 1e-5)
    # Euler3DTransform: y = R (x − c) + c + τ  ⇒  τ = b − c + R c for y = R x + b.
    tx.SetTranslation([float(v) for v in (t[:3, 3] - center + t[:3, :3] @ center)])
    return tx


def _matrix_from_sitk(tx) -> np.ndarray:
    m = np.eye(4)
    r = np.asarray(tx.GetMatrix(), float).reshape(3, 3)
    c = np.asarray(tx.GetCenter(), float)
    m[:3, :3] = r
    m[:3, 3] = np.asarray(tx.GetTranslation(), float) + c - r @ c
    return m


def _levels(region: BoneRegion, multires: bool) -> tuple[list[int], list[float]]:
    """Shrink factors and smoothing sigmas (voxels) per level.

    With ``multires`` (a root bone started from a rough initial pose) the
    crop is also registered shrunk by 4 and 2 when it is big enough.  Child
    bones start within a few degrees (the coarse joint search), where a
    smoothed level only moves the SSD minimum of a small bone (the fibula:
    docs/measurements/pose-and-initialisation.md), so they get one
    full-resolution level.
    """
    small = min(region.crop.geometry.size)
    if not multires:
        return [1], [0.0]
    if small >= 64:
        return [4, 2, 1], [2.0, 1.0, 0.0]
    if small >= 24:
        return [2, 1], [1.0, 0.0]
    return [1, 1], [1.0, 0.0]


def refine_intensity(
    region: BoneRegion,
    sampler: Sampler,
    init: np.ndarray,
    *,
    iterations: int = 300,
    polish: bool = True,
    prior_deg: float | None = 2.0,
    prior_mm: float | None = PRIOR_MM,
    multires: bool = False,
    metric: str = "ncc",
    prior_center: np.ndarray | None = None,
    noise_correlation: float = NOISE_CORRELATION,
    loss: str = ROBUST_LOSS,
    loss_scale: float = ROBUST_SCALE,
    min_ncc: float = 0.5,
    min_inside: float = 0.5,
) -> BoneFit:
    """Rhee Eq. 1: minimise the SSD over the bone region with SimpleITK, from ``init``.

    SimpleITK's ``ImageRegistrationMethod`` minimises mean squares over the
    region (a fixed-image mask on the template crop), multi-resolution, with
    the sampler's interpolation (linear or cubic B-spline).  Then, with
    ``polish``, :func:`polish_with_prior` minimises the same cost to
    convergence (robustly, ``loss``), settles the directions the image does
    not determine with the prior (``prior_deg`` / ``prior_mm``; None: no
    prior, as for a root bone) and estimates each bone's uncertainty.
    ``noise_correlation`` is the number of voxels that count as one
    independent sample in the data term (see ``NOISE_CORRELATION``).
    """
    import time

    import SimpleITK as sitk

    t0 = time.perf_counter()
    before, inside0 = _evaluate(region, sampler, init, min_inside=0.0)
    if inside0 < min_inside:
        return BoneFit(
            region.name,
            init,
            "intensity",
            "outside_field_of_view",
            before,
            math.nan,
            math.nan,
            inside0,
            stop=f"only {inside0:.0%} of the bone region maps inside the scan at the initialisation",
            seconds=time.perf_counter() - t0,
        )
    fixed = region.crop.to_sitk()
    mask = Volume(region.mask.astype(np.uint8), region.crop.geometry).to_sitk()
    moving = sampler.sitk_image()
    shrink, sigma = _levels(region, multires)
    reg = sitk.ImageRegistrationMethod()
    if metric not in ("ssd", "ncc"):
        raise ValueError(
            f"metric must be 'ssd' (Rhee Eq. 1) or 'ncc' (Rhee Eq. 1 after a linear intensity fit), got {metric!r}"
        )
    # Rhee Eq. 1 as printed.  (ITK's correlation metric with the same optimiser ran into the iteration cap on every
    # bone and took 25x longer; the intensity-invariant variant lives in the polish below.)
    reg.SetMetricAsMeanSquares()
    reg.SetMetricFixedMask(mask)
    reg.SetMetricSamplingStrategy(reg.NONE)
    reg.SetInterpolator(sitk.sitkBSpline if sampler.order == 3 else sitk.sitkLinear)
    # ITK's regular-step descent (learning rate 1, physical-shift scales): of ITK's optimisers it got closest and
    # fastest from a few degrees off (docs/measurements/pose-and-initialisation.md); none reaches the SSD minimum
    # in rotation, which is why polish_with_prior follows.
    reg.SetOptimizerAsRegularStepGradientDescent(
        learningRate=1.0,
        minStep=1e-4,
        numberOfIterations=iterations,
        relaxationFactor=0.7,
        gradientMagnitudeTolerance=1e-12,
    )
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel(shrink)
    reg.SetSmoothingSigmasPerLevel(sigma)
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    reg.SetInitialTransform(_euler_from_matrix(init, region.centroid), inPlace=False)
    iters = [0]
    reg.AddCommand(sitk.sitkIterationEvent, lambda: iters.__setitem__(0, iters[0] + 1))
    # ITK prints "No valid points were found during metric evaluation" when a trial step leaves the scan; the
    # outcome is judged below (inside fraction, convergence), so the console stays quiet.
    shown = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        out = reg.Execute(fixed, moving)
    except RuntimeError as e:  # e.g. "All samples map outside moving image buffer"
        return BoneFit(
            region.name,
            init,
            "intensity",
            "not_converged",
            before,
            math.nan,
            math.nan,
            inside0,
            stop=f"SimpleITK failed: {str(e).strip().splitlines()[-1]}",
            seconds=time.perf_counter() - t0,
        )
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(shown)
    t = _matrix_from_sitk(out.GetNthTransform(0) if hasattr(out, "GetNthTransform") else out)
    stop = reg.GetOptimizerStopConditionDescription()
    extra = {
        "ssd_eq1": _evaluate(region, sampler, t, min_inside=0.0)[0],
        "sitk_iterations": iters[0],
        "sitk_stop": stop,
    }
    not_converged = iters[0] >= iterations * len(shrink)
    if polish:
        centre = init if prior_center is None else np.asarray(prior_center, float)
        # σ (the RMS residual) weighs the data against the prior as before; the loss's threshold is set on the
        # robust scale of the residual (its MAD), which the voxels that do not follow the bone do not inflate.
        rms, mad = _data_sigma(region, sampler, t, metric)
        sigma = rms * math.sqrt(noise_correlation)
        robust = mad / rms if np.isfinite(rms) else 1.0  # NaN when the fit left the scan: polish re-measures σ
        opts = dict(
            prior_deg=prior_deg,
            prior_mm=prior_mm,
            metric=metric,
            sigma=sigma,
            loss=loss,
            loss_scale=loss_scale * robust,
        )
        runs = [polish_with_prior(region, sampler, centre, t, **opts)]
        if prior_center is not None:  # also from the prior's centre: the grid search may have taken a wrong basin
            runs.append(polish_with_prior(region, sampler, centre, centre, **opts))
        t, info = min(runs, key=lambda r: r[1].get("cost", math.inf))
        info["polish_starts"] = len(runs)
        extra.update(info)
        not_converged = not info.get("converged", True)
        stop = info.get("message", stop)
    return _finish(
        region,
        sampler,
        t,
        "intensity",
        before,
        iters[0],
        stop,
        t0,
        min_ncc=min_ncc,
        min_inside=min_inside,
        not_converged=not_converged,
        extra=extra,
    )


def _increment(x: np.ndarray, reference: np.ndarray, center: np.ndarray) -> np.ndarray:
    """``D(x) ∘ reference``: ``x`` = (rotation vector in degrees, translation mm) about ``center`` (scan)."""
    d = np.eye(4)
    r = Rotation.from_rotvec(np.deg2rad(x[:3])).as_matrix()
    d[:3, :3] = r
    d[:3, 3] = center - r @ center + x[3:]
    return compose(d, reference)


def _data_residuals(v: np.ndarray, ref: np.ndarray, metric: str) -> np.ndarray:
    if metric == "ncc":  # after the best linear intensity map a·v + b, in closed form (variable projection)
        vc = v - v.mean()
        den = float(vc @ vc)
        a = float(vc @ (ref - ref.mean())) / den if den > 0 else 0.0
        return a * vc + ref.mean() - ref
    return v - ref  # Rhee Eq. 1's residuals I_scan(T x) − I_template(x)


def _data_sigma(region: BoneRegion, sampler: Sampler, t: np.ndarray, metric: str) -> tuple[float, float]:
    """The residual's scale at ``t``: ``(RMS, robust σ)``, the robust one 1.4826 × the median absolute
    deviation (the noise's σ for Gaussian residuals, unmoved by the voxels that do not follow the bone), never
    below 1 % of the RMS nor above it.  NaN when fewer than 12 points map into the scan."""
    v = sampler(apply(t, region.points))
    ok = np.isfinite(v)
    if ok.sum() < 12:
        return math.nan, math.nan
    r = _data_residuals(v[ok], region.values[ok], metric)
    rms = math.sqrt(max(float(np.mean(r**2)), 1e-12))
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return rms, min(max(mad, 0.01 * rms), rms)


def polish_with_prior(
    region: BoneRegion,
    sampler: Sampler,
    init: np.ndarray,
    start: np.ndarray,
    *,
    prior_deg: float | None = 2.0,
    prior_mm: float | None = PRIOR_MM,
    metric: str = "ncc",
    sigma: float | None = None,
    loss: str = ROBUST_LOSS,
    loss_scale: float = ROBUST_SCALE,
) -> tuple[np.ndarray, dict]:
    """Rhee Eq. 1 plus a weak Gaussian prior tying the bone to its hierarchical initialisation.

    A bone that is nearly symmetric about an axis (a phalanx two voxels
    across, seen about its length; a small patella about its normal) leaves
    Rhee Eq. 1 almost flat along that rotation: noise alone then moves it by
    degrees.  We minimise::

        Σ_x (I_scan(T x) − I_template(x))² / σ² + |θ|² / τ_θ² + |t|² / τ_t²

    where ``(θ, t)`` is ``T``'s rotation (degrees, about the bone's centroid)
    and translation relative to ``init`` (the prior's centre: the parent's
    transform turned by the joint's flexion from the grid search, other joint
    angles zero — joints move mostly in flexion), and ``σ²`` the mean squared
    residual of the plain Rhee Eq. 1 fit (``sigma``, so that costs from several
    starts compare).  Directions the image determines well are practically
    unchanged (their data curvature is orders of magnitude above ``1/τ²``);
    undetermined ones stay at the initialisation instead of fitting noise
    (MAP estimation; Gauss–Newton through ``scipy.optimize.least_squares``
    with a cubic B-spline sampler).  ``prior_deg`` / ``prior_mm`` None drop
    that part of the prior (a root bone has no parent to be tied to).

    ``loss`` (a ``least_squares`` loss; ``"linear"`` is
    Rhee Eq. 1's plain sum of squares) with ``loss_scale`` in units of ``σ`` (here;
    :func:`refine_intensity` sets it on the residual's robust scale) makes
    the fit robust: voxels of the dilated region whose residual exceeds
    ``loss_scale·σ`` — soft tissue that slides past the bone, a neighbour
    entering the region — count linearly instead of quadratically (see
    ``ROBUST_LOSS``).  The loss applies to the prior's terms too, which
    only matters more than ``loss_scale`` prior widths from its centre.  Returns the transform and, from the
    posterior covariance ``σ² (JᵀJ + Λ)⁻¹``, the standard deviations of the
    rotation (largest over directions, degrees) and of the translation (mm),
    so each bone's result says how well the image fixed it.
    """
    from scipy.optimize import least_squares

    c = apply(init, region.centroid)
    d = compose(start, np.linalg.inv(init))
    x0 = np.concatenate([np.degrees(Rotation.from_matrix(d[:3, :3]).as_rotvec()), apply(d, c) - c])
    vals0 = sampler(apply(start, region.points))
    ok = np.isfinite(vals0)
    if ok.sum() < 12:
        return start, {"prior": "skipped: too few points inside the scan"}
    pts, ref = region.points[ok], region.values[ok]

    def data_residuals(v):
        return _data_residuals(v, ref, metric)

    if sigma is None or not np.isfinite(sigma):
        sigma = math.sqrt(max(float(np.mean(data_residuals(vals0[ok]) ** 2)), 1e-12))
    w = np.array([0.0 if prior_deg is None else 1 / prior_deg] * 3 + [0.0 if prior_mm is None else 1 / prior_mm] * 3)

    def residuals(y, v=None):
        # y: the change from ``start`` (so the solver starts at exactly 0: its first trust region is sized
        # from |x0|, which is round-off small when start == init, and it then stopped after one tiny step).
        # ``v``: the scan at the points under that pose, when already sampled.
        x = x0 + y
        if v is None:
            v = sampler(pts, _increment(x, init, c)[None])[0]
        v = np.where(np.isfinite(v), v, ref)  # points leaving the grid stop contributing
        # Rhee Eq. 1 / σ² plus the prior's terms (the prior is ours: Rhee Eq. 1 has none)
        return np.concatenate([data_residuals(v) / sigma, w * x])

    def jacobian(y, f0=None):
        # Forward differences with absolute steps of 0.01° and 0.01 mm, the six poses sampled in one call.
        # (SciPy's relative diff_step scales with |x|, so at the start, where x is round-off close to 0, its
        # Jacobian was exactly zero.)
        f0 = residuals(y) if f0 is None else f0
        h = 1e-2
        steps = y + h * np.eye(6)
        vs = sampler(pts, np.stack([_increment(x0 + s, init, c) for s in steps]))
        return np.column_stack([(residuals(s, v) - f0) / h for s, v in zip(steps, vs)])

    res = least_squares(
        residuals,
        np.zeros(6),
        jac=jacobian,
        method="trf",
        x_scale=1.0,
        xtol=1e-8,
        ftol=1e-10,
        loss=loss,
        f_scale=float(loss_scale),
    )
    j = res.jac
    cov = np.linalg.pinv(j.T @ j)
    sd = np.sqrt(np.clip(np.linalg.eigvalsh(cov[:3, :3]), 0, None))
    sd_t = np.sqrt(np.clip(np.linalg.eigvalsh(cov[3:, 3:]), 0, None))
    image_sd = _image_rotation_sd(j[:-6])
    t = _increment(x0 + res.x, init, c)
    return t, {
        "prior_deg": prior_deg,
        "prior_mm": prior_mm,
        "residual_sigma": sigma,
        "metric": metric,
        "loss": loss,
        "loss_scale": float(loss_scale),
        "cost": float(2 * res.cost),
        "converged": bool(res.status > 0),
        "message": f"polish: {res.message}",
        "polish_evaluations": int(res.nfev),
        "rotation_sd_deg": float(sd.max()),
        "translation_sd_mm": float(sd_t.max()),
        "image_rotation_sd_deg": image_sd,
        "change_from_eq1_deg": rotation_angle_deg(compose(t, np.linalg.inv(start))),
    }


def _image_rotation_sd(j_data: np.ndarray) -> float | None:
    """Largest rotation standard deviation (degrees) that the image alone gives, without the prior.

    ``j_data``: the data residuals' Jacobian (residuals in units of σ, parameters in degrees and mm), so the
    covariance is ``(JᵀJ)⁻¹``.  None (stored as null) when the image leaves a direction undetermined.
    """
    f = j_data.T @ j_data
    w = np.linalg.eigvalsh(f)
    if not w[0] > 1e-12 * max(w[-1], 1e-300):
        return None
    cov = np.linalg.inv(f)
    return float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0)))


def _finish(
    region, sampler, t, method, before, iterations, stop, t0, *, min_ncc, min_inside, not_converged=False, extra=None
) -> BoneFit:
    import time

    vals = sampler(apply(t, region.points))
    inside = float(np.isfinite(vals).mean())
    after = ssd(vals, region.values)
    c = ncc(vals, region.values)
    if inside < min_inside:
        status = "outside_field_of_view"
    elif not_converged:
        status = "not_converged"
    elif not np.isfinite(c) or c < min_ncc:
        status = "poor_match"
    else:
        status = "ok"
    return BoneFit(
        region.name,
        t,
        method,
        status,
        before,
        after,
        c,
        inside,
        iterations=iterations,
        stop=stop,
        seconds=time.perf_counter() - t0,
        extra=extra or {},
    )


# -- Kurihara §3: isosurfaces and ICP ------------------------------------------------------------------
def auto_iso_level(region: BoneRegion) -> float:
    """An isosurface level for the bone's outer edge: midway between the intensities just inside and just
    outside its labelled voxels (medians over one-voxel shells), so it works for bright (CT) and dark (MRI
    cortex) bone alike."""
    inner = region.bone & ~ndimage.binary_erosion(region.bone)
    outer = ndimage.binary_dilation(region.bone) & ~region.bone
    d = region.crop.data
    return 0.5 * (float(np.median(d[inner])) + float(np.median(d[outer])))


def _crop_around(scan: Volume, points: np.ndarray, margin_mm: float) -> Volume | None:
    """The part of ``scan`` whose box holds ``points`` ± margin (None when it misses the scan)."""
    ijk = scan.geometry.world_to_index(points)
    pad = margin_mm / np.asarray(scan.geometry.spacing)
    try:
        crop = scan.crop(np.floor(ijk.min(axis=0) - pad), np.ceil(ijk.max(axis=0) + pad) + 1)
    except ValueError:  # the box misses the scan
        return None
    return crop if min(crop.geometry.size) >= 2 else None


def surface_prior(
    points: np.ndarray,
    normals: np.ndarray,
    fitted: np.ndarray,
    prior: np.ndarray,
    centroid: np.ndarray,
    sigma_mm: float,
    *,
    prior_deg: float | None = 2.0,
    prior_mm: float | None = PRIOR_MM,
) -> tuple[np.ndarray, dict]:
    """ICP's result combined with :func:`polish_with_prior`'s Gaussian prior (MAP).

    A bone nearly symmetric about its length (a phalanx) leaves point-to-plane ICP flat along that rotation:
    each surface point's ``(q − c) × n`` is perpendicular to the axis of a surface of revolution, so ICP keeps
    whatever roll its start or the noise gave (the CT hand's distal phalanges 10–40° off in roll with their
    centroids within 0.1 mm).  About the ICP fit, the point-to-plane residuals of the template's bone surface
    ``points`` (with ``normals``) give the information ``H = JᵀJ / σ²`` about an increment ``x`` (rotation
    vector in degrees about the fitted centroid ``c``, translation mm, applied after the fit;
    ``J_i = [(q_i − c) × m_i · π/180, m_i]`` at the fitted points ``q_i`` and normals ``m_i``; ``sigma_mm`` the
    residual scale per point, :func:`refine_surface` gives ICP's RMS distance).  The prior
    ``N(prior, diag(τ_θ², τ_t²))`` is the intensity method's (the parent turned by the joint's flexion).  We
    minimise ``xᵀHx + |Λ^½ log(D(x) ∘ fitted ∘ prior⁻¹)|²`` (the
    prior's residual exact in the rotation, so that a large roll is removed about the *fitted* axis, along
    which ``H`` is exactly flat): directions the surface fixes keep ICP's value (their information is orders
    of magnitude above ``1/τ²``), undetermined ones go to the prior.  Returns the transform and the
    posterior's largest rotation standard deviation (degrees).
    """
    from scipy.optimize import least_squares

    c = apply(fitted, centroid)
    q = apply(fitted, points)
    m = normals @ fitted[:3, :3].T
    j = np.hstack([np.cross(q - c, m) * (np.pi / 180.0), m]) / max(float(sigma_mm), 1e-6)
    h = j.T @ j
    ev, vec = np.linalg.eigh(h)
    root = vec * np.sqrt(np.clip(ev, 0.0, None))  # h = root rootᵀ
    w = np.array([0.0 if prior_deg is None else 1 / prior_deg] * 3 + [0.0 if prior_mm is None else 1 / prior_mm] * 3)
    cp = apply(prior, centroid)

    def from_prior(x):
        d = compose(_increment(x, fitted, c), np.linalg.inv(prior))
        return np.concatenate([np.degrees(Rotation.from_matrix(d[:3, :3]).as_rotvec()), apply(d, cp) - cp])

    res = least_squares(
        lambda x: np.concatenate([root.T @ x, w * from_prior(x)]), np.zeros(6), method="lm", xtol=1e-12, ftol=1e-12
    )
    t = _increment(res.x, fitted, c)
    cov = np.linalg.inv(h + np.diag(w**2))
    return t, {
        "prior_deg": prior_deg,
        "prior_mm": prior_mm,
        "residual_sigma_mm": float(sigma_mm),
        "rotation_sd_deg": float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))),
        "change_from_icp_deg": rotation_angle_deg(compose(t, np.linalg.inv(fitted))),
    }


def refine_surface(
    region: BoneRegion,
    sampler: Sampler,
    init: np.ndarray,
    *,
    level: float | None = None,
    min_ncc: float = 0.5,
    min_inside: float = 0.5,
    min_fitness: float = 0.5,
    prior: np.ndarray | None = None,
    prior_deg: float | None = 2.0,
    prior_mm: float | None = PRIOR_MM,
) -> BoneFit:
    """Kurihara §3: ICP of the bone's isosurface (template) onto the scan's isosurface near it.

    Source: the template's ``level`` isosurface inside the bone's region;
    target: the scan's isosurface at the same level in a box around the
    initialised bone.  ``level`` defaults to :func:`auto_iso_level`.  With a ``prior`` (the transform the
    hierarchy expects: a child bone's parent turned by its joint's flexion), the ICP fit is combined with
    it by :func:`surface_prior`, so a rotation the bone's shape cannot fix (a phalanx's roll) is not noise.
    """
    import time

    from registration.icp import icp_point_to_plane
    from registration.surface_fit import vertex_normals

    t0 = time.perf_counter()
    scan = sampler.image
    before, inside0 = _evaluate(region, sampler, init, min_inside=0.0)
    if inside0 < min_inside:
        return BoneFit(
            region.name,
            init,
            "surface",
            "outside_field_of_view",
            before,
            math.nan,
            math.nan,
            inside0,
            stop=f"only {inside0:.0%} of the bone region maps inside the scan at the initialisation",
            seconds=time.perf_counter() - t0,
        )
    lvl = auto_iso_level(region) if level is None else float(level)
    mesh = isosurface(region.crop, lvl)
    src, src_n = mesh.vertices, vertex_normals(mesh.vertices, mesh.triangles)
    if len(src):
        ijk = np.rint(region.crop.geometry.world_to_index(src)).astype(int)
        ijk = np.clip(ijk, 0, np.asarray(region.crop.geometry.size) - 1)
        inside = region.mask[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        src, src_n = src[inside], src_n[inside]
    spacing = float(max(scan.geometry.spacing))
    sub = _crop_around(scan, apply(init, region.points), 4.0 * spacing)
    tgt = isosurface(sub, lvl).vertices if sub is not None else np.zeros((0, 3))  # also the prior's matches
    extra = {"iso_level": lvl, "source_points": int(len(src)), "target_points": int(len(tgt))}
    if len(src) < 10 or len(tgt) < 10:
        return BoneFit(
            region.name,
            init,
            "surface",
            "poor_match",
            before,
            math.nan,
            math.nan,
            inside0,
            stop=f"isosurface at level {lvl:.1f} has {len(src)} template / {len(tgt)} scan points near the bone",
            seconds=time.perf_counter() - t0,
            extra=extra,
        )
    d = spacing
    res = icp_point_to_plane(
        src, tgt, init=init, distances_mm=(3 * d, 2 * d, d, 0.5 * d), normals_radius_mm=2.5 * d, min_fitness=min_fitness
    )
    extra.update({"fitness": res.fitness, "inlier_rmse_mm": res.inlier_rmse_mm})
    t = res.transform
    if prior is not None and res.converged:
        # The information is the matched points': those with a scan point within ICP's last distance (a point
        # with no partner — cropped, outside the field of view — fixes nothing).  σ is ICP's inlier RMS (point
        # to point), not the point-to-plane RMS: two isosurfaces of one bone sampled on different grids differ
        # systematically, their residuals correlated along the surface, so the plane distances would count each
        # point as independent evidence and overstate the information (registration-settings.md, "The surface
        # polish's σ")
        from scipy.spatial import cKDTree

        dist, _ = cKDTree(tgt).query(apply(t, src), distance_upper_bound=0.5 * d)
        hit = np.isfinite(dist)
        if hit.sum() >= 6:
            t, info = surface_prior(
                src[hit],
                src_n[hit],
                t,
                np.asarray(prior, float),
                region.centroid,
                max(res.inlier_rmse_mm, 0.05 * spacing),
                prior_deg=prior_deg,
                prior_mm=prior_mm,
            )
            extra.update(info, matched_points=int(hit.sum()))
    return _finish(
        region,
        sampler,
        t,
        "surface",
        before,
        sum(1 for _ in res.stages),
        res.message,
        t0,
        min_ncc=min_ncc,
        min_inside=min_inside,
        not_converged=not res.converged,
        extra=extra,
    )
