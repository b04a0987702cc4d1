"""Off-screen volume rendering with VTK: stills, clipped views, overlays (Rhee Figures 1, 8–12).

Everything renders without a display.  :func:`opengl_backend` finds an
off-screen OpenGL context — EGL first, then OSMesa (``AVW_OPENGL=egl`` or
``osmesa`` forces one) — and says which, with the OpenGL renderer string.  On
a software renderer (Mesa's llvmpipe, as on machines without a GPU) the CPU
ray caster ``vtkFixedPointVolumeRayCastMapper`` is used: it is faster there
than the GPU ray caster, which then runs on the CPU through Mesa
(docs/measurements/library-choices.md, ``benchmarks/bench_rendering.py``); with a
hardware renderer ``vtkGPUVolumeRayCastMapper`` is used.

Geometry is honest: the volume is placed in world millimetres (ITK physical
space) by its origin, spacing *and* direction — the direction goes into the
prop's matrix, so any mapper honours it — and cameras, clipping planes and
bounding boxes are all in world mm.

* :class:`TransferFunction` — colour and opacity as functions of intensity,
  absolute or relative to the volume's robust range; presets in
  :data:`PRESETS` (``mri``, ``ct``), or the user's own JSON file.
* :class:`Camera` — a view (``auto``, ``iso``, or a world axis such as
  ``+z``), azimuth, elevation and zoom.
* :class:`ClipPlane` — ``[+|-]x|y|z:FRACTION``: a plane across a world axis
  at that fraction of the anatomy's extent; the side facing the camera is cut
  away (``+``/``-`` keep the larger / smaller coordinates instead), showing
  the interior (Rhee Fig. 10).
* :class:`VolumeRenderer` — one render window and pipeline, reused from
  frame to frame (animations); :func:`render_volume`, :func:`render_overlay`
  (two volumes in contrasting colours: Rhee's green/cyan template against the
  magenta target, Figs. 1, 8, 9, 11) and :func:`render_difference` are the
  one-call forms.

Images are ``(height, width, 3)`` uint8 arrays; :func:`write_png` writes one
atomically.  Rendering is deterministic: automatic sample-distance
adjustment (which depends on the time a frame took) is switched off.
"""

from __future__ import annotations

import functools
import math
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from deformation.geometry import GridGeometry, Volume
from workbench.errors import InputFileError, WorkbenchError

__all__ = [
    "Backend",
    "RenderError",
    "opengl_backend",
    "offscreen_available",
    "TransferFunction",
    "PRESETS",
    "Camera",
    "ClipPlane",
    "VolumeRenderer",
    "render_volume",
    "render_overlay",
    "render_difference",
    "write_png",
    "parse_size",
    "label_colour",
    "content_mask",
    "points_bounds",
    "union_bounds",
    "content_bounds",
    "CONTRAST_COLOURS",
    "LEVEL_COLOURS",
    "transfer_function",
    "robust_range",
    "first_visible",
    "MARKER_COLOUR",
]

#: template and target colours of the papers' overlays (cyan and magenta; Rhee Figs. 1, 8, 9, 11)
CONTRAST_COLOURS = ((0.0, 0.9, 1.0), (1.0, 0.1, 0.9))
#: colours of registration control points by block level (Rhee Fig. 9 draws level 3), then cycling
LEVEL_COLOURS = ((0.3, 1.0, 0.3), (1.0, 0.9, 0.2), (1.0, 0.5, 0.1), (1.0, 0.2, 0.2), (0.7, 0.4, 1.0))
MARKER_COLOUR = (1.0, 1.0, 1.0)
SKIN_COLOUR = (0.93, 0.76, 0.65)  # a mesh's default colour: a light skin tone
_SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "software rasterizer", "lavapipe")


class RenderError(WorkbenchError, RuntimeError):
    """No off-screen OpenGL, or a rendering request that cannot be met."""


