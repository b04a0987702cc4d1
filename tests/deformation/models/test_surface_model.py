"""Kurihara's surface model (deformation.models.surface_model): SSD, PSD and WPSD over consistent meshes (§5)."""

from __future__ import annotations

import numpy as np
import pytest

from deformation.meshes.mesh import SurfaceMesh
from deformation.models.evd import template_pose
from deformation.models.skinning import SkinningWeights, lbs
from deformation.models.surface_model import SurfaceModel
from validation.phantoms import hand


@pytest.fixture(scope="module")
def setup():
    """The phantom hand's skeleton, 4 flexed poses, a 'skin' of points near the bones with smooth weights, and
    example meshes = SSD of the base plus a pose-dependent offset SSD cannot make."""
    rng = np.random.default_rng(5)
    sk = hand.skeleton()
    poses = [sk.pose(a) for a in hand.default_poses(5, rng)][1:]  # the flexed ones (pose 0 is near rest)
    bones = tuple(sk.bone_names)
    origins = np.stack([np.asarray(sk.joint_of(b).center) if sk.joint_of(b) else np.zeros(3) for b in bones])
    p = origins[rng.integers(0, len(bones), 1200)] + rng.normal(scale=8.0, size=(1200, 3))
    d = np.linalg.norm(p[:, None] - origins[None], axis=2)
    w = SkinningWeights.from_dense(np.exp(-((d / 15.0) ** 2)) + 1e-12, bones)
    base = SurfaceMesh(p, np.arange(1200).reshape(-1, 3))  # connectivity only has to be shared
    meshes = [
        SurfaceMesh(lbs(p + 1.5 * np.sin(p / 13.0 + k), w, q.transforms), base.triangles) for k, q in enumerate(poses)
    ]
    return sk, poses, w, base, meshes


@pytest.mark.parametrize("template_example", [True, False])
def test_psd_and_wpsd_reproduce_the_examples_and_ssd_is_the_skinned_base(setup, template_example):
    sk, poses, w, base, meshes = setup
    model = SurfaceModel.from_meshes(base, w, sk, poses, meshes, template_example=template_example)
    assert model.n_examples == len(poses) + int(template_example)
    for q, m in zip(poses, meshes):
        # Kurihara Eq. 10 at a training pose: s = e_k (PSD) and per vertex (WPSD), so Kurihara Eq. 7–8 give the
        # example back; inverse blend + Gaussian solve round-off ≤ 1e-6 mm on ~100 mm coordinates (as test_posespace)
        for method in ("psd", "wpsd"):
            np.testing.assert_allclose(model.deform(q, method).vertices, m.vertices, atol=1e-5)
        np.testing.assert_allclose(model.deform(q, "ssd").vertices, lbs(base.vertices, w, q.transforms), atol=1e-9)
    rest = template_pose(sk)
    if template_example:  # S0 is the example at rest: every method gives S0 there
        for method in ("ssd", "psd", "wpsd"):
            np.testing.assert_allclose(model.deform(rest, method).vertices, base.vertices, atol=1e-5)
    else:  # extrapolated from the flexed examples: not S0
        assert np.abs(model.deform(rest, "psd").vertices - base.vertices).max() > 0.1


def test_auto_takes_the_base_mesh_when_no_example_is_at_rest(setup):
    sk, poses, w, base, meshes = setup
    assert SurfaceModel.from_meshes(base, w, sk, poses, meshes).template_example
    at_rest = [template_pose(sk)] + poses[1:]
    assert not SurfaceModel.from_meshes(base, w, sk, at_rest, [base] + meshes[1:]).template_example


def test_bad_inputs_are_refused(setup):
    sk, poses, w, base, meshes = setup
    other = SurfaceMesh(base.vertices, base.triangles[:, [0, 2, 1]])
    with pytest.raises(ValueError, match="connectivity"):
        SurfaceModel.from_meshes(base, w, sk, poses[:1], [other])
    with pytest.raises(ValueError, match="one consistent mesh per pose"):
        SurfaceModel.from_meshes(base, w, sk, poses, meshes[:2])
    with pytest.raises(ValueError, match="method"):
        SurfaceModel.from_meshes(base, w, sk, poses, meshes).deform(poses[0], "lbs")
