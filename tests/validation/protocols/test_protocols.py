"""The papers' protocols (validation.protocols): tables, the pose library and its eigenposes, the measures' logic.

The protocols that run the pipeline are checked here with a stand-in runner whose study returns known
measures (the arithmetic of the table), and end to end in tests/workbench/test_reproduce.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from validation.phantoms import hand
from validation.protocols import PROTOCOLS, Column, Table
from validation.protocols.eigenposes import eigenposes, explained_variance, loo_reconstruction_rms, pose_matrix
from validation.protocols.hand_poses import LIBRARY, RANGE_OF_MOTION, check_range, library_angles
from validation.protocols.kurihara import joint_centre_measures
from validation.protocols.registration import ALGORITHM1_ROW, PAPER, registration_table, ssd_scale


def test_table_round_trip_keeps_numbers_and_turns_nan_into_none():
    t = Table("x", "a title", [Column("a", "A", "mm"), Column("b", "B", "", 3)], definitions={"a": "the a"})
    t.add("ours", "ours", {"a": 1.25, "b": float("nan")}, n=3)
    t.add("paper: source", "paper", {"a": 5.5}, source="somewhere")
    back = Table.from_dict(t.to_dict())
    assert back.value("ours", "a") == 1.25
    assert back.value("ours", "b") is None  # NaN is not a number a JSON reader can take
    assert back.row("paper: source")["source"] == "somewhere"
    assert back.columns == t.columns and back.definitions == {"a": "the a"}
    with pytest.raises(ValueError, match="row kind"):
        t.add("odd", "mine", {})
    with pytest.raises(KeyError, match="no row 'missing'"):
        t.row("missing")


def test_every_protocol_is_registered():
    assert set(PROTOCOLS) == {"table2", "table3", "table4", "loo", "eigenposes", "kurihara", "kurihara_skin"}


# -- the pose library --------------------------------------------------------------------------------------
def test_library_has_at_least_60_documented_poses_within_normal_ranges():
    sk = hand.skeleton()
    entries = library_angles(sk)
    assert len(entries) >= 60  # Rhee §6.2 used 60 poses
    assert len({e[0] for e in entries}) == len(entries)  # no name twice
    assert {e[1] for e in entries} == {"GRASP (Feix et al. 2016)", "ASL manual alphabet", "gesture"}
    assert sum(e[1].startswith("GRASP") for e in entries) == 33  # the taxonomy's 33 grasp types
    for name, _, angles in entries:
        assert set(angles) == {j.name for j in sk.joints}
        assert check_range(angles) == [], name


def test_range_check_names_the_joint_outside_its_range():
    sk = hand.skeleton()
    angles = dict(library_angles(sk)[0][2])
    angles["index_pip"] = np.array([130.0, 0.0, 0.0])  # beyond the PIP's 110° (AAOS 100°, widened) of flexion
    bad = check_range(angles)
    assert len(bad) == 1 and bad[0].startswith("index_pip[0] = 130")
    assert RANGE_OF_MOTION["pip"][0] == (-10, 110)


def test_explained_variance_of_two_known_directions():
    # rows ±2 along e1 and ±1 along e2 (four rows each way, centred): variances 4 and 1 → shares 0.8 and 0.2
    e1, e2 = np.eye(5)[0], np.eye(5)[3]
    x = np.array([s * 2 * e1 for s in (1, -1, 1, -1)] + [s * e2 for s in (1, -1, 1, -1)]) + 7.0
    v = explained_variance(x)
    assert v[:2] == pytest.approx([0.8, 0.2], abs=1e-12)
    assert v[2:] == pytest.approx(0.0, abs=1e-12)


def test_left_out_rows_in_the_span_of_the_others_are_rebuilt_exactly():
    rng = np.random.default_rng(3)
    basis = rng.normal(size=(3, 12))
    x = rng.normal(size=(20, 3)) @ basis + 5.0  # a 3-dimensional affine subspace
    assert loo_reconstruction_rms(x, 3) == pytest.approx(0.0, abs=1e-9)
    assert loo_reconstruction_rms(x, 1) > 0.1  # fewer components lose something


def test_eigenpose_table_matches_its_own_definition():
    t = eigenposes()
    x, names, _ = pose_matrix(hand.skeleton())
    cum = np.cumsum(explained_variance(x))
    ours = t.row("ours")
    assert ours["n_poses"] == len(LIBRARY) == len(names)
    assert ours["variance_10"] == pytest.approx(cum[9])
    assert (
        cum[ours["components_for_90"] - 1]
        >= 0.90
        > (cum[ours["components_for_90"] - 2] if ours["components_for_90"] > 1 else -1)
    )
    assert t.row("paper (Rhee §6.2, Poser poses)")["variance_10"] == 0.90


# -- Kurihara Eq. 1 measures -------------------------------------------------------------------------------
class _Joint:
    def __init__(self, c):
        self.center = c


class _Skeleton:
    def __init__(self, centres):
        self.c = centres

    def joint(self, name):
        return _Joint(self.c[name])


def test_joint_centre_measures_against_hand_computed_values():
    sk = _Skeleton({"a": (0.0, 0.0, 0.0), "b": (10.0, 0.0, 0.0), "c": (0.0, 5.0, 0.0)})
    joints = {
        # a hinge along z, its estimate 3 mm along the axis and 0.4 mm off it
        "a": {
            "dof": 3,
            "per_scan_mm": [0.3, 0.4],
            "center": [0.4, 0.0, 3.0],
            "is_hinge": True,
            "axis": [0, 0, 2.0],
            "estimated": True,
        },
        "b": {
            "dof": 3,
            "per_scan_mm": [1.2],
            "center": [10.0, 1.0, 0.0],
            "is_hinge": False,
            "axis": [0, 0, 0],
            "estimated": True,
        },
        # a 6-DOF joint: its residual is left out of Kurihara's figure, its centre is not
        "c": {
            "dof": 6,
            "per_scan_mm": [9.0],
            "center": [0.0, 5.0, 2.0],
            "is_hinge": False,
            "axis": [0, 0, 0],
            "estimated": True,
        },
        "still": {"dof": 3, "per_scan_mm": [0.0], "center": [0, 0, 0], "estimated": False},
    }
    m = joint_centre_measures(joints, sk)
    assert m["eq1_rms_mm"] == pytest.approx(math.sqrt((0.09 + 0.16 + 1.44) / 3))
    assert m["center_error_mean_mm"] == pytest.approx((math.hypot(0.4, 3.0) + 1.0 + 2.0) / 3)
    assert m["center_error_max_mm"] == pytest.approx(math.hypot(0.4, 3.0))
    assert m["off_axis_mean_mm"] == pytest.approx((0.4 + 1.0 + 2.0) / 3)
    assert m["n_joints"] == 3


# -- the registration tables' arithmetic --------------------------------------------------------------------
class _Vol:
    def __init__(self, data):
        self.data = data


class _Study:
    """A stand-in for a workbench Study: three scans with known validate-stage rows."""

    root = "/nowhere"
    manifest = {"phantom": {"region": "knee"}}

    def __init__(self):
        self.scan_ids = ["pose00", "pose01", "pose02"]
        self.rows = {
            s: {
                "source": {
                    "med_mm": 10.0 + i,
                    "marker_med_mm": 8.0,
                    "ssd": 100.0 * (i + 1),
                    "cc": 0.5,
                    "mi": 0.2,
                    "folded_fraction": 0.0,
                },
                "initialised": {
                    "med_mm": 2.0 + i,
                    "marker_med_mm": 3.0,
                    "ssd": 40.0,
                    "cc": 0.8,
                    "mi": 0.4,
                    "folded_fraction": 0.01 * i,
                },
                "registered": {
                    "med_mm": 1.0 + i,
                    "marker_med_mm": None,
                    "ssd": 20.0,
                    "cc": 0.9,
                    "mi": 0.5,
                    "folded_fraction": 0.0,
                },
            }
            for i, s in enumerate(self.scan_ids)
        }

    def validation(self, s):
        return {"rows": self.rows[s]}

    def stage_entry(self, stage, s):  # the times are the manifest's (log.json holds none)
        assert stage == "register"
        return {"timings": {"registration": {"pose00": 1.0, "pose01": 2.0, "pose02": 4.0}[s]}}

    def template(self):
        return _Vol(np.linspace(0.0, 510.0, 1001))  # 0.5-99.5th percentiles 2.55 and 507.45

    def recorded_settings(self, stage):
        return None

    def weights(self):
        return None, None


class _Settings:
    def to_dict(self):
        return {"levels": [3, 4], "optimizer": "bobyqa"}


class _Result:
    """A stand-in for an AdaptiveResult: its scan's name in place of the fields, and a time."""

    def __init__(self, sid, seconds):
        self.registered = self.correspondence = sid
        self.seconds = seconds
        self.settings = _Settings()


