"""The compiled phantom kernels evaluate exactly the NumPy definitions (shapes, intensity, posing)."""

from __future__ import annotations

import numpy as np
import pytest

from deformation.kinematics.transforms import apply
from validation.phantoms import make_phantom
from validation.phantoms.posing import blend_weights


@pytest.fixture(scope="module", params=["knee", "hand"])
def phantom_and_points(request):
    ph = make_phantom(request.param, seed=1)
    g = ph.geometry
    rng = np.random.default_rng(7)
    lo, hi = g.index_to_world([0, 0, 0]), g.index_to_world(np.array(g.size) - 1)
    return ph, rng.uniform(lo, hi, size=(20000, 3))


def test_distances_and_intensity_match_numpy(phantom_and_points):
    ph, p = phantom_and_points
    d = ph.anatomy.distances_fast(p)
    np.testing.assert_allclose(d[:, :-1], ph.anatomy.bone_distances(p), atol=1e-9)
    np.testing.assert_allclose(d[:, -1], ph.anatomy.body_distance(p), atol=1e-9)
    fast = ph.anatomy.intensity_fast(p, ph.contrast, edge_mm=ph.edge_mm, texture=ph.texture)
    ref = ph.anatomy.intensity(p, ph.contrast, edge_mm=ph.edge_mm, texture=ph.texture)
    np.testing.assert_allclose(fast, ref, atol=1e-8)


def test_posed_intensity_with_rigid_bone_edges_matches_numpy(phantom_and_points):
    """Posed rendering: soft tissue at the template points, each bone's distance at T_k⁻¹ x of the scan point."""
    ph, p = phantom_and_points
    _, angles = ph.poses[-1]
    t = ph.pose_of(angles).transforms
    m = ph.posing_model(angles)
    x = m.forward(p)  # scan points whose template positions are p
    frames = (x, t)
    fast = ph.anatomy.intensity_fast(p, ph.contrast, edge_mm=ph.edge_mm, texture=ph.texture, bone_frames=frames)
    ref = ph.anatomy.intensity(p, ph.contrast, edge_mm=ph.edge_mm, texture=ph.texture, bone_frames=frames)
    np.testing.assert_allclose(fast, ref, atol=1e-8)
    # Inside every bone the posing map is T_k⁻¹, so there the posed rendering is the template's exactly...
    plain = ph.anatomy.intensity_fast(p, ph.contrast, edge_mm=ph.edge_mm, texture=ph.texture)
    d = ph.anatomy.distances_fast(p)[:, :-1].min(axis=1)
    deep = d < -2.0 * ph.edge_mm  # deeper than the blur of any other bone's edge
    np.testing.assert_allclose(fast[deep], plain[deep], atol=1e-8)
    # ...and within a blur width outside the bones, where the tissue slides by millimetres across an edge whose
    # intensity changes by hundreds per blur width, the two differ by far more than 1 (round-off is 1e-8).
    halo = (d > 0) & (d < ph.edge_mm)
    assert np.abs(fast[halo] - plain[halo]).max() > 1.0
    with pytest.raises(ValueError, match="must match"):
        ph.anatomy.intensity_fast(p, ph.contrast, edge_mm=ph.edge_mm, bone_frames=(x[:10], t))


@pytest.mark.parametrize("mode", ["vbd", "soft"])
def test_forward_map_matches_numpy(phantom_and_points, mode):
    ph, p = phantom_and_points
    _, angles = ph.poses[-1]
    m = ph.posing_model(angles, mode=mode)
    np.testing.assert_allclose(m.forward(p), m.forward_reference(p), atol=1e-9)


def test_vbd_is_rhee_equation_2(phantom_and_points):
    """F(v) = (Σ_j w_j T_j) v with the blend weights, computed here by hand."""
    ph, p = phantom_and_points
    _, angles = ph.poses[-1]
    m = ph.posing_model(angles, mode="vbd")
    w = blend_weights(
        ph.anatomy.bone_distances(p), power=ph.anatomy.weight_power, falloff_mm=ph.anatomy.weight_falloff_mm
    )
    t = ph.pose_of(angles).transforms
    expected = sum(w[:, [k]] * apply(t[n], p) for k, n in enumerate(ph.anatomy.bone_names))
    np.testing.assert_allclose(m.forward(p), expected, atol=1e-9)
    assert np.allclose(w.sum(axis=1), 1.0)


def test_inverse_recovers_template_points_in_the_body(phantom_and_points):
    ph, p = phantom_and_points
    _, angles = ph.poses[len(ph.poses) // 2]
    m = ph.posing_model(angles)
    body = ph.anatomy.distances_fast(p)[:, -1] < 0
    q = m.forward(p[body])
    back, res = m.inverse(q)
    ok = res < 1e-6
    assert ok.mean() > 0.99
    # Where it converged the preimage is F's (F(back) == q) and, where the posed tissue does not
    # overlap other tissue, the original point.  Skinning cannot compress a crease, so at mid-curl
    # ~1-2 % of the hand's soft tissue (palmar MCP creases, thenar web) lies on a second sheet.
    np.testing.assert_allclose(m.forward(back[ok]), q[ok], atol=1e-5)
    assert np.mean(np.linalg.norm(back[ok] - p[body][ok], axis=1) < 1e-4) > 0.98


def test_bones_are_rigid_in_both_modes(phantom_and_points):
    ph, p = phantom_and_points
    _, angles = ph.poses[-1]
    d = ph.anatomy.distances_fast(p)[:, :-1]
    t = ph.pose_of(angles).transforms
    for mode in ("soft", "vbd"):
        m = ph.posing_model(angles, mode=mode)
        f = m.forward(p)
        for k, n in enumerate(ph.anatomy.bone_names):
            inside = d[:, k] < 0
            if inside.any():
                np.testing.assert_allclose(f[inside], apply(t[n], p[inside]), atol=1e-9)
