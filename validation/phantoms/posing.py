"""Posing models for phantoms: template → scan maps and their inverses.

Two models, both leaving every bone exactly rigid:

``vbd``
    Plain volume blend deformation (Rhee Eq. 2): ``F(v) = (Σ_k w_k(v) T_k) v``
    with template-space weights, the posing of Rhee's Table 2 protocol.
``soft``
    ``F(v) = DQS_w(v)(v + δ(v))``: the bones' transforms blended as dual
    quaternions (rigid blends: soft tissue turns about the joint instead of
    collapsing towards it), applied after ``δ``: near each flexed joint a
    flexor-side bulge and an extensor-side sliding of the skin, plus smooth
    random shear waves growing with the flexion.  ``δ`` vanishes inside bones
    and fades in over ``Anatomy.bone_fade_mm``; VBD cannot represent it.

Weights are ``w_k ∝ d_k^-p exp(−d_k/λ)`` on the bones' signed distances
(:func:`blend_weights`), exactly one-hot inside a bone.  The ground truth for
a scan voxel ``x`` is ``φ(x) = F⁻¹(x)``, found by damped Newton steps from the
inverse blend (:meth:`PosingModel.inverse`; the few voxels left near folds
are restarted by :meth:`validation.phantoms.Phantom.correspondence`); the
residual ``‖F(φ(x)) − x‖`` is returned.  Neither blend is guaranteed
one-to-one: at strong flexion a small fraction of soft-tissue voxels fold
over, as in linear and dual quaternion skinning; the generator reports that
fraction per scan and keeps skin markers out of folds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deformation.kinematics import dual_quaternion

from . import kernels
from .anatomy import Anatomy

__all__ = ["PosingModel", "blend_weights", "residual_waves", "POSING_MODES"]

POSING_MODES = ("soft", "vbd")


def blend_weights(bone_distances: np.ndarray, *, power: float = 4.0, falloff_mm: float = 20.0) -> np.ndarray:
    """Skinning weights ``(n, n_bones)`` from signed bone distances; rows sum to one.

    ``w_k ∝ d_k^-p · exp(−d_k / λ)``: inverse-distance weights, localised by an
    exponential so that far from the body only the nearest bones count (pure
    inverse-distance weights blend all bones almost equally there, and a blend
    of a fist's transforms is nearly singular).  Inside a bone (distance ≤ 0)
    the weight of that bone is exactly one.  The factor is computed relative
    to the nearest bone's distance, which cancels in the normalisation.
    """
    d = np.maximum(bone_distances, 0.0)
    inside = d <= 0.0
    dmin = d.min(axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        w = np.where(inside, 0.0, d ** (-power) * np.exp(-(d - dmin) / falloff_mm))
    any_in = inside.any(axis=1)
    w[any_in] = inside[any_in].astype(float)
    w /= w.sum(axis=1, keepdims=True)
    return w


def residual_waves(anatomy: Anatomy, rng: np.random.Generator, *, n_waves: int = 3) -> np.ndarray:
    """Random shear waves of the ``soft`` posing's uneven soft-tissue motion, per soft-tissue joint.

    Each wave has wavelength ``anatomy.residual_wavelength_mm`` (±20 %), a
    random direction ``k``, a displacement direction ``e ⊥ k`` (a shear wave:
    no change of volume to first order) and a weight; the weights sum to one,
    so the motion's amplitude is at most ``residual_gain·R·|sin θ|`` and its
    Lipschitz constant about that times ``2π / wavelength`` (kept < 0.3 by the
    anatomies' settings, so that the posing stays one-to-one).
    """
    out = np.zeros((len(anatomy.joint_radius_mm), n_waves, 8))
    for j in range(out.shape[0]):
        for q in range(n_waves):
            k = rng.normal(size=3)
            k /= np.linalg.norm(k)
            e = np.cross(k, rng.normal(size=3))
            e /= np.linalg.norm(e)
            lam = anatomy.residual_wavelength_mm * rng.uniform(0.8, 1.2)
            out[j, q, :3] = k * (2.0 * np.pi / lam)
            out[j, q, 3:6] = e
            out[j, q, 6] = rng.uniform(0.0, 2.0 * np.pi)
        w = rng.uniform(0.5, 1.0, size=n_waves)
        out[j, :, 7] = w / w.sum()
    return out


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _bump(t):
    """Compactly supported C² bump ``(1 − t²)³`` on ``|t| < 1``."""
    u = np.clip(1.0 - t * t, 0.0, None)
    return u * u * u


@dataclass
class _SoftJoint:
    center: np.ndarray
    axes: np.ndarray
    flexion_deg: float
    radius: float
    parent_index: int
    child_index: int


class PosingModel:
    """The template → scan map ``F`` of one posed scan, and its inverse.

    Parameters
    ----------
    anatomy : Anatomy
    transforms : dict bone name → 4x4 template → scan world transform
    joint_angles : dict joint name → angles (degrees); the first angle of each
        soft-tissue joint (its flexion) drives the ``soft`` bulge and sliding
    mode : "soft" or "vbd"
    residual : ``(n_soft_joints, n_waves, 8)`` shear waves per soft-tissue joint,
        rows ``k (3, rad/mm), e (3, unit, ⊥ k), phase, weight`` (see
        :func:`residual_waves`); ``None``: no random motion.
    """

    def __init__(
        self,
        anatomy: Anatomy,
        transforms: dict,
        joint_angles: dict,
        *,
        mode: str = "soft",
        residual: np.ndarray | None = None,
    ):
        if mode not in POSING_MODES:
            raise ValueError(f"posing mode must be one of {POSING_MODES}, got {mode!r}")
        self.anatomy = anatomy
        self.mode = mode
        names = anatomy.bone_names
        self.t = np.stack([np.asarray(transforms[n], float) for n in names])  # (nb, 4, 4)
        self.t_inv = np.stack([np.linalg.inv(t) for t in self.t])
        self._t12 = np.ascontiguousarray(self.t[:, :3, :].reshape(len(names), 12))
        self._dq = dual_quaternion.from_transforms(self.t)
        self._kparams = None
        n_soft = len(anatomy.joint_radius_mm)
        self.residual = np.zeros((n_soft, 0, 8)) if residual is None else np.ascontiguousarray(residual, dtype=float)
        if self.residual.shape[0] != n_soft or self.residual.shape[2:] != (8,):
            raise ValueError(f"residual waves must be (n_soft_joints={n_soft}, n_waves, 8), got {self.residual.shape}")
        sk = anatomy.skeleton
        self.soft_joints = [
            _SoftJoint(
                np.asarray(sk.joint(j).center),
                sk.joint(j).axes,
                float(np.asarray(joint_angles.get(j, [0.0]))[0]),
                float(r),
                names.index(sk.joint(j).parent),
                names.index(sk.joint(j).child),
            )
            for j, r in anatomy.joint_radius_mm.items()
        ]

    # -- the definition, in NumPy --------------------------------------------------------------
    def displacement(self, p: np.ndarray, bone_d: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Template-space soft-tissue offset ``δ(p)`` (bulge + skin sliding), zero in bones.

        Per flexed joint with soft radius ``R``, in the joint frame
        ``(l_x, l_y, l_z)``: a compact envelope ``bump(l_z/1.5R)·bump(ρ/2R)``
        (``bump(t) = (1 − t²)³``, ``ρ = hypot(l_x, l_y)``), restricted to the
        joint's two bones by their blend weights; the bulge pushes flexor-side
        tissue outward by up to ``bulge_gain·R·|sin θ|``; the skin on the
        extensor side slides proximally by up to ``slide_gain·R·|θ|``.
        """
        out = np.zeros_like(p)
        if self.mode != "soft":
            return out
        fade = _smoothstep(np.min(bone_d, axis=1) / self.anatomy.bone_fade_mm)
        body = None
        for j, waves in zip(self.soft_joints, self.residual):
            if j.flexion_deg == 0.0:
                continue
            lx, ly, lz = ((p - j.center) @ j.axes).T
            rho = np.hypot(lx, ly)
            along = _bump(lz / (1.5 * j.radius)) * _bump(rho / (2.0 * j.radius))
            member = w[:, j.parent_index] + w[:, j.child_index]
            s = np.sign(j.flexion_deg)
            th = np.deg2rad(j.flexion_deg)
            flexor = _smoothstep(-s * ly / (0.5 * j.radius))
            radial = np.minimum(rho / j.radius, 1.2)
            bulge = self.anatomy.bulge_gain * j.radius * abs(np.sin(th)) * along * flexor * radial * member * fade
            out += bulge[:, None] * (-s * j.axes[:, 1])
            if body is None:
                body = self.anatomy.body_distance(p)
            extensor = _smoothstep(s * ly / (0.5 * j.radius))
            skin = np.exp(-0.5 * (body / (0.15 * j.radius)) ** 2)
            slide = self.anatomy.slide_gain * j.radius * abs(th) * along * extensor * skin * member * fade
            out += slide[:, None] * (-j.axes[:, 2])
            amp = self.anatomy.residual_gain * j.radius * abs(np.sin(th)) * along * member * fade
            for wave in waves:  # uneven sliding and bulging: transverse (shear) waves, zero in the bones
                out += (amp * wave[7] * np.sin(p @ wave[:3] + wave[6]))[:, None] * wave[3:6]
        return out

    def forward_reference(self, p: np.ndarray) -> np.ndarray:
        """``F(p)`` in plain NumPy — the definition the compiled :meth:`forward` is tested against."""
        bone_d = self.anatomy.bone_distances(p)
        w = blend_weights(bone_d, power=self.anatomy.weight_power, falloff_mm=self.anatomy.weight_falloff_mm)
        if self.mode == "vbd":
            m = (w @ self._t12).reshape(-1, 3, 4)  # Rhee Eq. 2: (Σ_j w_j T_j) v
            return np.einsum("nij,nj->ni", m[:, :, :3], p) + m[:, :, 3]
        return dual_quaternion.blend_apply(w, self._dq, p + self.displacement(p, bone_d, w))[0]

    # -- compiled evaluation ---------------------------------------------------------------------
    def _params(self):
        if self._kparams is None:
            sign = np.sign(self._dq[:, :4] @ self._dq[:, :4].T)
            sign[sign == 0] = 1.0
            joints = np.zeros((len(self.soft_joints), 18))
            for i, j in enumerate(self.soft_joints):
                joints[i, :3] = j.center
                joints[i, 3:12] = j.axes.reshape(-1)
                joints[i, 12:18] = (
                    j.flexion_deg,
                    j.radius,
                    j.parent_index,
                    j.child_index,
                    self.anatomy.bulge_gain,
                    self.anatomy.slide_gain,
                )
            self._kparams = (
                self._t12,
                self._dq,
                sign,
                joints,
                0 if self.mode == "vbd" else 1,
                float(self.anatomy.weight_power),
                float(self.anatomy.weight_falloff_mm),
                float(self.anatomy.bone_fade_mm),
                self.residual,
                float(self.anatomy.residual_gain),
            )
        return self._kparams

    def forward(self, p: np.ndarray) -> np.ndarray:
        """``F(p)`` for template points ``(n, 3)`` (compiled, parallel)."""
        return kernels.forward_map(kernels.points(p), self.anatomy.tables, self._params())

    def inverse(
        self,
        x: np.ndarray,
        *,
        guess: np.ndarray | None = None,
        tol_mm: float = 1e-6,
        max_iter: int = 60,
        fd_jacobian: bool = False,
    ):
        """Template positions ``φ(x)`` with ``F(φ(x)) = x``; returns ``(φ, residual_mm)``.

        Starts from ``guess`` or, by default, from the inverse blend with
        posed-bone weights; Newton steps use the blended rotation as the
        Jacobian, or finite differences with ``fd_jacobian=True``.
        """
        return kernels.inverse_map(
            kernels.points(x),
            kernels.points(np.zeros((1, 3)) if guess is None else guess),
            guess is not None,
            self.anatomy.tables,
            self._params(),
            np.ascontiguousarray(self.t_inv[:, :3, :].reshape(-1, 12)),
            tol_mm,
            max_iter,
            fd_jacobian,
        )