class _Runner:
    with_peers = False

    def __init__(self):
        self.asked = []
        self.adaptive = []

    def study(self, name, phantom, *, settings, targets):
        self.asked.append((name, settings, tuple(targets)))
        return _Study()

    def register_adaptive(self, study, sid, *, settings):
        self.adaptive.append((sid, settings))
        return _Result(sid, {"pose00": 10.0, "pose01": 20.0, "pose02": 40.0}[sid])

    def say(self, m):
        pass


@pytest.fixture
def scored(monkeypatch):
    """Algorithm 1's registrations scored by known measures (the scan's MED 0.5 + its index), not by
    validation_rows on real volumes (which tests/workbench/test_reproduce.py runs)."""
    from validation.protocols import registration

    def measured(study, sid, template, body, *, registered, field, seconds):
        assert registered == field == sid  # the result of this scan, as the runner returned it
        i = int(sid[-1])
        return {
            "med_mm": 0.5 + i,
            "marker_med_mm": 1.0,
            "ssd": 10.0,
            "cc": 0.95,
            "mi": 0.6,
            "folded_fraction": 0.0,
            "seconds": seconds,
        }

    monkeypatch.setattr(registration, "_measured", measured)


def test_table3_averages_the_posed_scans_only_and_scales_ssd_to_8_bit(scored):
    runner = _Runner()
    t = registration_table(runner, "table3", title="t3", init="vbd")
    assert runner.asked == [("table3", {"init": {"method": "vbd"}, "weights": {}, "register": {}}, ("validate",))]
    scale = (255.0 / (507.45 - 2.55)) ** 2
    assert ssd_scale(_Study().template()) == pytest.approx(scale)
    src = t.row("source (no deformation)")
    # pose00 (the template's own pose) is left out: means over pose01, pose02
    assert src["med_mm"] == pytest.approx(11.5)
    assert src["ssd"] == pytest.approx(250.0 * scale)
    assert t.row("initialised")["folded_fraction"] == pytest.approx(0.015)
    reg = t.row("registered (ours)")
    assert reg["marker_med_mm"] is None  # no marker measure: nothing to average
    assert reg["seconds"] == pytest.approx(3.0)
    assert t.row("paper: registered")["marker_med_mm"] == PAPER["table3"]["registered"]["marker_med_mm"]
    assert all(k in t.definitions for k in ("med_mm", "ssd", "mi", "folded_fraction"))
    # Rhee's Algorithm 1 on the same posed scans, with the register stage's (default) settings, averaged alike
    assert runner.adaptive == [("pose01", {}), ("pose02", {})]
    alg1 = t.row(ALGORITHM1_ROW)
    assert alg1["kind"] == "ours" and alg1["n_scans"] == 2
    assert alg1["med_mm"] == pytest.approx(2.0) and alg1["seconds"] == pytest.approx(30.0)
    assert alg1["ssd"] == pytest.approx(10.0 * scale)
    labels = [r["label"] for r in t.rows]
    assert labels.index("registered (ours)") + 1 == labels.index(ALGORITHM1_ROW) < labels.index("paper: source")
    assert t.meta["algorithm1_settings"] == {"levels": [3, 4], "optimizer": "bobyqa"}
    assert any(n.startswith(ALGORITHM1_ROW) and "not the paper's figures" in n for n in t.notes)


