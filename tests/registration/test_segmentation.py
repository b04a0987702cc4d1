"""Template bone segmentation from seeds, against the phantom's exact label map."""

from __future__ import annotations

import json

import numpy as np
import pytest

from registration.segmentation import guess_modality, seeds_from_labels, segment_bones
from workbench.errors import InputFileError
from workbench.io.inputs import read_seeds


def dice(a, b):
    return 2.0 * (a & b).sum() / (a.sum() + b.sum())


@pytest.fixture(scope="module")
def knee_templates():
    from validation.phantoms import make_phantom

    out = {}
    for modality in ("ct", "mri"):
        ph = make_phantom("knee", size="test", modality=modality, n_poses=1, seed=4)
        out[modality] = ph.template() + (ph.skeleton,)
    return out


def test_ct_threshold_components_and_watershed(knee_templates):
    img, lab, sk = knee_templates["ct"]
    assert guess_modality(img) == "ct"
    seg, rep = segment_bones(img, sk, seeds_from_labels(lab, sk))
    assert rep.warnings == []
    d = {b.name: dice(lab.data == b.label, seg.data == b.label) for b in sk.bones}
    # At 5 mm voxels the label map marks voxel centres inside the bone and the 400 HU threshold marks voxels
    # more than about a third bone, so the partial-volume rim differs: measured Dice 0.84 (patella) - 0.89.
    # All four bones touch at this resolution, so this also checks the watershed split.
    assert min(d.values()) >= 0.8, d
    assert seg.geometry == img.geometry and seg.data.dtype == np.uint16


@pytest.mark.xfail(strict=True, reason=(
    "known, issue L: with the phantom's structured soft tissue (issue I: fat septa of marrow-like intensity, "
    "vessels), intensity-only MRI region growing at 5 mm leaks for the patella and fibula (reported, voxels "
    "dropped) and under-segments the femur silently (Dice 0.29, 281 voxels, no warning)"))
def test_mri_region_growing_reports_what_it_cannot_segment(knee_templates):
    img, lab, sk = knee_templates["mri"]
    assert guess_modality(img) == "mri"
    seg, rep = segment_bones(img, sk, seeds_from_labels(lab, sk))
    d = {b.name: dice(lab.data == b.label, seg.data == b.label) for b in sk.bones}
    # Marrow enclosed by dark cortex grows for the big bones (measured Dice 0.77-0.92 over two seeds; the
    # rim of partial-volume voxels is where they differ, and a leak retried with a tighter band
    # under-segments).  Weaker than CT, as expected of intensity-only MRI segmentation at 5 mm.  The
    # fibula's marrow is about one voxel wide at 5 mm: its growth leaks into muscle, and that must be
    # reported (and its voxels dropped), not passed on.
    for b in ("femur", "tibia", "patella"):
        assert d[b] >= 0.75, d
    if d["fibula"] < 0.75:  # a poor fibula must come with a warning and no voxels, never silently
        assert any("fibula" in w for w in rep.warnings), rep.warnings
        assert rep.voxels["fibula"] == 0


def test_seeds_file_errors(tmp_path, knee_templates):
    img, lab, sk = knee_templates["ct"]
    good = {b: p.tolist() for b, p in seeds_from_labels(lab, sk).items()}

    def write(obj):
        p = tmp_path / "seeds.json"
        p.write_text(json.dumps(obj))
        return p

    ok = read_seeds(write({"format": "avw-seeds", "version": 1, "seeds": good}), sk)
    assert set(ok) == set(sk.bone_names)
    with pytest.raises(InputFileError, match="no seed for bones"):
        read_seeds(write({"format": "avw-seeds", "version": 1, "seeds": {"femur": good["femur"]}}), sk)
    with pytest.raises(InputFileError, match="unknown bones"):
        read_seeds(write({"format": "avw-seeds", "version": 1, "seeds": {**good, "ulna": [[0, 0, 0]]}}), sk)
    with pytest.raises(InputFileError, match="not a seeds file"):
        read_seeds(write({"seeds": good}), sk)
    with pytest.raises(InputFileError, match=r"\[x, y, z\]"):
        read_seeds(write({"format": "avw-seeds", "version": 1, "seeds": {**good, "femur": [[1, 2]]}}), sk)
    far = {**{b: np.asarray(p) for b, p in good.items()}, "femur": np.array([[1e4, 0.0, 0.0]])}
    with pytest.raises(ValueError, match="outside the image"):
        segment_bones(img, sk, far)
