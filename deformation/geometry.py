"""Grid geometry: where the voxels of a volume sit in world millimetres.

Axis-order convention (the one place it is defined)
----------------------------------------------------
* Points, spacings, origins, sizes and voxel *indices* are in ITK order
  ``(x, y, z)`` (``i`` along x, ``j`` along y, ``k`` along z).
* NumPy arrays of voxels, as SimpleITK's ``GetArrayFromImage`` returns them,
  are indexed ``[z, y, x]``; a vector image adds a trailing component axis
  ``[z, y, x, c]`` whose components are ``(x, y, z)``.

``GridGeometry.array_shape`` is the NumPy shape ``(nz, ny, nx)``;
``GridGeometry.size`` is the ITK size ``(nx, ny, nz)``.  The mapping from a
continuous index ``ijk`` to a world point ``p`` is ITK's::

    p = origin + direction @ (spacing * ijk)

with ``direction`` a 3x3 matrix whose *columns* are the world directions of
the i, j and k axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "GridGeometry",
    "Volume",
    "GeometryMismatchError",
    "every_nth",
    "slabs",
    "SLAB_VOXELS",
    "from_every",
    "points_bounds",
    "covering_grid",
]


class GeometryMismatchError(ValueError):
    """Two volumes that must share a grid do not."""


def _as_vec3(value, name: str, *, positive: bool = False) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have 3 components (x, y, z), got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be positive, got {value!r}")
    return tuple(float(v) for v in arr)


def every_nth(f: int) -> str:
    """'every 2nd', 'every 3rd', 'every 4th' ... (the factor of :meth:`GridGeometry.every` in messages)."""
    f = int(f)
    suffix = "th" if 10 <= f % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(f % 10, "th")
    return f"every {f}{suffix}"


SLAB_VOXELS = 1 << 22  #: voxels of a slab of planes that big-grid passes work on at a time (32 MiB of float64)


def slabs(n_planes: int, plane_voxels: int, voxels: int = SLAB_VOXELS):
    """``(k0, k1)``: the planes ``0 .. n_planes`` (an array's first axis, z) in slabs of about ``voxels``
    voxels (at least one plane each), for passes over a grid too big to hold its temporaries whole."""
    step = max(1, int(voxels) // max(1, int(plane_voxels)))
    for k0 in range(0, n_planes, step):
        yield k0, min(k0 + step, n_planes)


def from_every(values: np.ndarray, f: int, shape) -> np.ndarray:
    """Values on :meth:`GridGeometry.every` ``(f)`` given back to the full grid of array ``shape`` (z, y, x):
    each of its voxels takes the coarse voxel at or before it along every axis (coarse voxel ``I`` is fine
    voxel ``f·I``)."""
    nz, ny, nx = shape
    return np.repeat(np.repeat(np.repeat(values, f, 0)[:nz], f, 1)[:, :ny], f, 2)[:, :, :nx]


@dataclass(frozen=True)
class GridGeometry:
    """Shape and placement of a 3-D voxel grid in world millimetres.

    Parameters
    ----------
    size : (nx, ny, nz)
        Number of voxels along x, y, z (ITK order).
    spacing : (sx, sy, sz)
        Voxel spacing in mm.
    origin : (ox, oy, oz), optional
        World position (mm) of the centre of voxel index (0, 0, 0).
    direction : 3x3 array-like, optional
        Orthonormal matrix whose columns are the world directions of the
        i, j, k index axes. Identity by default.
    """

    size: tuple[int, int, int]
    spacing: tuple[float, float, float]
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple[float, ...] = field(default=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))

    def __post_init__(self):
        size = tuple(int(s) for s in np.asarray(self.size).reshape(-1))
        if len(size) != 3 or min(size) < 1:
            raise ValueError(f"size must be 3 positive integers (nx, ny, nz), got {self.size!r}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "spacing", _as_vec3(self.spacing, "spacing", positive=True))
        object.__setattr__(self, "origin", _as_vec3(self.origin, "origin"))
        d = np.asarray(self.direction, dtype=float).reshape(-1)
        if d.shape != (9,):
            raise ValueError(f"direction must be a 3x3 matrix, got {self.direction!r}")
        m = d.reshape(3, 3)
        if not np.allclose(m.T @ m, np.eye(3), atol=1e-6):
            raise ValueError(f"direction must be orthonormal, got\n{m}")
        object.__setattr__(self, "direction", tuple(float(v) for v in d))

    # -- derived quantities -------------------------------------------------
    @property
    def direction_matrix(self) -> np.ndarray:
        """3x3 direction matrix (columns: world directions of i, j, k)."""
        return np.asarray(self.direction, dtype=float).reshape(3, 3)

    @property
    def array_shape(self) -> tuple[int, int, int]:
        """NumPy shape ``(nz, ny, nx)`` of a scalar volume on this grid."""
        return self.size[::-1]

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.size))

    @property
    def index_to_world_matrix(self) -> np.ndarray:
        """4x4 affine mapping a continuous index (i, j, k, 1) to world (x, y, z, 1) mm."""
        a = np.eye(4)
        a[:3, :3] = self.direction_matrix * np.asarray(self.spacing)[None, :]
        a[:3, 3] = self.origin
        return a

    @property
    def world_to_index_matrix(self) -> np.ndarray:
        return np.linalg.inv(self.index_to_world_matrix)

    @property
    def extent_mm(self) -> tuple[float, float, float]:
        """Physical extent ``size * spacing`` along the index axes, in mm."""
        return tuple(float(n * s) for n, s in zip(self.size, self.spacing))

    # -- conversions --------------------------------------------------------
    def index_to_world(self, ijk) -> np.ndarray:
        """Continuous indices ``(..., 3)`` in (i, j, k) order → world points ``(..., 3)`` mm."""
        ijk = np.asarray(ijk, dtype=float)
        a = self.index_to_world_matrix
        return ijk @ a[:3, :3].T + a[:3, 3]

    def world_to_index(self, points) -> np.ndarray:
        """World points ``(..., 3)`` mm → continuous indices ``(..., 3)`` in (i, j, k) order."""
        p = np.asarray(points, dtype=float)
        a = self.world_to_index_matrix
        return p @ a[:3, :3].T + a[:3, 3]

    def world_coordinates(self, *, dtype=np.float64, z_slice: slice | None = None) -> np.ndarray:
        """World position of every voxel centre, shape ``(nz, ny, nx, 3)`` (components x, y, z).

        ``z_slice`` restricts the result to a range of k (slice) indices, so
        that large grids can be processed slab by slab.
        """
        nx, ny, nz = self.size
        ks = np.arange(nz)[z_slice] if z_slice is not None else np.arange(nz)
        k, j, i = np.meshgrid(ks, np.arange(ny), np.arange(nx), indexing="ij")
        a = self.index_to_world_matrix.astype(dtype)
        out = np.empty(k.shape + (3,), dtype=dtype)
        for c in range(3):
            out[..., c] = a[c, 0] * i + a[c, 1] * j + a[c, 2] * k + a[c, 3]
        return out

    def contains_world(self, points, *, margin_voxels: float = 0.0) -> np.ndarray:
        """True where a world point falls inside the grid's voxel-centre box (± margin)."""
        ijk = self.world_to_index(points)
        lo = -margin_voxels
        hi = np.asarray(self.size) - 1 + margin_voxels
        return np.all((ijk >= lo - 1e-9) & (ijk <= hi + 1e-9), axis=-1)

    # -- comparison ---------------------------------------------------------
    def is_close(self, other: GridGeometry, *, rtol: float = 1e-6, atol_mm: float = 1e-4) -> bool:
        return (
            self.size == other.size
            and np.allclose(self.spacing, other.spacing, rtol=rtol, atol=0)
            and np.allclose(self.origin, other.origin, rtol=0, atol=atol_mm)
            and np.allclose(self.direction, other.direction, rtol=0, atol=1e-6)
        )

    def check_same(self, other: GridGeometry, *, names=("first", "second"), remedy: str | None = None) -> None:
        """Raise :class:`GeometryMismatchError` unless ``other`` is the same grid.

        The message prints both geometries and the remedy; the mismatch is never
        silently papered over (no ``CopyInformation``).
        """
        if self.is_close(other):
            return
        remedy = remedy or (
            "resample one volume onto the other's grid explicitly "
            "(e.g. SimpleITK.Resample with the reference image), or check that "
            "the two files belong together"
        )
        raise GeometryMismatchError(
            f"grid geometries differ:\n  {names[0]}: {self.describe()}\n  {names[1]}: {other.describe()}\n"
            f"Remedy: {remedy}."
        )

    def every(self, factor: int) -> GridGeometry:
        """The grid of every ``factor``-th voxel along each axis: voxel ``I`` of it is voxel ``factor·I`` of
        this one (same origin and direction, spacing × factor)."""
        f = int(factor)
        if f < 1:
            raise ValueError(f"factor must be a positive integer, got {factor!r}")
        return GridGeometry(
            tuple((n - 1) // f + 1 for n in self.size), tuple(s * f for s in self.spacing), self.origin, self.direction
        )

    def factor_within(self, max_voxels: int) -> int:
        """The smallest ``f`` whose :meth:`every` ``(f)`` grid has at most ``max_voxels`` voxels."""
        f = 1
        while self.every(f).n_voxels > max_voxels and min(self.every(f).size) > 1:
            f += 1
        return f

    def factor_of(self, grid: GridGeometry) -> int | None:
        """``f`` when ``grid`` is :meth:`every` ``(f)`` of this grid (1: the grid itself), else None."""
        f = max(1, int(round(grid.spacing[0] / self.spacing[0])))
        return f if grid.is_close(self.every(f)) else None

    def crop(self, lo, hi) -> GridGeometry:
        """The sub-grid of voxel indices ``lo ≤ (i, j, k) < hi`` (in range, non-empty): voxel ``lo`` is its
        origin, spacing and direction are kept, so every voxel stays where it was in world mm."""
        lo, hi = np.asarray(lo, dtype=int), np.asarray(hi, dtype=int)
        if np.any(lo < 0) or np.any(hi > np.asarray(self.size)) or np.any(hi <= lo):
            raise ValueError(
                f"crop index range {lo.tolist()}..{hi.tolist()} is empty or outside a grid of size {list(self.size)}"
            )
        return GridGeometry(
            tuple(int(v) for v in hi - lo), self.spacing, tuple(self.index_to_world(lo.astype(float))), self.direction
        )

    def describe(self) -> str:
        d = np.round(self.direction_matrix, 6).tolist()
        return (
            f"size={self.size} spacing={tuple(round(s, 6) for s in self.spacing)} mm "
            f"origin={tuple(round(o, 4) for o in self.origin)} mm direction={d}"
        )

    # -- (de)serialisation ---------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "size": list(self.size),
            "spacing": list(self.spacing),
            "origin": list(self.origin),
            "direction": list(self.direction),
        }

    @classmethod
    def from_dict(cls, d: dict) -> GridGeometry:
        return cls(
            size=d["size"],
            spacing=d["spacing"],
            origin=d.get("origin", (0, 0, 0)),
            direction=d.get("direction", np.eye(3).reshape(-1)),
        )

    @classmethod
    def from_sitk(cls, image) -> GridGeometry:
        if image.GetDimension() != 3:
            raise ValueError(f"expected a 3-D image, got {image.GetDimension()}-D")
        return cls(
            size=image.GetSize(), spacing=image.GetSpacing(), origin=image.GetOrigin(), direction=image.GetDirection()
        )

    def apply_to_sitk(self, image) -> None:
        """Set origin, spacing and direction of a SimpleITK image (size must match)."""
        if tuple(image.GetSize()) != self.size:
            raise GeometryMismatchError(f"image size {image.GetSize()} differs from grid size {self.size}")
        image.SetOrigin(self.origin)
        image.SetSpacing(self.spacing)
        image.SetDirection(self.direction)


@dataclass
class Volume:
    """A voxel array together with its grid geometry.

    ``data`` is indexed ``[z, y, x]`` (scalar) or ``[z, y, x, c]`` (vector
    image, e.g. a displacement field with components (x, y, z) in mm).
    """

    data: np.ndarray
    geometry: GridGeometry

    def __post_init__(self):
        self.data = np.asarray(self.data)
        if self.data.shape[:3] != self.geometry.array_shape:
            raise GeometryMismatchError(
                f"array shape {self.data.shape} does not match grid {self.geometry.describe()} "
                f"(expected leading shape (nz, ny, nx) = {self.geometry.array_shape})"
            )
        if self.data.ndim not in (3, 4):
            raise ValueError(f"Volume data must be 3-D or 4-D (vector), got shape {self.data.shape}")

    @property
    def is_vector(self) -> bool:
        return self.data.ndim == 4

    @property
    def n_components(self) -> int:
        return 1 if self.data.ndim == 3 else int(self.data.shape[3])

    def crop(self, lo, hi) -> Volume:
        """The sub-volume of voxel indices ``lo ≤ (i, j, k) < hi`` (clipped to the grid), with its geometry.

        Indices are in (i, j, k) = (x, y, z) order; the new origin is the world
        position of voxel ``lo``, spacing and direction are kept, so every voxel
        stays where it was in world mm.  The data are a copy.
        """
        size = np.asarray(self.geometry.size)
        lo = np.clip(np.asarray(lo, dtype=int), 0, size)
        hi = np.clip(np.asarray(hi, dtype=int), 0, size)
        if np.any(hi <= lo):
            raise ValueError(f"empty crop: index range {lo.tolist()}..{hi.tolist()} of a grid of size {size.tolist()}")
        geo = self.geometry.crop(lo, hi)
        data = self.data[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]]  # array order [z, y, x]
        return Volume(np.array(data, copy=True, order="C"), geo)

    def every(self, factor: int, *, smooth: bool = False) -> Volume:
        """The volume on :meth:`GridGeometry.every` ``(factor)``: every ``factor``-th voxel along each axis.

        The voxels are taken as they are (labels, masks: nearest neighbour); with
        ``smooth`` (intensities) they are first smoothed by a Gaussian of σ =
        factor / 2 voxels along each axis (SimpleITK, in float32), so that the
        coarse samples do not alias the detail between them.  ``factor`` 1
        returns the volume itself.
        """
        f = int(factor)
        if f == 1:
            return self
        g = self.geometry.every(f)
        if not smooth:
            return Volume(np.ascontiguousarray(self.data[::f, ::f, ::f]), g)
        from deformation.filters import smooth as gaussian

        zyx = np.asarray(self.geometry.spacing, float)[::-1]  # σ in mm along each axis: half the coarse voxel
        blurred = gaussian(self.data, 0.5 * f * zyx, units="mm", spacing=zyx, method="recursive")
        return Volume(np.ascontiguousarray(blurred[::f, ::f, ::f]), g)

    def to_sitk(self):
        """A SimpleITK image with the same voxels and geometry (vector images stay vector)."""
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(self.data, isVector=self.is_vector)
        self.geometry.apply_to_sitk(img)
        return img

    @classmethod
    def from_sitk(cls, image) -> Volume:
        import SimpleITK as sitk

        return cls(sitk.GetArrayFromImage(image), GridGeometry.from_sitk(image))


