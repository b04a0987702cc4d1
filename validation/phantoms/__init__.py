"""Synthetic knee and hand phantoms with exact ground truth (see DESIGN.md, "Validation")."""

from .generate import MODALITIES, REGIONS, SIZES, Phantom, PhantomScan, PhantomSpec, make_phantom

__all__ = ["Phantom", "PhantomScan", "PhantomSpec", "make_phantom", "REGIONS", "SIZES", "MODALITIES"]
