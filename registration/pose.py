"""Bone poses, joint centres and joint angles of a study's scans (Rhee §3.1; Kurihara §3).

The pipeline, per scan:

1. **Root bone.**  Initialised from the identity (scans share the
   template's scanner frame), from image moments (the centres of mass of the
   two images, SimpleITK's ``CenteredTransformInitializer``), or from a
   user-supplied pose file (the papers' semi-automatic step), then refined.
2. **Every other bone, down the hierarchy** (``Skeleton.order``):
   initialised from its parent's result, improved by a coarse search over
   rotations about the joint centre
   (:func:`registration.rigid.coarse_rotation_search`), then refined by
   intensity (Rhee Eq. 1) or by surfaces (Kurihara §3 ICP).
3. **Checks.**  Each bone's fit is ``ok`` or is reported with the reason
   (outside the field of view, optimiser not converged, normalised
   cross-correlation below ``min_ncc``), the scan, the bone and the metric.

Then, over all scans: each joint's centre by Kurihara Eq. 1
(:func:`registration.joint_centers.estimate_joint_center`) with hinge
detection, the hinge's centre placed on its axis nearest the bones' contact
region (the mean midpoint of the closest voxel pairs of the two bones in the
template), and each scan's joint angles (:meth:`~deformation.kinematics.skeleton.Joint.angles_from_motion`,
intrinsic XYZ in the skeleton's joint frame).  Poses use the same schema as
the phantoms' truth (:class:`deformation.kinematics.skeleton.Pose`), so estimate and
truth compare with :func:`validation.pose_measures.compare_poses`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from deformation.filters import smooth
from deformation.geometry import Volume
from deformation.kinematics.skeleton import Joint, Pose, Skeleton
from deformation.kinematics.transforms import apply, compose, rotation_angle_deg

from .joint_centers import HINGE_SD_MM, JointCenterResult, estimate_joint_center
from .rigid import (
    PRIOR_MM,
    BoneFit,
    BoneRegion,
    Sampler,
    bone_regions,
    coarse_rotation_search,
    refine_intensity,
    refine_surface,
)

__all__ = [
    "correct_bias",
    "METHODS",
    "ScanPose",
    "PoseResult",
    "register_scan",
    "estimate_poses",
    "pose_scans",
    "template_regions",
    "TemplateRegions",
    "contact_point",
    "moments_init",
    "flag_joint_outliers",
    "MOVING_DEG",
    "released_labels",
]

METHODS = ("intensity", "surface")
MOVING_DEG = 5.0  # a joint whose largest rotation over the scans is below this has no identifiable centre
COARSE_SMOOTH = 1.5  # voxels: Gaussian blur of both images for the joint grid search
RUNNERS_UP = 3  # a flagged child bone is refined again from this many of the grid search's next local winners
MAX_JOINT_GAP_MM = 10.0  # a bone whose joint centre lands farther than this from its parent's is flagged
# Kurihara Eq. 1 consistency (estimate_poses): a scan whose child-bone motion misses the joint centre estimated from all
# scans by more than OUTLIER_FACTOR x the joint's median miss (and more than OUTLIER_VOXELS voxels) is flagged.
OUTLIER_FACTOR = 4.0
OUTLIER_VOXELS = 0.5
OUTLIER_MIN_MOTIONS = 4  # fewer motions than this leave too little redundancy to tell an outlier


@dataclass
class ScanPose:
    scan_id: str
    pose: Pose
    fits: dict[str, BoneFit]
    seconds: float
    voxel_mm: float = math.nan  #: the scan's largest spacing (Kurihara Eq. 1's outlier test counts misses in voxels)

    @property
    def failures(self) -> list[BoneFit]:
        return [f for f in self.fits.values() if not f.ok]


@dataclass
class PoseResult:
    method: str
    scans: list[ScanPose]
    joints: dict[str, JointCenterResult]
    skeleton: Skeleton  # the input skeleton with estimated joint centres
    contacts: dict[str, np.ndarray] = field(default_factory=dict)

    def failures(self) -> list[dict]:
        return [
            {"scan": s.scan_id, "bone": f.bone, "status": f.status, "ncc": f.ncc, "ssd": f.ssd_after, "stop": f.stop}
            for s in self.scans
            for f in s.failures
        ]

    def joints_dict(self) -> dict:
        out = {}
        for name, r in self.joints.items():
            j = self.skeleton.joint(name)
            out[name] = {
                "parent": j.parent,
                "child": j.child,
                "dof": j.dof,
                "center": r.center.tolist(),
                "rms_mm": r.rms_mm,
                "per_scan_mm": r.per_motion_mm.tolist(),
                "n_motions": r.n_motions,
                "estimated": r.estimated,
                "is_hinge": r.is_hinge,
                "axis": r.axis.tolist(),
                "singular_values": r.singular_values.tolist(),
                "axis_sd_mm": r.axis_sd_mm,
                "iterative_center": None if r.iterative_center is None else r.iterative_center.tolist(),
                "closed_form_vs_iterative_mm": (
                    None if r.iterative_center is None else float(np.linalg.norm(r.iterative_center - r.center))
                ),
                "contact_point": self.contacts[name].tolist() if name in self.contacts else None,
                "max_rotation_deg": float(
                    max(
                        (
                            rotation_angle_deg(self.skeleton.relative_motion(s.pose.transforms, name))
                            for s in self.scans
                        ),
                        default=0.0,
                    )
                ),
                "note": r.message,
            }
        return out

    def overall_rms_mm(self) -> float:
        """RMS of Kurihara Eq. 1's residual over all joints and moving scans (Kurihara's 0.91 mm figure)."""
        res = np.concatenate([r.per_motion_mm for r in self.joints.values()] or [np.zeros(0)])
        return float(np.sqrt(np.mean(res**2))) if res.size else math.nan


def moments_init(template: Volume, scan: Volume) -> np.ndarray:
    """Template → scan translation that aligns the images' centres of mass (SimpleITK MOMENTS)."""
    import SimpleITK as sitk

    f = template.to_sitk()
    m = scan.to_sitk()
    f = sitk.Cast(f, sitk.sitkFloat32) - float(np.min(template.data))  # moments of non-negative mass
    m = sitk.Cast(m, sitk.sitkFloat32) - float(np.min(scan.data))
    tx = sitk.CenteredTransformInitializer(
        f, m, sitk.Euler3DTransform(), sitk.CenteredTransformInitializerFilter.MOMENTS
    )
    t = np.eye(4)
    t[:3, 3] = tx.GetTranslation()
    return t


