"""Build phantom studies: template, label map, posed scans and their exact ground truth.

Everything here returns arrays with their geometry; writing the study folder
is :mod:`workbench.study`'s job.  Scans are produced one at a time
(:meth:`Phantom.scans` is a generator) so that paper-size studies stay well
under a few GiB of memory.

Randomness: one ``seed`` feeds a ``numpy.random.SeedSequence``, spawned
into independent streams for the texture, pose jitter, markers, and each
image's noise and bias field, so the same seed gives identical files and
another seed gives different noise (and jitter).

Acquisition: by default (``acquisition="fixed"``) every image of a modality
has the same tissue intensities, noise model, noise level and bias amplitude
(``validation.phantoms.anatomy.CONTRASTS``).  ``acquisition="random"``
draws them instead (:func:`draw_acquisition`), from a stream of their own
(the root sequence's sixth child, spawned into [study, image 0, image 1, ...];
image 0 is the template): per study a tissue-intensity table and, unless the
spec gives ``spacing``, an anisotropic voxel spacing; per image a noise model,
SNR, gain, offset and bias amplitude.  The noise and bias field themselves
still come from each image's own noise/bias stream.  Only intensities and the
grid change: the anatomy, poses, correspondence and markers are those of the
same seed without it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, fields

import numpy as np

from deformation.fields.displacement import jacobian_determinant
from deformation.geometry import GridGeometry, Volume
from deformation.kinematics.skeleton import Pose, Skeleton

from . import hand, knee
from .anatomy import CONTRASTS, Anatomy, Contrast, Texture
from .posing import POSING_MODES, PosingModel, residual_waves
from .soft_tissue import SoftTissue

__all__ = [
    "PhantomSpec",
    "PhantomScan",
    "Phantom",
    "REGIONS",
    "make_phantom",
    "SIZES",
    "MODALITIES",
    "ACQUISITIONS",
    "draw_acquisition",
    "ANISOTROPY_RANGE",
    "BIAS_RANGE",
    "GAIN_RANGE",
    "MIN_AXIS_VOXELS",
    "OFFSET_FRACTION",
    "SNR_RANGE",
    "TISSUES",
    "TISSUE_JITTER",
    "describe_acquisition",
]

REGIONS = {"knee": knee, "hand": hand}
SIZES = ("test", "paper")
MODALITIES = tuple(CONTRASTS)
CHUNK = 1 << 17  # points per vectorised chunk: bounds temporary memory (~100 MB)
RESTARTS = 8  # nearest forward-mapped template voxels tried for voxels Newton did not solve
N_MARKERS = 12  # skin markers per study (Rhee Table 3 used eight)
#: a phantom's grid keeps at least this many voxels along each axis (the test hand's is 30 across its thickness):
#: coarser, its smallest bones fall between voxels and the generator's gradients have too few samples
MIN_AXIS_VOXELS = 16
#: and at most this many voxels in all (Kurihara's CT, the largest grid the project works on, has 197 M)
MAX_GRID_VOXELS = 250_000_000

#: ``PhantomSpec.acquisition``: "fixed" (the modality's table, noise and bias for every image) or "random"
ACQUISITIONS = ("fixed", "random")
#: Ranges of ``acquisition="random"`` (see :func:`draw_acquisition`).  SNR is the muscle's mean signal above
#: air (times the image's gain) over the noise σ: σ = gain · (muscle − air) / SNR.
SNR_RANGE = (8.0, 40.0)  # log-uniform
BIAS_RANGE = (0.0, 0.20)  # max |bias − 1|, uniform
GAIN_RANGE = (0.9, 1.1)  # uniform
OFFSET_FRACTION = 0.02  # Gaussian-noise images: offset uniform in ±this × (muscle − air); Rician: none
ANISOTROPY_RANGE = (1.0, 3.0)  # slice / in-plane spacing factor, log-uniform
TISSUE_JITTER = 0.10  # each tissue's signal above air (but muscle's) times uniform 1 ± this
#: the tissues of a Contrast with an intensity (muscle is the reference of the random tables)
TISSUES = ("skin", "fat", "muscle", "cortex", "marrow", "tendon", "vessel")
_ACQUISITION_STREAM = 5  # the root SeedSequence's child holding the random acquisition's draws (see Phantom)


@dataclass(frozen=True)
class PhantomSpec:
    """Everything that determines a phantom study (recorded in its manifest)."""

    region: str = "knee"
    size: str = "test"
    modality: str = "mri"
    n_poses: int | None = None
    posing: str = "soft"
    seed: int = 0
    noise: bool = True
    poses: tuple | None = None  # explicit joint angles: tuple of (id, {joint: angles})
    direction: tuple | None = None  # grid direction (default identity)
    spacing: tuple | None = None  # override the size's voxel spacing (mm); the field of view is kept
    acquisition: str = "fixed"  # "random": draw contrast, noise, bias, gain and spacing (draw_acquisition)

    def __post_init__(self):
        if self.region not in REGIONS:
            raise ValueError(f"region must be one of {sorted(REGIONS)}, got {self.region!r}")
        if self.size not in SIZES:
            raise ValueError(f"size must be one of {SIZES}, got {self.size!r}")
        if self.modality not in MODALITIES:
            raise ValueError(f"modality must be one of {MODALITIES}, got {self.modality!r}")
        if self.posing not in POSING_MODES:
            raise ValueError(f"posing must be one of {POSING_MODES}, got {self.posing!r}")
        if self.spacing is not None:
            sp = np.asarray(self.spacing, float).reshape(-1)
            if sp.shape != (3,) or np.any(~np.isfinite(sp)) or np.any(sp <= 0):
                raise ValueError(f"spacing must be 3 positive numbers (mm), got {self.spacing!r}")
        if self.n_poses is not None and self.n_poses < 1:
            raise ValueError(f"n_poses must be at least 1, got {self.n_poses}")
        if self.acquisition not in ACQUISITIONS:
            raise ValueError(f"acquisition must be one of {ACQUISITIONS}, got {self.acquisition!r}")

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("region", "size", "modality", "n_poses", "posing", "seed", "noise")}
        if self.direction is not None:
            d["direction"] = list(self.direction)
        if self.spacing is not None:
            d["spacing"] = list(self.spacing)
        if self.acquisition != "fixed":  # recorded only when not the default: older manifests stay the same
            d["acquisition"] = self.acquisition
        return d

    @classmethod
    def from_dict(cls, d: dict) -> PhantomSpec:
        """The spec ``to_dict()`` wrote (e.g. a study manifest's ``phantom`` entry).

        Keys ``to_dict()`` does not write are not read: a manifest's recorded ``poses`` (the poses the
        spec drew, or its explicit ones, which ``to_dict()`` leaves out), ``acquisition_drawn`` and the
        generator's notes.  ``PhantomSpec.from_dict(spec.to_dict()) == spec`` for every spec without
        explicit ``poses``.
        """
        known = {f.name for f in fields(cls)} - {"poses", "direction", "spacing"}
        kw = {k: v for k, v in d.items() if k in known}
        for k in ("direction", "spacing"):
            if d.get(k) is not None:
                kw[k] = tuple(float(v) for v in np.ravel(np.asarray(d[k], float)))
        return cls(**kw)


@dataclass
class PhantomScan:
    """One posed scan with its ground truth.

    ``correspondence`` is the ``scan_to_template`` displacement field on the
    scan grid: for every scan voxel at world ``x``, ``x + u(x)`` is the template
    world position it came from (mm).  ``markers`` is a list of
    ``{"name", "template": [x,y,z], "scan": [x,y,z]}``.  ``template_to_scan``
    is the exact forward map on the template grid (scan position − template
    voxel, mm): what EVD (Rhee Eq. 7) needs, and not recoverable from
    ``correspondence`` where the posing folds.
    """

    id: str
    image: Volume
    pose: Pose
    correspondence: Volume
    markers: list
    stats: dict = field(default_factory=dict)
    template_to_scan: Volume | None = None


def _acquisition_seq(seed: int, child: int) -> np.random.SeedSequence:
    """Child ``child`` (0: the study, 1 + i: image i) of the random acquisition's stream of ``seed``."""
    return np.random.SeedSequence(seed, spawn_key=(_ACQUISITION_STREAM, int(child)))


