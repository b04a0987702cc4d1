"""Fast sampling of volumes at world points (compiled, parallel trilinear / nearest interpolation).

The convention is SimpleITK's ``sitk.Resample`` (checked in
``tests/deformation/fields/test_fields.py``).  A world point ``p`` (mm, components
x, y, z) is mapped to a continuous index ``(i, j, k) = world_to_index(p)``
(:class:`~deformation.geometry.GridGeometry`).  Along every axis of ``n``
voxels:

* **inside** means ``-0.5 <= index < n - 0.5`` — the voxel-centre box grown by
  half a voxel, half-open like ITK's ``ImageFunction::IsInsideBuffer``;
* inside but beyond the outermost voxel centres the index is **clamped** to
  ``[0, n - 1]``, as ITK's ``LinearInterpolateImageFunction`` does;
* outside (or a NaN point) the result is ``fill``.

``order=1`` is trilinear interpolation; ``order=0`` is nearest neighbour with
ITK's rounding (``floor(index + 0.5)``), meant for label maps: it never mixes
values and keeps integer dtypes.  Indices, weights and sums are computed in
float64 whatever the data or point dtype; float32 data give float32 output
(one final rounding, as SimpleITK does: the two agree to 1 float32 ulp),
integer or boolean data float64 with ``order=1``.

The kernels are numba-compiled (``parallel=True``, ``cache=True``, no
fastmath); against SciPy's and SimpleITK's resampling:
docs/measurements/library-choices.md (``benchmarks/bench_interpolation.py``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from deformation.geometry import GeometryMismatchError, GridGeometry, Volume

__all__ = [
    "sample",
    "sample_array",
    "warp",
    "sample_displaced_array",
    "sample_shifted",
    "SERIAL_BELOW",
    "fill_value",
    "flat_data",
    "interp_scalar",
    "interp_vector",
    "native_order",
    "output_dtype",
    "serial_twin",
    "to_index",
]


# -- compiled kernels -----------------------------------------------------------------------
# Voxel data are passed flattened: ``f[(k*ny + j)*nx + i]`` (scalar) or ``f[(k*ny + j)*nx + i, c]``
# (vector), with the grid size (nx, ny, nz) alongside.  Scalar and vector kernels are separate: a run-time
# component loop slows the scalar volumes (docs/measurements/deformation-and-validation.md).
@nb.njit(cache=True)
def to_index(m, x, y, z):
    """Continuous index (i, j, k) of world point (x, y, z) through the 4x4 (or 3x4) matrix ``m``."""
    return (
        m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3],
        m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3],
        m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3],
    )


@nb.njit(cache=True)
def _inside(ci, cj, ck, nx, ny, nz):
    """ITK's ``IsInsideBuffer``: ``-0.5 <= index < n - 0.5`` on every axis (NaN is outside)."""
    return ci >= -0.5 and ci < nx - 0.5 and cj >= -0.5 and cj < ny - 0.5 and ck >= -0.5 and ck < nz - 0.5


@nb.njit(cache=True)
def _nearest(ci, cj, ck, nx, ny, nz):
    """Flat offset of the nearest voxel (ITK rounding: floor(index + 0.5)) of an inside point."""
    i = min(max(int(math.floor(ci + 0.5)), 0), nx - 1)
    j = min(max(int(math.floor(cj + 0.5)), 0), ny - 1)
    k = min(max(int(math.floor(ck + 0.5)), 0), nz - 1)
    return (k * ny + j) * nx + i


@nb.njit(cache=True)
def _linear(ci, cj, ck, nx, ny, nz):
    """Base offset, neighbour strides and weights of trilinear interpolation of an inside point.

    The index is clamped to the voxel-centre box [0, n-1] first (edge extension in the
    half-voxel border); a neighbour stride is 0 on the last voxel of an axis.
    """
    ci = min(max(ci, 0.0), nx - 1.0)
    cj = min(max(cj, 0.0), ny - 1.0)
    ck = min(max(ck, 0.0), nz - 1.0)
    i0 = int(ci)  # ci >= 0: truncation is floor
    j0 = int(cj)
    k0 = int(ck)
    di = 1 if i0 < nx - 1 else 0
    dj = nx if j0 < ny - 1 else 0
    dk = nx * ny if k0 < nz - 1 else 0
    return (k0 * ny + j0) * nx + i0, di, dj, dk, ci - i0, cj - j0, ck - k0