def correct_bias(image: Volume) -> Volume:
    """N4 bias-field correction (SimpleITK), for MRI-like images.

    The multiplicative bias of an MRI scan differs between scans, so a bone's
    intensities differ by a smooth gain *gradient* that the per-bone linear
    intensity fit (``metric="ncc"``) cannot absorb (its effect on the pose:
    docs/measurements/pose-and-initialisation.md).  The body mask is Otsu's;
    large images are corrected on a grid shrunk to about 200k voxels and the
    bias is evaluated at full resolution.
    """
    import SimpleITK as sitk

    img = sitk.Cast(image.to_sitk(), sitk.sitkFloat32)
    shrink = max(1, int(round((image.geometry.n_voxels / 2e5) ** (1 / 3))))
    small = sitk.Shrink(img, [shrink] * 3) if shrink > 1 else img
    mask = sitk.OtsuThreshold(small, 0, 1, 200)
    n4 = sitk.N4BiasFieldCorrectionImageFilter()
    n4.SetMaximumNumberOfIterations([50, 50, 30])
    n4.Execute(small, mask)
    log_bias = n4.GetLogBiasFieldAsImage(img)
    out = sitk.GetArrayFromImage(img) / np.exp(sitk.GetArrayFromImage(log_bias))
    return Volume(out.astype(np.float32), image.geometry)


