"""Locally adaptive non-rigid volume registration (Rhee et al. 2011, §4, Algorithm 1).

The template (``moving``, optionally initialised by VBD) is registered to a
scan (``fixed``) by intensity alone, a few degrees of freedom at a time: on a
hierarchy of blocks, the most mismatched block (normalised MI on coarse
levels, SSD on fine ones: Rhee Eqs. 4–5, §4.1) takes one local step, a
biharmonic clamped plate spline through 8 control points (§4.2), optimised by
an NLopt derivative-free method over the block's neighbourhood through the
running deformation (§4.3), checked for folding and *composed* into the
running ``scan_to_template`` field.  :func:`register_adaptive` describes each
part; the measurements behind :class:`AdaptiveSettings` are in
``docs/measurements/pose-and-initialisation.md`` and
``docs/measurements/registration-settings.md``.

Serial, so that a seed gives the same field to the last bit.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import nlopt
import numba
import numpy as np

from deformation.fields.displacement import folding_statistics
from deformation.fields.interpolate import sample_array
from deformation.fields.splines import cps_green, cps_green_gradient
from deformation.filters import smooth
from deformation.geometry import GridGeometry, Volume

from .metrics import (
    MI_BINS,
    HistogramBins,
    accumulate_joint_histogram,
    air_level,
    block_statistics,
    entropies,
    similarity,
)

__all__ = [
    "AdaptiveSettings",
    "AdaptiveResult",
    "StepRecord",
    "LevelRecord",
    "register_adaptive",
    "register_block",
    "block_layout",
    "step_control_points",
    "control_points_from_log",
    "local_step_basis",
    "OPTIMIZERS",
    "BlockLevel",
    "BlockRegistration",
    "control_points_unit",
    "neg_mi_cost",
    "ssd_cost",
]


#: NLopt derivative-free algorithms a step may use (the paper: Nelder–Mead).
OPTIMIZERS = {
    "neldermead": nlopt.LN_NELDERMEAD,
    "sbplx": nlopt.LN_SBPLX,
    "bobyqa": nlopt.LN_BOBYQA,
    "cobyla": nlopt.LN_COBYLA,
}
METRICS = ("auto", "ssd", "mi")


@dataclass(frozen=True)
class AdaptiveSettings:
    """Parameters of the locally adaptive registration (defaults: the paper's where it gives them)."""

    levels: tuple = (1, 4)  #: first and last block level (inclusive; Rhee used 3–5, see :meth:`paper`)
    metric: str = "auto"  #: "auto" = normalised MI below ``ssd_from_level``, SSD from it (Rhee §4.1); "ssd"; "mi"
    ssd_from_level: int = 4  #: the paper switches from MI (≈32³ blocks) to SSD (≈16³ blocks)
    tolerance_factor: float = 3.0  #: Rhee §6.1 used ≈ 1.5 × the base MI
    bins: int = MI_BINS  #: MI histogram bins (nats)
    optimizer: str = "bobyqa"  #: key of :data:`OPTIMIZERS` (Rhee: Nelder–Mead)
    restarts: int = 1  #: random restarts of the simplex after the first run from zero
    max_evals: int = 1500  #: evaluations per simplex run
    ftol_rel: float = 1e-6  #: the simplex stops when an iteration changes the cost by less than this fraction
    initial_step: float = 0.5  #: simplex's initial step, in voxels (of the largest spacing)
    max_displacement: float = 0.5  #: bound on each control displacement, in block sizes (smallest axis)
    min_jacobian: float = 0.25  #: smallest det(I + ∇u) a step may have (0 would be a fold)
    min_improvement: float = 0.001  #: relative decrease of the region's cost a step must reach to count
    max_visits: int = 6  #: steps per block and level before the block is retired
    max_steps_per_level: int | None = 200  #: budget per level (None: until no block is mismatched)
    min_block_voxels: int = 4  #: blocks are never smaller than this many voxels a side
    eval_voxels: int = 6  #: samples per block side in the cost (coarser levels are smoothed and strided)
    regularization: float = 1.0  #: weight of the spline's bending energy against the relative data cost (0: none)
    inset: float = 0.25  #: control points this fraction of the half-block inside the block's corners
    fix_bones: bool = True  #: zero-displacement control points on bone voxels (when a bone mask is given)
    max_fixed_points: int = 4  #: Rhee: "potentially a few more points (less than 4 × 3)"
    active_fraction: float = 0.05  #: a block takes part when this fraction of it is tissue (either image)
    seed: int = 0

    def __post_init__(self):
        lv = tuple(int(v) for v in self.levels)
        if len(lv) != 2 or lv[0] < 0 or lv[1] < lv[0] or lv[1] > 8:
            raise ValueError(f"levels must be (first, last) with 0 ≤ first ≤ last ≤ 8, got {self.levels!r}")
        object.__setattr__(self, "levels", lv)
        if self.metric not in METRICS:
            raise ValueError(f"metric must be one of {METRICS}, got {self.metric!r}")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {sorted(OPTIMIZERS)}, got {self.optimizer!r}")
        if not self.tolerance_factor > 0:
            raise ValueError(f"tolerance_factor must be positive, got {self.tolerance_factor}")
        if not 0 <= self.min_jacobian < 1:
            raise ValueError(f"min_jacobian must be in [0, 1), got {self.min_jacobian}")
        if not 0 < self.ftol_rel < 1:
            raise ValueError(f"ftol_rel must be in (0, 1), got {self.ftol_rel}")
        if not 0 < self.inset < 1:
            raise ValueError(f"inset must be in (0, 1), got {self.inset}")
        for name in ("restarts", "max_visits", "max_fixed_points"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be ≥ 0, got {getattr(self, name)}")
        for name in ("max_evals", "min_block_voxels", "eval_voxels", "bins"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be ≥ 1, got {getattr(self, name)}")
        if self.max_steps_per_level is not None and self.max_steps_per_level < 0:
            raise ValueError(f"max_steps_per_level must be ≥ 0 or None, got {self.max_steps_per_level}")

    @classmethod
    def paper(cls, **overrides) -> AdaptiveSettings:
        """Rhee et al. 2011 as published: levels 3–5, Nelder–Mead, tolerance 1.5 × base, no regulariser."""
        d = dict(
            levels=(3, 5),
            optimizer="neldermead",
            tolerance_factor=1.5,
            regularization=0.0,
            max_visits=3,
            min_improvement=0.005,
            eval_voxels=10,
        )
        d.update(overrides)
        return cls(**d)

    @classmethod
    def initialised(cls, **overrides) -> AdaptiveSettings:
        """Ours after an articulated (VBD) initialisation: the large motion is done, so only small, sure
        steps are wanted:

        * start at level 3 and regularise harder (λ = 3): finer starts and a weaker λ moved
          well-initialised soft tissue away from the truth;
        * no restarts: they changed nothing but the number of evaluations;
        * a step must improve its region's cost by 1 % (``min_improvement``, 0.1 % by default) and the
          simplex stops at a relative cost change of 1e-4 (``ftol_rel``, 1e-6 by default): started from
          the ground truth, every intensity registration drifts off it, and the many steps that gain
          < 1 % follow noise and resampling error, not anatomy.

        The measurements: docs/measurements/pose-and-initialisation.md.
        """
        d = dict(levels=(3, 4), regularization=3.0, restarts=0, min_improvement=0.01, ftol_rel=1e-4)
        d.update(overrides)
        return cls(**d)

    def metric_at(self, level: int) -> str:
        if self.metric != "auto":
            return self.metric
        return "mi" if level < self.ssd_from_level else "ssd"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["levels"] = list(self.levels)
        return d


@dataclass
class StepRecord:
    """One local step (Algorithm 1, lines 5–10)."""

    level: int
    block: tuple  #: block index (i, j, k) along x, y, z
    metric: str
    block_before: float  #: the block's NMI or SSD before the step
    block_after: float
    region_before: float  #: the cost (SSD or −MI) over the 3×3×3 region
    region_after: float
    evaluations: int
    accepted: bool
    fixed_points: int
    max_displacement_mm: float
    min_jacobian: float
    seconds: float

    def to_dict(self) -> dict:
        d = asdict(self)
        d["block"] = list(self.block)
        return d


@dataclass
class LevelRecord:
    """What one block level did (a per-level log)."""

    level: int
    blocks: tuple  #: blocks along x, y, z
    block_voxels: tuple  #: voxels per block along x, y, z (approximate at the edges)
    stride: tuple  #: cost sampling stride along x, y, z (multi-resolution)
    metric: str
    tolerance: float
    active_blocks: int
    mismatched_before: int
    mismatched_after: int
    blocks_visited: int
    steps: int
    accepted: int
    control_points: int
    metric_before: float  #: the level's measure over the whole volume (NMI or SSD)
    metric_after: float
    evaluations: int
    seconds: float
    stopped: str  #: "tolerance" (no mismatched block left), "exhausted" (none could improve), "budget"

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("blocks", "block_voxels", "stride"):
            d[k] = list(d[k])
        return d


@dataclass
class AdaptiveResult:
    """The registration: ``correspondence`` is ``scan_to_template`` (mm) on the scan grid."""

    correspondence: Volume
    registered: Volume
    levels: list
    steps: list
    settings: AdaptiveSettings
    seconds: float
    similarity_before: dict
    similarity_after: dict
    folding: dict = field(default_factory=dict)

    @property
    def control_points(self) -> int:
        """Control points allocated by accepted steps (8 per step; the paper counts these)."""
        return sum(lv.control_points for lv in self.levels)

    @property
    def evaluations(self) -> int:
        return sum(lv.evaluations for lv in self.levels)

    def log(self) -> dict:
        return {
            "settings": self.settings.to_dict(),
            "seconds": round(self.seconds, 3),
            "control_points": self.control_points,
            "evaluations": self.evaluations,
            "similarity_before": self.similarity_before,
            "similarity_after": self.similarity_after,
            "folding": self.folding,
            "levels": [lv.to_dict() for lv in self.levels],
            "steps": [s.to_dict() for s in self.steps],
        }


# -- geometry of the hierarchy ------------------------------------------------------------------------
def block_layout(shape_zyx, level: int, min_block_voxels: int = 4) -> list[np.ndarray]:
    """Block edges along x, y, z (voxel indices, ``n + 1`` each) at block ``level``.

    ``2**level`` blocks along each axis, fewer where that would make blocks
    smaller than ``min_block_voxels`` voxels (at least one block).
    """
    out = []
    for n in (shape_zyx[2], shape_zyx[1], shape_zyx[0]):
        nb = max(1, min(2**level, n // max(1, min_block_voxels)))
        out.append(np.round(np.linspace(0, n, nb + 1)).astype(np.int64))
    return out


def step_control_points(shape_zyx, level: int, block, *, inset: float = 0.25, min_block_voxels: int = 4) -> np.ndarray:
    """The 8 moving control points of a step on ``block`` (i, j, k) at ``level``: index coordinates (x, y, z).

    Rhee §4.3: a 2×2×2 pattern ``inset`` of the half-block inside the
    block's corners — the points ``BlockRegistration._step`` places in
    region-unit coordinates (``control_points_unit``; the region is
    the 3×3×3 blocks, half-extent 1.5 blocks), mapped back to voxel indices.
    """
    _, _, centre, half = _block_frame(block_layout(shape_zyx, level, min_block_voxels), block)
    return centre + control_points_unit(inset) * half


def _block_frame(edges, block):
    """``(lo, hi, centre, half)`` of ``block`` (i, j, k), index space x y z: the block's voxel range, its
    centre and the half-extent of its 3×3×3 region — the frame of region-unit coordinates (§4.3)."""
    lo = np.array([edges[a][int(block[a])] for a in range(3)], float)
    hi = np.array([edges[a][int(block[a]) + 1] for a in range(3)], float)
    return lo, hi, (lo + hi - 1.0) / 2.0, 1.5 * (hi - lo)


def control_points_from_log(log: dict, geometry) -> list[tuple[int, np.ndarray]]:
    """``[(level, world points (8, 3) mm), ...]`` of every accepted step in a registration log (``result.log()``).

    ``geometry`` is the grid the registration ran on (the scan's).  This is
    what Rhee's Fig. 9 draws: the control points allocated per block level.
    """
    st = log["settings"]
    shape = geometry.array_shape
    out = []
    for step in log["steps"]:
        if step["accepted"]:
            ijk = step_control_points(
                shape, step["level"], step["block"], inset=st["inset"], min_block_voxels=st["min_block_voxels"]
            )
            out.append((int(step["level"]), np.asarray(geometry.index_to_world(ijk))))
    return out


def _block_ids(shape_zyx, edges) -> np.ndarray:
    ex, ey, ez = edges
    ix = np.searchsorted(ex, np.arange(shape_zyx[2]), side="right") - 1
    iy = np.searchsorted(ey, np.arange(shape_zyx[1]), side="right") - 1
    iz = np.searchsorted(ez, np.arange(shape_zyx[0]), side="right") - 1
    nx, ny = len(ex) - 1, len(ey) - 1
    return ((iz[:, None, None] * ny + iy[None, :, None]) * nx + ix[None, None, :]).astype(np.int32)


def control_points_unit(inset: float) -> np.ndarray:
    """The 2×2×2 control points in region-unit coordinates: the block spans (−1/3, 1/3)³."""
    a = (1.0 / 3.0) * (1.0 - inset)
    return np.array([[x, y, z] for z in (-a, a) for y in (-a, a) for x in (-a, a)], float)


def local_step_basis(
    samples_unit,
    controls_unit,
    n_moving: int = 8,
    *,
    gradient: bool = False,
    h: float | None = None,
    values: bool = True,
):
    """Clamped-plate-spline basis of one local step (Rhee §4.2) in region-unit coordinates.

    Returns ``B (m, n_moving)`` with the displacement at sample ``p`` equal to
    ``B[p] @ d`` for the moving control points' displacements ``d``; the
    remaining control points (fixed, e.g. on bone) have zero displacement.
    With ``gradient=True`` also ``dB (m, 3, n_moving)``, the derivative of
    ``B`` along each unit axis: analytic (:func:`deformation.fields.splines.cps_green_gradient`), or central
    differences of step ``h`` when ``h`` is given.  ``values=False`` (with the analytic gradient) skips ``B``
    and returns ``(None, dB)``: the fold checks need only the gradient.
    """
    c = np.asarray(controls_unit, float)
    # B = K G⁻¹ restricted to the moving columns; G (≤ 12 × 12, symmetric positive definite) is inverted
    # once through its Cholesky factor, so each sample costs one small matrix product
    chol = np.linalg.cholesky(cps_green(c, c))
    linv = np.linalg.inv(chol)
    ginv_moving = np.ascontiguousarray((linv.T @ linv)[:, :n_moving])

    def basis(p):
        return cps_green(p, c) @ ginv_moving  # (m, n) @ (n, n_moving)

    s = np.asarray(samples_unit, float)
    if not values and (not gradient or h is not None):
        raise ValueError("local_step_basis: values=False needs gradient=True and the analytic gradient (h=None)")
    b = basis(s) if values else None
    if not gradient:
        return b
    if h is not None:  # central differences (the reference the analytic gradient is tested against)
        db = np.empty((s.shape[0], 3, n_moving))
        for a in range(3):
            e = np.zeros(3)
            e[a] = h
            db[:, a, :] = (basis(s + e) - basis(s - e)) / (2 * h)
        return b, db
    _, dg = cps_green_gradient(s, c)  # (m, n, 3)
    return b, np.ascontiguousarray(np.matmul(dg.transpose(0, 2, 1), ginv_moving))  # (m, 3, n_moving)


# -- compiled cost kernels -----------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True, inline="always")
def _trilinear_box(box, x, y, z):
    nz, ny, nx = box.shape
    x = min(max(x, 0.0), nx - 1.0)
    y = min(max(y, 0.0), ny - 1.0)
    z = min(max(z, 0.0), nz - 1.0)
    i = min(int(x), nx - 2) if nx > 1 else 0
    j = min(int(y), ny - 2) if ny > 1 else 0
    k = min(int(z), nz - 2) if nz > 1 else 0
    tx, ty, tz = x - i, y - j, z - k
    i1 = i + 1 if nx > 1 else i
    j1 = j + 1 if ny > 1 else j
    k1 = k + 1 if nz > 1 else k
    c00 = box[k, j, i] * (1 - tx) + box[k, j, i1] * tx
    c01 = box[k, j1, i] * (1 - tx) + box[k, j1, i1] * tx
    c10 = box[k1, j, i] * (1 - tx) + box[k1, j, i1] * tx
    c11 = box[k1, j1, i] * (1 - tx) + box[k1, j1, i1] * tx
    return (c00 * (1 - ty) + c01 * ty) * (1 - tz) + (c10 * (1 - ty) + c11 * ty) * tz


@numba.njit(cache=True, nogil=True)
def _min_jacobian(e, dB):
    """min over check points of det(I + Σ_k e_k ⊗ ∇B_k), index space; ``e (8, 3)``, ``dB (c, 3, 8)``.

    Nine scalar accumulators, no per-point array (the inner loop of every cost evaluation)."""
    best = 1e30
    nk = e.shape[0]
    for p in range(dB.shape[0]):
        a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = 0.0
        for k in range(nk):
            g0 = dB[p, 0, k]
            g1 = dB[p, 1, k]
            g2 = dB[p, 2, k]
            e0 = e[k, 0]
            e1 = e[k, 1]
            e2 = e[k, 2]
            a00 += e0 * g0
            a01 += e0 * g1
            a02 += e0 * g2
            a10 += e1 * g0
            a11 += e1 * g1
            a12 += e1 * g2
            a20 += e2 * g0
            a21 += e2 * g1
            a22 += e2 * g2
        a00 += 1.0
        a11 += 1.0
        a22 += 1.0
        det = a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20) + a02 * (a10 * a21 - a11 * a20)
        if det < best:
            best = det
    return best


@numba.njit(cache=True, nogil=True)
def _moved_values(e, B, base, box, out):
    """Registered image at each sample moved by ``u = B @ e`` (index units): ``out[p] = box(base[p] + u)``."""
    for p in range(B.shape[0]):
        ux = 0.0
        uy = 0.0
        uz = 0.0
        for k in range(B.shape[1]):
            w = B[p, k]
            ux += w * e[k, 0]
            uy += w * e[k, 1]
            uz += w * e[k, 2]
        out[p] = _trilinear_box(box, base[p, 0] + ux, base[p, 1] + uy, base[p, 2] + uz)


@numba.njit(cache=True, nogil=True)
def ssd_cost(e, B, base, box, fixed, buf):
    _moved_values(e, B, base, box, buf)
    acc = 0.0
    for p in range(buf.shape[0]):
        d = buf[p] - fixed[p]
        acc += d * d  # Rhee Eq. 4: Σ_i (I_s(v_i) − I_t(v_i))², then divided by n
    return acc / buf.shape[0]


@numba.njit(cache=True, nogil=True)
def neg_mi_cost(e, B, base, box, fixed_bin, lo, scale, bins, buf, hist):
    """−MI (nats): moving values triangular-binned, fixed values pre-binned (:mod:`registration.metrics`)."""
    _moved_values(e, B, base, box, buf)
    top = bins - 1.0
    for p in range(buf.shape[0]):  # value → continuous bin coordinate (HistogramBins.position)
        buf[p] = min(max((buf[p] - lo) * scale - 0.5, 0.0), top)
    hist[:, :] = 0.0
    accumulate_joint_histogram(buf, fixed_bin, bins, hist)
    ha, hb, hab = entropies(hist)
    return -(ha + hb - hab)  # −Rhee Eq. 5: −(H(V_s) + H(V_t) − H(V_s, V_t))


# -- the registration -----------------------------------------------------------------------------------
class BlockLevel:
    """Per-level images and block bookkeeping."""

    def __init__(self, reg: BlockRegistration, level: int):
        s = reg.settings
        self.level = level
        self.metric = s.metric_at(level)
        shape = reg.shape
        self.edges = block_layout(shape, level, s.min_block_voxels)
        self.nb = tuple(len(e) - 1 for e in self.edges)  # x, y, z
        self.ids = _block_ids(shape, self.edges)
        self.n_blocks = int(np.prod(self.nb))
        bsize = [float(np.max(np.diff(e))) for e in self.edges]
        self.block_voxels = tuple(int(round(b)) for b in bsize)
        self.stride = tuple(max(1, int(math.ceil(b / s.eval_voxels))) for b in bsize)
        if max(self.stride) > 1:  # multi-resolution: smooth to the sampling (σ = ½ stride, in mm)
            sig_f = [0.5 * st * sp if st > 1 else 0.0 for st, sp in zip(self.stride, reg.fixed.geometry.spacing)]
            sig_m = [0.5 * st * sp if st > 1 else 0.0 for st, sp in zip(self.stride, reg.moving.geometry.spacing)]
            # SimpleITK's recursive Gaussian, σ in mm along z, y, x (it takes no σ 0: 1e-6 mm on an unsmoothed axis)
            self.fixed = smooth(reg.fixed, [max(v, 1e-6) for v in sig_f[::-1]], units="mm", method="recursive").data
            self.moving = smooth(reg.moving, [max(v, 1e-6) for v in sig_m[::-1]], units="mm", method="recursive").data
        else:
            self.fixed = reg.fixed.data.astype(np.float32)
            self.moving = reg.moving.data.astype(np.float32)
        fg = reg.tissue_fixed.reshape(-1).astype(np.float64)
        self.tissue_fixed = np.bincount(self.ids.reshape(-1), weights=fg, minlength=self.n_blocks)
        self.count = np.bincount(self.ids.reshape(-1), minlength=self.n_blocks).astype(np.float64)


#: at most this many voxels of a step's ball get the step's own Jacobian check (more than a whole
#: test-size grid, so only paper-size coarse levels are subsampled)
_STEP_CHECK_MAX = 200_000


class BlockRegistration:
    def __init__(
        self,
        fixed: Volume,
        moving: Volume,
        initial: Volume | None,
        rigid: Volume | None,
        settings: AdaptiveSettings,
        progress,
    ):
        self.fixed, self.moving, self.settings = fixed, moving, settings
        self.progress = progress or (lambda info: None)
        g = fixed.geometry
        self.g = g
        self.shape = g.array_shape
        x = g.world_coordinates()
        if initial is None:
            self.disp = np.zeros(self.shape + (3,))
        else:
            g.check_same(
                initial.geometry,
                names=("fixed image", "initial correspondence"),
                remedy="give the initial scan → template field on the scan's grid",
            )
            self.disp = np.asarray(initial.data, np.float64).copy()
        self.x = x
        self.w2i_m = moving.geometry.world_to_index_matrix
        self.i2w = g.index_to_world_matrix
        self.w2i = g.world_to_index_matrix
        self.fill = air_level(moving)  # what lies beyond the template's field of view
        self.rigid = rigid
        if rigid is not None:
            moving.geometry.check_same(rigid.geometry, names=("moving image", "bone mask"))
        # tissue: half-way between air and tissue levels of the fixed image (as segmentation.segment_body)
        f = fixed.data
        lo, hi = np.percentile(f, [5, 95])
        self.tissue_level = 0.5 * (lo + hi) if hi > lo else hi
        self.tissue_fixed = f > self.tissue_level
        both = np.concatenate([f.ravel(), moving.data.ravel()])
        lo, hi = np.percentile(both, [0.1, 99.9])
        self.bins = HistogramBins(lo, hi, settings.bins)
        self.warped = self._warp_all(self.moving.data)
        self.steps: list[StepRecord] = []
        self.levels: list[LevelRecord] = []
        self.t0 = time.perf_counter()
        self.step_seconds: list[float] = []

    # -- the running deformation --
    def _positions(self, sl=None) -> np.ndarray:
        if sl is None:
            return self.x + self.disp
        return self.x[sl] + self.disp[sl]

    def _warp_all(self, data) -> np.ndarray:
        return sample_array(data, self.w2i_m, self._positions(), 1, self.fill).astype(np.float32)

    def _warp_box(self, data, sl) -> np.ndarray:
        return sample_array(data, self.w2i_m, self._positions(sl), 1, self.fill).astype(np.float32)

    # -- block measures --
    def block_measures(self, lv: BlockLevel, blocks=None) -> dict:
        if blocks is None:
            st = block_statistics(self.fixed.data, self.warped, lv.ids, lv.n_blocks, self.bins, self.bins)
            return st
        # recompute only the given blocks (those a step touched) on the box that holds them, numbered
        # locally, so a step costs O(its neighbourhood) and not O(grid × blocks × bins²)
        blocks = np.asarray(blocks, np.int64)
        nx, ny, _ = lv.nb
        bi = np.stack([blocks % nx, (blocks // nx) % ny, blocks // (nx * ny)], axis=1)  # x y z
        lo = [lv.edges[a][bi[:, a].min()] for a in range(3)]
        hi = [lv.edges[a][bi[:, a].max() + 1] for a in range(3)]
        box = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
        local = np.full(lv.n_blocks, -1, np.int64)
        local[blocks] = np.arange(blocks.size)
        st = block_statistics(
            self.fixed.data[box], self.warped[box], local[lv.ids[box]], blocks.size, self.bins, self.bins
        )
        out = {}
        for key, v in st.items():
            full = np.full(lv.n_blocks, 0 if key == "count" else np.nan, dtype=v.dtype)
            full[blocks] = v
            out[key] = full
        return out

    def _whole(self, metric: str) -> float:
        if metric == "ssd":
            return float(np.mean((self.warped.astype(np.float64) - self.fixed.data) ** 2))  # Rhee Eq. 4 / n
        st = block_statistics(self.fixed.data, self.warped, np.zeros(self.shape, np.int32), 1, self.bins, self.bins)
        return float(st["nmi"][0])

    # -- one local step --
    def _step(self, lv: BlockLevel, block: int, step_no: int) -> StepRecord:
        s = self.settings
        t0 = time.perf_counter()
        nx, ny, _ = lv.nb
        bi = (block % nx, (block // nx) % ny, block // (nx * ny))  # x, y, z
        lo, hi, centre, half = _block_frame(lv.edges, bi)  # index space, x y z; half: the region's half-extent
        lo, hi = lo.astype(int), hi.astype(int)
        rlo = [max(0, lv.edges[a][max(bi[a] - 1, 0)]) for a in range(3)]
        rhi = [min(self.shape[2 - a], lv.edges[a][min(bi[a] + 2, len(lv.edges[a]) - 1)]) for a in range(3)]
        # cost samples: the region on the level's stride
        axes = [np.arange(rlo[a] + (lv.stride[a] - 1) // 2, rhi[a], lv.stride[a]) for a in range(3)]
        gz, gy, gx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        samp = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1).astype(np.float64)  # x y z index
        q = (samp - centre) / half
        inball = np.einsum("ij,ij->i", q, q) < 1.0
        controls = control_points_unit(s.inset)
        cache = []

        def ball():  # the ball's voxels and unit coordinates, computed once per step when first needed
            if not cache:
                cache.append(self._ball_voxels(centre, half, rlo, rhi))
            return cache[0]

        fixed_pts = (
            self._fixed_points(controls, ball())
            if (self.rigid is not None and s.fix_bones and s.max_fixed_points > 0)
            else np.zeros((0, 3))
        )
        all_controls = np.vstack([controls, fixed_pts])
        b = local_step_basis(q, all_controls, 8)
        b[~inball] = 0.0
        # check points for the fold test: at most ~1500 of the in-ball samples (the gradient only there)
        qin = q[inball]
        every = max(1, int(math.ceil(qin.shape[0] / 1500)))
        _, dbc = local_step_basis(qin[::every], all_controls, 8, gradient=True, values=False)
        dbc = np.ascontiguousarray(dbc / half[None, :, None])  # d/d(index) = d/dq / half
        # moving image of the level through the running deformation on the region's box (+ margin)
        lin = self.w2i[:3, :3]  # world mm → index offsets
        spacing_min = min(self.g.spacing)
        block_mm = min((hi[a] - lo[a]) * self.g.spacing[a] for a in range(3))
        bound = s.max_displacement * block_mm
        reach = bound * float(np.abs(b).sum(axis=1).max(initial=0.0)) * math.sqrt(3)
        margin = int(math.ceil(reach / spacing_min)) + 2
        blo = [max(0, rlo[a] - margin) for a in range(3)]
        bhi = [min(self.shape[2 - a], rhi[a] + margin) for a in range(3)]
        sl = (slice(blo[2], bhi[2]), slice(blo[1], bhi[1]), slice(blo[0], bhi[0]))
        box = self._warp_box(lv.moving, sl)
        base = samp - np.array(blo, float)
        fz = lv.fixed[samp[:, 2].astype(int), samp[:, 1].astype(int), samp[:, 0].astype(int)].astype(np.float64)
        buf = np.empty(samp.shape[0])
        metric = lv.metric
        if metric == "mi":
            fbin = self.bins.index(fz)
            hist = np.zeros((self.bins.bins, self.bins.bins))
            lo_v, sc, nbins = self.bins.lo, self.bins.scale, self.bins.bins

            def data_cost(e):
                return neg_mi_cost(e, b, base, box, fbin, lo_v, sc, nbins, buf, hist)
        else:

            def data_cost(e):
                return ssd_cost(e, b, base, box, fz, buf)

        zero = np.zeros((8, 3))
        c0 = data_cost(zero)
        norm = abs(c0) if c0 != 0 else 1.0
        # Bending energy of the clamped plate spline through the control points, Σ_c d_cᵀ (G⁻¹)_mm d_c
        # (G in region-unit coordinates; fixed points have d = 0), made dimensionless by the block size.
        ginv = np.linalg.inv(cps_green(all_controls, all_controls))[:8, :8]
        lam = s.regularization / (block_mm**2)
        counter = [0]

        def cost(xv, grad):
            counter[0] += 1
            d = xv.reshape(8, 3)
            e = d @ lin.T  # world mm → index units
            mj = _min_jacobian(e, dbc)
            if mj < s.min_jacobian:
                return 2.0 + 10.0 * (s.min_jacobian - mj)
            # Rhee Eq. 3: SM(V_s + D(V_s, c, f), V_t) over the block's region, D the CPS through the control
            # points c with displacements f = d; the bending-energy term (λ > 0) is ours, not in Rhee Eq. 3
            return data_cost(e) / norm + lam * float(np.einsum("kc,kl,lc->", d, ginv, d))

        rng = np.random.default_rng([s.seed, lv.level, step_no])
        step = s.initial_step * max(self.g.spacing)
        c0n = c0 / norm
        best_x, best_f = np.zeros(24), c0n
        for r in range(s.restarts + 1):
            x0 = best_x.copy() if r == 0 else np.clip(best_x + rng.uniform(-1, 1, 24) * 2 * step, -bound, bound)
            # Rhee Eq. 3's optimisation over f, the 8 control points' displacements (Rhee: Nelder–Mead)
            xr, fr = _run_simplex(s.optimizer, cost, x0, bound, step, s.max_evals, 0.01 * spacing_min, s.ftol_rel)
            if fr < best_f:
                best_x, best_f = xr, fr
        # verify on every voxel of the ball (full resolution) and accept
        accepted, d, mj_full = self._accept(
            best_x.reshape(8, 3), best_f * norm, c0, data_cost, lin, ball, all_controls, half
        )
        region_after = data_cost(d @ lin.T) if accepted else c0
        if accepted:
            accepted, mj_full = self._compose(d, all_controls, ball(), mj_full)
            if not accepted:
                region_after = c0
        rec = StepRecord(
            level=lv.level,
            block=tuple(int(v) for v in bi),
            metric=metric,
            block_before=math.nan,
            block_after=math.nan,
            region_before=float(c0),
            region_after=float(region_after),
            evaluations=counter[0],
            accepted=bool(accepted),
            fixed_points=int(fixed_pts.shape[0]),
            max_displacement_mm=float(np.linalg.norm(d, axis=1).max()) if accepted else 0.0,
            min_jacobian=float(mj_full),
            seconds=time.perf_counter() - t0,
        )
        return rec

    def _accept(self, d, best_f, c0, data_cost, lin, ball, controls, half):
        s = self.settings
        improved = (c0 - best_f) > s.min_improvement * abs(c0) if c0 != 0 else best_f < c0
        if not improved:
            return False, d, 1.0
        q = ball()[1]
        if q.shape[0] > _STEP_CHECK_MAX:
            # a paper-size level-1 ball holds millions of voxels: check the smooth step on an even subset;
            # the composed field is still checked on every voxel (_compose), so no fold can slip through
            q = q[:: int(math.ceil(q.shape[0] / _STEP_CHECK_MAX))]
        _, db = local_step_basis(q, controls, 8, gradient=True, values=False)
        db = db / half[None, :, None]
        for _ in range(4):
            mj = _min_jacobian(d @ lin.T, db)
            if mj > max(s.min_jacobian * 0.5, 1e-3):
                f = data_cost(d @ lin.T)
                if (c0 - f) > s.min_improvement * abs(c0):
                    return True, d, mj
                return False, d, mj
            d = 0.5 * d
        return False, d, mj

    def _ball_voxels(self, centre, half, rlo, rhi):
        axes = [np.arange(rlo[a], rhi[a]) for a in range(3)]
        gz, gy, gx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        vox = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1).astype(np.float64)
        q = (vox - centre) / half
        keep = np.einsum("ij,ij->i", q, q) < 1.0
        return vox[keep].astype(np.int64), q[keep]

    def _compose(self, d, controls, ball, mj_step):
        """φ ← φ ∘ U on the ball's voxels: new disp(y) = u(y) + disp(y + u(y)) (Algorithm 1, line 10).

        The composed field's Jacobian determinant (the finite differences of
        :func:`deformation.fields.displacement.jacobian_determinant`, the measure the
        folding statistics report) is checked on the ball's voxels: where the
        step would bring a voxel above ``min_jacobian / 4`` below it, or lower
        the ball's minimum when it is already below (a fold inherited from the
        initialisation), the step is undone.  Returns ``(accepted, min det of the composed field)``.
        """
        vox, q = ball
        b = local_step_basis(q, controls, 8)
        u = b @ d  # world mm
        iz, iy, ix = vox[:, 2], vox[:, 1], vox[:, 0]
        xw = self.x[iz, iy, ix]
        moved = xw + u
        # the running displacement at the moved points (SimpleITK boundary rule; identity beyond the grid)
        old = sample_array(self.disp, self.w2i, moved, 1, 0.0)
        lo = np.maximum(vox.min(axis=0) - 1, 0)
        hi = np.minimum(vox.max(axis=0) + 2, np.asarray(self.g.size))
        crop = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
        det_before = self._det(crop, lo)
        saved = self.disp[iz, iy, ix].copy()
        self.disp[iz, iy, ix] = u + old
        det_after = self._det(crop, lo)
        inside = np.zeros(det_after.shape, bool)
        inside[iz - lo[2], iy - lo[1], ix - lo[0]] = True
        floor = 0.25 * self.settings.min_jacobian
        before, after = det_before[inside], det_after[inside]
        mj = float(after.min())
        # reject a step that folds a voxel that was not folded, or deepens an inherited fold
        # (a VBD initialisation can bring folds: they must not spread)
        if np.any((after <= floor) & (before > floor)) or mj < min(float(before.min()), floor):
            self.disp[iz, iy, ix] = saved
            return False, mj
        newpos = moved + old
        self.warped[iz, iy, ix] = sample_array(self.moving.data, self.w2i_m, newpos, 1, self.fill)
        return True, min(mj, mj_step)

    def _det(self, crop, lo) -> np.ndarray:
        from deformation.fields.displacement import jacobian_determinant

        sub = self.disp[crop]
        geo = GridGeometry(
            tuple(int(v) for v in (sub.shape[2], sub.shape[1], sub.shape[0])),
            self.g.spacing,
            tuple(self.g.index_to_world(np.asarray(lo, float))),
            self.g.direction,
        )
        return jacobian_determinant(Volume(np.ascontiguousarray(sub), geo))

    def _fixed_points(self, controls, ball) -> np.ndarray:
        """Up to ``max_fixed_points`` bone voxels of the region (farthest-point order), in unit coordinates."""
        s = self.settings
        vox, qv = ball
        pos = self.x[vox[:, 2], vox[:, 1], vox[:, 0]] + self.disp[vox[:, 2], vox[:, 1], vox[:, 0]]
        lab = sample_array(self.rigid.data, self.w2i_m, pos, 0, 0)
        r = np.sqrt(np.einsum("ij,ij->i", qv, qv))
        near = np.min(np.linalg.norm(qv[:, None, :] - controls[None], axis=2), axis=1)
        cand = qv[(lab > 0) & (r < 0.85) & (near > 0.3)]
        if cand.shape[0] == 0:
            return np.zeros((0, 3))
        chosen = [cand[np.argmin(np.einsum("ij,ij->i", cand, cand))]]
        dist = np.linalg.norm(cand - chosen[0], axis=1)
        while len(chosen) < s.max_fixed_points:
            k = int(np.argmax(dist))
            if dist[k] < 0.3:
                break
            chosen.append(cand[k])
            dist = np.minimum(dist, np.linalg.norm(cand - cand[k], axis=1))
        return np.array(chosen)

    # -- Algorithm 1 --
    def run(self) -> AdaptiveResult:
        s = self.settings
        before = similarity(self.fixed.data, self.warped, bins=s.bins)
        base = {"mi": self._whole("mi"), "ssd": self._whole("ssd")}
        step_no = 0
        for level in range(s.levels[0], s.levels[1] + 1):
            lv = BlockLevel(self, level)
            t_level = time.perf_counter()
            metric = lv.metric
            tol = base["mi"] * s.tolerance_factor if metric == "mi" else base["ssd"] / s.tolerance_factor
            st = self.block_measures(lv)
            warped_tissue = np.bincount(
                lv.ids.reshape(-1), weights=(self.warped > self.tissue_level).reshape(-1), minlength=lv.n_blocks
            )
            active = np.maximum(lv.tissue_fixed, warped_tissue) >= s.active_fraction * np.maximum(lv.count, 1)
            value = st["nmi"] if metric == "mi" else st["ssd"]
            if metric == "mi":
                active &= np.isfinite(value)

            def mismatched(v):
                return active & ((v < tol) if metric == "mi" else (v > tol))

            mis0 = int(mismatched(value).sum())
            retired = np.zeros(lv.n_blocks, bool)
            visits = np.zeros(lv.n_blocks, np.int64)
            n_steps = n_acc = evals = 0
            visited = set()
            metric_before = self._whole(metric)
            stopped = "tolerance"
            while True:
                cand = mismatched(value) & ~retired
                if not cand.any():
                    stopped = "exhausted" if (mismatched(value)).any() else "tolerance"
                    break
                if s.max_steps_per_level is not None and n_steps >= s.max_steps_per_level:
                    stopped = "budget"
                    break
                score = np.where(cand, value if metric == "mi" else -value, np.inf)
                block = int(np.argmin(score))
                rec = self._step(lv, block, step_no)
                rec.block_before = float(value[block])
                step_no += 1
                n_steps += 1
                evals += rec.evaluations
                visits[block] += 1
                visited.add(block)
                # the step changed the 3×3×3 neighbourhood: refresh those blocks' measures
                touched = self.neighbours(lv, block)
                st2 = self.block_measures(lv, touched)
                v2 = st2["nmi"] if metric == "mi" else st2["ssd"]
                value[touched] = v2[touched]
                rec.block_after = float(value[block])
                if rec.accepted:
                    n_acc += 1
                if not rec.accepted or visits[block] >= s.max_visits:
                    retired[block] = True
                self.steps.append(rec)
                self.step_seconds.append(rec.seconds)
                remaining = int((mismatched(value) & ~retired).sum())
                if s.max_steps_per_level is not None:
                    remaining = min(remaining, s.max_steps_per_level - n_steps)
                self.progress(
                    {
                        "level": level,
                        "step": n_steps,
                        "block": rec.block,
                        "metric": metric,
                        "block_before": rec.block_before,
                        "block_after": rec.block_after,
                        "accepted": rec.accepted,
                        "elapsed": time.perf_counter() - self.t0,
                        "remaining_steps": remaining,
                        "eta": remaining * float(np.mean(self.step_seconds[-20:])),
                    }
                )
            self.levels.append(
                LevelRecord(
                    level=level,
                    blocks=lv.nb,
                    block_voxels=lv.block_voxels,
                    stride=lv.stride,
                    metric=metric,
                    tolerance=float(tol),
                    active_blocks=int(active.sum()),
                    mismatched_before=mis0,
                    mismatched_after=int(mismatched(value).sum()),
                    blocks_visited=len(visited),
                    steps=n_steps,
                    accepted=n_acc,
                    control_points=8 * n_acc,
                    metric_before=metric_before,
                    metric_after=self._whole(metric),
                    evaluations=evals,
                    seconds=time.perf_counter() - t_level,
                    stopped=stopped,
                )
            )
            self.progress({"level_done": self.levels[-1]})
        after = similarity(self.fixed.data, self.warped, bins=s.bins)
        corr = Volume(self.disp.astype(np.float32), self.g)
        return AdaptiveResult(
            correspondence=corr,
            registered=Volume(self.warped.copy(), self.g),
            levels=self.levels,
            steps=self.steps,
            settings=s,
            seconds=time.perf_counter() - self.t0,
            similarity_before=before,
            similarity_after=after,
            folding=folding_statistics(corr),
        )

    def neighbours(self, lv: BlockLevel, block: int) -> list[int]:
        nx, ny, nz = lv.nb
        bi = (block % nx, (block // nx) % ny, block // (nx * ny))
        out = []
        for dz in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    x, y, z = bi[0] + dx, bi[1] + dy, bi[2] + dz
                    if 0 <= x < nx and 0 <= y < ny and 0 <= z < nz:
                        out.append((z * ny + y) * nx + x)
        return out


def _run_simplex(name, cost, x0, bound, step, max_evals, xtol, ftol_rel=1e-6):
    opt = nlopt.opt(OPTIMIZERS[name], x0.size)
    opt.set_lower_bounds(np.full(x0.size, -bound))
    opt.set_upper_bounds(np.full(x0.size, bound))
    opt.set_initial_step(np.full(x0.size, min(step, bound)))
    opt.set_maxeval(int(max_evals))
    opt.set_xtol_abs(xtol)
    opt.set_ftol_rel(ftol_rel)
    best = [np.asarray(x0, float).copy(), cost(x0, None)]

    def tracked(x, grad):
        f = cost(x, grad)
        if f < best[1]:
            best[0], best[1] = np.array(x, float), f
        return f

    opt.set_min_objective(tracked)
    try:
        opt.optimize(np.asarray(x0, float))
    except (nlopt.RoundoffLimited, RuntimeError, ValueError):
        pass  # keep the best point seen (NLopt raises on round-off; the best iterate is still valid)
    return best[0], best[1]


def register_block(
    fixed: Volume,
    moving: Volume,
    level: int,
    block,
    *,
    initial: Volume | None = None,
    rigid_mask: Volume | None = None,
    settings: AdaptiveSettings | None = None,
):
    """One local step (Algorithm 1, lines 6–10) on block ``(i, j, k)`` of ``level``, whatever its mismatch.

    Returns ``(StepRecord, correspondence)``: the step's record and the
    ``scan_to_template`` field after it.  For tests and for inspecting what a
    step does; :func:`register_adaptive` runs the whole loop.
    """
    settings = settings or AdaptiveSettings()
    reg = BlockRegistration(fixed, moving, initial, rigid_mask, settings, None)
    lv = BlockLevel(reg, int(level))
    nx, ny, nz = lv.nb
    i, j, k = (int(v) for v in block)
    if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
        raise ValueError(f"block {tuple(block)} is outside level {level}'s {nx}×{ny}×{nz} blocks")
    rec = reg._step(lv, (k * ny + j) * nx + i, 0)
    return rec, Volume(reg.disp.astype(np.float32), reg.g)


def register_adaptive(
    fixed: Volume,
    moving: Volume,
    *,
    initial: Volume | None = None,
    rigid_mask: Volume | None = None,
    settings: AdaptiveSettings | None = None,
    progress=None,
) -> AdaptiveResult:
    """Register ``moving`` (template) to ``fixed`` (scan) by Rhee's Algorithm 1 (see Notes).

    Parameters
    ----------
    fixed : Volume
        The scan.  The result lives on its grid.
    moving : Volume
        The template (any grid; sampled trilinearly in world space).
    initial : Volume, optional
        Initial ``scan_to_template`` field on the scan grid (e.g. the inverse
        of VBD, :func:`registration.initialise.vbd_initial_field`); identity
        if omitted.
    rigid_mask : Volume, optional
        Bone labels on the template grid (nonzero = bone): with
        ``settings.fix_bones``, bone voxels in a step's ball become
        zero-displacement control points (Rhee §4.3).
    settings : AdaptiveSettings, optional
    progress : callable, optional
        Called with a dict after every step (``level``, ``step``, ``block``,
        ``metric``, ``elapsed``, ``eta`` …) and with ``{"level_done":
        LevelRecord}`` after every level.

    Returns
    -------
    AdaptiveResult

    Notes
    -----
    1. **Block hierarchy** (Algorithm 1, lines 1–3).  At block level ``b`` the
       scan grid is split into ``2**b`` blocks along each axis (level 3 = 8 blocks
       ≈ 32³ voxels on a 256³ grid; never fewer than ``min_block_voxels`` voxels a
       side).  *Multi-resolution volumes* (the loop the paper mentions but does
       not list): the cost of a level is evaluated on its images smoothed with a
       Gaussian and sampled every ``f`` voxels, ``f`` chosen so that a block has
       at most ``eval_voxels`` samples a side.
    2. **The most mismatched block** (lines 4–5): the block of lowest normalised
       MI ``MI / min(H(Bs), H(Bt))`` (§4.1, coarse levels) or highest SSD (fine
       levels; the paper switches at ≈32³ → ≈16³ blocks, i.e. from level 4 on).
       Only blocks with tissue in them take part (featureless air has no
       information); a block is *mismatched* while its measure is worse than the
       tolerance, ``tolerance_factor`` times better than the whole volume's value
       before registration: ``NMI < f · NMI₀`` or ``SSD > SSD₀ / f`` (Rhee §6.1:
       f ≈ 1.5, :meth:`AdaptiveSettings.paper`; our default 3 visits more blocks).
    3. **One local step** (lines 6–9): 8 control points in a 2×2×2 pattern a
       quarter of the half-block inside the block's corners; the region is the
       block's 3×3×3 neighbourhood, scaled per axis and centred so that it spans
       ``(−1, 1)³`` (§4.3) — the moving points are those inside the unit ball, so
       every point that moves lies in the region over which the cost is
       evaluated.  The displacement is the biharmonic clamped plate spline
       (§4.2, :func:`deformation.fields.splines.cps_green`) through the 8 control points
       and, optionally, up to ``max_fixed_points`` zero-displacement control points
       on bone voxels (§4.3, "to maintain rigidity in the bone region").  The 24
       displacement values (mm) are optimised by an NLopt derivative-free method
       with seeded random restarts (Nelder–Mead is the paper's choice and
       :meth:`AdaptiveSettings.paper`'s; BOBYQA is our default:
       ``docs/measurements/registration-settings.md``), plus — our addition — the spline's
       bending energy as a regulariser (``regularization``); the cost
       (SSD, or −MI) is evaluated over the whole region *through the running
       deformation* (§4.3: "previously computed displacements affecting the
       neighboring blocks are considered").
    4. **No folding.**  A candidate whose Jacobian ``det(I + ∇u)`` falls below
       ``min_jacobian`` at any check point of the ball is rejected inside the
       cost (a penalty the simplex retreats from), and the accepted step is
       checked again on every voxel of the ball (halved until it passes).  Every
       step is then orientation-preserving, and so is their composition.
    5. **Composition** (line 10): the accepted step ``U(x) = x + u(x)`` is
       *composed* into the running correspondence, ``φ ← φ ∘ U`` — the
       registered template at scan voxel ``x`` is the template at ``φ(x + u(x))``
       — never added.  A block that cannot improve its region's cost by
       ``min_improvement`` (or has been visited ``max_visits`` times) is retired
       for the level, so the loop always ends.

    Direction.  The running field is ``scan_to_template`` on the scan grid — for
    scan voxel ``x``, the template position ``φ(x)`` it came from, exactly the
    convention of the phantoms' truth field — so a registration's MED is one
    subtraction.

    Cost of one evaluation.  The 3×3×3 region's samples (≲ ``(3·eval_voxels)³``,
    e.g. 13 824 at 8³-sample blocks), the spline basis ``B`` precomputed per
    step, and the running registered image precomputed on the region: one
    compiled serial pass of ``B @ d``, a trilinear sample and the SSD or the
    joint histogram — tens of microseconds (``benchmarks/bench_registration.py``).
    Serial, so that a seed gives the same field to the last bit.
    """
    if fixed.is_vector or moving.is_vector:
        raise ValueError("fixed and moving must be scalar images")
    settings = settings or AdaptiveSettings()
    nlopt.srand(int(settings.seed))
    return BlockRegistration(fixed, moving, initial, rigid_mask, settings, progress).run()