@nb.njit(cache=True)
def _lerp_scalar(f, b, di, dj, dk, ti, tj, tk):
    si = 1.0 - ti
    sj = 1.0 - tj
    sk = 1.0 - tk
    v00 = si * np.float64(f[b]) + ti * np.float64(f[b + di])
    v01 = si * np.float64(f[b + dj]) + ti * np.float64(f[b + dj + di])
    v10 = si * np.float64(f[b + dk]) + ti * np.float64(f[b + dk + di])
    v11 = si * np.float64(f[b + dk + dj]) + ti * np.float64(f[b + dk + dj + di])
    return sk * (sj * v00 + tj * v01) + tk * (sj * v10 + tj * v11)


@nb.njit(cache=True)
def _lerp_component(f, b, di, dj, dk, ti, tj, tk, c):
    si = 1.0 - ti
    sj = 1.0 - tj
    sk = 1.0 - tk
    v00 = si * np.float64(f[b, c]) + ti * np.float64(f[b + di, c])
    v01 = si * np.float64(f[b + dj, c]) + ti * np.float64(f[b + dj + di, c])
    v10 = si * np.float64(f[b + dk, c]) + ti * np.float64(f[b + dk + di, c])
    v11 = si * np.float64(f[b + dk + dj, c]) + ti * np.float64(f[b + dk + dj + di, c])
    return sk * (sj * v00 + tj * v01) + tk * (sj * v10 + tj * v11)


@nb.njit(cache=True)
def _lerp_xyz(f, b, di, dj, dk, ti, tj, tk):
    """Trilinear interpolation of a 3-component ``f (nvox, 3)`` (displacement fields), unrolled: the same
    arithmetic as the component loop, bit for bit, and faster (docs/measurements/deformation-and-validation.md)."""
    si = 1.0 - ti
    sj = 1.0 - tj
    sk = 1.0 - tk
    o = b + di
    a0 = si * np.float64(f[b, 0]) + ti * np.float64(f[o, 0])
    a1 = si * np.float64(f[b, 1]) + ti * np.float64(f[o, 1])
    a2 = si * np.float64(f[b, 2]) + ti * np.float64(f[o, 2])
    p = b + dj
    o = p + di
    c0 = si * np.float64(f[p, 0]) + ti * np.float64(f[o, 0])
    c1 = si * np.float64(f[p, 1]) + ti * np.float64(f[o, 1])
    c2 = si * np.float64(f[p, 2]) + ti * np.float64(f[o, 2])
    p = b + dk
    o = p + di
    d0 = si * np.float64(f[p, 0]) + ti * np.float64(f[o, 0])
    d1 = si * np.float64(f[p, 1]) + ti * np.float64(f[o, 1])
    d2 = si * np.float64(f[p, 2]) + ti * np.float64(f[o, 2])
    p = b + dk + dj
    o = p + di
    e0 = si * np.float64(f[p, 0]) + ti * np.float64(f[o, 0])
    e1 = si * np.float64(f[p, 1]) + ti * np.float64(f[o, 1])
    e2 = si * np.float64(f[p, 2]) + ti * np.float64(f[o, 2])
    return (
        sk * (sj * a0 + tj * c0) + tk * (sj * d0 + tj * e0),
        sk * (sj * a1 + tj * c1) + tk * (sj * d1 + tj * e1),
        sk * (sj * a2 + tj * c2) + tk * (sj * d2 + tj * e2),
    )


@nb.njit(cache=True)
def interp_vector(f, nx, ny, nz, ci, cj, ck, order, fill, out, row):
    """Interpolate vector data ``f (nvox, nc)`` at continuous index (ci, cj, ck) into ``out[row, :]``."""
    nc = f.shape[1]
    if not _inside(ci, cj, ck, nx, ny, nz):
        for c in range(nc):
            out[row, c] = fill
    elif order == 0:
        b = _nearest(ci, cj, ck, nx, ny, nz)
        for c in range(nc):
            out[row, c] = f[b, c]
    else:
        b, di, dj, dk, ti, tj, tk = _linear(ci, cj, ck, nx, ny, nz)
        if nc == 3:
            v0, v1, v2 = _lerp_xyz(f, b, di, dj, dk, ti, tj, tk)
            out[row, 0] = v0
            out[row, 1] = v1
            out[row, 2] = v2
        else:
            for c in range(nc):
                out[row, c] = _lerp_component(f, b, di, dj, dk, ti, tj, tk, c)