def test_table2_keeps_its_single_scan(scored):
    t = registration_table(_Runner(), "table2", title="t2", init="identity")
    assert t.row("source (no deformation)")["med_mm"] == pytest.approx(11.0)  # mean of the three scans
    assert t.row(ALGORITHM1_ROW)["med_mm"] == pytest.approx(1.5)  # Algorithm 1 on all three as well
    assert t.row("paper: source")["med_mm"] == 5.5


def test_registration_training_positions_keep_the_found_voxels_and_pose_the_others_by_vbd():
    """The EVD example of a study scan (the model stage's and the loo protocol's): where the registration's
    inverse found a template voxel its position is kept; elsewhere VBD puts it (Rhee Eq. 2), here a one-hot
    blend, so bone b's voxels move by its translation and bone a's stay."""
    from deformation.geometry import GridGeometry
    from deformation.kinematics.skeleton import Pose
    from deformation.models.skinning import SkinningWeights
    from validation.leave_one_out import registration_training_positions

    g = GridGeometry((4, 3, 2), (1.0, 2.0, 3.0), (10.0, 0.0, -5.0), np.eye(3).reshape(-1))
    x = g.world_coordinates()
    on_b = (np.arange(g.n_voxels) % 2).reshape(g.array_shape).astype(bool)  # alternate voxels on bone b
    weights = SkinningWeights.from_dense(np.stack([~on_b.reshape(-1), on_b.reshape(-1)], 1).astype(float), ("a", "b"))
    shift = np.eye(4)
    shift[:3, 3] = (5.0, -1.0, 2.0)
    pose = Pose({"a": np.eye(4), "b": shift})
    registered = x + 0.25  # where the registration put every voxel
    found = np.zeros(g.array_shape, bool)
    found[0] = True

    class Study:
        def pose(self, scan_id):
            assert scan_id == "s1"
            return pose

        def registration_positions(self, scan_id):
            return registered, found

    got_pose, pos, got_found = registration_training_positions(Study(), "s1", g, weights)
    assert got_pose is pose and got_found is found
    expected = np.where(found[..., None], registered, x + np.where(on_b[..., None], shift[:3, 3], 0.0))
    np.testing.assert_allclose(pos, expected, rtol=0, atol=1e-5)  # VBD's positions are float32