def _draw_study(spec: PhantomSpec) -> dict:
    """The study's tissue-intensity table and (unless ``spec.spacing``) anisotropic spacing (see
    :func:`draw_acquisition`)."""
    rng = np.random.default_rng(_acquisition_seq(spec.seed, 0))
    mri, ct, base = CONTRASTS["mri"], CONTRASTS["ct"], CONTRASTS[spec.modality]
    weight = float(rng.beta(0.5, 0.5))  # 0: the MRI (T1-like) table, 1: the CT table; the ends most likely
    jitter = {t: (1.0 if t == "muscle" else float(rng.uniform(1 - TISSUE_JITTER, 1 + TISSUE_JITTER))) for t in TISSUES}

    def relative(c, t):  # signal above air in units of the muscle's
        return (getattr(c, t) - c.air) / (c.muscle - c.air)

    span = base.muscle - base.air
    table = {"air": float(base.air)}
    for t in TISSUES:
        rel = (1 - weight) * relative(mri, t) + weight * relative(ct, t)
        table[t] = float(base.air + span * rel * jitter[t])
    table["texture_amplitude"] = float((1 - weight) * mri.texture_amplitude + weight * ct.texture_amplitude)
    out = {
        "contrast_weight_ct": weight,
        "tissue_jitter": jitter,
        "contrast": table,
        "spacing": None,
        "slice_axis": None,
        "anisotropy": None,
    }
    # The spacing is drawn (the same numbers) whether or not the spec gives one; it is used only when not.
    ratio = float(np.exp(rng.uniform(*np.log(ANISOTROPY_RANGE))))
    axis = int(rng.integers(3))
    if spec.spacing is None:
        size, spacing = REGIONS[spec.region].GRIDS[spec.size]
        spacing = np.asarray(spacing, float)
        extent = np.asarray(size) * spacing
        # the voxel's volume is kept: in-plane ratio^(-1/3), slice ratio^(2/3), so ratio between them
        sp = spacing * ratio ** (-1.0 / 3.0)
        sp[axis] = spacing[axis] * ratio ** (2.0 / 3.0)
        coarsest = np.floor(extent / MIN_AXIS_VOXELS * 1e4) / 1e4  # MIN_AXIS_VOXELS along every axis
        sp = np.minimum(np.round(sp, 4), coarsest)
        out.update(spacing=[float(v) for v in sp], slice_axis="xyz"[axis], anisotropy=ratio)
    return out


