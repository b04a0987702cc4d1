"""Sparse skinning weights, LBS (Kurihara Eq. 2), VBD (Rhee Eq. 2) and their per-point inverse (Eq. 6/7)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.models.skinning import SkinningWeights, distance_weights, inverse_lbs, lbs, stack_transforms

BONES = ("a", "b", "c", "d", "e", "f")


def _rigid(rng, max_deg=60.0, max_mm=30.0):
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.radians(rng.uniform(0, max_deg))).as_matrix()
    t[:3, 3] = rng.uniform(-max_mm, max_mm, 3)
    return t


@pytest.fixture
def rng():
    return np.random.default_rng(20261201)


def test_from_dense_keeps_four_largest_and_is_a_partition_of_unity(rng):
    dense = rng.random((500, 6)) ** 3
    w = SkinningWeights.from_dense(dense, BONES)
    assert w.max_influences == 4
    # Kurihara Eq. 3; float32 storage rounds each weight by ≤ 6e-8 relative.
    np.testing.assert_allclose(w.value.astype(float).sum(1), 1.0, atol=1e-6)
    assert w.value.min() >= 0.0
    # the kept bones are the four largest of each row, in decreasing order
    top = np.argsort(-dense, axis=1)[:, :4]
    np.testing.assert_array_equal(np.sort(w.index, axis=1), np.sort(top, axis=1))
    assert np.all(np.diff(w.value, axis=1) <= 0)
    # dense() puts the renormalised weights back in place
    expect = np.zeros_like(dense)
    np.put_along_axis(expect, top, np.take_along_axis(dense, top, 1), 1)
    np.testing.assert_allclose(w.dense(), expect / expect.sum(1, keepdims=True), rtol=1e-6, atol=1e-7)


def test_bad_weights_are_refused():
    with pytest.raises(ValueError, match="sum to one"):
        SkinningWeights(BONES, np.zeros((2, 2), int), np.array([[0.5, 0.4], [1.0, 0.0]]))
    with pytest.raises(ValueError, match="non-negative"):
        SkinningWeights(BONES, np.zeros((1, 2), int), np.array([[1.5, -0.5]]))
    with pytest.raises(ValueError, match="out of range"):
        SkinningWeights(BONES, np.full((1, 1), 6), np.ones((1, 1)))
    with pytest.raises(ValueError, match="no positive weight"):
        SkinningWeights.from_dense(np.zeros((1, 6)), BONES)


def test_lbs_with_all_weight_on_one_bone_is_that_bones_rigid_transform(rng):
    ts = {b: _rigid(rng) for b in BONES}
    p = rng.uniform(-150, 150, (300, 3))
    for k, b in enumerate(BONES):
        w = SkinningWeights.one_hot(np.full(len(p), k), BONES)
        # ~100 mm coordinates, one 4×4 product: float64 round-off ≪ 1e-10 mm.
        np.testing.assert_allclose(lbs(p, w, ts), p @ ts[b][:3, :3].T + ts[b][:3, 3], atol=1e-10)


def test_lbs_is_the_weighted_sum_of_transformed_points_and_inverts_per_point(rng):
    ts = stack_transforms({b: _rigid(rng, max_deg=30) for b in BONES}, BONES)
    p = rng.uniform(-100, 100, (400, 3))
    w = SkinningWeights.from_dense(rng.random((400, 6)), BONES)
    d = w.dense()
    expect = np.einsum("nk,kij,nj->ni", d, ts[:, :3, :3], p) + d @ ts[:, :3, 3]
    # float32 weights: each product carries ≤ 6e-8 relative error on ~100 mm values.
    np.testing.assert_allclose(lbs(p, w, ts), expect, atol=1e-5)
    # Kurihara Eq. 6 / Rhee Eq. 7: the blended matrix of the template point undoes the blend
    np.testing.assert_allclose(inverse_lbs(lbs(p, w, ts), w, ts), p, atol=1e-9)


def test_missing_transform_names_the_bone(rng):
    w = SkinningWeights.one_hot(np.zeros(3, int), BONES)
    with pytest.raises(ValueError, match="'f'"):
        lbs(np.zeros((3, 3)), w, {b: np.eye(4) for b in BONES[:-1]})


def test_distance_weights_are_one_hot_inside_a_bone_and_follow_the_nearest_bone(rng):
    d = rng.uniform(1.0, 60.0, (200, 6))
    d[:20, 2] = -1.0  # inside bone c
    w = distance_weights(d, BONES)
    dense = w.dense()
    np.testing.assert_array_equal(dense[:20, 2], 1.0)
    np.testing.assert_allclose(dense.sum(1), 1.0, atol=1e-6)
    # the nearest bone has the largest weight (w ∝ d^-p e^(-d/λ) decreases with d)
    assert np.all(np.argmax(dense[20:], 1) == np.argmin(d[20:], 1))


def test_dense_to_sparse_in_chunks_gives_the_same_bits(monkeypatch):
    """distance_weights and from_dense work in row chunks (memory): any chunk size, the same arrays."""
    import deformation.models.skinning as sk

    rng = np.random.default_rng(3)
    d = rng.normal(20, 15, (1000, 9))
    d[:7] = -1.0  # inside a bone
    bones = [f"b{i}" for i in range(9)]
    whole = sk.distance_weights(d, bones)
    dense = np.abs(rng.normal(size=(1000, 9)))
    whole_dense = sk.SkinningWeights.from_dense(dense, bones)
    monkeypatch.setattr(sk, "DENSE_CHUNK", 37)  # 28 chunks, the last one short
    parts = sk.distance_weights(d, bones)
    parts_dense = sk.SkinningWeights.from_dense(dense, bones)
    for a, b in ((whole, parts), (whole_dense, parts_dense)):
        assert np.array_equal(a.index, b.index) and np.array_equal(a.value, b.value)
        assert a.index.dtype == b.index.dtype and a.value.dtype == b.value.dtype
    assert sk.distance_weights(np.zeros((0, 9)), bones).n_points == 0