def points_bounds(points, margin_mm: float) -> tuple:
    """Robust world box of points ``(n, 3)`` mm: the 0.1 and 99.9 percentiles per axis, widened by ``margin_mm``."""
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[:: max(1, p.shape[0] // 200_000)]
    lo, hi = np.percentile(p, [0.1, 99.9], axis=0)
    return tuple(float(v) for pair in zip(lo - margin_mm, hi + margin_mm) for v in pair)


def covering_grid(geometry: GridGeometry, bounds, *, max_growth: float = 2.0) -> GridGeometry:
    """``geometry`` extended (same spacing and direction, whole voxels) to cover the world box ``bounds``
    ``(xmin, xmax, ymin, ymax, zmin, zmax)``; each side grows by at most ``max_growth`` − 1 times the grid's
    extent along it."""
    b = np.asarray(bounds, float).reshape(3, 2)
    corners = np.array([[x, y, z] for x in b[0] for y in b[1] for z in b[2]])
    ijk = np.asarray(geometry.world_to_index(corners))
    n = np.asarray(geometry.size, float)
    lo = np.maximum(np.minimum(np.floor(ijk.min(axis=0)), 0.0), -(max_growth - 1.0) * n).astype(int)
    hi = np.minimum(np.maximum(np.ceil(ijk.max(axis=0)), n - 1), (max_growth * n) - 1).astype(int)
    size = tuple(int(v) for v in hi - lo + 1)
    origin = tuple(float(v) for v in geometry.index_to_world(lo.astype(float)[None])[0])
    return GridGeometry(size, geometry.spacing, origin, geometry.direction)
