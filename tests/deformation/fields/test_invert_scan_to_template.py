"""The one inversion of a ``scan_to_template`` field, both routes, against an analytic inverse.

φ = A⁻¹ ∘ U on the scan grid: A an affine template → scan map (the articulated start's forward map, here
exactly representable by trilinear interpolation), U = id + u a smooth near-identity map of scan space (the
registration's correction).  The exact inverse is φ⁻¹(v) = U⁻¹(A v); both grids are rotated and anisotropic.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from deformation.fields.resample import OK, invert_scan_to_template
from deformation.geometry import GridGeometry, Volume


def _centred(size, spacing, euler, centre) -> GridGeometry:
    d = Rotation.from_euler("ZYX", euler, degrees=True).as_matrix()
    origin = np.asarray(centre) - d @ (np.asarray(spacing) * (np.asarray(size) - 1) / 2.0)
    return GridGeometry(size, spacing, tuple(origin), tuple(d.reshape(-1)))


G_T = _centred((24, 20, 16), (1.1, 0.9, 1.6), [25.0, -10.0, 35.0], (0.0, 0.0, 0.0))
# the scan's grid: larger, rotated otherwise, so most (not all) of the template lands inside it
G_S = _centred((30, 34, 22), (1.0, 0.85, 1.8), [-20.0, 15.0, 40.0], (1.0, -1.5, 0.5))
ROT = Rotation.from_euler("xyz", [6.0, -4.0, 8.0], degrees=True).as_matrix()
SHIFT = np.array([1.5, -2.0, 0.8])
MODES = [((0.9, -0.5, 0.4), (0.12, 0.05, -0.08), 0.3), ((-0.4, 0.6, 0.7), (-0.06, 0.1, 0.09), 1.1)]


def _a(p):
    return p @ ROT.T + SHIFT


def _a_inv(p):
    return (p - SHIFT) @ ROT


def _u(p):
    out = np.zeros(np.shape(p))
    for a, k, ph in MODES:
        out += np.asarray(a) * np.sin(p @ np.asarray(k) + ph)[..., None]
    return out


def _u_inverse(y, n=80):
    x = np.array(y, float)
    for _ in range(n):  # x = y − u(x): a contraction, |∇u| ≤ Σ|a||k| < 0.3
        x = y - _u(x)
    return x


def _phi() -> Volume:
    x = G_S.world_coordinates()
    return Volume(_a_inv(x + _u(x)) - x, G_S)


def _interior(points, g: GridGeometry, margin: float = 2.0):
    ijk = g.world_to_index(points.reshape(-1, 3))
    return np.all((ijk >= margin) & (ijk <= np.asarray(g.size) - 1 - margin), axis=-1)


def test_both_routes_recover_the_analytic_inverse():
    v = G_T.world_coordinates().reshape(-1, 3)
    exact = _u_inverse(_a(v))
    # away from both grids' faces (3 template voxels: near the template's faces U = F ∘ φ is unknown where φ
    # leaves the template grid, and such voxels are only flagged — see the next test)
    inside = _interior(exact, G_S) & _interior(v, G_T, margin=3.0)
    assert inside.mean() > 0.15  # the grids overlap enough for the test to mean something
    forward = _a(G_T.world_coordinates())  # the start's forward map on the template grid
    # Tolerance: three chained trilinear interpolations of fields whose second derivatives are
    # ≤ Σ|a||k|² ≈ 0.02 /mm, at spacings ≤ 1.8 mm: each ≤ h²/8 · 0.02 ≈ 0.01 mm; 0.05 mm covers the chain.
    for bm in (
        invert_scan_to_template(_phi(), G_T, forward=forward),
        invert_scan_to_template(_phi(), G_T, transforms=np.stack([np.vstack([np.c_[ROT, SHIFT], [0, 0, 0, 1]])])),
    ):
        got = bm.scan_to_template().data.reshape(-1, 3) + v
        status = bm.status.reshape(-1)
        assert np.all(status[inside] == OK)
        err = np.linalg.norm(got[inside] - exact[inside], axis=1)
        assert err.max() < 0.05, err.max()


def test_the_forward_route_reports_found_only_where_the_result_maps_back():
    """A start torn in two (the forward map jumps by 12 mm across the template's mid-plane, as VBD's inverse
    jumps between the two sheets of a crease): U = F ∘ φ is then not near the identity there.  Every voxel
    marked found maps back through the analytic φ to within the stated tolerance, and voxels at the tear
    are not marked found."""
    x = G_T.world_coordinates()
    ijk = G_T.world_to_index(x.reshape(-1, 3)).reshape(x.shape)
    tear = ijk[..., 0] >= G_T.size[0] / 2
    forward = _a(x) + np.where(tear[..., None], np.array([0.0, 12.0, 0.0]), 0.0)
    bm = invert_scan_to_template(_phi(), G_T, forward=forward)
    pos = (bm.scan_to_template().data + x).reshape(-1, 3)
    ok = bm.status.reshape(-1) == OK
    back = _a_inv(pos + _u(pos))  # φ(pos), analytic
    tol = 0.5 * max(G_T.spacing) + 0.05  # the route's own acceptance, plus the interpolation error above
    assert ok.any() and np.linalg.norm(back[ok] - x.reshape(-1, 3)[ok], axis=1).max() <= tol
    seam = (np.abs(ijk[..., 0] - G_T.size[0] / 2) < 1.0).reshape(-1) & _interior(_u_inverse(_a(x.reshape(-1, 3))), G_S)
    assert seam.any() and not np.all(ok[seam])
