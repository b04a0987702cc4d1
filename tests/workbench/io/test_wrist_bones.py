"""Real wrist bones in three poses (workbench.io.wrist_bones); skipped when the data are absent."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from deformation.meshes.mesh import SurfaceMesh
from workbench.errors import MissingFileError
from workbench.io.meshes import write_mesh
from workbench.io.wrist_bones import (
    POSES,
    WristDataError,
    default_wrist_root,
    find_wrist_data,
    load_wrist_study,
    true_motion,
    wrist_volunteers,
)

WRIST = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "wrist-bones-mri"
ROOT = find_wrist_data(WRIST)
needs_wrist = pytest.mark.skipif(ROOT is None, reason=f"real data absent: {WRIST}")


@pytest.fixture(scope="module", params=[1, 2], ids=["volunteer1", "volunteer2"])
def study(request):
    if ROOT is None:
        pytest.skip(f"real data absent: {WRIST}")
    return load_wrist_study(request.param, root=ROOT)


def test_find_wrist_data_returns_none_when_absent(tmp_path):
    assert find_wrist_data(tmp_path / "nowhere") is None
    assert find_wrist_data(tmp_path) is None  # folder without the files
    assert wrist_volunteers(tmp_path) == []


@needs_wrist
def test_default_root_is_the_shared_data_folder():
    assert default_wrist_root() == WRIST.resolve()
    assert find_wrist_data() == WRIST.resolve()
    assert wrist_volunteers() == [1, 2]


def test_ten_bones_and_debris_dropped(study):
    assert study.poses == POSES
    assert len(study.bones) == 10
    counts = [b.n_triangles for b in study.bones]
    assert min(counts) == 4950 and max(counts) == 22885  # the README's range
    assert all(4950 <= c <= 22885 for c in counts)
    # Debris: 42 tiny components, none over 4 triangles; with the bones they make the whole file.
    assert len(study.debris_sizes) == 42 and max(study.debris_sizes) <= 4
    assert sum(counts) + study.n_debris_triangles == 109304
    # Bones are ordered by lowest source vertex; vertex sets are disjoint.
    firsts = [int(b.vertex_ids[0]) for b in study.bones]
    assert firsts == sorted(firsts) and firsts[0] == 0
    all_ids = np.concatenate([b.vertex_ids for b in study.bones])
    assert np.unique(all_ids).size == all_ids.size


def test_each_bone_is_one_manifold_surface_with_small_holes(study):
    # The surfaces are edge-manifold but not all closed: 9 of the 10 bones
    # have a few small holes (boundary edges), which matters for voxelising them.
    boundary = []
    for bone in study.bones:
        mesh = bone.mesh("neutral")
        assert isinstance(mesh, SurfaceMesh)
        assert mesh.n_vertices == bone.vertex_ids.size
        edges = np.sort(
            np.vstack([bone.triangles[:, [0, 1]], bone.triangles[:, [1, 2]], bone.triangles[:, [2, 0]]]), axis=1
        )
        _, uses = np.unique(edges, axis=0, return_counts=True)
        assert uses.max() == 2  # no edge shared by three triangles
        boundary.append(int((uses == 1).sum()))
        assert boundary[-1] < 0.01 * uses.size
        for pose in POSES:
            assert bone.positions[pose].shape == (bone.n_vertices, 3)
    assert boundary == [8, 45, 10, 12, 11, 10, 0, 20, 153, 71]


def test_bones_move_rigidly_between_poses(study):
    rotations = []
    for bone in study.bones:
        for to_pose in ("radial_deviation", "ulnar_deviation"):
            motion = true_motion(study, bone, "neutral", to_pose)
            # Vertices are stored as float32 (~4e-6 mm at 50 mm): the rigid fit
            # must explain the motion to that precision.
            assert motion.rms_mm < 1e-3
            assert motion.max_mm < 1e-3
            assert np.isclose(np.linalg.det(motion.transform[:3, :3]), 1.0, atol=1e-12)
            moved = bone.positions["neutral"] @ motion.transform[:3, :3].T + motion.transform[:3, 3]
            assert np.abs(moved - bone.positions[to_pose]).max() < 1e-3
        rotations.append(true_motion(study, bone, "neutral", "radial_deviation").rotation_deg)
    assert max(rotations) > 1.0  # the poses differ by real motion


def test_motion_composes_and_inverts(study):
    bone = study.bones[0]
    a = true_motion(study, bone, "neutral", "radial_deviation").transform
    b = true_motion(study, bone, "radial_deviation", "ulnar_deviation").transform
    c = true_motion(study, bone, "neutral", "ulnar_deviation").transform
    np.testing.assert_allclose(b @ a, c, atol=1e-5)
    back = true_motion(study, 0, "radial_deviation", "neutral").transform
    np.testing.assert_allclose(back @ a, np.eye(4), atol=1e-5)


def test_missing_volunteer(tmp_path):
    with pytest.raises(MissingFileError) as err:
        load_wrist_study(3, root=tmp_path)
    assert "volunteer3_neutral.ply" in str(err.value) and "root=" in str(err.value)


@needs_wrist
def test_poses_with_different_meshes_are_refused(tmp_path):
    for pose in ("neutral", "radial_deviation"):
        shutil.copy(ROOT / f"volunteer1_{pose}.ply", tmp_path)
    # An "ulnar" file whose triangles differ: the wrist split must notice.
    s = load_wrist_study(1, root=ROOT, poses=("neutral",))
    bone = s.bones[0]
    shuffled = SurfaceMesh(bone.positions["neutral"], bone.triangles[::-1])
    write_mesh(shuffled, tmp_path / "volunteer1_ulnar_deviation.ply")
    with pytest.raises(WristDataError) as err:
        load_wrist_study(1, root=tmp_path)
    assert "volunteer1_ulnar_deviation.ply" in str(err.value)
