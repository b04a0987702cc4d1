"""Gaussian smoothing of volumes: the one helper every package uses, each convention an explicit option.

:func:`smooth` takes an array (array axes z, y, x) or a :class:`deformation.geometry.Volume` and states what
differs between the project's uses: the standard deviation in voxels or in mm, the method (SciPy's sampled
kernel or SimpleITK's recursive filter), and, for SciPy's, the boundary mode and where the kernel is cut.

References
----------
Deriche R. Recursively implementing the Gaussian and its derivatives. INRIA research report 1893 (1993).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["smooth"]


def smooth(
    data,
    sigma,
    *,
    units: str = "voxels",
    spacing=None,
    method: str = "scipy",
    mode: str = "reflect",
    truncate: float = 4.0,
    dtype=None,
):
    """Gaussian smoothing of ``data`` by ``sigma`` along each array axis.

    Parameters
    ----------
    data : ndarray or Volume
        The array (array axes z, y, x; any dimension for ``method="scipy"``, 3-D for ``"recursive"``), or a
        volume (anything with ``data`` and ``geometry``): then its spacing is the default ``spacing`` and the
        result is a volume on the same geometry.
    sigma : float or sequence of float
        The Gaussian's standard deviation, one value or one per array axis (z, y, x).  When every σ is 0,
        ``data`` itself is returned (the same object, not converted to ``dtype``).
    units : {"voxels", "mm"}
        What ``sigma`` is in.  ``"mm"`` needs ``spacing`` (or a volume).
    spacing : sequence of float, optional
        The voxel size in mm along the array axes (z, y, x).
    method : {"scipy", "recursive"}
        ``"scipy"``: ``scipy.ndimage.gaussian_filter``, the sampled kernel cut at ``truncate`` σ, the
        edges continued by ``mode``, the result in the (converted) array's dtype; an axis whose σ is 0 is left
        as it is.  ``"recursive"``: SimpleITK's ``SmoothingRecursiveGaussian`` (Deriche's recursive filter) on
        a float32 copy, the result float32; ``mode`` and ``truncate`` do not apply and every σ must be > 0.
        With ``units="mm"`` SimpleITK is given the spacing and σ in mm, as for the image itself.
    mode : str
        SciPy's boundary mode: ``"reflect"`` (SciPy's default), ``"nearest"`` (the edge values continued), ...
    truncate : float
        SciPy's kernel radius in σ (4, SciPy's default).
    dtype : numpy dtype, optional
        The array is converted to it before SciPy's filter (None: as it is).

    Returns
    -------
    ndarray or Volume
        A new array (a volume for a volume), or ``data`` itself when every σ is 0.
    """
    if hasattr(data, "geometry") and hasattr(data, "data"):  # a Volume (duck-typed: geometry may import this)
        if spacing is None:
            spacing = np.asarray(data.geometry.spacing, float)[::-1]
        out = smooth(
            data.data,
            sigma,
            units=units,
            spacing=spacing,
            method=method,
            mode=mode,
            truncate=truncate,
            dtype=dtype,
        )
        return data if out is data.data else type(data)(out, data.geometry)
    if units not in ("voxels", "mm"):
        raise ValueError(f"units must be 'voxels' or 'mm', got {units!r}")
    if method not in ("scipy", "recursive"):
        raise ValueError(f"method must be 'scipy' or 'recursive', got {method!r}")
    if units == "mm" and spacing is None:
        raise ValueError("units='mm' needs the spacing (mm per voxel along the array axes)")
    data = np.asarray(data)
    sig = np.broadcast_to(np.asarray(sigma, float), (data.ndim,))
    if not np.any(sig > 0):
        return data
    if method == "scipy":
        if units == "mm":
            sigma = sig / np.asarray(spacing, float)
        return ndimage.gaussian_filter(
            data if dtype is None else np.asarray(data, dtype), sigma, mode=mode, truncate=truncate
        )
    import SimpleITK as sitk

    if data.ndim != 3 or not np.all(sig > 0):
        raise ValueError(f"the recursive Gaussian needs a 3-D array and σ > 0 on every axis, got {sig.tolist()}")
    img = sitk.GetImageFromArray(np.asarray(data, np.float32))
    if units == "mm":
        img.SetSpacing([float(v) for v in np.asarray(spacing, float)[::-1]])  # SimpleITK's order: x, y, z
    return sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(img, [float(v) for v in sig[::-1]]))