@nb.njit(cache=True, inline="always")
def interp_scalar(f, nx, ny, nz, ci, cj, ck, order, fill):
    """Scalar ``f`` at continuous index (ci, cj, ck): ``fill`` outside, nearest or trilinear inside."""
    if not _inside(ci, cj, ck, nx, ny, nz):
        return fill
    if order == 0:
        return f[_nearest(ci, cj, ck, nx, ny, nz)]
    b, di, dj, dk, ti, tj, tk = _linear(ci, cj, ck, nx, ny, nz)
    return _lerp_scalar(f, b, di, dj, dk, ti, tj, tk)


@nb.njit(cache=True, parallel=True)
def _sample_points_scalar(f, nx, ny, nz, w2i, points, order, fill, out):
    """``out[p]`` = scalar data ``f`` sampled at world point ``points[p]``; ``w2i`` world → index."""
    for p in nb.prange(points.shape[0]):
        ci, cj, ck = to_index(w2i, np.float64(points[p, 0]), np.float64(points[p, 1]), np.float64(points[p, 2]))
        out[p] = interp_scalar(f, nx, ny, nz, ci, cj, ck, order, fill)


@nb.njit(cache=True, parallel=True)
def _sample_points_vector(f, nx, ny, nz, w2i, points, order, fill, out):
    """``out[p, :]`` = vector data ``f (nvox, nc)`` sampled at world point ``points[p]``."""
    for p in nb.prange(points.shape[0]):
        ci, cj, ck = to_index(w2i, np.float64(points[p, 0]), np.float64(points[p, 1]), np.float64(points[p, 2]))
        interp_vector(f, nx, ny, nz, ci, cj, ck, order, fill, out, p)


# Serial twins for small inputs (a local registration step samples a few thousand points many times):
# below SERIAL_BELOW points, starting the thread team costs more than the work, the more so on a busy
# machine.  Same arithmetic per point, so the same result.
SERIAL_BELOW = 32768


def serial_twin(kernel):
    """``kernel`` (a ``parallel=True`` numba function) compiled without threads, ``prange`` running as
    ``range``.  The twin's Python function is a copy under a name of its own (``…_serial``): numba's on-disk
    cache names a function's entry by its qualified name and first line, so a twin made from the same function
    would share the parallel kernel's entry, and whichever compiled first would be loaded for both."""
    import types

    f = kernel.py_func
    twin = types.FunctionType(f.__code__, f.__globals__, f.__name__ + "_serial", f.__defaults__, f.__closure__)
    twin.__kwdefaults__ = f.__kwdefaults__
    twin.__qualname__ = f.__qualname__ + "_serial"
    twin.__doc__ = f.__doc__
    # the kernel's other options (fastmath, error_model, ...) kept: the same arithmetic, the same bits
    options = {k: v for k, v in kernel.targetoptions.items() if k not in ("parallel", "nopython")}
    return nb.njit(cache=True, **options)(twin)


_sample_points_scalar_serial = serial_twin(_sample_points_scalar)
_sample_points_vector_serial = serial_twin(_sample_points_vector)


@nb.njit(cache=True)
def _displaced_point(i2w, disp, k, j, i):
    """World point x(i, j, k) + disp[k, j, i] of a target voxel."""
    return (
        i2w[0, 0] * i + i2w[0, 1] * j + i2w[0, 2] * k + i2w[0, 3] + np.float64(disp[k, j, i, 0]),
        i2w[1, 0] * i + i2w[1, 1] * j + i2w[1, 2] * k + i2w[1, 3] + np.float64(disp[k, j, i, 1]),
        i2w[2, 0] * i + i2w[2, 1] * j + i2w[2, 2] * k + i2w[2, 3] + np.float64(disp[k, j, i, 2]),
    )