def register_scan(
    regions: dict[str, BoneRegion],
    scan: Volume,
    skeleton: Skeleton,
    *,
    method: str = "intensity",
    root_init=None,
    coarse: bool = True,
    min_ncc: float = 0.5,
    interpolation: int = 3,
    prior_deg: float | None = 2.0,
    smooth_voxels: float = 0.6,
    metric: str = "ncc",
    coarse_regions=None,
    max_joint_gap_mm: float | None = MAX_JOINT_GAP_MM,
    progress=None,
) -> dict[str, BoneFit]:
    """Every bone's template → scan transform, root first, then down the hierarchy.

    ``regions`` come from :func:`~registration.rigid.bone_regions` on the template smoothed by
    ``smooth_voxels``; ``coarse_regions`` (optional) from the template
    smoothed by ``COARSE_SMOOTH`` voxels, for the joint grid search, whose
    wider blur widens the capture basin (on the 2x-resolution knee the
    fibula's grid search otherwise locked onto the tibia).
    ``root_init`` is the root's initial 4x4 (identity by default);
    ``progress(bone, done, total, fit)`` is called after each bone.

    Bones do not dislocate: the skeleton's joint centre, carried by the
    child's transform and by the parent's, must land within
    ``max_joint_gap_mm`` of itself (``joint_gap_mm`` in the fit).  A bone
    that correlates well where it cannot be is flagged ``joint_detached``
    rather than accepted.  A bone whose parent was flagged (for any reason)
    is flagged ``parent_flagged``: it is fitted from the parent's result, so
    a chain that moved together (a finger registered onto its neighbour)
    would otherwise pass every check below its first wrong bone; nothing in
    the scan tells a right child of a wrong parent from a wrong one.  The gap is measured at the input skeleton's
    centre, so a rough skeleton (centres off by ``d`` mm, joints turning by
    ``θ``) needs a limit above ``θ·d``; None switches the check off.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    sampler = Sampler(scan, order=interpolation, smooth_voxels=smooth_voxels)
    coarse_sampler = None
    fits: dict[str, BoneFit] = {}
    for k, name in enumerate(skeleton.order):
        region = regions[name]
        joint = skeleton.joint_of(name)
        prior_center = None
        runners_up = []  # the coarse search's other local winners (cost, angles, transform), best first
        t0 = time.perf_counter()
        if joint is None:
            init = np.eye(4) if root_init is None else np.asarray(root_init, float)
            how = "root initial pose"
        else:
            parent_t = fits[joint.parent].transform
            if coarse:
                if coarse_sampler is None:  # the scan blurred like the template regions of the search
                    coarse_sampler = Sampler(
                        scan,
                        order=3,
                        smooth_voxels=(
                            max(COARSE_SMOOTH, smooth_voxels) if coarse_regions is not None else smooth_voxels
                        ),
                    )
                init, _, n, ang = coarse_rotation_search(
                    (coarse_regions or regions)[name],
                    coarse_sampler,
                    parent_t,
                    joint,
                    metric=metric,
                    runners_up=runners_up,
                )
                how = (
                    f"parent + grid search about the joint ({n} evaluations): flexion {ang[0]:.1f}°, "
                    f"abduction {ang[1]:.1f}°, twist {ang[2]:.1f}°"
                )
                prior_center = compose(parent_t, joint.motion(np.r_[ang[0], np.zeros(joint.dof - 1)]))
            else:
                init, how = parent_t.copy(), "parent"
        if method == "intensity":  # the root starts from a rough pose: multi-resolution, no prior to tie it to
            # ``prior_deg`` None is Rhee Eq. 1 through SimpleITK alone; otherwise the polish follows, with the prior
            # for a child bone and without one for the root (no parent to tie it to).
            def refine(start, centre):
                return refine_intensity(
                    region,
                    sampler,
                    start,
                    min_ncc=min_ncc,
                    metric=metric,
                    multires=joint is None,
                    polish=prior_deg is not None,
                    prior_deg=None if joint is None else prior_deg,
                    prior_mm=None if joint is None else PRIOR_MM,
                    prior_center=centre,
                )

            fit = refine(init, prior_center)
            # A flagged fit gets second chances from the grid search's runners-up, refined at the fine scale: the
            # search's blur widens the basin but can rank a wrong pose of a thin bone first, which the fine scale
            # tells apart (docs/measurements/pose-and-initialisation.md).  There the search's own
            # remedy (points turned out of the scan count as unmatched, coarse_rotation_search) was what placed
            # it; this is the fallback.  The best passing one is taken; a bone none of them places stays flagged.
            if not fit.ok and runners_up and fits[joint.parent].ok:
                for rank, (_, ang_k, t_k) in enumerate(runners_up[:RUNNERS_UP], start=2):
                    alt = refine(t_k, compose(parent_t, joint.motion(np.r_[ang_k[0], np.zeros(joint.dof - 1)])))
                    if alt.ok and (not fit.ok or alt.ncc > fit.ncc):
                        fit = alt
                        how = (
                            f"{how}; refined from its candidate {rank} (flexion {ang_k[0]:.1f}°): the first was flagged"
                        )
        else:
            # Kurihara §3's ICP, with the intensity method's prior on what the bone's shape leaves open
            fit = refine_surface(
                region,
                sampler,
                init,
                min_ncc=min_ncc,
                prior=None
                if joint is None or prior_deg is None
                else (prior_center if prior_center is not None else init),
                prior_deg=prior_deg,
                prior_mm=PRIOR_MM,
            )
        fit.init = how
        if joint is not None:
            c = np.asarray(joint.center, float)
            gap = float(np.linalg.norm(apply(fit.transform, c) - apply(fits[joint.parent].transform, c)))
            fit.extra["joint_gap_mm"] = gap
            parent = fits[joint.parent]
            if fit.ok and not parent.ok:
                fit.status = "parent_flagged"
                fit.stop = (
                    f"{fit.stop}; its parent '{joint.parent}' was flagged ({parent.status}) and this bone "
                    f"was fitted from it, so it is not trusted either (joint gap {gap:.1f} mm)"
                )
            elif fit.ok and max_joint_gap_mm is not None and gap > max_joint_gap_mm:
                fit.status = "joint_detached"
                fit.stop = (
                    f"{fit.stop}; the bone left joint '{joint.name}': its centre lands {gap:.1f} mm from "
                    f"where the parent puts it (limit {max_joint_gap_mm:g} mm)"
                )
        fit.seconds = time.perf_counter() - t0
        fits[name] = fit
        if progress is not None:
            progress(name, k + 1, len(skeleton.order), fit)
    return fits


def contact_point(labels: Volume, a: int, b: int, *, tolerance_mm: float | None = None) -> np.ndarray:
    """Mean midpoint of the closest voxel pairs of labels ``a`` and ``b`` (world mm).

    All pairs within ``tolerance_mm`` (default the largest voxel spacing) of
    the closest pair count, from either bone's side, so a joint with two contact areas (the knee's
    condyles) gets a point between them.
    """
    g = labels.geometry
    lab = np.asarray(labels.data)

    def pts(v):
        k, j, i = np.nonzero(lab == v)
        return g.index_to_world(np.column_stack([i, j, k]).astype(float))

    pa, pb = pts(a), pts(b)
    if len(pa) == 0 or len(pb) == 0:
        raise ValueError(f"labels {a} and {b} must both be present to find their contact")
    da, ia = cKDTree(pb).query(pa)
    db, ib = cKDTree(pa).query(pb)
    tol = float(max(g.spacing)) if tolerance_mm is None else tolerance_mm
    dmin = min(da.min(), db.min())
    na, nb = da <= dmin + tol, db <= dmin + tol
    # Both directions, so that the layers within the tolerance count equally on either side.
    mids = np.concatenate([0.5 * (pa[na] + pb[ia[na]]), 0.5 * (pb[nb] + pa[ib[nb]])])
    return mids.mean(axis=0)


def estimate_poses(
    template: Volume,
    labels: Volume,
    scans: dict,
    skeleton: Skeleton,
    *,
    method: str = "intensity",
    root_init=None,
    coarse: bool = True,
    min_ncc: float = 0.5,
    interpolation: int = 3,
    prior_deg: float | None = 2.0,
    smooth_voxels: float = 0.6,
    metric: str = "ncc",
    hinge_ratio: float = 0.05,
    hinge_sd_mm: float | None = HINGE_SD_MM,
    bias_correction: bool | None = None,
    margin_mm: float | None = None,
    max_joint_gap_mm: float | None = MAX_JOINT_GAP_MM,
    outlier_factor: float | None = OUTLIER_FACTOR,
    progress=None,
    scan_poses: list[ScanPose] | None = None,
    prepared: TemplateRegions | None = None,
) -> PoseResult:
    """Register every bone in every scan (:func:`pose_scans`), then estimate joint centres and angles.

    Parameters
    ----------
    scans : dict scan id → :class:`~deformation.geometry.Volume` (or a callable returning it, to load lazily)
    root_init : None, ``"identity"``, ``"moments"``, or dict scan id → 4x4 root transform
    bias_correction : N4-correct template and scans first (:func:`correct_bias`);
        None (default) does so for MRI-like images (no values below −500)
    outlier_factor : Kurihara Eq. 1 consistency check (None: off).  All the scans of a
        joint (of 3 DOF or fewer, moving, with at least
        ``OUTLIER_MIN_MOTIONS`` scans where both bones are ok) fix its
        centre ``c``; a scan whose child motion misses it, ``|M_i c − c|``,
        by more than ``outlier_factor`` times the joint's median miss and by
        more than ``OUTLIER_VOXELS`` voxels is an outlier: its child bone
        is flagged ``joint_outlier`` (and the bones below it
        ``parent_flagged``), one scan at a time, worst first, until none is
        left.  This catches a bone that turned with its neighbour or slid off
        its joint by less than ``max_joint_gap_mm``.
    progress : callable(scan_id, scan_index, n_scans, bone, done, total, fit), optional
    scan_poses : the scans' bone fits already made by :func:`pose_scans` with the same arguments (e.g. one scan
        per Dask task, :mod:`workbench.scale`); then only the pooling (Kurihara Eq. 1, outliers, angles) runs here
    prepared : the template's regions already made by :func:`template_regions` (see :func:`pose_scans`)
    """
    results = (
        scan_poses
        if scan_poses is not None
        else pose_scans(
            template,
            labels,
            scans,
            skeleton,
            method=method,
            root_init=root_init,
            coarse=coarse,
            min_ncc=min_ncc,
            interpolation=interpolation,
            prior_deg=prior_deg,
            smooth_voxels=smooth_voxels,
            metric=metric,
            bias_correction=bias_correction,
            margin_mm=margin_mm,
            max_joint_gap_mm=max_joint_gap_mm,
            progress=progress,
            prepared=prepared,
        )
    )
    voxel_mm = {s.scan_id: s.voxel_mm for s in results}
    bad = [sid for sid, v in voxel_mm.items() if not (np.isfinite(v) and v > 0)]
    if bad:  # a NaN spacing would switch Kurihara Eq. 1's outlier test off without a word
        raise ValueError(
            f"scan_poses of scans {bad} carry no voxel size (ScanPose.voxel_mm): make them with pose_scans"
        )
    return _pool(results, voxel_mm, labels, skeleton, method, hinge_ratio, hinge_sd_mm, outlier_factor)


@dataclass
class TemplateRegions:
    """The template's side of the bones' registration (:func:`template_regions`), made once for many scans."""

    template: Volume  #: the template, N4-corrected when ``bias_correction``
    regions: dict  #: bone → :class:`~registration.rigid.BoneRegion` (the refinement's)
    coarse_regions: dict | None  #: the coarse rotation search's, on a more smoothed template (None: no search)
    bias_correction: bool  #: whether the scans are N4-corrected too
    coarse: bool  #: the arguments it was made with that the scans' fits use again
    smooth_voxels: float


def template_regions(
    template: Volume,
    labels: Volume,
    skeleton: Skeleton,
    *,
    coarse: bool = True,
    smooth_voxels: float = 0.6,
    bias_correction: bool | None = None,
    margin_mm: float | None = None,
) -> TemplateRegions:
    """The template's bone regions for :func:`pose_scans` (its arguments of the same names)."""
    from .segmentation import guess_modality

    if bias_correction is None:
        bias_correction = guess_modality(template) == "mri"
    if bias_correction:
        template = correct_bias(template)
    regions = bone_regions(smooth(template, smooth_voxels, dtype=np.float32), labels, skeleton, margin_mm=margin_mm)
    coarse_regions = (
        bone_regions(
            smooth(template, max(COARSE_SMOOTH, smooth_voxels), dtype=np.float32), labels, skeleton, margin_mm=margin_mm
        )
        if coarse
        else None
    )
    return TemplateRegions(template, regions, coarse_regions, bool(bias_correction), bool(coarse), float(smooth_voxels))


