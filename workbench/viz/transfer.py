"""Colours: transfer functions (colour and opacity of intensity) with their presets, label and overlay colours.

* :class:`TransferFunction` — colour and opacity as functions of intensity,
  absolute or relative to the volume's robust range (:func:`robust_range`);
  presets in :data:`PRESETS` (``mri``, ``ct``), or the user's own JSON file
  (:func:`transfer_function`).
* :data:`CONTRAST_COLOURS` — Rhee's green/cyan template against the magenta
  target (Rhee Figs. 1, 8, 9, 11); :func:`label_colour` — one colour per label.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from workbench.errors import InputFileError

__all__ = [
    "TransferFunction",
    "PRESETS",
    "robust_range",
    "transfer_function",
    "first_visible",
    "label_colour",
    "CONTRAST_COLOURS",
    "LEVEL_COLOURS",
    "MARKER_COLOUR",
    "SKIN_COLOUR",
]

#: template and target colours of the papers' overlays (cyan and magenta; Rhee Figs. 1, 8, 9, 11)
CONTRAST_COLOURS = ((0.0, 0.9, 1.0), (1.0, 0.1, 0.9))
#: colours of registration control points by block level (Rhee Fig. 9 draws level 3), then cycling
LEVEL_COLOURS = ((0.3, 1.0, 0.3), (1.0, 0.9, 0.2), (1.0, 0.5, 0.1), (1.0, 0.2, 0.2), (0.7, 0.4, 1.0))
MARKER_COLOUR = (1.0, 1.0, 1.0)
SKIN_COLOUR = (0.93, 0.76, 0.65)  # a mesh's default colour: a light skin tone


@dataclass(frozen=True)
class TransferFunction:
    """Colour and opacity of intensity for the volume ray caster.

    ``color``: ``((value, r, g, b), ...)`` with r, g, b in [0, 1];
    ``opacity``: ``((value, alpha), ...)`` — alpha per unit length
    ``unit_mm`` (VTK's scalar-opacity unit distance), so the look does not
    depend on the voxel size.  With ``relative=True`` the values are fractions
    of the volume's robust range (its 0.5 and 99.5 percentiles map to 0 and
    1), so one preset fits any scanner's units; otherwise they are intensities
    (e.g. Hounsfield units).
    """

    name: str
    color: tuple
    opacity: tuple
    relative: bool = True
    unit_mm: float = 4.0
    shade: bool = True

    def __post_init__(self):
        for what, pts, n in (("color", self.color, 4), ("opacity", self.opacity, 2)):
            if len(pts) < 2 or any(len(p) != n for p in pts):
                raise ValueError(
                    f"transfer function {self.name!r}: {what} needs ≥ 2 points of {n} numbers "
                    f"(value{', r, g, b' if n == 4 else ', alpha'}), got {pts!r}"
                )
            v = [float(p[0]) for p in pts]
            if any(b <= a for a, b in zip(v, v[1:])):
                raise ValueError(f"transfer function {self.name!r}: {what} values must increase, got {v}")
        if not self.unit_mm > 0:
            raise ValueError(f"transfer function {self.name!r}: unit_mm must be > 0, got {self.unit_mm}")

    def resolved(self, lo: float, hi: float) -> TransferFunction:
        """Absolute values for a volume whose robust range is ``[lo, hi]``."""
        if not self.relative:
            return self
        span = (hi - lo) or 1.0

        def m(v):
            return lo + float(v) * span

        return replace(
            self,
            color=tuple((m(p[0]), *p[1:]) for p in self.color),
            opacity=tuple((m(p[0]), p[1]) for p in self.opacity),
            relative=False,
        )

    def tinted(self, rgb) -> TransferFunction:
        """The same opacity with a single colour (the overlays' contrasting colours)."""
        r, g, b = (float(c) for c in rgb)
        return replace(
            self, name=f"{self.name}-tint", color=((self.color[0][0], r, g, b), (self.color[-1][0], r, g, b))
        )

    def to_dict(self) -> dict:
        return {
            "format": "avw-transfer-function",
            "name": self.name,
            "relative": self.relative,
            "unit_mm": self.unit_mm,
            "shade": self.shade,
            "color": [list(map(float, p)) for p in self.color],
            "opacity": [list(map(float, p)) for p in self.opacity],
        }

    @classmethod
    def from_json(cls, path) -> TransferFunction:
        """Read ``{"color": [[v, r, g, b], ...], "opacity": [[v, a], ...], "relative": bool, ...}``."""
        from workbench.io.jsonio import read_json

        path = Path(path)
        d = read_json(path)  # missing file, syntax errors: errors naming the file and the line
        if "color" not in d or "opacity" not in d:
            raise InputFileError(
                f"{path}: a transfer function needs 'color' [[value, r, g, b], ...] and "
                "'opacity' [[value, alpha], ...] (and optionally 'relative', 'unit_mm', "
                "'shade'); see `workbench render --help`.",
                path,
            )
        try:
            return cls(
                name=str(d.get("name", path.stem)),
                color=tuple(tuple(map(float, p)) for p in d["color"]),
                opacity=tuple(tuple(map(float, p)) for p in d["opacity"]),
                relative=bool(d.get("relative", False)),
                unit_mm=float(d.get("unit_mm", 4.0)),
                shade=bool(d.get("shade", True)),
            )
        except (TypeError, ValueError) as e:
            raise InputFileError(f"{path}: {e}", path) from e


#: MRI-like (T1: fat and marrow bright, cortical bone dark, air black): relative to the robust range, the
#: soft tissue a faint translucent shell and the brightest tissue (fat, marrow) warm and denser.
#: CT-like, in Hounsfield units: skin and muscle faint, bone (≥ 200 HU) ivory and nearly opaque.
PRESETS = {
    "mri": TransferFunction(
        "mri",
        color=(
            (0.0, 0.0, 0.0, 0.0),
            (0.2, 0.55, 0.35, 0.3),
            (0.45, 0.85, 0.55, 0.45),
            (0.75, 1.0, 0.85, 0.65),
            (1.0, 1.0, 0.97, 0.9),
        ),
        opacity=((0.0, 0.0), (0.12, 0.0), (0.3, 0.04), (0.6, 0.12), (1.0, 0.4)),
    ),
    "ct": TransferFunction(
        "ct",
        relative=False,
        color=(
            (-1000.0, 0.0, 0.0, 0.0),
            (-150.0, 0.55, 0.3, 0.2),
            (40.0, 0.85, 0.45, 0.4),
            (200.0, 0.95, 0.85, 0.7),
            (1200.0, 1.0, 1.0, 0.95),
        ),
        opacity=(
            (-1000.0, 0.0),
            (-300.0, 0.0),
            (-100.0, 0.01),
            (60.0, 0.03),
            (180.0, 0.05),
            (300.0, 0.6),
            (1500.0, 0.9),
        ),
    ),
}


def robust_range(data) -> tuple[float, float]:
    """The 0.5–99.5 % intensity range of ``data`` (finite values; ``(0, 1)`` when there are none)."""
    a = np.asarray(data, np.float64)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return 0.0, 1.0
    step = max(1, a.size // 200_000)  # percentiles of a regular subsample: fast and deterministic
    lo, hi = np.percentile(a.reshape(-1)[::step], [0.5, 99.5])
    return float(lo), float(hi if hi > lo else lo + 1.0)


def transfer_function(tf) -> TransferFunction:
    """A :class:`TransferFunction` from a preset name (``mri``, ``ct``), a JSON file, or one already made."""
    if isinstance(tf, TransferFunction):
        return tf
    if isinstance(tf, (str, os.PathLike)) and str(tf) in PRESETS:
        return PRESETS[str(tf)]
    p = Path(tf)
    if p.suffix.lower() == ".json":
        return TransferFunction.from_json(p)
    raise ValueError(f"preset {tf!r}: expected one of {sorted(PRESETS)} or a transfer-function .json file")


def first_visible(tf: TransferFunction) -> float:
    """The intensity from which ``tf`` (absolute) is not fully transparent."""
    pts = tf.opacity
    for (v0, a0), (_, a1) in zip(pts, pts[1:]):
        if a0 > 0 or a1 > 0:  # opacity rises from v0 on (piecewise linear)
            return float(v0)
    return float(pts[-1][0])


_PALETTE = np.array(
    [
        [0.89, 0.85, 0.72],
        [0.35, 0.65, 0.95],
        [0.95, 0.55, 0.25],
        [0.45, 0.85, 0.45],
        [0.9, 0.35, 0.45],
        [0.7, 0.5, 0.9],
        [0.95, 0.85, 0.3],
        [0.35, 0.85, 0.85],
        [0.85, 0.6, 0.75],
        [0.6, 0.75, 0.35],
    ]
)


def label_colour(label: int) -> tuple:
    """A fixed colour per label id (a 10-colour cycle; label 0, the background, is never drawn)."""
    return tuple(float(c) for c in _PALETTE[(int(label) - 1) % len(_PALETTE)])