@nb.njit(cache=True, parallel=True)
def _sample_displaced_scalar(f, nx, ny, nz, w2i, i2w, disp, order, fill, out):
    """For every target voxel (k, j, i) (index → world ``i2w``), scalar ``f`` at ``x + disp[k, j, i]``
    into ``out[(k*ty + j)*tx + i]``.  Fused: the world points are never stored."""
    tz, ty, tx = disp.shape[0], disp.shape[1], disp.shape[2]
    for r in nb.prange(tz * ty):
        k = r // ty
        j = r - k * ty
        for i in range(tx):
            x, y, z = _displaced_point(i2w, disp, k, j, i)
            ci, cj, ck = to_index(w2i, x, y, z)
            out[r * tx + i] = interp_scalar(f, nx, ny, nz, ci, cj, ck, order, fill)


@nb.njit(cache=True, parallel=True)
def _sample_displaced_vector(f, nx, ny, nz, w2i, i2w, disp, order, fill, out):
    """Vector version of :func:`_sample_displaced_scalar`: ``out[(k*ty + j)*tx + i, :]``."""
    tz, ty, tx = disp.shape[0], disp.shape[1], disp.shape[2]
    for r in nb.prange(tz * ty):
        k = r // ty
        j = r - k * ty
        for i in range(tx):
            x, y, z = _displaced_point(i2w, disp, k, j, i)
            ci, cj, ck = to_index(w2i, x, y, z)
            interp_vector(f, nx, ny, nz, ci, cj, ck, order, fill, out, r * tx + i)


@nb.njit(cache=True, parallel=True)
def _sample_shifted(f, nx, ny, nz, shift, scale, order, out):
    """``f`` (nc, nvox) at index ``(k, j, i) + scale · shift[:, k, j, i]`` (array axes) into ``out`` (nc, nvox),
    extended by the edge values beyond the grid."""
    nc = f.shape[0]
    for r in nb.prange(nz * ny):
        k = r // ny
        j = r - k * ny
        for i in range(nx):
            p = r * nx + i
            ck = k + scale[0] * np.float64(shift[0, p])
            cj = j + scale[1] * np.float64(shift[1, p])
            ci = i + scale[2] * np.float64(shift[2, p])
            if order == 0:
                b = _nearest(ci, cj, ck, nx, ny, nz)
                for c in range(nc):
                    out[c, p] = f[c, b]
            else:
                b, di, dj, dk, ti, tj, tk = _linear(ci, cj, ck, nx, ny, nz)
                for c in range(nc):
                    out[c, p] = _lerp_scalar(f[c], b, di, dj, dk, ti, tj, tk)


# -- helpers --------------------------------------------------------------------------------
def _check_order(order) -> int:
    if order not in (0, 1):
        raise ValueError(f"order must be 0 (nearest neighbour) or 1 (trilinear), got {order!r}")
    return int(order)


def flat_data(data) -> tuple[np.ndarray, tuple[int, int, int], bool]:
    """Flattened voxel data (``(nvox,)`` scalar or ``(nvox, c)`` vector, C order, booleans as uint8),
    the grid size (nx, ny, nz) and whether the data are scalar."""
    data = np.asarray(data)
    if data.ndim not in (3, 4):
        raise ValueError(f"voxel data must be [z, y, x] or [z, y, x, c], got shape {data.shape}")
    if np.iscomplexobj(data) or not (np.issubdtype(data.dtype, np.number) or data.dtype == np.bool_):
        raise TypeError(f"voxel data must be real numbers or booleans, got dtype {data.dtype}")
    nz, ny, nx = data.shape[:3]
    f = native_order(np.ascontiguousarray(data))
    if f.dtype == np.float16:  # numba has no float16 arithmetic
        f = f.astype(np.float32)
    if f.dtype == np.bool_:  # sample booleans as bytes (viewed back by the caller)
        f = f.view(np.uint8)
    f = f.reshape(nz * ny * nx) if data.ndim == 3 else f.reshape(nz * ny * nx, data.shape[3])
    return f, (nx, ny, nz), data.ndim == 3


def native_order(a: np.ndarray) -> np.ndarray:
    """``a`` in native byte order (NIfTI files may be big-endian; numba needs native)."""
    return a if a.dtype.isnative else a.astype(a.dtype.newbyteorder("="))


def output_dtype(dtype: np.dtype, order: int) -> np.dtype:
    """The dtype sampling data of ``dtype`` gives: float16 as float32, integers and booleans kept by nearest
    neighbour (``order=0``) and float64 by trilinear interpolation, floats kept."""
    dtype = np.dtype(dtype).newbyteorder("=")
    if dtype == np.float16:
        return np.dtype(np.float32)
    if order == 0 or np.issubdtype(dtype, np.floating):
        return dtype
    return np.dtype(np.float64)