def pose_scans(
    template: Volume,
    labels: Volume,
    scans: dict,
    skeleton: Skeleton,
    *,
    method: str = "intensity",
    root_init=None,
    coarse: bool = True,
    min_ncc: float = 0.5,
    interpolation: int = 3,
    prior_deg: float | None = 2.0,
    smooth_voxels: float = 0.6,
    metric: str = "ncc",
    bias_correction: bool | None = None,
    margin_mm: float | None = None,
    max_joint_gap_mm: float | None = MAX_JOINT_GAP_MM,
    progress=None,
    prepared: TemplateRegions | None = None,
) -> list[ScanPose]:
    """Every bone of every scan in ``scans`` (the first half of :func:`estimate_poses`, whose arguments these
    are): one :class:`ScanPose` per scan, each independent of the others.  ``prepared``: the template's regions
    already made by :func:`template_regions` with the same arguments (one scan per task: made once, shared)."""
    if prepared is None:
        prepared = template_regions(
            template,
            labels,
            skeleton,
            coarse=coarse,
            smooth_voxels=smooth_voxels,
            bias_correction=bias_correction,
            margin_mm=margin_mm,
        )
    elif (prepared.coarse, prepared.smooth_voxels) != (bool(coarse), float(smooth_voxels)):
        raise ValueError(
            f"the template's regions were made with coarse={prepared.coarse}, smooth_voxels={prepared.smooth_voxels}; "
            f"these fits ask for coarse={coarse}, smooth_voxels={smooth_voxels}"
        )
    template, regions, coarse_regions = prepared.template, prepared.regions, prepared.coarse_regions
    bias_correction = prepared.bias_correction
    results = []
    ids = list(scans)
    voxel_mm = {}
    for si, sid in enumerate(ids):
        t0 = time.perf_counter()
        scan = scans[sid]() if callable(scans[sid]) else scans[sid]
        if bias_correction:
            scan = correct_bias(scan)
        voxel_mm[sid] = float(max(scan.geometry.spacing))
        if isinstance(root_init, dict):
            r0 = root_init.get(sid)
        elif root_init == "moments":
            r0 = moments_init(template, scan)
        else:
            r0 = None
        cb = None if progress is None else (lambda b, d, n, f, sid=sid, si=si: progress(sid, si, len(ids), b, d, n, f))
        fits = register_scan(
            regions,
            scan,
            skeleton,
            method=method,
            root_init=r0,
            coarse=coarse,
            min_ncc=min_ncc,
            interpolation=interpolation,
            prior_deg=prior_deg,
            smooth_voxels=smooth_voxels,
            coarse_regions=coarse_regions,
            metric=metric,
            max_joint_gap_mm=max_joint_gap_mm,
            progress=cb,
        )
        transforms = {b: fits[b].transform for b in skeleton.order}
        results.append(
            ScanPose(sid, Pose(transforms, skeleton=skeleton.name), fits, time.perf_counter() - t0, voxel_mm[sid])
        )
    return results