# -- the OpenGL context --------------------------------------------------------------------------
@dataclass(frozen=True)
class Backend:
    name: str  #: "egl" or "osmesa"
    window_class: str  #: the VTK render-window class
    renderer: str  #: the OpenGL renderer string (e.g. "llvmpipe (LLVM 15.0.6, 256 bits)")
    software: bool  #: a software rasteriser (no GPU)

    @property
    def mapper(self) -> str:
        """The volume mapper ``auto`` picks: ``fixed`` (CPU ray cast) on software OpenGL, else ``gpu``."""
        return "fixed" if self.software else "gpu"

    def describe(self) -> str:
        kind = "software" if self.software else "hardware"
        return f"{self.name.upper()} ({self.window_class}), {kind} OpenGL: {self.renderer}"


_WINDOWS = {"egl": "vtkEGLRenderWindow", "osmesa": "vtkOSOpenGLRenderWindow"}


def _probe(name: str) -> Backend | None:
    import vtkmodules.vtkRenderingOpenGL2 as gl
    from vtkmodules.vtkCommonCore import vtkObject
    from vtkmodules.vtkRenderingCore import vtkRenderer

    cls = getattr(gl, _WINDOWS[name], None)
    if cls is None:
        return None
    warn = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()  # a failed probe prints VTK errors; we report our own
    win = None
    try:
        win = cls()
        win.SetOffScreenRendering(1)
        win.SetSize(8, 8)
        win.AddRenderer(vtkRenderer())
        win.Render()
        if not win.SupportsOpenGL():
            return None
        caps = win.ReportCapabilities() or ""
        m = re.search(r"OpenGL renderer string:\s*(.+)", caps)
        renderer = m.group(1).strip() if m else "unknown"
    except Exception:  # noqa: BLE001 - any failure means this backend is unusable here
        return None
    finally:
        if win is not None:
            try:
                win.Finalize()
            except Exception:  # noqa: BLE001 - releasing a context that never worked
                pass
        vtkObject.SetGlobalWarningDisplay(warn)
    software = any(s in renderer.lower() for s in _SOFTWARE_GL)
    return Backend(name, _WINDOWS[name], renderer, software)


@functools.cache
def _backend_cached(forced: str) -> Backend | None:
    for name in [forced] if forced else ["egl", "osmesa"]:
        b = _probe(name)
        if b is not None:
            return b
    return None


def opengl_backend() -> Backend:
    """The off-screen OpenGL context this machine offers: EGL, else OSMesa (probed once per process).

    ``AVW_OPENGL=egl`` or ``AVW_OPENGL=osmesa`` forces one.  Raises
    :class:`RenderError` naming the Debian packages to install when neither works.
    """
    forced = os.environ.get("AVW_OPENGL", "").strip().lower()
    if forced and forced not in _WINDOWS:
        raise RenderError(f"AVW_OPENGL={forced!r}: expected 'egl' or 'osmesa' (or unset it to probe both)")
    b = _backend_cached(forced)
    if b is None:
        tried = forced or "EGL and OSMesa"
        raise RenderError(
            f"no off-screen OpenGL context ({tried} tried): install the Debian packages libegl1 "
            "libegl-mesa0 libgl1-mesa-dri (EGL) or libosmesa6 (OSMesa) — `make venv` does it "
            "as root."
        )
    return b


def offscreen_available() -> bool:
    """Whether :func:`opengl_backend` finds a context (tests skip rendering when not)."""
    try:
        opengl_backend()
        return True
    except RenderError:
        return False


# -- transfer functions --------------------------------------------------------------------------
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


# -- camera and clipping -------------------------------------------------------------------------
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
    (``-z:0.5``) the smaller.  Parsed by :meth:`parse`.
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


# -- labels -----------------------------------------------------------------------------------------
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