def fill_value(fill, dtype: np.dtype):
    """``fill`` converted to the output dtype, refusing values the dtype cannot hold."""
    if np.issubdtype(dtype, np.floating):
        return dtype.type(fill)
    if dtype == np.bool_:  # the kernels write booleans as bytes
        if fill not in (0, 1, False, True):
            raise ValueError(f"fill {fill!r} is not representable in a boolean volume")
        return np.uint8(bool(fill))
    info = np.iinfo(dtype)
    if not (float(fill) == int(fill) and info.min <= int(fill) <= info.max):
        raise ValueError(f"fill {fill!r} is not representable in the volume's dtype {dtype}")
    return dtype.type(int(fill))


def _as_points(points) -> np.ndarray:
    p = np.asarray(points)
    if p.shape[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3) with components (x, y, z) in mm, got {p.shape}")
    if p.dtype.newbyteorder("=") not in (np.float32, np.float64):
        p = p.astype(np.float64)
    return native_order(np.ascontiguousarray(p.reshape(-1, 3)))


def _matrix(m, name) -> np.ndarray:
    m = np.ascontiguousarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 homogeneous matrix, got shape {m.shape}")
    return m


def _output(n, nc, scalar, dtype):
    kernel_dtype = np.uint8 if dtype == np.bool_ else dtype
    return np.empty(n if scalar else (n, nc), dtype=kernel_dtype)


# -- public API -----------------------------------------------------------------------------
def sample_array(data, world_to_index, points, order: int = 1, fill: float = 0.0) -> np.ndarray:
    """Sample voxel ``data`` ([z, y, x] or [z, y, x, c]) at world ``points`` ``(..., 3)`` mm.

    ``world_to_index`` is the 4x4 matrix mapping a world point (x, y, z, 1) to
    the continuous index (i, j, k, 1) of ``data`` (e.g.
    ``GridGeometry.world_to_index_matrix``).  Returns ``(...)`` for scalar data
    and ``(..., c)`` for vector data.  See the module docstring for the
    boundary rule, the rounding and the dtypes.
    """
    order = _check_order(order)
    odt = output_dtype(np.asarray(data).dtype, order)
    f, (nx, ny, nz), scalar = flat_data(data)
    w2i = _matrix(world_to_index, "world_to_index")
    pts = _as_points(points)
    lead = np.shape(points)[:-1]
    out = _output(pts.shape[0], 1 if scalar else f.shape[1], scalar, odt)
    if pts.shape[0] < SERIAL_BELOW:
        kernel = _sample_points_scalar_serial if scalar else _sample_points_vector_serial
    else:
        kernel = _sample_points_scalar if scalar else _sample_points_vector
    kernel(f, nx, ny, nz, w2i, pts, order, fill_value(fill, odt), out)
    if odt == np.bool_:
        out = out.view(np.bool_)
    return out.reshape(lead) if scalar else out.reshape(lead + (f.shape[1],))


def sample(volume: Volume, points, *, order: int = 1, fill: float = 0.0) -> np.ndarray:
    """Sample ``volume`` at world ``points`` ``(..., 3)`` (mm, components x, y, z).

    ``order=1`` trilinear, ``order=0`` nearest neighbour (label maps; integer
    dtypes kept).  Points outside the voxel-centre box grown by half a voxel
    give ``fill``; inside that half-voxel border the edge value is extended
    (SimpleITK's ``sitk.Resample`` convention).  Returns ``(...)`` for a scalar
    volume and ``(..., c)`` for a vector volume.
    """
    return sample_array(volume.data, volume.geometry.world_to_index_matrix, points, order, fill)