def _pool(
    results: list[ScanPose],
    voxel_mm: dict,
    labels: Volume,
    skeleton: Skeleton,
    method: str,
    hinge_ratio: float,
    hinge_sd_mm,
    outlier_factor,
) -> PoseResult:
    """Kurihara Eq. 1 over the scans' fits: outliers flagged, joint centres, each scan's angles."""

    def usable(s, j):  # flagged fits are reported, not used
        return s.fits[j.parent].ok and s.fits[j.child].ok

    contacts = {
        j.name: contact_point(labels, skeleton.label_of(j.parent), skeleton.label_of(j.child)) for j in skeleton.joints
    }
    if outlier_factor is not None:
        flag_joint_outliers(
            results,
            skeleton,
            contacts,
            voxel_mm,
            factor=outlier_factor,
            hinge_ratio=hinge_ratio,
            hinge_sd_mm=hinge_sd_mm,
        )
    joints, new_joints = {}, []
    for j in skeleton.joints:
        # Kurihara Eq. 1's M_{i,k}: the child's motion relative to its parent in every usable scan i
        motions = [skeleton.relative_motion(s.pose.transforms, j.name) for s in results if usable(s, j)]
        if not motions:
            new_joints.append(j)  # no scan where both bones were found: the skeleton's centre stays
            continue
        r = (  # Kurihara Eq. 1 minimised over the scans
            estimate_joint_center(motions, reference=contacts[j.name], hinge_ratio=hinge_ratio, hinge_sd_mm=hinge_sd_mm)
            if max(rotation_angle_deg(m) for m in motions) >= MOVING_DEG
            else None
        )
        if r is None:
            # The joint barely turns: Kurihara Eq. 1's centre would be translation noise over a tiny angle (millimetres
            # off for 0.3° of noise), so the skeleton's centre stays, with its residual reported.
            c = np.asarray(j.center, float)
            # Kurihara Eq. 1's residuals ‖M_i c − c‖ at the skeleton's centre
            per = np.array([np.linalg.norm(m[:3, :3] @ c + m[:3, 3] - c) for m in motions])
            r = JointCenterResult(
                center=c,
                rms_mm=float(np.sqrt(np.mean(per**2))),
                per_motion_mm=per,
                singular_values=np.zeros(3),
                is_hinge=False,
                axis=np.zeros(3),
                n_motions=len(motions),
                iterative_center=c.copy(),
                estimated=False,
                message=f"moves less than {MOVING_DEG:.0f}° in every scan: the skeleton's centre "
                "is kept (Kurihara Eq. 1 cannot place it)",
            )
        joints[j.name] = r
        new_joints.append(Joint(j.name, j.parent, j.child, j.dof, tuple(r.center), j.axes, j.limits))
    est = Skeleton(skeleton.bones, new_joints, name=skeleton.name)
    for s in results:
        angles, centres = {}, {}
        for j in est.joints:
            if s.fits[j.parent].ok:
                centres[j.name] = apply(s.pose.transforms[j.parent], j.center)
            if usable(s, j):  # a joint with a flagged bone gets no angles (it is listed in the failures)
                angles[j.name] = j.angles_from_motion(est.relative_motion(s.pose.transforms, j.name))
        s.pose = Pose(
            placed_transforms(s.fits, skeleton), joint_angles=angles, joint_centers=centres, skeleton=skeleton.name
        )
    return PoseResult(method, results, joints, est, contacts)