# -- the renderer ------------------------------------------------------------------------------------
def _prop_matrix(g: GridGeometry):
    """The vtkMatrix4x4 taking the image's (spacing-scaled, origin 0) coordinates to world mm."""
    m = np.eye(4)
    m[:3, :3] = g.direction_matrix
    m[:3, 3] = np.asarray(g.origin, float)
    return _vtk_matrix(m)


def _vtk_matrix(m):
    """A 4×4 numpy matrix as a vtkMatrix4x4."""
    from vtkmodules.vtkCommonMath import vtkMatrix4x4

    m = np.asarray(m, float)
    vm = vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            vm.SetElement(i, j, float(m[i, j]))
    return vm


def _world_bounds(g: GridGeometry) -> tuple:
    """Axis-aligned world box of the voxel centres (any direction)."""
    n = np.asarray(g.size, float) - 1.0
    corners = np.array([[i, j, k] for i in (0, n[0]) for j in (0, n[1]) for k in (0, n[2])])
    w = np.asarray(g.index_to_world(corners))
    lo, hi = w.min(axis=0), w.max(axis=0)
    return tuple(float(v) for pair in zip(lo, hi) for v in pair)


def first_visible(tf: TransferFunction) -> float:
    """The intensity from which ``tf`` (absolute) is not fully transparent."""
    pts = tf.opacity
    for (v0, a0), (_, a1) in zip(pts, pts[1:]):
        if a0 > 0 or a1 > 0:  # opacity rises from v0 on (piecewise linear)
            return float(v0)
    return float(pts[-1][0])


def content_mask(data, threshold: float) -> np.ndarray:
    """Voxels whose 3×3×3 mean is above ``threshold``: the tissue, without the isolated noisy voxels of the air."""
    from scipy import ndimage as ndi

    return ndi.uniform_filter(np.asarray(data, np.float32), size=3, mode="nearest") > threshold


