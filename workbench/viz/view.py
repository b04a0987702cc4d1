"""Where the renderer looks: the camera, the clipping plane, the picture's size and the anatomy's world box.

Everything is in world millimetres (ITK physical space):

* :class:`Camera` — a view (``auto``, ``iso``, or a world axis such as
  ``+z``), azimuth, elevation and zoom.
* :class:`ClipPlane` — ``[+|-]x|y|z:FRACTION``: a plane across a world axis
  at that fraction of the anatomy's extent; the side facing the camera is cut
  away (``+``/``-`` keep the larger / smaller coordinates instead), showing
  the interior (Rhee Fig. 10).
* :func:`content_bounds`, :func:`union_bounds`, :func:`grid_bounds` — world
  boxes ``(xmin, xmax, ymin, ymax, zmin, zmax)`` the camera is fitted to.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from deformation.geometry import GridGeometry, points_bounds

__all__ = [
    "Camera",
    "ClipPlane",
    "parse_size",
    "grid_bounds",
    "content_mask",
    "points_bounds",
    "union_bounds",
    "content_bounds",
]

_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class Camera:
    """Where the camera looks from, in world mm (ITK physical space, LPS for patient scans).

    ``view``: ``auto`` (from the + side of the volume's thinnest world axis,
    the longest axis up, then turned by 30° azimuth and 15° elevation — the
    knee phantom's flexion plane; the hand's back, so its ready keyframes
    look from ``+x``, the little-finger side), ``iso`` (from
    ``(+1, +1, +1)``), or a world axis ``+x -x +y -y +z -z`` (from that side,
    the longest remaining axis up); ``azimuth``/``elevation`` (degrees) turn
    the camera about the view-up axis and the horizontal axis (added to the
    view's own); ``zoom`` > 1 enlarges.
    """

    view: str = "auto"
    azimuth: float = 0.0
    elevation: float = 0.0
    zoom: float = 1.0

    VIEWS = ("auto", "iso", "+x", "-x", "+y", "-y", "+z", "-z")

    def __post_init__(self):
        if self.view not in self.VIEWS:
            raise ValueError(f"camera view {self.view!r}: expected one of {', '.join(self.VIEWS)}")
        if not self.zoom > 0:
            raise ValueError(f"camera zoom must be > 0, got {self.zoom}")

    def place(self, cam, bounds, aspect: float = 4 / 3, distance: float | None = None) -> float:
        """Point a ``vtkCamera`` at the world box ``bounds`` (xmin, xmax, ymin, ymax, zmin, zmax).

        The distance is the smallest at which the box's eight corners fit the
        30° view angle (and ``aspect`` = width / height), 5 % margin, then
        ``zoom``; or ``distance`` (mm, before the zoom) when given — an orbit
        keeps its first frame's, so the picture does not breathe.  Returns the
        distance used.
        """
        b = np.asarray(bounds, float).reshape(3, 2)
        centre, ext = b.mean(axis=1), b[:, 1] - b[:, 0]
        az, el = self.azimuth, self.elevation
        if self.view == "iso":
            d, up = np.array([1.0, 1.0, 1.0]), np.array([0.0, 0.0, 1.0])
        else:
            if self.view == "auto":
                a, sign = int(np.argmin(ext)), 1.0
                az, el = az + 30.0, el + 15.0
            else:
                a, sign = _AXES[self.view[1]], (1.0 if self.view[0] == "+" else -1.0)
            others = [k for k in range(3) if k != a]
            u = max(others, key=lambda k: (ext[k], -k))
            d, up = np.zeros(3), np.zeros(3)
            d[a], up[u] = sign, 1.0
        d = d / np.linalg.norm(d)
        radius = 0.5 * float(np.linalg.norm(ext)) or 1.0
        cam.SetFocalPoint(*centre)
        cam.SetPosition(*(centre + 4.0 * radius * d))
        cam.SetViewUp(*up)
        cam.SetViewAngle(30.0)
        cam.Azimuth(az)
        cam.Elevation(el)
        cam.OrthogonalizeViewUp()
        # fit: every corner c (relative to the centre) must satisfy |c·up| ≤ t (D − c·back), |c·right| ≤ t·aspect
        # (D − c·back)
        back = np.asarray(cam.GetPosition()) - centre
        back /= np.linalg.norm(back)
        vup = np.asarray(cam.GetViewUp())
        right = np.cross(vup, back)
        t = math.tan(math.radians(15.0))
        corners = np.array([[x, y, z] for x in b[0] for y in b[1] for z in b[2]]) - centre
        depth = corners @ back
        if distance is None:
            dist = (
                max(
                    float(np.max(np.abs(corners @ vup) / t + depth)),
                    float(np.max(np.abs(corners @ right) / (t * aspect) + depth)),
                    1e-3,
                )
                * 1.05
            )
        else:
            dist = float(distance)
        cam.SetPosition(*(centre + dist * back))
        cam.Zoom(self.zoom)
        cam.SetClippingRange(max(dist - 2 * radius, 1e-3 * dist), dist + 2 * radius)
        return dist


@dataclass(frozen=True)
class ClipPlane:
    """A plane across world ``axis`` at ``fraction`` of the anatomy's extent along it; one side is cut away.

    ``keep="auto"`` (``z:0.5``) cuts away the side facing the camera, so the
    cut face — the interior — is what one sees (Rhee Fig. 10);
    ``keep="above"`` (``+z:0.5``) keeps the larger coordinates, ``"below"``
    (``-z:0.5``) the smaller.  Parsed by ``ClipPlane.parse``.
    """

    axis: str
    fraction: float
    keep: str = "auto"

    def __post_init__(self):
        if self.axis not in _AXES:
            raise ValueError(f"clip axis {self.axis!r}: expected x, y or z")
        if not 0.0 <= self.fraction <= 1.0:
            raise ValueError(f"clip fraction must be within [0, 1], got {self.fraction}")
        if self.keep not in ("auto", "above", "below"):
            raise ValueError(f"clip keep must be 'auto', 'above' or 'below', got {self.keep!r}")

    @classmethod
    def parse(cls, text: str) -> ClipPlane:
        m = re.fullmatch(r"\s*([+-]?)([xyz])\s*:\s*([0-9.eE+-]+)\s*", str(text))
        if not m:
            raise ValueError(
                f"--clip {text!r}: expected [+|-]AXIS:FRACTION, e.g. z:0.5 (cut at the middle, "
                "the half facing the camera removed), +x:0.3 (keep x above 30 % of the extent) "
                "or -x:0.3 (keep it below)"
            )
        keep = {"": "auto", "+": "above", "-": "below"}[m.group(1)]
        return cls(m.group(2), float(m.group(3)), keep)

    def plane(self, bounds, camera_position=None):
        """``(origin, normal)`` in world mm; VTK keeps the side the normal points to."""
        b = np.asarray(bounds, float).reshape(3, 2)
        a = _AXES[self.axis]
        origin = b.mean(axis=1)
        origin[a] = b[a, 0] + self.fraction * (b[a, 1] - b[a, 0])
        normal = np.zeros(3)
        if self.keep == "auto":
            toward = 0.0 if camera_position is None else float(np.asarray(camera_position)[a] - origin[a])
            normal[a] = -1.0 if toward > 0 else 1.0  # keep the far side
        else:
            normal[a] = 1.0 if self.keep == "above" else -1.0
        return origin, normal


def parse_size(text: str) -> tuple[int, int]:
    """``"640x480"`` → ``(640, 480)``; both even (H.264's 4:2:0 chroma needs it) and 16–8192 pixels."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", str(text))
    if not m:
        raise ValueError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480")
    w, h = int(m.group(1)), int(m.group(2))
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ValueError(f"--size {text!r}: width and height must be between 16 and 8192 pixels")
    if w % 2 or h % 2:
        raise ValueError(f"--size {text!r}: video encoders need an even width and height; use {w + w % 2}x{h + h % 2}")
    return w, h


def grid_bounds(g: GridGeometry) -> tuple:
    """Axis-aligned world box of the voxel centres (any direction)."""
    n = np.asarray(g.size, float) - 1.0
    corners = np.array([[i, j, k] for i in (0, n[0]) for j in (0, n[1]) for k in (0, n[2])])
    w = np.asarray(g.index_to_world(corners))
    lo, hi = w.min(axis=0), w.max(axis=0)
    return tuple(float(v) for pair in zip(lo, hi) for v in pair)


def content_mask(data, threshold: float) -> np.ndarray:
    """Voxels whose 3×3×3 mean is above ``threshold``: the tissue, without the isolated noisy voxels of the air."""
    from scipy import ndimage as ndi

    return ndi.uniform_filter(np.asarray(data, np.float32), size=3, mode="nearest") > threshold


def union_bounds(boxes) -> tuple:
    """The world box holding every ``(xmin, xmax, ymin, ymax, zmin, zmax)`` box of ``boxes``."""
    b = np.asarray(boxes, float).reshape(-1, 6)
    return tuple(float(b[:, k].min() if k % 2 == 0 else b[:, k].max()) for k in range(6))


def content_bounds(data, geometry: GridGeometry, threshold: float, *, margin_mm: float | None = None) -> tuple:
    """World box (xmin, xmax, ymin, ymax, zmin, zmax) of the tissue above ``threshold``.

    :func:`content_mask`, then :func:`points_bounds` of the voxel centres'
    world positions, widened by ``margin_mm`` (default: two of the largest
    voxel spacing).  The grid's own box when no voxel is above.
    """
    mask = content_mask(data, threshold)
    if not mask.any():
        return grid_bounds(geometry)
    kji = np.argwhere(mask)  # (z, y, x) index rows
    w = geometry.index_to_world(kji[:, ::-1].astype(float))
    return points_bounds(w, 2.0 * max(geometry.spacing) if margin_mm is None else float(margin_mm))