def placed_transforms(fits: dict, skeleton: Skeleton) -> dict:
    """The pose's transforms: each placed bone's fit; a flagged bone (its fit is kept in ``fits``) follows its
    nearest placed ancestor rigidly, its joints as in the template.  A flagged fit is one the image did not
    confirm (NCC < 0.5, outside the scan, detached from its joint, a Kurihara Eq. 1 outlier): handing it on made
    every later stage start from it (the measurements: docs/measurements/pose-and-initialisation.md).  A
    flagged root keeps its fit (nothing to follow)."""
    out = {}
    for b in skeleton.order:
        parent = skeleton.bone(b).parent
        out[b] = fits[b].transform if fits[b].ok or parent is None else out[parent]
    return out


def released_labels(labels: Volume, skeleton: Skeleton, flagged) -> Volume:
    """The template's label map without the bones in ``flagged`` (the pose stage could not place them): a
    registration that holds the labelled bones rigid at the pose's transforms lets these move with the soft
    tissue instead of holding them where their nearest placed ancestor put them (see ``placed_transforms``)."""
    ids = [skeleton.label_of(b) for b in flagged]
    if not ids:
        return labels
    return Volume(
        np.where(np.isin(labels.data, ids), 0, labels.data).astype(labels.data.dtype, copy=False), labels.geometry
    )


