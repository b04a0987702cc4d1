"""Signed distance functions (mm) for the phantoms' analytic anatomy.

Negative inside, positive outside, gradient magnitude ≈ 1 near the surface.
All functions take world points ``(n, 3)`` and return ``(n,)`` float64.
The formulas are the standard ones for implicit modelling (round cone,
ellipsoid bound, polynomial smooth minimum); the ellipsoid and tapered-cone
distances are close approximations, which is all a phantom needs: the tissue
model is defined *by* these functions, so the ground truth stays exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RoundCone", "Ellipsoid", "SmoothUnion", "smooth_min"]


def smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: a blend of width ``k`` mm between two distances."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


@dataclass(frozen=True)
class RoundCone:
    """Segment ``a → b`` swept by a sphere whose radius goes linearly from ``ra`` to ``rb``."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    ra: float
    rb: float

    def __call__(self, p: np.ndarray) -> np.ndarray:
        a = np.asarray(self.a, float)
        ba = np.asarray(self.b, float) - a
        pa = p - a
        t = np.clip(pa @ ba / (ba @ ba), 0.0, 1.0)
        q = pa - t[:, None] * ba
        return np.sqrt(np.einsum("ij,ij->i", q, q)) - (self.ra + t * (self.rb - self.ra))

    def transformed(self, t4: np.ndarray) -> RoundCone:
        r, tr = t4[:3, :3], t4[:3, 3]
        return RoundCone(tuple(r @ self.a + tr), tuple(r @ self.b + tr), self.ra, self.rb)


@dataclass(frozen=True)
class Ellipsoid:
    """Axis-aligned ellipsoid (in the frame ``rotation``) centred at ``center`` with semi-axes ``radii``."""

    center: tuple[float, float, float]
    radii: tuple[float, float, float]
    rotation: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        r = np.asarray(self.radii, float)
        rot = np.asarray(self.rotation, float).reshape(3, 3)
        q = (p - np.asarray(self.center, float)) @ rot  # into the ellipsoid frame
        k0 = np.sqrt(np.einsum("ij,ij->i", q / r, q / r))
        k1 = np.sqrt(np.einsum("ij,ij->i", q / r**2, q / r**2))
        with np.errstate(invalid="ignore", divide="ignore"):
            d = k0 * (k0 - 1.0) / k1
        return np.where(k1 > 0, d, -float(np.min(r)))

    def transformed(self, t4: np.ndarray) -> Ellipsoid:
        r, tr = t4[:3, :3], t4[:3, 3]
        rot = r @ np.asarray(self.rotation, float).reshape(3, 3)
        return Ellipsoid(tuple(r @ self.center + tr), self.radii, tuple(rot.reshape(-1)))


@dataclass(frozen=True)
class SmoothUnion:
    """Smooth union of several shapes with blend width ``k`` mm."""

    parts: tuple
    k: float = 0.0

    def __call__(self, p: np.ndarray) -> np.ndarray:
        d = self.parts[0](p)
        for s in self.parts[1:]:
            d = smooth_min(d, s(p), self.k)
        return d

    def transformed(self, t4: np.ndarray) -> SmoothUnion:
        return SmoothUnion(tuple(s.transformed(t4) for s in self.parts), self.k)
