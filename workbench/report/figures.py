"""Pictures for the HTML report, as compressed image bytes (PNG for plots and maps, JPEG for grey slices).

Slices are drawn from index planes of a volume through a chosen voxel and
resampled to square millimetres (the grid's spacing sets each plane's
aspect), so an anisotropic scan is not squashed.  Overlays use the papers'
colours: the target scan in magenta, the (registered) template in green
(Rhee Figs. 8–9: "differences between registrations (cyan points) and target
volumes (magenta)"), so that where they agree the picture is grey.  Plots
are matplotlib (Agg).
"""

from __future__ import annotations

import io

import numpy as np

__all__ = [
    "PLANES",
    "plane",
    "grey",
    "overlay",
    "colour_map",
    "encode_png",
    "encode_jpeg",
    "line_plot",
    "bar_plot",
    "centre_index",
]

# Index planes of the array [k, j, i] = [z, y, x]: "xy" at a fixed k, "xz" at a fixed j, "yz" at a fixed i.  Not
# called axial / coronal / sagittal: which anatomical plane an index plane is depends on the scan's direction.
PLANES = ("xy", "xz", "yz")
PIXELS_PER_MM = 1.0  # slices are resampled to this many pixels per mm (a test-size knee: ~300 px across)
MAX_SIDE = 420  # … and at most this many pixels on a side


