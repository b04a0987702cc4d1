"""Structure inside a phantom's soft tissue: septa, lobules, tendons and vessels.

Real MRI and CT soft tissue is not uniform: muscle is split into fascicles by
bright fat septa and fascia, subcutaneous fat into lobules by fibrous septa,
and tendons (dark on T1 MRI) and vessels run through it.  That structure is
what lets an intensity registration see soft-tissue motion at all: in
uniform tissue a registration that stands still looks as good as one that
moves.  Everything here is a function of the *template* position, so it moves
with its tissue and a posed scan rendered at ``φ(x)`` keeps its exact truth.

* **Cells** (fascicles, lobules): the Voronoi cells of one site per cell of a
  jittered lattice; each site and the cell's intensity factor come from a
  counter-based hash of ``(i, j, k, key)`` (splitmix64): no table, unbounded,
  seeded, and identical in NumPy and in the compiled kernel.  A point's
  distance to its cell's boundary is
  ``min_j (‖p − s_j‖² − ‖p − s_1‖²) / (2 ‖s_j − s_1‖)`` over the sites of the
  5×5×5 neighbouring lattice cells (``s_1`` the nearest).
* **Septa**: a sheet of half-width ``w`` on every cell boundary, blurred by
  the scanner's point spread (``0.5·(1 − tanh((s − w)/edge))``).
* **Tubes**: tendons cross every soft-tissue joint on its flexor and
  extensor side, along the child bone; a vessel crosses it on the flexor
  side, wiggling: chains of round cones (:mod:`.shapes`) drawn from the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .shapes import RoundCone

__all__ = ["SoftTissue", "hash_uniform", "cell_boundary_distance", "blurred_box", "LATTICE_REACH"]

MASK64 = (1 << 64) - 1
OFFSET = 1 << 20  # lattice indices are shifted positive before hashing (|index| < 2^20 cells)
JITTER = 0.9  # a site lies anywhere in the central 90 % of its lattice cell
LATTICE_REACH = 2  # neighbouring lattice cells searched per axis (5×5×5): enough for JITTER ≤ 1


def blurred_box(s, half_width, edge_mm):
    """A sheet or tube ``|s| < half_width`` blurred by ``edge_mm`` (mass-preserving partial volume), ``s ≥ 0``:
    ``0.5·(tanh((s + w)/e) − tanh((s − w)/e))``, whose integral across stays ``2w`` on a coarse grid
    instead of swelling to a blur width."""
    return 0.5 * (np.tanh((s + half_width) / edge_mm) - np.tanh((s - half_width) / edge_mm))


def _mix(z: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser on uint64 arrays (wrapping arithmetic)."""
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def hash_uniform(i, j, k, key: int, channel: int) -> np.ndarray:
    """Uniform numbers in [0, 1) of lattice cells ``(i, j, k)`` (int arrays), one stream per ``channel``."""
    h = _mix(np.full(np.shape(i), key & MASK64, dtype=np.uint64))
    for c in (i, j, k):
        h = _mix(h ^ (np.asarray(c, np.int64) + OFFSET).astype(np.uint64))
    h = _mix(h ^ np.uint64(channel))
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def cell_boundary_distance(p: np.ndarray, cell_mm: float, key: int) -> tuple[np.ndarray, np.ndarray]:
    """Distance (mm) from points ``p`` (n, 3) to the boundary of their Voronoi cell, and the cell's value in [0, 1).

    The NumPy definition; ``validation.phantoms.kernels.intensity_map`` evaluates the same per point.
    """
    p = np.asarray(p, float)
    base = np.floor(p / cell_mm).astype(np.int64)
    r = np.arange(-LATTICE_REACH, LATTICE_REACH + 1)
    off = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)  # (125, 3) in i, j, k order
    idx = base[:, None, :] + off[None]  # (n, 125, 3)
    u = [hash_uniform(idx[..., 0], idx[..., 1], idx[..., 2], key, c) for c in range(4)]
    sites = (idx + 0.5 + JITTER * (np.stack(u[:3], axis=-1) - 0.5)) * cell_mm
    d2 = np.sum((sites - p[:, None, :]) ** 2, axis=-1)
    nearest = np.argmin(d2, axis=1)
    rows = np.arange(len(p))
    s1, d1 = sites[rows, nearest], d2[rows, nearest]
    gap = np.linalg.norm(sites - s1[:, None, :], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(gap > 0, (d2 - d1[:, None]) / (2.0 * np.where(gap > 0, gap, 1.0)), np.inf)
    return bound.min(axis=1), u[3][rows, nearest]


@dataclass(frozen=True)
class SoftTissue:
    """The seeded structure of one phantom's soft tissue (see the module docstring).

    ``tubes`` is a list of round cones; ``tube_kind`` says 0 (tendon) or 1
    (vessel) per cone.  ``muscle_key`` and ``fat_key`` seed the two cell
    lattices.
    """

    muscle_key: int
    fat_key: int
    muscle_cell_mm: float
    fat_cell_mm: float
    muscle_septum_mm: float  #: half-width of the intermuscular fat septa
    fat_septum_mm: float  #: half-width of the fibrous septa between fat lobules
    cell_amplitude: float  #: relative intensity spread between muscle cells (fascicles)
    lobule_amplitude: float  #: relative intensity spread between fat lobules
    tubes: tuple
    tube_kind: tuple

    @classmethod
    def random(cls, anatomy, rng: np.random.Generator) -> SoftTissue:
        """Cells, septa and tubes for ``anatomy`` (its ``structure`` sizes), drawn from ``rng``."""
        s = anatomy.structure
        keys = rng.integers(0, 2**63 - 1, size=2)
        tubes, kinds = [], []
        sk = anatomy.skeleton
        for name, radius in anatomy.joint_radius_mm.items():
            j = sk.joint(name)
            c, ax = np.asarray(j.center, float), np.asarray(j.axes, float)
            x, y, z = ax[:, 0], ax[:, 1], ax[:, 2]
            off = s["tendon_offset"] * radius
            # Tendons: flexor side (−y of the joint frame: the side the flexion closes, posing.py) and
            # extensor side, two a side for a wide joint, along the child bone across the joint.
            lateral = (0.0,) if radius < 30.0 else (-0.35 * radius, 0.35 * radius)
            for side in (-1.0, 1.0):
                for lat in lateral:
                    shift = lat + rng.normal(0.0, 0.05 * radius)
                    a = c + side * off * y + shift * x - 1.3 * radius * z
                    b = c + side * off * y + shift * x + 1.3 * radius * z
                    r_t = s["tendon_radius_mm"] * rng.uniform(0.8, 1.2)
                    tubes.append(RoundCone(tuple(a), tuple(b), r_t, r_t))
                    kinds.append(0)
            # A vessel on the flexor side, as the popliteal and digital vessels run, wiggling laterally.
            nodes = [
                c
                - s["vessel_offset"] * radius * y
                + (t * radius) * z
                + rng.normal(0.0, 0.12 * radius) * x
                + rng.normal(0.0, 0.06 * radius) * y
                for t in np.linspace(-2.0, 2.0, 5)
            ]
            r_v = s["vessel_radius_mm"]
            for a, b in zip(nodes[:-1], nodes[1:]):
                tubes.append(RoundCone(tuple(a), tuple(b), r_v, 0.95 * r_v))
                kinds.append(1)
        return cls(
            int(keys[0]),
            int(keys[1]),
            float(s["muscle_cell_mm"]),
            float(s["fat_cell_mm"]),
            float(s["muscle_septum_mm"]),
            float(s["fat_septum_mm"]),
            float(s["cell_amplitude"]),
            float(s["lobule_amplitude"]),
            tuple(tubes),
            tuple(kinds),
        )

    def tube_fraction(self, p: np.ndarray, kind: int, edge_mm: float) -> np.ndarray:
        """How much of each point is tube of ``kind`` (0 tendon, 1 vessel): the largest over the tubes.

        A tube of radius ``r`` at distance ``ρ`` from its axis is the box
        ``|ρ| < r`` blurred like every edge, ``0.5·(tanh((ρ + r)/e) − tanh((ρ − r)/e))``
        with ``ρ − r`` the round cone's signed distance: its cross-section
        keeps its mass on a coarse grid instead of swelling to a blur width.
        """
        out = np.zeros(len(p))
        for t, k in zip(self.tubes, self.tube_kind):
            if k == kind:
                r = 0.5 * (t.ra + t.rb)
                out = np.maximum(out, blurred_box(t(p) + r, r, edge_mm))  # ρ = distance to the axis
        return out

    def tube_table(self) -> tuple[np.ndarray, np.ndarray]:
        """``(rows (T, PRIM_WIDTH) as :func:`kernels.compile_shapes` writes round cones, (T, 2) kind and radius)``."""
        from .kernels import PRIM_WIDTH, prim_row

        if not self.tubes:
            return np.zeros((0, PRIM_WIDTH)), np.zeros((0, 2))
        rows = np.stack([prim_row(t) for t in self.tubes])
        info = np.array([[k, 0.5 * (t.ra + t.rb)] for t, k in zip(self.tubes, self.tube_kind)], float)
        return rows, info

    def keys(self) -> np.ndarray:
        return np.array([self.muscle_key, self.fat_key], dtype=np.uint64)

    def site_tables(self, p: np.ndarray, *, max_cells: int = 1 << 22) -> tuple:
        """Each lattice's sites and values over the cells the points ``p`` can reach, for the compiled kernel.

        ``(muscle table, muscle first cell, fat table, fat first cell)``; a table is ``(ni, nj, nk, 4)``:
        site x, y, z (mm) and the cell's value, from the same hash as :func:`cell_boundary_distance`, so
        the kernel hashes each lattice cell once instead of 125 times per point.  A lattice whose box
        would hold more than ``max_cells`` cells gets an empty table (the kernel then hashes per point).
        """
        out = []
        lo, hi = np.min(p, axis=0), np.max(p, axis=0)
        for cell, key in ((self.muscle_cell_mm, self.muscle_key), (self.fat_cell_mm, self.fat_key)):
            first = np.floor(lo / cell).astype(np.int64) - LATTICE_REACH
            last = np.floor(hi / cell).astype(np.int64) + LATTICE_REACH
            n = last - first + 1
            if np.prod(n.astype(float)) > max_cells:
                out += [np.zeros((0, 0, 0, 4)), np.zeros(3, np.int64)]
                continue
            idx = np.stack(np.meshgrid(*(np.arange(a, b + 1) for a, b in zip(first, last)), indexing="ij"), -1)
            u = [hash_uniform(idx[..., 0], idx[..., 1], idx[..., 2], key, c) for c in range(4)]
            table = np.empty(tuple(n) + (4,))
            table[..., :3] = (idx + 0.5 + JITTER * (np.stack(u[:3], axis=-1) - 0.5)) * cell
            table[..., 3] = u[3]
            out += [table, first]
        return tuple(out)

    def params(self) -> np.ndarray:
        """The scalar parameters in the order the compiled kernel reads them."""
        return np.array(
            [
                self.muscle_cell_mm,
                self.fat_cell_mm,
                self.muscle_septum_mm,
                self.fat_septum_mm,
                self.cell_amplitude,
                self.lobule_amplitude,
            ],
            float,
        )
