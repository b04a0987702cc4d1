"""Analytic anatomy of a phantom and its MRI-/CT-like appearance.

An :class:`Anatomy` is defined in *template world* millimetres by signed
distance functions: one per bone, one for the body (skin surface).  Every
tissue is a function of the distance to these surfaces:

* bone: cortical shell of thickness ``cortex_mm`` around marrow;
* soft tissue, from the skin inwards: skin (``skin_mm``), subcutaneous fat
  (``fat_mm``), then muscle;
* air outside the body.

Edges are smoothed with a ``tanh`` profile of width ``edge_mm`` (a partial
volume model) so that images are band-limited on the grid they are sampled
on.  Because the appearance is a continuous function of the template
position, a posed scan is rendered *exactly* as ``I_template(φ(x))`` where
``φ`` is the scan → template correspondence: ground truth by construction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from deformation.kinematics.skeleton import Skeleton
from deformation.kinematics.transforms import invert

__all__ = ["Anatomy", "Contrast", "CONTRASTS", "Texture"]


@dataclass(frozen=True)
class Contrast:
    """Mean intensity per tissue and the noise model of a modality."""

    name: str
    air: float
    skin: float
    fat: float
    muscle: float
    cortex: float
    marrow: float
    noise: str  # "rician" (MRI magnitude) or "gaussian" (CT)
    noise_sigma: float
    texture_amplitude: float  # relative modulation of soft tissue and marrow
    bias_amplitude: float  # relative amplitude of the smooth multiplicative bias field
    tendon: float = 0.0  # tendons and fibrous tissue (soft_tissue.SoftTissue)
    vessel: float = 0.0


# MRI-like: T1-weighted appearance. Cortical bone is dark, marrow and fat are
# bright and overlap once texture, bias and noise are added; skin and muscle
# overlap likewise (Rhee §2: "overlapping intensity ranges between different
# tissues"). Arbitrary units on a 0..1000 scale.
# Tendons are dark on T1 (short T2*), slow-flowing vessels intermediate-bright.
MRI = Contrast(
    "mri",
    air=0.0,
    skin=520.0,
    fat=900.0,
    muscle=380.0,
    cortex=60.0,
    marrow=780.0,
    noise="rician",
    noise_sigma=30.0,
    texture_amplitude=0.08,
    bias_amplitude=0.12,
    tendon=90.0,
    vessel=640.0,
)
# CT-like: Hounsfield units; bright cortical bone (Kurihara §2), no bias field.
# CT: tendons a little denser than muscle, vessels contrast-enhanced (an angiographic phase).
CT = Contrast(
    "ct",
    air=-1000.0,
    skin=30.0,
    fat=-100.0,
    muscle=45.0,
    cortex=1300.0,
    marrow=250.0,
    noise="gaussian",
    noise_sigma=20.0,
    texture_amplitude=0.05,
    bias_amplitude=0.0,
    tendon=95.0,
    vessel=180.0,
)
CONTRASTS = {"mri": MRI, "ct": CT}


@dataclass(frozen=True)
class Texture:
    """A smooth random texture attached to the tissue: a sum of plane waves in template mm.

    Zero mean, unit RMS; wavelengths log-uniform between ``min_wavelength_mm``
    and ``max_wavelength_mm`` (the phantom keeps the shortest at 4 voxels, so
    that the texture is resolved on its grid).
    """

    wavevectors: np.ndarray  # (K, 3) rad/mm
    phases: np.ndarray  # (K,)
    amplitudes: np.ndarray  # (K,)

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        *,
        n_waves: int = 24,
        min_wavelength_mm: float = 12.0,
        max_wavelength_mm: float = 45.0,
    ) -> Texture:
        dirs = rng.normal(size=(n_waves, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        # Log-uniform wavelengths: as many waves per octave at every scale (multi-scale texture).
        lam = np.exp(rng.uniform(np.log(min_wavelength_mm), np.log(max_wavelength_mm), size=n_waves))
        amps = rng.uniform(0.5, 1.0, size=n_waves)
        amps *= np.sqrt(2.0 / np.sum(amps**2))  # unit RMS for independent random phases
        return cls(dirs * (2 * np.pi / lam)[:, None], rng.uniform(0, 2 * np.pi, size=n_waves), amps)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        return np.cos(p @ self.wavevectors.T + self.phases) @ self.amplitudes


@dataclass
class Anatomy:
    """Bones, body envelope and layer thicknesses of a phantom, in template world mm.

    ``bones`` maps each skeleton bone name to a signed distance function;
    ``joint_radius_mm`` gives, per joint, the soft-tissue radius around the
    joint used by the ``soft`` posing model (bulge and skin sliding scale).
    """

    skeleton: Skeleton
    bones: dict
    body: object
    joint_radius_mm: dict
    cortex_mm: float = 2.0
    skin_mm: float = 2.0
    fat_mm: float = 6.0
    weight_power: float = 4.0  # inverse-distance power of the posing weights
    weight_falloff_mm: float = 20.0  # exponential localisation of the posing weights
    # ``soft`` posing, per flexed joint of soft radius R: flexor-side bulge up to
    # bulge_gain·R·|sin θ| and extensor-side skin slide up to slide_gain·R·|θ| (θ in radians).
    bulge_gain: float = 0.10
    slide_gain: float = 0.08
    bone_fade_mm: float = 3.0  # soft-tissue offsets fade in over this distance from the bones
    # ``soft`` posing: a smooth random soft-tissue motion near each flexed joint of amplitude up to
    # residual_gain·R·|sin θ| — muscles sliding and bulging unevenly, which no skinning of the bones captures.
    residual_gain: float = 0.05
    residual_wavelength_mm: float = 90.0  #: wavelength of that motion (its Lipschitz constant stays < 0.3)
    # Sizes of the soft-tissue structure (soft_tissue.SoftTissue): cells, septa, tubes (mm; offsets in joint radii).
    structure: dict = field(
        default_factory=lambda: dict(
            muscle_cell_mm=16.0,
            fat_cell_mm=6.0,
            muscle_septum_mm=0.8,
            fat_septum_mm=0.4,
            cell_amplitude=0.10,
            lobule_amplitude=0.06,
            tendon_offset=0.6,
            tendon_radius_mm=3.5,
            vessel_offset=0.65,
            vessel_radius_mm=2.5,
        )
    )
    bone_names: list = field(init=False)
    _tables: tuple | None = field(init=False, repr=False, default=None)

    def __post_init__(self):
        missing = set(self.skeleton.bone_names) - set(self.bones)
        if missing:
            raise ValueError(f"anatomy lacks shapes for bones {sorted(missing)}")
        self.bone_names = list(self.skeleton.bone_names)
        self._tables = None

    @property
    def tables(self):
        """Flattened shape tables for the compiled kernels (bones in skeleton order, then the body)."""
        if self._tables is None:
            from .kernels import compile_shapes

            self._tables = compile_shapes([self.bones[n] for n in self.bone_names] + [self.body])
        return self._tables

    # -- distances ----------------------------------------------------------------
    def bone_distances(self, p: np.ndarray) -> np.ndarray:
        """Signed distance to every bone, ``(n, n_bones)`` in skeleton bone order."""
        out = np.empty((p.shape[0], len(self.bone_names)))
        for i, name in enumerate(self.bone_names):
            out[:, i] = self.bones[name](p)
        return out

    def body_distance(self, p: np.ndarray) -> np.ndarray:
        return self.body(p)

    # -- appearance ---------------------------------------------------------------
    def intensity_fast(
        self,
        p: np.ndarray,
        contrast: Contrast,
        *,
        edge_mm: float,
        texture: Texture | None = None,
        bone_frames: tuple | None = None,
        tissue=None,
    ) -> np.ndarray:
        """Compiled, parallel equivalent of :meth:`intensity`."""
        from . import kernels

        tex = texture or Texture(np.zeros((0, 3)), np.zeros(0), np.zeros(0))
        c = (
            contrast.air,
            contrast.skin,
            contrast.fat,
            contrast.muscle,
            contrast.cortex,
            contrast.marrow,
            contrast.tendon,
            contrast.vessel,
        )
        p = kernels.points(p)
        scan, frames = self._bone_frames(p, bone_frames)
        if tissue is None:
            tparams, keys, tubes, info = np.zeros(0), np.zeros(2, np.uint64), np.zeros((0, 18)), np.zeros((0, 2))
            none = (np.zeros((0, 0, 0, 4)), np.zeros(3, np.int64))
            sites = none + none
        else:
            tparams, keys = tissue.params(), tissue.keys()
            tubes, info = tissue.tube_table()
            sites = tissue.site_tables(p) if len(p) else tissue.site_tables(np.zeros((1, 3)))
        return kernels.intensity_map(
            p,
            self.tables,
            len(self.bone_names),
            c,
            float(edge_mm),
            (self.skin_mm, self.fat_mm, self.cortex_mm),
            tex.wavevectors,
            tex.phases,
            tex.amplitudes,
            contrast.texture_amplitude,
            scan,
            frames,
            tparams,
            keys,
            tubes,
            info,
            sites,
        )

    def _bone_frames(self, p: np.ndarray, bone_frames) -> tuple[np.ndarray, np.ndarray]:
        """``(scan points (n, 3), scan → bone template frames (n_bones, 3, 4))``; empty when not given."""
        from . import kernels

        if bone_frames is None:
            return kernels.points(np.zeros((0, 3))), np.zeros((0, 3, 4))
        scan, transforms = bone_frames
        scan = kernels.points(scan)
        if scan.shape != p.shape:
            raise ValueError(f"bone_frames scan points {scan.shape} must match the template points {p.shape}")
        missing = set(self.bone_names) - set(transforms)
        if missing:
            raise ValueError(f"bone_frames lacks transforms for bones {sorted(missing)}")
        frames = np.stack([invert(transforms[n])[:3] for n in self.bone_names])
        return scan, np.ascontiguousarray(frames)

    def distances_fast(self, p: np.ndarray) -> np.ndarray:
        """Compiled signed distances ``(n, n_bones + 1)``: every bone, then the body."""
        from . import kernels

        return kernels.distances_map(kernels.points(p), self.tables, len(self.bone_names) + 1)

    def intensity(
        self,
        p: np.ndarray,
        contrast: Contrast,
        *,
        edge_mm: float,
        texture: Texture | None = None,
        bone_frames: tuple | None = None,
        tissue=None,
    ) -> np.ndarray:
        """Noise-free, bias-free intensity at template points ``p`` (n, 3).

        Tissues are layered (air, skin, fat, muscle, cortex, marrow), each edge
        blurred by ``tanh(sdf / edge_mm)`` — the scanner's point spread.

        ``bone_frames = (scan_points, transforms)`` renders a posed scan: soft
        tissue at ``p`` (each scan point's template position through the posing
        map), but each bone's distance at ``T_k⁻¹ x`` (``transforms``: bone name
        → 4x4 template → scan), so that a bone's blurred edge moves rigidly with
        the bone, as a scanner's point spread in the scan does.  Inside a bone
        the posing map is ``T_k⁻¹`` and both agree; outside, the surrounding
        tissue slides (up to a few mm within a voxel of a knee bone at 70° of
        flexion) and would otherwise drag the edge's halo with it, a
        non-rigid bone edge that no rigid registration can fit.

        ``tissue`` (:class:`~validation.phantoms.soft_tissue.SoftTissue`) adds
        the soft tissue's structure: muscle cells of their own intensity split
        by fat septa, fat lobules split by fibrous (skin-intensity) septa, then
        tendons and vessels, all at the template position.
        """

        def inside(sdf):  # 1 inside (sdf < 0), 0 outside, smooth edge
            return 0.5 * (1.0 - np.tanh(sdf / edge_mm))

        b = self.body_distance(p)
        scan, frames = self._bone_frames(np.ascontiguousarray(p, dtype=float), bone_frames)
        if len(frames):
            db = np.min(
                np.column_stack([self.bones[n](scan @ m[:, :3].T + m[:, 3]) for n, m in zip(self.bone_names, frames)]),
                axis=1,
            )
        else:
            db = np.min(self.bone_distances(p), axis=1)
        tex = 0.0 if texture is None else contrast.texture_amplitude * texture(p)

        val = contrast.muscle * (1.0 + tex)
        fat = contrast.fat * (1.0 + tex)
        if tissue is not None:
            from .soft_tissue import blurred_box, cell_boundary_distance

            sm, um = cell_boundary_distance(p, tissue.muscle_cell_mm, tissue.muscle_key)
            val = val * (1.0 + tissue.cell_amplitude * (2.0 * um - 1.0))
            val += (fat - val) * blurred_box(sm, tissue.muscle_septum_mm, edge_mm)  # intermuscular fat septa
            sf, uf = cell_boundary_distance(p, tissue.fat_cell_mm, tissue.fat_key)
            fat = fat * (1.0 + tissue.lobule_amplitude * (2.0 * uf - 1.0))
            fat += (contrast.skin - fat) * blurred_box(sf, tissue.fat_septum_mm, edge_mm)  # fibrous septa of lobules
        val += (fat - val) * (1.0 - inside(b + self.skin_mm + self.fat_mm))
        if tissue is not None:
            val += (contrast.tendon - val) * tissue.tube_fraction(p, 0, edge_mm)
            val += (contrast.vessel - val) * tissue.tube_fraction(p, 1, edge_mm)
        val += (contrast.skin - val) * (1.0 - inside(b + self.skin_mm))
        val += (contrast.cortex - val) * inside(db)
        val += (contrast.marrow * (1.0 + tex) - val) * inside(db + self.cortex_mm)
        return contrast.air + (val - contrast.air) * inside(b)