def centre_index(mask: np.ndarray) -> tuple[int, int, int]:
    """The voxel ``(k, j, i)`` at the centre of ``mask``'s bounding box (the grid's centre if it is empty)."""
    if mask is None or not np.any(mask):
        return tuple(int(s // 2) for s in np.shape(mask))
    idx = np.nonzero(mask)
    return tuple(int((a.min() + a.max()) // 2) for a in idx)


def plane(
    data: np.ndarray, spacing_xyz, which: str, at: tuple[int, int, int]
) -> tuple[np.ndarray, tuple[float, float]]:
    """A 2-D index plane of ``data`` ``[k, j, i, ...]`` through voxel ``at``, rows running up the picture,
    with its pixel size in mm ``(row, column)``."""
    sx, sy, sz = (float(v) for v in spacing_xyz)
    k, j, i = at
    if which == "xy":
        sl, px = data[k], (sy, sx)
    elif which == "xz":
        sl, px = data[:, j], (sz, sx)
    elif which == "yz":
        sl, px = data[:, :, i], (sz, sy)
    else:
        raise ValueError(f"plane must be one of {PLANES}, got {which!r}")
    return np.ascontiguousarray(sl[::-1]), px


def _resize(img, px_mm) -> object:
    from PIL import Image

    h, w = img.size[1], img.size[0]
    hh, ww = h * px_mm[0] * PIXELS_PER_MM, w * px_mm[1] * PIXELS_PER_MM
    f = min(MAX_SIDE / max(hh, ww), 4.0)
    f = max(f, 1.0) if max(hh, ww) < MAX_SIDE else f
    return img.resize((max(1, int(round(ww * f))), max(1, int(round(hh * f)))), Image.BILINEAR)


def _unit(a: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((np.asarray(a, np.float64) - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)


def robust(a: np.ndarray) -> tuple[float, float]:
    lo, hi = np.percentile(np.asarray(a, np.float64), [0.5, 99.5])
    return float(lo), float(hi)


def grey(sl: np.ndarray, px_mm, window: tuple[float, float]):
    """A grey picture (PIL image) of a plane, intensities windowed to ``window``."""
    from PIL import Image

    img = Image.fromarray((255 * _unit(sl, *window)).astype(np.uint8), "L")
    return _resize(img, px_mm)


def overlay(target: np.ndarray, template: np.ndarray, px_mm, windows):
    """Target in magenta, template in green (module docstring); each windowed to its own range."""
    from PIL import Image

    t = _unit(target, *windows[0])
    m = _unit(template, *windows[1])
    rgb = np.stack([t, m, t], axis=-1)
    return _resize(Image.fromarray((255 * rgb).astype(np.uint8), "RGB"), px_mm)


def colour_map(
    sl: np.ndarray,
    px_mm,
    vmin: float,
    vmax: float,
    *,
    cmap: str = "magma",
    mask=None,
    background: np.ndarray | None = None,
    window=None,
):
    """A colour-mapped plane (e.g. an error map in mm), grey ``background`` where ``mask`` is false."""
    from matplotlib import colormaps
    from PIL import Image

    rgba = colormaps[cmap](_unit(sl, vmin, vmax))[..., :3]
    if mask is not None:
        bg = np.zeros(sl.shape) if background is None else 0.6 * _unit(background, *window)
        rgba = np.where(np.asarray(mask)[..., None], rgba, bg[..., None])
    return _resize(Image.fromarray((255 * rgba).astype(np.uint8), "RGB"), px_mm)


def encode_png(img) -> bytes:
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def encode_jpeg(img, quality: int = 82) -> bytes:
    buf = io.BytesIO()
    img.convert("RGB").save(buf, format="JPEG", quality=quality, optimize=True)
    return buf.getvalue()


def _figure(width=5.2, height=2.8):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(width, height), dpi=90)
    return plt, fig, ax


def _png(plt, fig) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")  # no date in a PNG's metadata (only "Software"): the same bytes every run
    plt.close(fig)
    return buf.getvalue()


def line_plot(series: dict, *, xlabel: str, ylabel: str, title: str = "") -> bytes:
    """``{name: (x, y)}`` as lines on one axes (PNG bytes)."""
    plt, fig, ax = _figure()
    for name, (x, y) in series.items():
        ax.plot(x, y, label=name, lw=1.4)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=10)
    if len(series) > 1:
        ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return _png(plt, fig)


def bar_plot(labels, values, *, ylabel: str, title: str = "", reference: float | None = None) -> bytes:
    plt, fig, ax = _figure()
    ax.bar(range(len(values)), values, color="#8a4fbf")
    ax.set_xticks(range(len(values)))
    ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(ylabel)
    if reference is not None:
        ax.axhline(reference, color="k", lw=1, ls="--")
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, axis="y")
    return _png(plt, fig)


def plane_point_coordinates(ijk: np.ndarray, spacing_xyz, which: str) -> np.ndarray:
    """Index points ``(n, 3)`` (x, y, z) as ``(column, row)`` mm in :func:`plane`'s picture (rows up),
    projected along the plane's normal."""
    sx, sy, sz = (float(v) for v in spacing_xyz)
    i, j, k = (np.asarray(ijk, float)[:, a] for a in range(3))
    if which == "xy":
        return np.stack([(i + 0.5) * sx, (j + 0.5) * sy], axis=1)
    if which == "xz":
        return np.stack([(i + 0.5) * sx, (k + 0.5) * sz], axis=1)
    if which == "yz":
        return np.stack([(j + 0.5) * sy, (k + 0.5) * sz], axis=1)
    raise ValueError(f"plane must be one of {PLANES}, got {which!r}")


def points_plot(
    background: np.ndarray,
    px_mm,
    points_xy_mm: np.ndarray,
    groups,
    window: tuple[float, float],
    *,
    title: str = "",
    label: str = "level",
) -> bytes:
    """Points (column, row mm of :func:`plane_point_coordinates`) over a grey plane, one colour per group
    (PNG bytes): Rhee Fig. 9's control points per block level."""
    plt, fig, ax = _figure(5.2, 4.2)
    h, w = background.shape
    ax.imshow(
        _unit(np.asarray(background, float), *window),
        cmap="gray",
        vmin=0,
        vmax=1,
        extent=(0, w * px_mm[1], 0, h * px_mm[0]),
        origin="upper",
        interpolation="bilinear",
    )
    groups = np.asarray(groups)
    pts = np.asarray(points_xy_mm, float).reshape(-1, 2)
    for n, gname in enumerate(sorted(set(groups.tolist()))):
        sel = groups == gname
        ax.scatter(
            pts[sel, 0],
            pts[sel, 1],
            s=9,
            color=f"C{n % 10}",
            label=f"{label} {gname} ({int(sel.sum())})",
            edgecolors="none",
            alpha=0.85,
        )
    ax.set_xlim(0, w * px_mm[1])
    ax.set_ylim(0, h * px_mm[0])
    ax.set_xlabel("mm")
    ax.set_ylabel("mm")
    if title:
        ax.set_title(title, fontsize=10)
    if len(pts):
        ax.legend(fontsize=7, loc="upper right")
    return _png(plt, fig)
