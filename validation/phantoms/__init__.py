"""Synthetic knee and hand phantoms with exact ground truth.

A phantom is a template (an analytic anatomy: bones, soft tissue, skin) and
posed scans of it, each with the exact template ↔ scan correspondence, the
bones' true poses and skin markers: the truth Rhee's and Kurihara's
evaluations measure against, which real scans do not have.
"""

from .generate import MODALITIES, REGIONS, SIZES, Phantom, PhantomScan, PhantomSpec, make_phantom

__all__ = ["Phantom", "PhantomScan", "PhantomSpec", "make_phantom", "REGIONS", "SIZES", "MODALITIES"]
