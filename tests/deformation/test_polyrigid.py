"""The polyrigid flow (deformation.polyrigid): rigid bones, an exact inverse, no folds where VBD folds.

Tolerances
----------
* Inside a bone the velocity is that bone's own, whose flow is exactly its
  rigid motion; RK4 with ≥ 8 steps integrates ``ẋ = V(t) x`` with an error
  far below 1e-4 mm over a 60° turn at 40 mm from the axis (O(h⁴·|V|⁵ r)).
* ``backward ∘ forward`` = identity up to the integrator's error.  The
  distance maps are trilinear (continuous, kinked at voxel faces), so RK4
  loses its order where the weights change fast (the crease): the bound there
  is a small fraction of a voxel, < 0.05 mm (1/30 of the finest spacing),
  while the median stays < 1e-5 mm.
"""

from __future__ import annotations

import numpy as np
import pytest

from deformation.fields import folding_statistics
from deformation.geometry import GridGeometry, Volume
from deformation.polyrigid import PolyrigidFlow, bone_distance_maps
from deformation.transforms import axis_angle_matrix, rotation_about_point


def _rotation(deg, axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return axis_angle_matrix(axis, deg)[:3, :3]


@pytest.fixture(scope="module")
def two_bones():
    """A femur-like and a tibia-like box along y on an anisotropic, rotated grid; the child bent 60° about z."""
    rot = _rotation(20.0, (1.0, 1.0, 0.0))
    size, spacing = (34, 44, 22), (2.0, 1.6, 2.5)
    half = rot @ ((np.asarray(size) - 1) * np.asarray(spacing) / 2.0)
    g = GridGeometry(size, spacing, tuple(-half), tuple(rot.reshape(-1)))
    x = g.world_coordinates()
    lab = np.zeros(g.array_shape, np.uint8)
    lab[(np.abs(x[..., 0]) < 6) & (np.abs(x[..., 2]) < 6) & (x[..., 1] > 3) & (x[..., 1] < 30)] = 1
    lab[(np.abs(x[..., 0]) < 6) & (np.abs(x[..., 2]) < 6) & (x[..., 1] < -3) & (x[..., 1] > -30)] = 2
    labels = Volume(lab, g)
    maps = bone_distance_maps(labels, {"upper": 1, "lower": 2})
    bend = rotation_about_point(_rotation(60.0, (0.0, 0.0, 1.0)), (0.0, 0.0, 0.0))
    t = np.stack([np.eye(4), bend])
    return g, labels, PolyrigidFlow(t, (-1, 0), maps, g), t


def test_bones_move_rigidly(two_bones):
    g, labels, flow, t = two_bones
    x = g.world_coordinates()
    for k, lab in enumerate((1, 2)):
        # deep inside the bone (one voxel in from its surface), where the weight is one
        inner = (labels.data == lab) & (flow.distance_maps[k] < -2.0)
        p = x[inner]
        moved = flow.forward(p)
        want = p @ t[k][:3, :3].T + t[k][:3, 3]
        assert np.abs(moved - want).max() < 1e-4
        back = flow.backward(want)
        assert np.abs(back - p).max() < 1e-4


def test_backward_inverts_forward(two_bones):
    g, _, flow, _ = two_bones
    rng = np.random.default_rng(3)
    lo, hi = g.index_to_world([4, 4, 4]), g.index_to_world(np.array(g.size) - 5)
    p = rng.uniform(np.minimum(lo, hi), np.maximum(lo, hi), size=(3000, 3))
    err = np.linalg.norm(flow.backward(flow.forward(p)) - p, axis=1)
    assert np.median(err) < 1e-5 and err.max() < 0.05


def test_scan_to_template_has_no_fold_in_the_crease(two_bones):
    """A 60° bend of two bones 6 mm apart: the flow's backward field is one-to-one everywhere on the grid."""
    g, _, flow, _ = two_bones
    field = flow.scan_to_template(g)
    assert field.geometry is g and field.data.dtype == np.float32
    stats = folding_statistics(field)
    assert stats["fraction_folded"] == 0.0


def test_parents_must_come_first(two_bones):
    g, _, flow, t = two_bones
    with pytest.raises(ValueError, match="parents"):
        PolyrigidFlow(t, (1, -1), flow.distance_maps, g)
    with pytest.raises(ValueError, match="agree"):
        PolyrigidFlow(t[:1], (-1, 0), flow.distance_maps, g)


def test_initial_field_from_a_skeleton_description(two_bones):
    """registration.initialise.polyrigid_initial_field orders bones parents-first, whatever order they come in."""
    from registration.initialise import polyrigid_initial_field

    g, labels, flow, t = two_bones
    field, fl = polyrigid_initial_field(labels, {"lower": 2, "upper": 1}, {"lower": "upper", "upper": None},
                                        {"upper": t[0], "lower": t[1]}, g)
    # the same bones, transforms and weights in parents-first order: the same flow, to the bit
    assert fl.parents == (-1, 0) and fl.steps == flow.steps
    assert np.array_equal(field.data, flow.scan_to_template(g).data)
    with pytest.raises(ValueError, match="no transform"):
        polyrigid_initial_field(labels, {"lower": 2, "upper": 1}, {"lower": "upper", "upper": None},
                                {"upper": t[0]}, g)
