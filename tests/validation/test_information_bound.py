"""Cramér–Rao bounds on rigid bone registration, against closed forms and the phantom's own rendering."""

from __future__ import annotations

import numpy as np
import pytest

from validation.information_bound import median_error_norm, phantom_pose_bounds, rigid_bound, rigid_information

SIGMA = 20.0


def blob(widths_mm, spacing_mm, amplitude=1000.0):
    """Samples and exact gradients of ``A exp(-½ Σ x_k²/w_k²)`` on an anisotropic grid out to ±6 widths."""
    axes = [np.arange(-6 * w, 6 * w + 1e-9, h) for w, h in zip(widths_mm, spacing_mm)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    a = 1.0 / np.asarray(widths_mm, float) ** 2
    i = amplitude * np.exp(-0.5 * (x**2 * a).sum(axis=1))
    return x, -(x * a) * i[:, None]


def test_information_of_a_gaussian_blob_matches_the_closed_form():
    """For I = A exp(-½ xᵀ diag(a, b, c) x), Σ_v |x × ∇I|_x² ≈ A² (c−b)² ∫ y² z² exp(-(a x² + b y² + c z²)) / V,
    V the voxel volume; the integral is π^{3/2}/√(abc) / (4bc).  The grid (0.7, 0.9, 1.1 mm) is fine against
    the widths (4, 6, 9 mm), so the sum is the integral to well under 1 %."""
    w, h = (4.0, 6.0, 9.0), (0.7, 0.9, 1.1)
    x, g = blob(w, h)
    f = rigid_information(x, g, np.zeros(3), SIGMA)
    a, b, c = 1.0 / np.asarray(w) ** 2
    v, amp2 = np.prod(h), 1000.0**2
    base = np.pi**1.5 / np.sqrt(a * b * c)
    rot_xx = amp2 * (c - b) ** 2 * base / (4 * b * c) / v / SIGMA**2
    tr_xx = amp2 * a**2 * base / (2 * a) / v / SIGMA**2
    assert f[0, 0] == pytest.approx(rot_xx, rel=1e-3)
    assert f[3, 3] == pytest.approx(tr_xx, rel=1e-3)
    # Symmetric blob about the origin: rotation and translation decouple, axes decouple.
    assert np.abs(f - np.diag(np.diag(f))).max() < 1e-6 * f.max()
    bound = rigid_bound(f)
    assert bound.rotation_cov_deg2[0, 0] == pytest.approx(np.rad2deg(1) ** 2 / rot_xx, rel=1e-3)
    # The weakest rotation is reported with its axis: here one of the blob's own axes, one whose sd is the
    # largest (these widths tie x and z: (c−b)²/(bc) = (b−a)²/(ab) up to rounding, so either may be named).
    sds = np.sqrt(np.diag(bound.rotation_cov_deg2))
    k = int(np.argmax(np.abs(bound.weakest_axis)))
    assert abs(bound.weakest_axis[k]) == pytest.approx(1.0, abs=1e-9)
    assert sds[k] == pytest.approx(sds.max(), rel=1e-9)
    assert bound.weakest_sd_deg == pytest.approx(sds.max(), rel=1e-9)


def test_a_body_of_revolution_has_an_unseen_spin():
    """A blob round about x leaves its spin about x out of every image: infinite variance there, finite elsewhere."""
    x, g = blob((4.0, 6.0, 6.0), (0.7, 0.9, 1.1))
    bound = rigid_bound(rigid_information(x, g, np.zeros(3), SIGMA))
    assert np.isinf(bound.weakest_sd_deg) and abs(bound.weakest_axis[0]) == pytest.approx(1.0, abs=1e-6)
    assert np.isfinite(bound.translation_cov_mm2).all()
    # A prior makes it finite: the spin's bound is then the prior's 2°, to the information's rounding.
    with_prior = rigid_bound(rigid_information(x, g, np.zeros(3), SIGMA), prior_deg=2.0)
    assert with_prior.weakest_sd_deg == pytest.approx(2.0, rel=1e-6)


def test_prior_bound_is_the_inverse_of_information_plus_prior_precision():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(6, 6))
    f = m @ m.T * 1e4
    b = rigid_bound(f, prior_deg=2.0, prior_mm=1.5)
    p = np.diag([1 / np.deg2rad(2.0) ** 2] * 3 + [1 / 1.5**2] * 3)
    cov = np.linalg.inv(f + p)
    np.testing.assert_allclose(b.rotation_cov_deg2, cov[:3, :3] * np.rad2deg(1) ** 2, rtol=1e-8)
    np.testing.assert_allclose(b.translation_cov_mm2, cov[3:, 3:], rtol=1e-8)