def sample_displaced_array(
    data, world_to_index, target_geometry: GridGeometry, displacement, order: int = 1, fill: float = 0.0
) -> np.ndarray:
    """Sample ``data`` at ``x + displacement[x]`` for every voxel centre ``x`` of ``target_geometry``.

    ``displacement`` is ``(nz, ny, nx, 3)`` mm on the target grid.  Fused: the
    world positions are never stored.  Returns ``(nz, ny, nx)`` or
    ``(nz, ny, nx, c)``.
    """
    order = _check_order(order)
    odt = output_dtype(np.asarray(data).dtype, order)
    f, (nx, ny, nz), scalar = flat_data(data)
    w2i = _matrix(world_to_index, "world_to_index")
    disp = np.asarray(displacement)
    if disp.shape != target_geometry.array_shape + (3,):
        raise GeometryMismatchError(
            f"displacement shape {disp.shape} does not match the target grid {target_geometry.describe()} "
            f"(expected {target_geometry.array_shape + (3,)})"
        )
    if disp.dtype.newbyteorder("=") not in (np.float32, np.float64):
        disp = disp.astype(np.float64)
    disp = native_order(np.ascontiguousarray(disp))
    out = _output(target_geometry.n_voxels, 1 if scalar else f.shape[1], scalar, odt)
    kernel = _sample_displaced_scalar if scalar else _sample_displaced_vector
    kernel(
        f,
        nx,
        ny,
        nz,
        w2i,
        np.ascontiguousarray(target_geometry.index_to_world_matrix),
        disp,
        order,
        fill_value(fill, odt),
        out,
    )
    if odt == np.bool_:
        out = out.view(np.bool_)
    shape = target_geometry.array_shape
    return out.reshape(shape) if scalar else out.reshape(shape + (f.shape[1],))


def sample_shifted(data, shift, scale=(1.0, 1.0, 1.0), order: int = 1) -> np.ndarray:
    """Sample ``data`` on its own grid at every voxel's index moved by ``scale · shift``, edge-extended.

    Index-space resampling for iterative registration on one grid: ``data`` is
    ``(nz, ny, nx)`` or a stack ``(c, nz, ny, nx)`` sampled at the same points;
    ``shift`` is ``(3, nz, ny, nx)`` along the array axes (z, y, x) and
    ``scale`` its factor per axis (e.g. ``1 / spacing`` for a shift in mm).
    Beyond the grid the edge values continue (``scipy.ndimage.map_coordinates``
    with ``mode="nearest"``), as an image cut by the field of view would.
    Float32 in, float32 out, anything else float64 (arithmetic in float64, as every kernel here); the
    numba kernel runs over rows in parallel and gives the same bits for any
    number of threads.
    """
    order = _check_order(order)
    a = np.asarray(data)
    scalar = a.ndim == 3
    stack = a[None] if scalar else a
    if stack.ndim != 4:
        raise ValueError(f"data must be (nz, ny, nx) or (c, nz, ny, nx), got shape {a.shape}")
    nz, ny, nx = stack.shape[1:]
    sh = np.asarray(shift)
    if sh.shape != (3, nz, ny, nx):
        raise ValueError(f"shift must have shape {(3, nz, ny, nx)} (array axes z, y, x first), got {sh.shape}")
    odt = np.float32 if stack.dtype == np.float32 else np.float64
    f = native_order(np.ascontiguousarray(stack.reshape(stack.shape[0], -1), dtype=odt))
    sh = native_order(np.ascontiguousarray(sh.reshape(3, -1)))
    if sh.dtype not in (np.float32, np.float64):
        sh = sh.astype(np.float64)
    sc = np.ascontiguousarray(np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)))
    if not np.all(np.isfinite(sc)) or not np.all(np.isfinite(sh)):
        raise ValueError("scale and shift must be finite")
    out = np.empty(f.shape, dtype=odt)
    _sample_shifted(f, nx, ny, nz, sh, sc, order, out)
    out = out.reshape(stack.shape)
    return out[0] if scalar else out