def _draw_image(seed: int, index: int, span: float) -> dict:
    """Image ``index``'s (0: the template) noise model, SNR, σ, gain, offset and bias amplitude; ``span`` is the
    study's muscle − air (see :func:`draw_acquisition`)."""
    rng = np.random.default_rng(_acquisition_seq(seed, 1 + index))
    noise = "rician" if rng.uniform() < 0.5 else "gaussian"
    snr = float(np.exp(rng.uniform(*np.log(SNR_RANGE))))
    gain = float(rng.uniform(*GAIN_RANGE))
    offset = float(rng.uniform(-OFFSET_FRACTION, OFFSET_FRACTION) * span)
    bias = float(rng.uniform(*BIAS_RANGE))
    return {
        "noise": noise,
        "snr": snr,
        "noise_sigma": gain * span / snr,
        "gain": gain,
        "offset": offset if noise == "gaussian" else 0.0,
        "bias_amplitude": bias,
    }


def _image_count(spec: PhantomSpec) -> int:
    return 1 + (len(spec.poses) if spec.poses is not None else spec.n_poses or REGIONS[spec.region].DEFAULT_POSES)


def draw_acquisition(spec: PhantomSpec, n_images: int | None = None) -> dict:
    """The acquisition ``acquisition="random"`` draws for ``spec`` (whatever ``spec.acquisition`` says).

    Returns ``{"study": {...}, "images": [template, scan 0, scan 1, ...]}`` (``n_images`` entries, by default
    the template and the spec's scans), all from ``spec.seed`` through the acquisition's own stream: child 0
    for the study, child 1 + i for image i, so an image's draws do not depend on how many images there are.

    Per study (the template and the scans share it, as one protocol's scans do):

    * ``contrast``: each tissue's signal above air in units of the muscle's is interpolated between the MRI
      (T1-like: fat 2.4 and marrow 2.1 times muscle, cortex dark) and the CT table (fat 0.86 times muscle,
      cortex bright) with weight ``contrast_weight_ct`` ~ Beta(½, ½) on [0, 1] (the two tables the most likely;
      in between, fat a little brighter than muscle and cortex near muscle; fat is darker than muscle for
      weights above about 0.9, a fifth of the draws), then times ``tissue_jitter`` ~ U(1 ± TISSUE_JITTER)
      per tissue but muscle.  The modality sets the units: its air level and its muscle − air.
      ``texture_amplitude`` is interpolated likewise.
    * ``spacing``: when the spec gives none, the size's spacing with one axis (``slice_axis``, uniform) made
      thicker by ``anisotropy``^(2/3) and the others finer by ``anisotropy``^(-1/3) (log-uniform in
      ANISOTROPY_RANGE; the voxel volume and field of view are kept), rounded to 1e-4 mm and capped so that
      every axis keeps MIN_AXIS_VOXELS voxels.  ``None`` (and ``slice_axis``, ``anisotropy`` None) when
      the spec gives ``spacing``.

    Per image: ``noise`` "rician" or "gaussian" (probability ½ each); ``snr`` log-uniform in SNR_RANGE, where
    SNR is the muscle's mean signal above air (times ``gain``) over σ, so ``noise_sigma`` = gain · (muscle −
    air) / snr; ``gain`` ~ U(GAIN_RANGE); ``offset`` ~ U(±OFFSET_FRACTION · (muscle − air)) for Gaussian
    noise (a CT-like calibration shift), 0 for Rician; ``bias_amplitude`` ~ U(BIAS_RANGE), the largest
    ``|bias − 1|`` of the image's smooth multiplicative bias field.
    """
    study = _draw_study(spec)
    span = study["contrast"]["muscle"] - study["contrast"]["air"]
    n = _image_count(spec) if n_images is None else int(n_images)
    return {"study": study, "images": [_draw_image(spec.seed, i, span) for i in range(n)]}


def describe_acquisition(drawn: dict) -> str:
    """One line of a drawn acquisition (:func:`draw_acquisition`'s, or ``Phantom.acquisition``, or the manifest's
    ``phantom.acquisition_drawn``): the study's contrast and fat/muscle ratio, then each image's noise, SNR, gain
    and bias, the template first."""
    st, images = drawn.get("study", {}), drawn.get("images", {})
    if not isinstance(images, dict):
        images = dict(enumerate(images))
    images = {i: images[i] for i in sorted(images, key=lambda i: i != "template")}
    c = st.get("contrast", {})
    fat = (c.get("fat", 0.0) - c.get("air", 0.0)) / max(c.get("muscle", 1.0) - c.get("air", 0.0), 1e-9)
    return (
        f"acquisition: random, contrast {st.get('contrast_weight_ct', float('nan')):.2f} of the way from the "
        f"MRI table to the CT one (fat/muscle {fat:.2f} above air)"
        + "".join(
            f"; {i}: {a['noise']}, SNR {a['snr']:.0f}, gain {a['gain']:.2f}, bias {100 * a['bias_amplitude']:.0f}%"
            for i, a in images.items()
        )
    )