def test_median_error_norm_of_an_isotropic_gaussian():
    """|e| of a 3-D isotropic Gaussian is Maxwell distributed: median 1.5382 s."""
    assert median_error_norm(np.eye(3) * 4.0, seed=1, n=200_000) == pytest.approx(1.5382 * 2.0, rel=5e-3)
    assert median_error_norm(np.diag([1.0, np.inf, 1.0])) == np.inf
    # Pooled: half the fits with sd 1, half with sd 3: the mixture's median m solves
    # ½F(m) + ½F(m/3) = ½ with the Maxwell CDF F(x) = erf(x/√2) − √(2/π) x exp(−x²/2).
    from scipy.optimize import brentq
    from scipy.special import erf

    def maxwell(x):
        return erf(x / np.sqrt(2)) - np.sqrt(2 / np.pi) * x * np.exp(-x * x / 2)

    m = brentq(lambda x: 0.5 * maxwell(x) + 0.5 * maxwell(x / 3) - 0.5, 0.1, 10)
    assert median_error_norm([np.eye(3), np.eye(3) * 9.0], seed=2, n=100_000) == pytest.approx(m, rel=5e-3)


def test_phantom_gradient_model_predicts_the_rendered_change(phantom):
    """The bound takes the scan's change under a bone's small motion as −∇S·δx with ∇S = R∇I(T⁻¹x).  Check
    it against the phantom itself: turn the knee by 0.1° of flexion in a noise-free rendering, and compare
    the tibia region's change with the prediction.  Measured: correlation 0.998, norm ratio 0.995 (bone
    voxels and the dilated rim alike).  At 0.5° the tibia's far end moves 1.7 mm, past the linear range of
    a 4 mm edge, and the correlation drops to 0.965; hence the small step."""
    from registration.rigid import bone_regions
    from validation.information_bound import template_gradient

    ph = phantom("knee", size="test", modality="ct", n_poses=2, seed=3, noise=False)
    tpl, lab = ph.template()
    region = bone_regions(tpl, lab, ph.skeleton)["tibia"]
    pid, angles = ph.poses[1]
    delta = 0.1
    turned = {k: np.array(v, float) for k, v in angles.items()}
    turned["knee"] = turned["knee"].copy()
    turned["knee"][0] += delta
    s0 = ph.make_scan(1, pid, angles).image.data.astype(float)
    s1 = ph.make_scan(1, pid, ph.region.complete_angles(turned)).image.data.astype(float)
    pose0, pose1 = ph.pose_of(angles), ph.pose_of(ph.region.complete_angles(turned))
    t0, t1 = np.asarray(pose0["tibia"]), np.asarray(pose1["tibia"])
    x = ph.geometry.world_coordinates().reshape(-1, 3)
    p = (x - t0[:3, 3]) @ t0[:3, :3]
    g = region.crop.geometry
    ijk = np.rint(g.world_to_index(p)).astype(int)
    ins = np.all((ijk >= 0) & (ijk < np.asarray(g.size)), axis=1)
    sel = np.zeros(len(x), bool)
    sel[ins] = region.mask[ijk[ins, 2], ijk[ins, 1], ijk[ins, 0]]
    grad = template_gradient(ph, p[sel], 0.05) @ t0[:3, :3].T
    motion = t1 @ np.linalg.inv(t0)  # scan-world motion of the tibia
    dx = x[sel] @ motion[:3, :3].T + motion[:3, 3] - x[sel]
    predicted = -(grad * dx).sum(axis=1)
    actual = (s1 - s0).reshape(-1)[sel]
    assert np.corrcoef(predicted, actual)[0, 1] > 0.99
    assert np.linalg.norm(actual) / np.linalg.norm(predicted) == pytest.approx(1.0, abs=0.02)


def test_phantom_bounds_shrink_with_the_voxel(phantom):
    """Halving the voxel gives ~8x the samples and ~2x the gradient per edge voxel, so the bound on a bone's
    rotation must shrink by well over 2x (measured on the CT knee's patella: 0.47° → 0.084° rms, 278 → 1694 voxels)."""
    from registration.rigid import bone_regions

    out = {}
    for scale in (1, 2):
        ph = phantom("knee", size="test", modality="ct", n_poses=2, seed=3)
        if scale != 1:
            _, sp = ph.region.GRIDS["test"]
            ph = phantom("knee", size="test", modality="ct", n_poses=2, seed=3, spacing=tuple(s / scale for s in sp))
        tpl, lab = ph.template()
        regs = bone_regions(tpl, lab, ph.skeleton)
        out[scale] = phantom_pose_bounds(ph, ph.poses[1][1], {"patella": regs["patella"]})["patella"]
    assert out[2].rotation_rms_deg < out[1].rotation_rms_deg / 2.5, (out[1].rotation_rms_deg, out[2].rotation_rms_deg)
    assert out[2].n_voxels > 5 * out[1].n_voxels