def points_bounds(points, margin_mm: float) -> tuple:
    """Robust world box of points ``(n, 3)`` mm: the 0.1 and 99.9 percentiles per axis, widened by ``margin_mm``."""
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[:: max(1, p.shape[0] // 200_000)]
    lo, hi = np.percentile(p, [0.1, 99.9], axis=0)
    return tuple(float(v) for pair in zip(lo - margin_mm, hi + margin_mm) for v in pair)


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
        return _world_bounds(geometry)
    kji = np.argwhere(mask)  # (z, y, x) index rows
    w = geometry.index_to_world(kji[:, ::-1].astype(float))
    return points_bounds(w, 2.0 * max(geometry.spacing) if margin_mm is None else float(margin_mm))


class VolumeRenderer:
    """One off-screen window rendering volumes on one grid, reused from frame to frame.

    ``geometry`` fixes the grid (every volume passed to :meth:`render` must
    be on it); ``transfer`` a preset name, a :class:`TransferFunction` or a
    JSON file — relative functions are resolved once against
    ``reference`` (default: the first volume rendered), so an animation's
    colours do not flicker; ``transfers`` (a list) renders that many volumes
    at once, each with its own transfer function, blended (overlays).
    ``mapper``: ``auto`` (:attr:`Backend.mapper`), ``fixed`` or ``gpu``.  The
    camera and clipping plane are placed on ``bounds`` (world mm), by default
    the box of the visible tissue of every volume of the first render
    (:func:`content_bounds`), and of the meshes added (:meth:`add_mesh`).
    ``geometry`` None: no volume at all, meshes only (``render()`` with no
    argument).
    """

    def __init__(
        self,
        geometry: GridGeometry | None,
        *,
        size=(640, 480),
        transfer="mri",
        transfers=None,
        reference=None,
        camera: Camera | None = None,
        clip: ClipPlane | None = None,
        background=(0.0, 0.0, 0.0),
        mapper: str = "auto",
        sample_mm: float | None = None,
        bounds=None,
    ):
        import vtkmodules.vtkRenderingOpenGL2 as gl
        import vtkmodules.vtkRenderingVolumeOpenGL2  # noqa: F401 - registers the OpenGL volume mappers
        from vtkmodules.vtkCommonDataModel import vtkPlane
        from vtkmodules.vtkRenderingCore import vtkRenderer, vtkWindowToImageFilter

        self.backend = opengl_backend()
        if mapper not in ("auto", "fixed", "gpu"):
            raise ValueError(f"mapper must be 'auto', 'fixed' or 'gpu', got {mapper!r}")
        self.mapper_name = self.backend.mapper if mapper == "auto" else mapper
        w, h = (int(v) for v in size)
        if w < 1 or h < 1:
            raise ValueError(f"size must be positive, got {size!r}")
        self.size = (w, h)
        self.geometry = geometry
        self.camera = camera or Camera()
        self.clip = clip
        tfs = (
            []
            if geometry is None
            else [transfer_function(t) for t in (transfers if transfers is not None else [transfer])]
        )
        self.n_components = len(tfs)
        self._tfs, self._resolved = tfs, None
        self._reference = reference
        self.bounds = None if bounds is None else tuple(float(v) for v in bounds)
        self._mesh_bounds = []
        self._ren = vtkRenderer()
        self._ren.SetBackground(*(float(c) for c in background))
        self._plane = vtkPlane() if clip is not None else None
        if geometry is not None:
            self._volume_actor(geometry, tfs, sample_mm)
        self._win = getattr(gl, self.backend.window_class)()
        self._win.SetOffScreenRendering(1)
        self._win.SetSize(w, h)
        self._win.SetMultiSamples(0)
        self._win.AddRenderer(self._ren)
        self._grab = vtkWindowToImageFilter()
        self._grab.SetInput(self._win)
        self._grab.SetInputBufferTypeToRGB()
        self._grab.ReadFrontBufferOff()
        self._surfaces = []
        self._placed = False
        self._distance = None

    def _volume_actor(self, geometry: GridGeometry, tfs, sample_mm) -> None:
        """The ray-cast volume of ``geometry``'s grid with one transfer function per component."""
        from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPiecewiseFunction
        from vtkmodules.vtkRenderingCore import vtkColorTransferFunction, vtkVolume, vtkVolumeProperty

        self._img = vtkImageData()
        self._img.SetDimensions(*(int(v) for v in geometry.size))
        self._img.SetSpacing(*(float(v) for v in geometry.spacing))
        self._img.SetOrigin(0.0, 0.0, 0.0)
        if self.mapper_name == "fixed":
            from vtkmodules.vtkRenderingVolume import vtkFixedPointVolumeRayCastMapper

            self._mapper = vtkFixedPointVolumeRayCastMapper()
            self._mapper.AutoAdjustSampleDistancesOff()  # time-driven: would make renders differ
            self._mapper.LockSampleDistanceToInputSpacingOff()
            self._mapper.SetImageSampleDistance(1.0)
        else:
            from vtkmodules.vtkRenderingVolume import vtkGPUVolumeRayCastMapper

            self._mapper = vtkGPUVolumeRayCastMapper()
            self._mapper.AutoAdjustSampleDistancesOff()
        self._mapper.SetSampleDistance(float(sample_mm or 0.5 * min(geometry.spacing)))
        self._mapper.SetInputData(self._img)
        self._prop = vtkVolumeProperty()
        self._prop.SetInterpolationTypeToLinear()
        self._prop.SetIndependentComponents(True)
        self._ctf = [vtkColorTransferFunction() for _ in tfs]
        self._otf = [vtkPiecewiseFunction() for _ in tfs]
        for c in range(len(tfs)):
            self._prop.SetColor(c, self._ctf[c])
            self._prop.SetScalarOpacity(c, self._otf[c])
            self._prop.SetScalarOpacityUnitDistance(c, tfs[c].unit_mm)
        self._prop.SetShade(bool(all(t.shade for t in tfs)))
        self._prop.SetAmbient(0.35)
        self._prop.SetDiffuse(0.75)
        self._prop.SetSpecular(0.15)
        self._volume = vtkVolume()
        self._volume.SetMapper(self._mapper)
        self._volume.SetProperty(self._prop)
        self._volume.SetUserMatrix(_prop_matrix(geometry))
        self._ren.AddVolume(self._volume)
        if self._plane is not None:
            self._mapper.AddClippingPlane(self._plane)

    @staticmethod
    def grid_bounds(geometry: GridGeometry) -> tuple:
        """The world box of a grid's voxel centres (any direction): a fixed ``bounds`` for the camera."""
        return _world_bounds(geometry)

    # -- inputs --
    def _set_scalars(self, arrays) -> None:
        from vtkmodules.util.numpy_support import numpy_to_vtk

        shape = self.geometry.array_shape
        cols = []
        for a in arrays:
            a = np.asarray(a.data if isinstance(a, Volume) else a)
            if a.shape != shape:
                raise ValueError(
                    f"render: a volume of shape {a.shape} on a renderer for grid {shape} "
                    "(resample it onto the renderer's grid first)"
                )
            cols.append(np.asarray(a, np.float32).reshape(-1))
        flat = np.ascontiguousarray(np.stack(cols, axis=1) if len(cols) > 1 else cols[0])
        self._keep = flat  # VTK shares the buffer
        arr = numpy_to_vtk(flat, deep=False)
        arr.SetName("intensity")
        self._img.GetPointData().SetScalars(arr)
        self._img.Modified()

    def _resolve(self, arrays) -> None:
        if self._resolved is not None:
            return
        refs = self._reference if self._reference is not None else arrays
        if isinstance(refs, (Volume, np.ndarray)):
            refs = [refs] * len(self._tfs)
        self._resolved = []
        for c, tf in enumerate(self._tfs):
            r = refs[c] if c < len(refs) else refs[0]
            lo, hi = robust_range(r.data if isinstance(r, Volume) else r)
            t = tf.resolved(lo, hi)
            self._resolved.append(t)
            self._ctf[c].RemoveAllPoints()
            for v, rr, gg, bb in t.color:
                self._ctf[c].AddRGBPoint(float(v), float(rr), float(gg), float(bb))
            self._otf[c].RemoveAllPoints()
            for v, a in t.opacity:
                self._otf[c].AddPoint(float(v), float(a))

    def add_labels(self, labels, *, smooth: int = 15, opacity: float = 1.0) -> int:
        """Draw the label map's boundaries (e.g. bones) as smooth opaque surfaces, one colour per label.

        ``labels``: a Volume (or array) on the renderer's grid.  The surfaces
        (VTK's discrete flying edges, windowed-sinc smoothed) are clipped by
        the same plane as the volume.  Returns the number of labels drawn.
        """
        from vtkmodules.vtkFiltersCore import vtkWindowedSincPolyDataFilter

        from deformation.isosurface import flying_edges

        lab = np.asarray(labels.data if isinstance(labels, Volume) else labels)
        if isinstance(labels, Volume):
            self.geometry.check_same(
                labels.geometry,
                names=("volume", "labels"),
                remedy="resample the labels onto the volume's grid (nearest neighbour)",
            )
        if lab.shape != self.geometry.array_shape:
            raise ValueError(f"labels of shape {lab.shape} on a grid of shape {self.geometry.array_shape}")
        ids = [int(v) for v in np.unique(lab) if v != 0]
        for lid in ids:
            sm = vtkWindowedSincPolyDataFilter()
            sm.SetInputData(flying_edges(lab, lid, discrete=True))  # index space
            sm.SetNumberOfIterations(int(smooth))
            sm.SetPassBand(0.05)
            sm.NormalizeCoordinatesOn()
            sm.Update()
            # the surface is in voxel indices: the grid's index → world matrix places it
            self._add_surface(
                sm.GetOutput(),
                label_colour(lid),
                opacity=opacity,
                matrix=_vtk_matrix(self.geometry.index_to_world_matrix),
            )
        return len(ids)

    def add_points(self, points, *, colour=(1.0, 0.85, 0.1), radius_mm: float | None = None) -> int:
        """Draw world points ``(n, 3)`` mm as small opaque spheres (markers, control points), clipped too.

        ``radius_mm`` defaults to one voxel (the largest spacing).  Returns the number drawn.
        """
        from vtkmodules.vtkCommonCore import vtkPoints
        from vtkmodules.vtkCommonDataModel import vtkPolyData
        from vtkmodules.vtkFiltersCore import vtkGlyph3D
        from vtkmodules.vtkFiltersSources import vtkSphereSource

        p = np.asarray(points, float).reshape(-1, 3)
        if not np.all(np.isfinite(p)):
            raise ValueError("add_points: the points must be finite world coordinates (mm)")
        pts = vtkPoints()
        for x in p:
            pts.InsertNextPoint(*x)
        poly = vtkPolyData()
        poly.SetPoints(pts)
        sphere = vtkSphereSource()
        sphere.SetRadius(float(radius_mm or (max(self.geometry.spacing) if self.geometry is not None else 1.0)))
        sphere.SetThetaResolution(12)
        sphere.SetPhiResolution(8)
        glyph = vtkGlyph3D()
        glyph.SetInputData(poly)
        glyph.SetSourceConnection(sphere.GetOutputPort())
        glyph.ScalingOff()
        glyph.Update()
        self._add_surface(glyph.GetOutput(), colour)  # already in world mm
        return int(p.shape[0])

    def add_mesh(self, mesh, *, colour=SKIN_COLOUR, opacity: float = 1.0) -> int:
        """Draw a triangle mesh in world mm (``SurfaceMesh``: a skin of ``workbench surface``, a posed model),
        smooth-shaded, clipped by the renderer's plane; with no volume it alone sets the camera's box.  Returns
        its triangle count."""
        from vtkmodules.vtkFiltersCore import vtkPolyDataNormals

        from deformation.isosurface import vtk_polydata

        nrm = vtkPolyDataNormals()
        nrm.SetInputData(vtk_polydata(mesh.vertices, mesh.triangles))
        nrm.SplittingOff()  # smooth shading across the whole skin
        nrm.ConsistencyOn()
        nrm.Update()
        self._add_surface(nrm.GetOutput(), colour, opacity=opacity)
        self._mesh_bounds.append(points_bounds(mesh.vertices, 0.0))
        return int(mesh.n_triangles)

    def _add_surface(self, polydata, colour, *, opacity: float = 1.0, matrix=None) -> None:
        """An opaque (or ``opacity``) surface actor, clipped by the renderer's plane."""
        from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

        mp = vtkPolyDataMapper()
        mp.SetInputData(polydata)
        mp.ScalarVisibilityOff()
        if self._plane is not None:
            mp.AddClippingPlane(self._plane)
        act = vtkActor()
        act.SetMapper(mp)
        if matrix is not None:
            act.SetUserMatrix(matrix)
        act.GetProperty().SetColor(*(float(c) for c in colour))
        act.GetProperty().SetOpacity(float(opacity))
        act.GetProperty().SetSpecular(0.2)
        self._ren.AddActor(act)
        self._surfaces.append(act)

    def clear_surfaces(self) -> None:
        """Remove every label surface, mesh and point set added so far (an animation's bones or skin, frame by
        frame; the camera's box stays)."""
        for act in self._surfaces:
            self._ren.RemoveActor(act)
        self._surfaces = []
        self._mesh_bounds = []

    def _place(self, volumes) -> None:
        """Camera and clipping plane on the anatomy's world box (``bounds``, or the union of every volume's tissue)."""
        if self.bounds is None:  # the union of every component's visible tissue and of the meshes
            self.bounds = union_bounds(
                [
                    content_bounds(v.data if isinstance(v, Volume) else v, self.geometry, first_visible(t))
                    for v, t in zip(volumes, self._resolved or ())
                ]
                + self._mesh_bounds
            )
        cam = self._ren.GetActiveCamera()
        first = self._distance is None
        self._distance = self.camera.place(cam, self.bounds, self.size[0] / self.size[1], self._distance)
        if self._plane is not None and first:  # the side an 'auto' plane keeps is chosen once, from here
            o, nrm = self.clip.plane(self.bounds, cam.GetPosition())
            self._plane.SetOrigin(*o)
            self._plane.SetNormal(*nrm)
        self._placed = True

    def set_camera(self, camera: Camera) -> None:
        """A new camera (e.g. the next azimuth of an orbit) on the same world box, at the first fit's distance.

        The clipping plane stays where the first placement put it: an orbit
        does not flip the side an ``auto`` plane keeps.
        """
        self.camera = camera
        self._placed = False

    def render(self, *volumes) -> np.ndarray:
        """Render ``volumes`` (one per component, on the renderer's grid); ``(height, width, 3)`` uint8."""
        from vtkmodules.util.numpy_support import vtk_to_numpy

        if len(volumes) != self.n_components:
            raise ValueError(f"render: {len(volumes)} volumes for a renderer of {self.n_components} components")
        for v in volumes:
            if isinstance(v, Volume):
                self.geometry.check_same(
                    v.geometry, names=("renderer grid", "volume"), remedy="resample the volume onto one grid first"
                )
        if volumes:
            self._resolve(volumes)
            self._set_scalars(volumes)
        elif self.bounds is None and not self._mesh_bounds:
            raise ValueError("render: nothing to render (no volume and no mesh added)")
        if not self._placed:
            self._place(volumes)
        self._win.Render()
        self._grab.Modified()
        self._grab.Update()
        out = self._grab.GetOutput()
        w, h, _ = out.GetDimensions()
        px = vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, -1)[::-1, :, :3]
        return np.ascontiguousarray(px)

    def close(self) -> None:
        self._win.Finalize()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# -- one-call forms ------------------------------------------------------------------------------------
def render_volume(
    volume: Volume | None, *, labels: Volume | None = None, points=(), meshes=(), transfer="mri", **kw
) -> np.ndarray:
    """A still of ``volume``, optionally with ``labels`` as bone surfaces, ``points`` and ``meshes``.

    ``points``: ``[(world points (n, 3) mm, (r, g, b)[, radius mm]), ...]``
    drawn as small spheres (skin markers, registration control points);
    ``meshes``: ``[SurfaceMesh or (SurfaceMesh, (r, g, b)[, opacity]), ...]``
    in world mm.  ``volume`` None: the meshes alone.  See :class:`VolumeRenderer`.
    """
    with VolumeRenderer(None if volume is None else volume.geometry, transfer=transfer, **kw) as r:
        if labels is not None:
            r.add_labels(labels)
        _add_point_sets(r, points)
        for m in meshes:
            m, colour, opacity = (m, SKIN_COLOUR, 1.0) if not isinstance(m, tuple) else (*m, 1.0)[:3]
            r.add_mesh(m, colour=colour, opacity=opacity)
        return r.render() if volume is None else r.render(volume)


def _add_point_sets(r: VolumeRenderer, points) -> None:
    for item in points:
        pts, colour = item[0], item[1]
        r.add_points(pts, colour=colour, radius_mm=item[2] if len(item) > 2 else None)


def _on_grid(vol: Volume, g: GridGeometry) -> Volume:
    """``vol`` resampled (linear, world coordinates) onto ``g``; itself when it is already on ``g``."""
    if vol.geometry.is_close(g):
        return vol
    import SimpleITK as sitk

    img = vol.to_sitk()
    ref = sitk.Image([int(v) for v in g.size], sitk.sitkFloat32)
    g.apply_to_sitk(ref)
    fill = float(np.percentile(np.asarray(vol.data), 0.5))
    out = sitk.Resample(sitk.Cast(img, sitk.sitkFloat32), ref, sitk.Transform(), sitk.sitkLinear, fill)
    return Volume(sitk.GetArrayFromImage(out), g)


def render_overlay(a: Volume, b: Volume, *, colours=CONTRAST_COLOURS, transfer="mri", points=(), **kw) -> np.ndarray:
    """``a`` and ``b`` in contrasting colours (default cyan and magenta, as Rhee Figs. 1, 8, 9, 11).

    Where the two agree the colours mix (lavender for cyan and magenta);
    where ``a`` has tissue and ``b`` not the image is cyan, and magenta the
    other way.
    ``b`` is resampled onto ``a``'s grid when the grids differ (world
    coordinates, linear).  ``points`` as in :func:`render_volume` (Rhee
    Fig. 9: the registration's control points over the overlay).
    """
    tf = transfer_function(transfer)
    b = _on_grid(b, a.geometry)
    with VolumeRenderer(
        a.geometry, transfers=[tf.tinted(colours[0]), tf.tinted(colours[1])], reference=[a, b], **kw
    ) as r:
        _add_point_sets(r, points)
        return r.render(a, b)


#: signed difference: blue where the first volume is darker, red where brighter; |difference| sets opacity
DIFFERENCE = TransferFunction(
    "difference",
    relative=False,
    shade=False,
    color=(
        (-1.0, 0.15, 0.35, 1.0),
        (-0.1, 0.6, 0.7, 1.0),
        (0.0, 1.0, 1.0, 1.0),
        (0.1, 1.0, 0.7, 0.5),
        (1.0, 1.0, 0.2, 0.1),
    ),
    opacity=((-1.0, 0.5), (-0.15, 0.08), (-0.05, 0.0), (0.05, 0.0), (0.15, 0.08), (1.0, 0.5)),
)


def render_difference(a: Volume, b: Volume, *, transfer="mri", **kw) -> np.ndarray:
    """The signed difference ``a − b`` (``b`` resampled onto ``a``'s grid), scaled by ``a``'s robust range.

    Red where ``a`` is brighter, blue where darker, transparent where they
    agree within 5 % of the range: the misregistered edges stand out.  The
    camera is fitted to the tissue of both volumes as ``transfer`` shows it,
    so the view matches :func:`render_volume` and :func:`render_overlay`.
    """
    b = _on_grid(b, a.geometry)
    lo, hi = robust_range(a.data)
    d = (np.asarray(a.data, np.float64) - np.asarray(b.data, np.float64)) / (hi - lo)
    diff = Volume(np.clip(d, -1.0, 1.0).astype(np.float32), a.geometry)
    if kw.get("bounds") is None:
        tf = transfer_function(transfer)
        kw["bounds"] = union_bounds(
            [content_bounds(v.data, a.geometry, first_visible(tf.resolved(*robust_range(v.data)))) for v in (a, b)]
        )
    with VolumeRenderer(a.geometry, transfer=DIFFERENCE, **kw) as r:
        return r.render(diff)


def write_png(image: np.ndarray, path, *, overwrite: bool = False) -> Path:
    """Write an ``(h, w, 3)`` uint8 image as PNG, atomically (temporary file, then rename)."""
    import imageio.v3 as iio

    from workbench.io.atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: stills are written as PNG; name the file *.png")
    # encoded in memory, written from Python: imageio writing the file itself repeats a failed write's error
    # from its finaliser ("Exception ignored ...") after the one that is raised
    data = iio.imwrite("<bytes>", np.asarray(image, np.uint8), extension=".png")
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return path