def _chunks(n: int, size: int = CHUNK):
    for s in range(0, n, size):
        yield slice(s, min(s + size, n))


def _apply_chunked(fn, points: np.ndarray, out_shape_tail=(), dtype=np.float64):
    n = points.shape[0]
    out = np.empty((n,) + tuple(out_shape_tail), dtype=dtype)
    for sl in _chunks(n):
        out[sl] = fn(points[sl])
    return out


class Phantom:
    """A synthetic study: analytic anatomy, a template grid and a list of poses."""

    def __init__(self, spec: PhantomSpec):
        self.spec = spec
        self.region = REGIONS[spec.region]
        self.anatomy: Anatomy = self.region.anatomy()
        self.skeleton: Skeleton = self.anatomy.skeleton
        self.contrast = CONTRASTS[spec.modality]
        size, spacing = self.region.GRIDS[spec.size]
        override = spec.spacing
        #: ``acquisition="random"``: ``{"study": {...}, "images": {image id: {...}}}`` (draw_acquisition; the
        #: template's id is "template"; no images with ``noise=False``, whose images are not acquired); else None
        self.acquisition = None
        if spec.acquisition == "random":
            study = _draw_study(spec)
            t = study["contrast"]
            base = self.contrast
            # the study's table; its noise fields stay the modality's and are not used (each image's noise,
            # σ and bias amplitude are in self.acquisition["images"])
            self.contrast = Contrast(
                f"{base.name}-random",
                air=t["air"],
                skin=t["skin"],
                fat=t["fat"],
                muscle=t["muscle"],
                cortex=t["cortex"],
                marrow=t["marrow"],
                noise=base.noise,
                noise_sigma=base.noise_sigma,
                texture_amplitude=t["texture_amplitude"],
                bias_amplitude=base.bias_amplitude,
                tendon=t["tendon"],
                vessel=t["vessel"],
            )
            self.acquisition = {"study": study, "images": {}}
            if override is None:
                override = tuple(study["spacing"])
        if override is not None:  # keep the field of view, change the sampling
            extent = np.asarray(size) * np.asarray(spacing)
            size = tuple(int(v) for v in np.maximum(1, np.round(extent / np.asarray(override, float))))
            spacing = tuple(float(v) for v in override)
            coarsest = extent / MIN_AXIS_VOXELS
            if min(size) < MIN_AXIS_VOXELS:
                raise ValueError(
                    f"spacing {tuple(round(v, 4) for v in spacing)} mm leaves the {spec.region}'s field "
                    f"of view ({' x '.join(f'{e:.0f}' for e in extent)} mm) only "
                    f"{' x '.join(str(n) for n in size)} voxels; a phantom needs at least "
                    f"{MIN_AXIS_VOXELS} along each axis: give a spacing of at most "
                    f"{', '.join(f'{c:.2f}' for c in coarsest)} mm (x, y, z)"
                )
            if int(np.prod(size, dtype=np.int64)) > MAX_GRID_VOXELS:
                raise ValueError(
                    f"spacing {tuple(round(v, 4) for v in spacing)} mm makes a grid of "
                    f"{' x '.join(str(n) for n in size)} voxels, more than {MAX_GRID_VOXELS:,}; give a "
                    "larger spacing"
                )
        direction = np.eye(3) if spec.direction is None else np.asarray(spec.direction, float).reshape(3, 3)
        centre = np.asarray(self.region.GRID_CENTER, float)
        half = direction @ ((np.asarray(size) - 1) * np.asarray(spacing) / 2.0)
        self.geometry = GridGeometry(size, spacing, tuple(centre - half), tuple(direction.reshape(-1)))
        # Partial-volume edge of 0.8 voxel (a scanner's point spread), so that
        # images are nearly band-limited on their grid and linear resampling
        # through the true correspondence reproduces a posed scan.
        self.edge_mm = 0.8 * max(spacing)
        ss = np.random.SeedSequence(spec.seed)
        self._tex_seq, self._pose_seq, self._marker_seq, self._noise_seq, motion_seq = ss.spawn(5)
        # The soft tissue's own uneven motion (posing.residual_waves): a property of this body, the same in
        # every pose and scaled by each pose's flexion.
        self.residual = residual_waves(self.anatomy, np.random.default_rng(motion_seq))
        # Texture: 48 plane waves from 4 voxels (at least 6 mm) to 45 mm, several scales of muscle texture;
        # then the structure (septa, lobules, tendons, vessels) from the same stream.
        wl = max(6.0, 4.0 * max(spacing))
        tex_rng = np.random.default_rng(self._tex_seq)
        self.texture = Texture.random(tex_rng, n_waves=48, min_wavelength_mm=wl, max_wavelength_mm=max(45.0, 3.0 * wl))
        self.tissue = SoftTissue.random(self.anatomy, tex_rng)
        self.poses = self._make_poses()
        # One independent noise/bias stream per image: [template, scan 0, scan 1, ...].
        self._image_seqs = self._noise_seq.spawn(len(self.poses) + 1)
        if self.acquisition is not None and spec.noise:
            span = self.contrast.muscle - self.contrast.air
            ids = ["template"] + [pid for pid, _ in self.poses]
            self._image_draws = [_draw_image(spec.seed, i, span) for i in range(len(ids))]
            self.acquisition["images"] = dict(zip(ids, self._image_draws))

    # -- poses --------------------------------------------------------------------------
    def _make_poses(self) -> list[tuple[str, dict]]:
        if self.spec.poses is not None:
            known = set(self.skeleton.joint_names)
            out = []
            for pid, angles in self.spec.poses:
                unknown = set(angles) - known
                if unknown:
                    raise ValueError(
                        f"pose {pid!r}: unknown joints {sorted(unknown)}; "
                        f"the {self.spec.region} skeleton has {sorted(known)}"
                    )
                full = self.region.complete_angles(angles)
                try:
                    self.skeleton.forward_kinematics(full)
                except ValueError as e:
                    raise ValueError(f"pose {pid!r}: {e}") from e
                outside = self.skeleton.limit_problems(full)
                if outside:
                    more = f" (and {len(outside) - 1} more)" if len(outside) > 1 else ""
                    raise ValueError(
                        f"pose {pid!r}: {outside[0]}{more}, the {self.spec.region} skeleton's range "
                        "of motion; give angles within it"
                    )
                out.append((str(pid), full))
            return out
        n = self.spec.n_poses or self.region.DEFAULT_POSES
        rng = np.random.default_rng(self._pose_seq)
        return [(f"pose{i:02d}", a) for i, a in enumerate(self.region.default_poses(n, rng))]

    # -- images -------------------------------------------------------------------------
    def _world_points(self) -> np.ndarray:
        """World position of every voxel centre, flat ``(n, 3)`` (computed once; read-only)."""
        if getattr(self, "_x", None) is None:
            self._x = self.geometry.world_coordinates().reshape(-1, 3)
            self._x.setflags(write=False)
        return self._x

    def render(
        self, template_points: np.ndarray, *, scan_points: np.ndarray | None = None, pose: Pose | None = None
    ) -> np.ndarray:
        """Noise-free intensity at template positions (chunked).

        With ``scan_points`` and ``pose`` (a posed scan's voxel positions and
        its bone transforms), soft tissue is rendered at ``template_points``
        and each bone's blurred edge rigidly, in the bone's own frame (see
        :meth:`~validation.phantoms.anatomy.Anatomy.intensity`).
        """
        if scan_points is not None and pose is None:
            raise ValueError("render: scan_points need the pose whose bone transforms they were posed by")
        out = np.empty(template_points.shape[0])
        for sl in _chunks(len(out)):
            frames = None if scan_points is None else (scan_points[sl], pose.transforms)
            out[sl] = self.anatomy.intensity_fast(
                template_points[sl],
                self.contrast,
                edge_mm=self.edge_mm,
                texture=self.texture,
                bone_frames=frames,
                tissue=self.tissue,
            )
        return out

    def _bias_field(self, rng: np.random.Generator, amplitude: float | None = None) -> np.ndarray:
        """Smooth multiplicative bias on the grid (scanner frame), mean ≈ 1, ``max |bias − 1|`` = ``amplitude``
        (default: the contrast's)."""
        amp = self.contrast.bias_amplitude if amplitude is None else amplitude
        if amp == 0:
            return np.ones(self.geometry.array_shape)
        nz, ny, nx = self.geometry.array_shape
        axes = [np.linspace(-1, 1, n) for n in (nz, ny, nx)]
        field_ = np.zeros((nz, ny, nx))
        for _ in range(4):
            f = rng.uniform(0.2, 0.7, size=3)
            ph = rng.uniform(0, 2 * np.pi, size=3)
            w = rng.normal()
            field_ += (
                w
                * np.cos(np.pi * f[0] * axes[0] + ph[0])[:, None, None]
                * np.cos(np.pi * f[1] * axes[1] + ph[1])[None, :, None]
                * np.cos(np.pi * f[2] * axes[2] + ph[2])[None, None, :]
            )
        field_ /= max(np.abs(field_).max(), 1e-12)
        return 1.0 + amp * field_

    def _acquire(self, clean: np.ndarray, rng: np.random.Generator, image: int = 0) -> np.ndarray:
        """Bias field and noise of a scanner acquisition (Rician for MRI, Gaussian for CT); with
        ``acquisition="random"``, image ``image``'s drawn one (:meth:`_acquire_drawn`)."""
        if not self.spec.noise:
            return clean.astype(np.float32)
        if self.acquisition is not None:
            return self._acquire_drawn(clean, rng, image)
        c = self.contrast
        img = clean - c.air
        img = img * self._bias_field(rng)
        if c.noise == "rician":
            img = np.hypot(img + rng.normal(0, c.noise_sigma, img.shape), rng.normal(0, c.noise_sigma, img.shape))
        else:
            img = img + rng.normal(0, c.noise_sigma, img.shape)
        return (img + c.air).astype(np.float32)

    def _acquire_drawn(self, clean: np.ndarray, rng: np.random.Generator, image: int) -> np.ndarray:
        """``air + offset + noise(gain · bias · (clean − air))`` with image ``image``'s drawn parameters;
        the bias field is drawn first from ``rng``, then the noise (as :meth:`_acquire` does)."""
        a = self._image_draws[image]
        air = self.contrast.air
        img = (clean - air) * (a["gain"] * self._bias_field(rng, a["bias_amplitude"]))
        sigma = a["noise_sigma"]
        if a["noise"] == "rician":
            img = np.hypot(img + rng.normal(0, sigma, img.shape), rng.normal(0, sigma, img.shape))
        else:
            img = img + rng.normal(0, sigma, img.shape)
        return (img + (air + a["offset"])).astype(np.float32)

    def bias_field(self, image: int) -> np.ndarray:
        """The multiplicative bias field image ``image`` (0: the template, 1 + i: scan i) was acquired with,
        ``(nz, ny, nx)``; ones with ``noise=False``.  Redrawn from the image's noise/bias stream."""
        if not self.spec.noise:
            return np.ones(self.geometry.array_shape)
        amp = None if self.acquisition is None else self._image_draws[image]["bias_amplitude"]
        return self._bias_field(np.random.default_rng(self._image_seqs[image]), amp)

    def template(self, grid: GridGeometry | None = None) -> tuple[Volume, Volume]:
        """``(template image, bone label map)`` on the template grid, or on ``grid``: another placement of a grid
        of the same size (e.g. moved by a fraction of a voxel, so that the scans do not share its lattice), with
        the same acquisition draws."""
        g = self.geometry if grid is None else grid
        if g.array_shape != self.geometry.array_shape:
            raise ValueError(
                f"grid {g.describe()}: the template's grid has {self.geometry.array_shape} voxels "
                "(z, y, x); give a grid of that size"
            )
        p = self._world_points() if grid is None else g.world_coordinates().reshape(-1, 3)
        clean = self.render(p).reshape(g.array_shape)
        labels = _apply_chunked(self._labels, p, dtype=np.uint8).reshape(g.array_shape)
        rng = np.random.default_rng(self._image_seqs[0])
        img = self._acquire(clean, rng)
        return Volume(img, g), Volume(labels, g)

    def _template_body_distance(self) -> np.ndarray:
        """Body distance at every template voxel (flat, cached)."""
        if getattr(self, "_tpl_body", None) is None:
            self._tpl_body = self.anatomy.distances_fast(self._world_points())[:, -1]
        return self._tpl_body

    def _labels(self, p: np.ndarray) -> np.ndarray:
        d = self.anatomy.distances_fast(p)[:, :-1]
        idx = np.argmin(d, axis=1)
        lab = np.array([self.skeleton.label_of(n) for n in self.anatomy.bone_names], dtype=np.uint8)[idx]
        return np.where(d[np.arange(len(idx)), idx] < 0, lab, 0)

    # -- posed scans ----------------------------------------------------------------------
    def pose_of(self, angles: dict) -> Pose:
        return self.skeleton.pose(angles)

    def posing_model(self, angles: dict, *, mode: str | None = None) -> PosingModel:
        pose = self.pose_of(angles)
        return PosingModel(self.anatomy, pose.transforms, angles, mode=mode or self.spec.posing, residual=self.residual)

    def correspondence(self, model: PosingModel) -> tuple[np.ndarray, np.ndarray]:
        """Template position of every scan voxel ``(nz, ny, nx, 3)`` and the inversion residual (mm).

        Near the posed body Newton starts from the inverse blend, and voxels it does not
        solve (near folds of the blend) restart from the nearest forward-mapped
        template voxels: there the residual ends below 1e-4 mm but for a handful
        of voxels in folds.  Far air (whose inverse blend lands more than 5 voxels
        + 10 mm from the template body) keeps the inverse blend as it is: Newton
        there would cost most of the time, and it stays air either way.  The scan
        is rendered from this field, so image and field agree everywhere; the
        residual says where the field is not the posing model's exact inverse.
        """
        from scipy.spatial import cKDTree

        x = self._world_points()
        h = max(self.geometry.spacing)
        fwd = model.forward(x)  # every template voxel, mapped into the scan
        tree = cKDTree(fwd)
        phi, res = model.inverse(x, max_iter=0)  # the inverse blend, for every voxel
        # Near the posed body: the inverse blend lands within 5 voxels + 10 mm of the template
        # body, or a forward-mapped template body voxel lies within 5 voxels.
        near = self.anatomy.distances_fast(phi)[:, -1] < 5.0 * h + 10.0
        body_fwd = fwd[self._template_body_distance() < 2.0 * h]
        if len(body_fwd):
            dist, _ = cKDTree(body_fwd).query(x[~near], distance_upper_bound=5.0 * h, workers=-1)
            near[np.nonzero(~near)[0][np.isfinite(dist)]] = True
        idx = np.nonzero(near)[0]
        phi[idx], res[idx] = model.inverse(x[idx], guess=phi[idx], max_iter=40)
        bad = idx[res[idx] > 1e-4]
        if bad.size:
            _, nn = tree.query(x[bad], k=RESTARTS, workers=-1)
            for r in range(RESTARTS):
                p2, r2 = model.inverse(x[bad], guess=x[nn[:, r]], fd_jacobian=True, max_iter=30)
                better = r2 < res[bad]
                phi[bad[better]], res[bad[better]] = p2[better], r2[better]
                keep = res[bad] > 1e-4
                bad, nn = bad[keep], nn[keep]
                if not bad.size:
                    break
        shape = self.geometry.array_shape
        return phi.reshape(shape + (3,)), res.reshape(shape)

    def markers(self, model: PosingModel, *, n: int = N_MARKERS, sample: int = 0) -> list[dict]:
        """Skin markers: template points on the skin near the joints, and their scan points ``F(p)``.

        ``sample`` 0 is the study's markers (:meth:`template_markers`); another ``sample`` number draws ``n``
        more by the same rule from a stream of its own (e.g. a few hundred, to measure what the study's dozen
        estimate without its sampling noise)."""
        pts = self.template_markers(n=n, sample=sample)
        scan_pts = model.forward(pts)
        return [
            {"name": f"m{i + 1:02d}", "template": pts[i].tolist(), "scan": scan_pts[i].tolist()}
            for i in range(len(pts))
        ]

    def template_markers(self, *, n: int = N_MARKERS, sample: int = 0) -> np.ndarray:
        """The study's skin markers in the template, the same for every scan (seeded).

        ``sample`` > 0: an independent draw of ``n`` markers by the same rule (its own random stream, derived
        from the markers' one).

        Candidates are drawn around the soft-tissue joints, projected onto the
        skin (body distance 0) and kept only if, in *every* pose, their scan
        position lies inside the grid and the inverse map at that position
        returns them — i.e. they are not where posed tissue overlaps other
        tissue, so the correspondence field and the markers agree.
        """
        drawn = self.__dict__.setdefault("_marker_draws", {})
        if (n, sample) in drawn:
            return drawn[n, sample]
        seq = self._marker_seq
        rng = np.random.default_rng(
            seq if sample == 0 else np.random.SeedSequence(seq.entropy, spawn_key=tuple(seq.spawn_key) + (int(sample),))
        )
        models = [self.posing_model(a) for _, a in self.poses]
        sk = self.skeleton
        joints = list(self.anatomy.joint_radius_mm)
        pts, tries = [], 0
        while len(pts) < n and tries < 40 * n:
            j = sk.joint(joints[tries % len(joints)])
            tries += 1
            radius = self.anatomy.joint_radius_mm[j.name]
            a = rng.uniform(0, 2 * np.pi)
            along = rng.normal(0, 0.5) * radius
            dirn = np.cos(a) * j.axes[:, 0] + np.sin(a) * j.axes[:, 1]
            p = self._project_to_skin(np.asarray(j.center) + along * j.axes[:, 2] + dirn * radius)
            if p is None or not self.geometry.contains_world(p, margin_voxels=-2):
                continue
            if np.min(self.anatomy.bone_distances(p[None])) < 2.0:
                continue
            ok = True
            for m in models:
                q = m.forward(p[None])
                back, res = m.inverse(q)
                if (
                    not self.geometry.contains_world(q[0], margin_voxels=-2)
                    or res[0] > 1e-6
                    or np.linalg.norm(back[0] - p) > 1e-4
                    or not self._unfolded_around(m, q[0], p)
                ):
                    ok = False
                    break
            if ok:
                pts.append(p)
        if len(pts) < 8:
            raise ValueError(
                f"could only place {len(pts)} skin markers outside folds and inside the field of "
                "view in every pose (need 8); use milder joint angles or fewer extreme poses"
            )
        drawn[n, sample] = np.array(pts)
        return drawn[n, sample]

    def _unfolded_around(self, model: PosingModel, q: np.ndarray, p: np.ndarray) -> bool:
        """True when the scan voxels around ``q`` map back next to ``p`` on one branch of ``F⁻¹``.

        Where posed tissue folds over or touches other tissue (a crease),
        ``F`` is not one-to-one and the correspondence jumps between voxels;
        a marker there would be ill-defined, as one in a skin fold would be.
        """
        g = self.geometry
        base = np.floor(g.world_to_index(q)).astype(int)
        corners = np.array([[i, j, k] for k in (-1, 0, 1, 2) for j in (-1, 0, 1, 2) for i in (-1, 0, 1, 2)]) + base
        pts = g.index_to_world(corners)
        back, res = model.inverse(pts)
        reach = 3.0 * float(np.linalg.norm(g.spacing))
        if np.any(res > 1e-6) or np.any(np.linalg.norm(back - p, axis=1) > reach):
            return False
        det = np.linalg.det(np.stack([back[1] - back[0], back[4] - back[0], back[16] - back[0]], axis=1))
        return bool(det * np.linalg.det(g.direction_matrix) > 0)  # index-space orientation → world

    def _project_to_skin(self, p):
        body = self.anatomy.body_distance
        h = 1e-4
        for _ in range(50):
            d = body(p[None])[0]
            g = np.array([(body((p + h * e)[None])[0] - body((p - h * e)[None])[0]) / (2 * h) for e in np.eye(3)])
            gn = g @ g
            if gn < 1e-12:
                return None
            p = p - d * g / gn
            if abs(d) < 1e-9:
                return p
        return p if abs(body(p[None])[0]) < 1e-6 else None

    def posing_difference(self, angles: dict) -> dict:
        """How far ``soft`` posing puts tissue from where ``vbd`` posing puts it, for one pose.

        Both correspondences are computed on the scan grid; the difference
        ``|φ_soft(x) − φ_vbd(x)|`` (template mm) is summarised over soft tissue
        near the joints (template position inside the body, ≥ 1 mm from every
        bone, within 1.5 soft radii of a flexed joint) and over bone voxels.
        Voxels where either inversion did not converge are left out.
        """
        phis, res = {}, {}
        for mode in ("soft", "vbd"):
            phi, r = self.correspondence(self.posing_model(angles, mode=mode))
            phis[mode], res[mode] = phi.reshape(-1, 3), r.reshape(-1)
        ok = (res["soft"] < 1e-4) & (res["vbd"] < 1e-4)
        d = self.anatomy.distances_fast(phis["soft"])
        near = np.zeros(len(d), bool)
        for j, radius in self.anatomy.joint_radius_mm.items():
            if np.asarray(angles.get(j, [0.0]))[0] != 0.0:
                c = np.asarray(self.skeleton.joint(j).center)
                near |= np.linalg.norm(phis["soft"] - c, axis=1) < 1.5 * radius
        soft = ok & near & (d[:, -1] < 0) & (d[:, :-1].min(axis=1) > 1.0)
        bone = ok & (d[:, :-1].min(axis=1) < -0.5)
        diff = np.linalg.norm(phis["soft"] - phis["vbd"], axis=1)
        return {
            "soft_tissue_near_joints_mean_mm": float(diff[soft].mean()) if soft.any() else 0.0,
            "soft_tissue_near_joints_p95_mm": float(np.percentile(diff[soft], 95)) if soft.any() else 0.0,
            "soft_tissue_near_joints_max_mm": float(diff[soft].max()) if soft.any() else 0.0,
            "soft_tissue_voxels": int(soft.sum()),
            "bone_max_mm": float(diff[bone].max()) if bone.any() else 0.0,
        }

    def scans(self) -> Iterator[PhantomScan]:
        """Posed scans with ground truth, one at a time."""
        for i, (pid, angles) in enumerate(self.poses):
            yield self.make_scan(i, pid, angles)

    def make_scan(self, index: int, pid: str, angles: dict, *, mode: str | None = None) -> PhantomScan:
        """Posed scan ``index`` (its noise stream) for joint ``angles``, with its ground truth."""
        model = self.posing_model(angles, mode=mode)
        pose = self.pose_of(angles)
        phi, residual = self.correspondence(model)
        if model.mode == "vbd":
            # Rhee's Table 2 target: the template image deformed by VBD, halo and all.
            clean = self.render(phi.reshape(-1, 3))
        else:
            # An acquisition of the posed body: bones' edges blurred where the bones are (Anatomy.intensity).
            clean = self.render(phi.reshape(-1, 3), scan_points=self._world_points(), pose=pose)
        clean = clean.reshape(self.geometry.array_shape)
        rng = np.random.default_rng(self._image_seqs[index + 1])
        img = self._acquire(clean, rng, index + 1)
        x = self._world_points().reshape(phi.shape)
        disp = phi - x
        body = self.anatomy.distances_fast(phi.reshape(-1, 3))[:, -1].reshape(residual.shape) < 0
        det = jacobian_determinant(Volume(disp, self.geometry))  # of the scan → template map, on the scan grid
        rb = residual[body]
        stats = {
            "body_voxels": int(body.sum()),
            "max_displacement_mm": float(np.linalg.norm(disp, axis=-1)[body].max()) if body.any() else 0.0,
            "inverse_residual_body_p99_mm": float(np.percentile(rb, 99)) if rb.size else 0.0,
            "inverse_residual_body_max_mm": float(rb.max()) if rb.size else 0.0,
            "unconverged_body_voxels": int(np.count_nonzero(rb > 1e-3)),
            "unsolved_voxels_all": int(np.count_nonzero(residual > 1e-4)),  # mostly far air (see correspondence)
            "folded_fraction_body": float(np.mean(det[body] <= 0)) if body.any() else 0.0,
            "jacobian_body_p1_p99": [float(v) for v in np.percentile(det[body], [1, 99])] if body.any() else [],
        }
        xt = self._world_points()
        forward = (model.forward(xt) - xt).reshape(self.geometry.array_shape + (3,))
        return PhantomScan(
            id=pid,
            image=Volume(img, self.geometry),
            pose=pose,
            correspondence=Volume(disp, self.geometry),
            markers=self.markers(model),
            stats=stats,
            template_to_scan=Volume(forward.astype(np.float32), self.geometry),
        )


def make_phantom(region: str = "knee", **kwargs) -> Phantom:
    """Convenience constructor: ``make_phantom("hand", size="test", seed=1)``."""
    return Phantom(PhantomSpec(region=region, **kwargs))
