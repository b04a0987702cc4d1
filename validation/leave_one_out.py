"""Leave-one-out check of the volume model: EVD from the other poses vs VBD alone (Rhee §5, §6).

For each pose ``k`` of a phantom, an EVD model (Rhee Eq. 6–7) is built from
the ground-truth correspondences of every *other* pose and asked for pose
``k``; VBD (Rhee Eq. 2) with the same skinning weights and pose is the
baseline.  Both are compared with the truth by the mean Euclidean distance
(MED, mm) over the body:

* ``med_template``: over template body voxels ``v``, ``|F(v) − F_true(v)|``
  (the predicted posed position against the true one);
* ``med_scan``: over posed body voxels ``y`` whose true template position
  lies in the template's field of view, ``|F⁻¹(y) − φ_true(y)|`` — Rhee's
  MED of correspondences, through the backward map (:mod:`deformation.fields.resample`).

:func:`leave_one_out_correspondences` does the same from any correspondences
(a study's registrations), and :func:`registration_training_positions` gives
a study scan's EVD example the way the pipeline's ``model`` stage builds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deformation.fields.resample import backward_map
from deformation.models.evd import ExampleVolumeDeformation, fill_unmatched, vbd_forward
from deformation.models.skinning import SkinningWeights, stack_transforms

__all__ = [
    "LeaveOneOut",
    "leave_one_out",
    "HeldOut",
    "leave_one_out_correspondences",
    "registration_training_positions",
    "registration_training_sigma",
]


def registration_training_positions(study, scan_id: str, geometry, weights: SkinningWeights):
    """A scan's estimated pose and where every template voxel lies in it by its registration: an EVD example.

    ``study`` is a :class:`workbench.study.Study` (anything with its ``pose`` and
    ``registration_positions``), ``geometry`` the template grid and ``weights``
    its per-voxel skinning weights.  Template voxels the registration's inverse
    did not find keep their VBD position (:func:`deformation.models.evd.fill_unmatched`),
    so they contribute ``d_k = 0`` to EVD (Rhee Eq. 7).  The training positions of
    the model stage (``--source registration``) and of the leave-one-out protocol.

    Returns
    -------
    pose : Pose
        The pose stage's estimate (template → scan).
    positions : (nz, ny, nx, 3) float64
        World mm in the scan.
    found : (nz, ny, nx) bool
        Where the registration's inverse found the voxel (elsewhere: VBD).
    """
    pose = study.pose(scan_id)
    pos, found = study.registration_positions(scan_id)
    return pose, fill_unmatched(geometry, weights, pose.transforms, pos, found), found


def registration_training_sigma(study, scan_id: str, positions, found) -> np.ndarray | None:
    """The expected error (mm) of a scan's EVD example at every template voxel: its registration's σ
    (``uncertainty.mha``, :meth:`workbench.study.Study.registration_uncertainty`) where the voxel lies in the
    scan (``positions``, ``found`` of :func:`registration_training_positions`), trilinear; where the registration
    did not find the voxel (its VBD position stands, ``d_k = 0``, a guess) the scan's largest σ.  ``None`` when
    the registration wrote no σ (Rhee's Algorithm 1, or the posterior off)."""
    from deformation.fields.interpolate import sample

    sig = study.registration_uncertainty(scan_id)
    if sig is None:
        return None
    pos = np.asarray(positions).reshape(-1, 3)
    out = sample(sig, pos, order=1, fill=np.nan).astype(np.float32)
    worst = np.float32(np.nanmax(sig.data)) if np.any(np.isfinite(sig.data)) else np.float32(0.0)
    out[~np.isfinite(out) | ~np.asarray(found, bool).reshape(-1)] = worst
    return out.reshape(np.asarray(found).shape)


def _calibration(model, pose, posed, truth, mask) -> dict:
    """The model's expected error at ``pose`` (:meth:`ExampleVolumeDeformation.expected_error`) against the true
    error of its posed positions over ``mask`` (the three measures of issue R, no bins)."""
    from validation.registration_measures import uncertainty_calibration

    err = np.linalg.norm(np.asarray(posed, np.float64) - truth, axis=1)
    sigma = model.expected_error(pose).reshape(-1)
    mask = np.asarray(mask, bool)
    if mask.any() and max(float(err[mask].max()), float(sigma[mask].max())) < 1e-3:
        # a pose the model reproduces exactly (the template's own, with exact examples): nothing to calibrate
        return {"within_2sigma": None, "rms_ratio": None, "spearman": None, "exact": True}
    cal = uncertainty_calibration(err, sigma, mask)
    cal.pop("bins")
    return cal


@dataclass
class LeaveOneOut:
    pose_id: str
    med_template_vbd: float
    med_template_evd: float
    med_scan_vbd: float | None = None
    med_scan_evd: float | None = None
    #: the model's expected error at the held-out pose against its true error over the body
    #: (:func:`validation.registration_measures.uncertainty_calibration`, without its bins)
    calibration: dict | None = None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def leave_one_out(
    phantom,
    weights: SkinningWeights,
    *,
    weighting: str = "psd",
    scan_side: bool = False,
    pose_indices=None,
    cap: bool = True,
    progress=None,
) -> list[LeaveOneOut]:
    """Run the leave-one-out comparison on a :class:`~validation.phantoms.Phantom` (see the module docstring).

    ``scan_side`` adds the correspondence MED on the posed grid (one backward
    map and one truth inversion per pose; slower); ``cap`` False poses by Rhee Eq. 6 as written, the blended
    displacement uncapped beyond the examples' range (:mod:`deformation.models.evd`).
    """
    g = phantom.geometry
    x = g.world_coordinates().reshape(-1, 3)
    body_t = phantom.anatomy.distances_fast(x)[:, -1] < 0
    poses, fields, angles = [], [], []
    for pid, ang in phantom.poses:
        poses.append(phantom.pose_of(ang))
        fields.append(phantom.posing_model(ang).forward(x).reshape(g.array_shape + (3,)))
        angles.append((pid, ang))
    n = len(poses)
    if n < 3:
        raise ValueError(f"leave-one-out needs at least 3 poses (2 to train on), got {n}")
    indices = list(range(n)) if pose_indices is None else [int(i) for i in pose_indices]
    if any(not 0 <= i < n for i in indices):
        raise ValueError(f"pose_indices must lie in 0..{n - 1}, got {indices}")
    out = []
    for k in indices:
        rest = [i for i in range(n) if i != k]
        model = ExampleVolumeDeformation.from_correspondences(  # Rhee Eq. 7 on the other poses
            g, weights, phantom.skeleton, [poses[i] for i in rest], [fields[i] for i in rest]
        )
        truth = fields[k].reshape(-1, 3)
        f_evd = model.forward(poses[k], weighting=weighting, cap=cap)  # Rhee Eq. 6
        f_vbd = vbd_forward(g, weights, poses[k].transforms)  # Rhee Eq. 2
        r = LeaveOneOut(
            angles[k][0],
            float(np.linalg.norm(f_vbd.reshape(-1, 3)[body_t] - truth[body_t], axis=1).mean()),
            float(np.linalg.norm(f_evd.reshape(-1, 3)[body_t] - truth[body_t], axis=1).mean()),
            calibration=_calibration(model, poses[k], f_evd.reshape(-1, 3), truth, body_t),
        )
        if scan_side:
            phi, _ = phantom.correspondence(phantom.posing_model(angles[k][1]))
            phi = phi.reshape(-1, 3)
            sel = (phantom.anatomy.distances_fast(phi)[:, -1] < 0) & g.contains_world(phi)
            t = stack_transforms(poses[k].transforms, weights.bones)
            prefer = body_t.reshape(g.array_shape)
            meds = []
            for fwd in (f_vbd, f_evd):
                bm = backward_map(fwd, g, transforms=t, prefer=prefer)
                meds.append(
                    float(np.linalg.norm(bm.template_positions().reshape(-1, 3)[sel] - phi[sel], axis=1).mean())
                )
            r.med_scan_vbd, r.med_scan_evd = meds
        out.append(r)
        if progress is not None:
            progress(r)
    return out


@dataclass
class HeldOut:
    """One held-out scan: VBD and EVD (from the other scans) at its pose, against its truth."""

    scan: str
    training: tuple  #: the scans the EVD model was built from
    med_vbd: float  #: mean ``|F(v) − F_true(v)|`` over template body voxels, mm
    med_evd: float
    cc_vbd: float | None = None  #: Pearson correlation of the posed template with the held-out scan
    cc_evd: float | None = None
    calibration: dict | None = None  #: the model's expected error against the true error (as LeaveOneOut's)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def leave_one_out_correspondences(
    template,
    weights: SkinningWeights,
    body,
    skeleton,
    poses: dict,
    positions: dict,
    truth_positions: dict,
    *,
    images: dict | None = None,
    sigmas: dict | None = None,
    held_out=None,
    weighting: str = "psd",
    progress=None,
) -> list[HeldOut]:
    """Leave each scan out of an EVD model built from the others' correspondences, predict it, compare with truth.

    Rhee Figs. 11–12 made quantitative, with the model built the way a user
    builds it: ``poses`` (scan → :class:`~deformation.kinematics.skeleton.Pose`, the
    *estimated* poses) and ``positions`` (scan → ``(nz, ny, nx, 3)`` world
    positions of every template voxel in that scan, e.g. from a
    registration's inverse field), Rhee Eq. 7.  The held-out scan is
    predicted at its own (estimated) pose by EVD (Rhee Eq. 6) and by VBD
    (Rhee Eq. 2) and compared with ``truth_positions`` (its true forward map)
    over the template's ``body`` voxels; with ``images`` (scan → Volume) the
    posed template is also resampled onto the scan's grid and correlated
    with it (:func:`registration.metrics.similarity`, whole grid).  ``sigmas`` (scan → ``(nz, ny, nx)``, the
    expected error of its positions, mm) gives the model its scans' errors; either way each held-out scan
    records how the model's expected error at its pose (the cross-validated interpolation's, and the scans')
    predicts the true error (``calibration``).
    """
    from deformation.models.posed_template import TemplatePoser
    from registration.metrics import similarity

    g = template.geometry
    ids = list(poses)
    if len(ids) < 3:
        raise ValueError(f"leave-one-out needs at least 3 scans (2 to train on), got {len(ids)}")
    body = np.asarray(body.data if hasattr(body, "data") else body, bool)
    mask = body.reshape(-1)
    out = []
    for k in held_out or ids:
        rest = tuple(s for s in ids if s != k)
        model = ExampleVolumeDeformation.from_correspondences(  # Rhee Eq. 7 on the other scans
            g,
            weights,
            skeleton,
            [poses[s] for s in rest],
            [positions[s] for s in rest],
            scan_sigma=None if sigmas is None else [sigmas[s] for s in rest],
        )
        truth_all = np.asarray(truth_positions[k], np.float64).reshape(-1, 3)
        truth = truth_all[mask]
        f_all = model.forward(poses[k], weighting=weighting).reshape(-1, 3)  # Rhee Eq. 6
        f_evd = f_all[mask]
        f_vbd = vbd_forward(g, weights, poses[k].transforms).reshape(-1, 3)[mask]  # Rhee Eq. 2
        r = HeldOut(
            k,
            rest,
            float(np.linalg.norm(f_vbd - truth, axis=1).mean()),
            float(np.linalg.norm(f_evd - truth, axis=1).mean()),
            calibration=_calibration(model, poses[k], f_all, truth_all, mask),
        )
        if images is not None and k in images:
            from deformation.geometry import Volume

            bvol = Volume(body.astype(np.uint8), g)
            ccs = []
            for m in (None, model):
                posed = (
                    TemplatePoser(template, weights, bvol, model=m, weighting=weighting)
                    .pose(poses[k], labels=False, target=images[k].geometry)
                    .volume
                )
                ccs.append(float(similarity(images[k], posed)["cc"]))
            r.cc_vbd, r.cc_evd = ccs
        out.append(r)
        if progress is not None:
            progress(r)
    return out