def warp(
    volume: Volume,
    positions=None,
    target_geometry: GridGeometry | None = None,
    *,
    displacement: Volume | None = None,
    order: int = 1,
    fill: float = 0.0,
    dtype=None,
) -> Volume:
    """Pull-resample ``volume`` onto ``target_geometry`` (or onto ``displacement``'s grid).

    ``positions`` ``(nz, ny, nx, 3)`` gives, for each target voxel, the world
    point (mm) of ``volume`` whose value it takes: for a field ``u`` on the
    target grid whose map ``U(x) = x + u(x)`` lands in ``volume``'s space,
    ``positions = fields.positions(u)`` and the result is ``volume ∘ U``.  For
    example a scan pulled onto the template grid is
    ``warp(scan, positions(template_to_scan), template.geometry)``, where the
    ``template_to_scan`` field gives, for each template voxel, the scan position
    minus the template position.  Points outside ``volume`` give ``fill``.

    ``displacement`` (a volume ``(nz, ny, nx, 3)``, mm) instead of ``positions``
    and ``target_geometry``: each voxel ``x`` of its grid takes ``volume``'s value
    at ``x + displacement[x]``, the points never stored
    (:func:`sample_displaced_array`); the template pulled onto a scan through a
    ``scan_to_template`` field is ``warp(template, displacement=scan_to_template)``.
    ``dtype``: the result converted to it (None: the sampling's dtype).
    """
    if displacement is not None:
        if positions is not None or target_geometry is not None:
            raise ValueError("give positions and target_geometry, or a displacement, not both")
        target_geometry = displacement.geometry
        out = sample_displaced_array(
            volume.data, volume.geometry.world_to_index_matrix, target_geometry, displacement.data, order, fill
        )
        return Volume(out if dtype is None else out.astype(dtype), target_geometry)
    if positions is None or target_geometry is None:
        raise ValueError("give positions and target_geometry, or a displacement")
    pos = np.asarray(positions)
    if pos.shape != target_geometry.array_shape + (3,):
        raise GeometryMismatchError(
            f"positions shape {pos.shape} does not match the target grid {target_geometry.describe()} "
            f"(expected {target_geometry.array_shape + (3,)})"
        )
    out = sample(volume, pos, order=order, fill=fill)
    return Volume(out if dtype is None else out.astype(dtype), target_geometry)


# -- B-spline sampling on SciPy's convention ----------------------------------------------------------------
# ``scipy.ndimage.map_coordinates(coefficients, ..., order, mode="mirror", prefilter=False)`` at world points,
# compiled and parallel (SciPy's interpolation runs on one core and holds the interpreter while it does): the
# rigid bone registration (registration.rigid.Sampler) samples a scan thousands of times per bone.
@nb.njit(cache=True, inline="always")
def _mirror(i, n):
    """SciPy's ``mode="mirror"`` index: reflected about the first and last voxel centres."""
    if n == 1:
        return 0
    period = 2 * (n - 1)
    i = abs(i) % period
    return period - i if i >= n else i