def flag_joint_outliers(
    results: list[ScanPose],
    skeleton: Skeleton,
    contacts: dict,
    voxel_mm: dict,
    *,
    factor: float = OUTLIER_FACTOR,
    hinge_ratio: float = 0.05,
    hinge_sd_mm: float | None = HINGE_SD_MM,
) -> list[tuple[str, str]]:
    """Flag child bones whose motion is inconsistent with their joint's Kurihara Eq. 1 centre (:func:`estimate_poses`).

    Returns the ``(scan id, bone)`` pairs flagged ``joint_outlier``; their
    fits (and those below them, ``parent_flagged``) are updated in place.
    """
    flagged = []
    by_id = {s.scan_id: s for s in results}
    while True:
        worst = None  # (excess ratio, scan, joint, miss, limit)
        for j in skeleton.joints:
            if j.dof > 3:  # a 6-DOF joint translates: Kurihara Eq. 1's residual is motion, not error
                continue
            used = [s for s in results if s.fits[j.parent].ok and s.fits[j.child].ok]
            if len(used) < OUTLIER_MIN_MOTIONS:
                continue
            motions = [skeleton.relative_motion(s.pose.transforms, j.name) for s in used]
            if max(rotation_angle_deg(m) for m in motions) < MOVING_DEG:
                continue
            r = estimate_joint_center(
                motions, reference=contacts[j.name], hinge_ratio=hinge_ratio, hinge_sd_mm=hinge_sd_mm, cross_check=False
            )
            miss = r.per_motion_mm
            med = float(np.median(miss))
            for s, d in zip(used, miss):
                limit = max(factor * med, OUTLIER_VOXELS * voxel_mm.get(s.scan_id, 0.0))
                if d > limit and (worst is None or d / limit > worst[0]):
                    worst = (d / limit, s.scan_id, j, float(d), limit)
        if worst is None:
            return flagged
        _, sid, j, d, limit = worst
        s = by_id[sid]
        f = s.fits[j.child]
        f.status = "joint_outlier"
        f.extra["eq1_miss_mm"] = d
        f.stop = (
            f"{f.stop}; its motion misses joint '{j.name}''s centre, estimated by Kurihara Eq. 1 from all scans, by "
            f"{d:.1f} mm (limit {limit:.1f} mm: {factor:g}x the joint's median, at least "
            f"{OUTLIER_VOXELS:g} voxel)"
        )
        flagged.append((sid, j.child))
        for name in skeleton.order:  # bones below a flagged bone were fitted from it
            jj = skeleton.joint_of(name)
            if jj is not None and s.fits[name].ok and not s.fits[jj.parent].ok:
                s.fits[name].status = "parent_flagged"
                s.fits[name].stop = (
                    f"{s.fits[name].stop}; its parent '{jj.parent}' was flagged "
                    f"({s.fits[jj.parent].status}) and this bone was fitted from it"
                )