@nb.njit(cache=True, inline="always")
def _spline_weights(t, order):
    """The 4 weights of the coefficients at ``floor(x) − 1 … floor(x) + 2`` (cubic B-spline, ``order=3``), or
    of ``floor(x) … floor(x) + 1`` in the middle two (linear, ``order=1``), ``t = x − floor(x)``."""
    if order == 1:
        return 0.0, 1.0 - t, t, 0.0
    s = 1.0 - t
    return (
        s * s * s / 6.0,
        (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0,
        (3.0 * s * s * s - 6.0 * s * s + 4.0) / 6.0,
        t * t * t / 6.0,
    )


@nb.njit(cache=True, inline="always")
def _spline_row(c, k, j, i0, i1, i2, i3, w0, w1, w2, w3):
    return w0 * c[k, j, i0] + w1 * c[k, j, i1] + w2 * c[k, j, i2] + w3 * c[k, j, i3]


@nb.njit(cache=True, inline="always")
def _spline_plane(c, k, j0, j1, j2, j3, i0, i1, i2, i3, wj, wi):
    return (
        wj[0] * _spline_row(c, k, j0, i0, i1, i2, i3, wi[0], wi[1], wi[2], wi[3])
        + wj[1] * _spline_row(c, k, j1, i0, i1, i2, i3, wi[0], wi[1], wi[2], wi[3])
        + wj[2] * _spline_row(c, k, j2, i0, i1, i2, i3, wi[0], wi[1], wi[2], wi[3])
        + wj[3] * _spline_row(c, k, j3, i0, i1, i2, i3, wi[0], wi[1], wi[2], wi[3])
    )


@nb.njit(cache=True)
def _spline_at(c, ci, cj, ck, order):
    """The spline of coefficients ``c`` ``(nz, ny, nx)`` at continuous index (i, j, k); NaN outside the
    voxel-centre box grown by half a voxel (registration.rigid.Sampler's convention).  The 4 × 4 × 4 stencil
    (2 × 2 × 2 read for ``order=1``: the outer weights are 0) with SciPy's mirrored indices at the edges."""
    nz, ny, nx = c.shape
    if not (-0.5 <= ci <= nx - 0.5 and -0.5 <= cj <= ny - 0.5 and -0.5 <= ck <= nz - 0.5):
        return np.nan
    fi, fj, fk = math.floor(ci), math.floor(cj), math.floor(ck)
    wi = _spline_weights(ci - fi, order)
    wj = _spline_weights(cj - fj, order)
    wk = _spline_weights(ck - fk, order)
    i, j, k = int(fi), int(fj), int(fk)
    i0, i1, i2, i3 = _mirror(i - 1, nx), _mirror(i, nx), _mirror(i + 1, nx), _mirror(i + 2, nx)
    j0, j1, j2, j3 = _mirror(j - 1, ny), _mirror(j, ny), _mirror(j + 1, ny), _mirror(j + 2, ny)
    if order == 1:  # the middle 2 × 2 × 2
        return wk[1] * (
            wj[1] * (wi[1] * c[_mirror(k, nz), j1, i1] + wi[2] * c[_mirror(k, nz), j1, i2])
            + wj[2] * (wi[1] * c[_mirror(k, nz), j2, i1] + wi[2] * c[_mirror(k, nz), j2, i2])
        ) + wk[2] * (
            wj[1] * (wi[1] * c[_mirror(k + 1, nz), j1, i1] + wi[2] * c[_mirror(k + 1, nz), j1, i2])
            + wj[2] * (wi[1] * c[_mirror(k + 1, nz), j2, i1] + wi[2] * c[_mirror(k + 1, nz), j2, i2])
        )
    return (
        wk[0] * _spline_plane(c, _mirror(k - 1, nz), j0, j1, j2, j3, i0, i1, i2, i3, wj, wi)
        + wk[1] * _spline_plane(c, _mirror(k, nz), j0, j1, j2, j3, i0, i1, i2, i3, wj, wi)
        + wk[2] * _spline_plane(c, _mirror(k + 1, nz), j0, j1, j2, j3, i0, i1, i2, i3, wj, wi)
        + wk[3] * _spline_plane(c, _mirror(k + 2, nz), j0, j1, j2, j3, i0, i1, i2, i3, wj, wi)
    )


@nb.njit(cache=True, parallel=True)
def _spline_transformed(c, w2i, transforms, points, order, out):
    """``out[t, p]``: the spline at ``transforms[t] · points[p]`` (world, through ``w2i`` to indices)."""
    n_t, n_p = transforms.shape[0], points.shape[0]
    for q in nb.prange(n_t * n_p):
        t, p = q // n_p, q % n_p
        m = transforms[t]
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        wx = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]
        wy = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]
        wz = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]
        ci, cj, ck = to_index(w2i, wx, wy, wz)
        out[t, p] = _spline_at(c, ci, cj, ck, order)


_spline_transformed_serial = serial_twin(_spline_transformed)


def sample_spline(coefficients, world_to_index, points, *, order: int = 3, transforms=None) -> np.ndarray:
    """SciPy's ``map_coordinates(coefficients, …, order, mode="mirror", prefilter=False)`` at world ``points``
    ``(n, 3)`` (NaN beyond half a voxel outside the grid), compiled and parallel.

    ``coefficients`` ``(nz, ny, nx)``: B-spline coefficients (``scipy.ndimage.spline_filter(…, mode="mirror")``)
    for ``order=3``, the voxel values for ``order=1``.  With ``transforms`` ``(k, 4, 4)`` (or ``(k, 3, 4)``) the
    points are sampled under each of them: ``(k, n)``.  Agrees with SciPy to rounding (summation order).
    """
    if order not in (1, 3):
        raise ValueError(f"order must be 1 (linear) or 3 (cubic B-spline), got {order!r}")
    c = np.ascontiguousarray(coefficients, dtype=np.float64)
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    one = transforms is None
    t = np.eye(4)[None] if one else np.asarray(transforms, dtype=np.float64)
    t = np.ascontiguousarray(t[:, :3, :4])
    out = np.empty((len(t), len(pts)))
    kernel = _spline_transformed_serial if out.size < SERIAL_BELOW else _spline_transformed
    kernel(c, _matrix(world_to_index, "world_to_index"), t, pts, int(order), out)
    return out[0] if one else out
