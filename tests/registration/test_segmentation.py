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
def knee_templates(phantom):
    out = {}
    for modality in ("ct", "mri"):
        ph = phantom("knee", size="test", modality=modality, n_poses=1, seed=4)
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


def _brightest(img, lab, sk, bone, n=5):
    """``n`` seeds in the bone's brightest voxels (world mm), as a user clicking on bright marrow would."""
    m = lab.data == sk.label_of(bone)
    flat = np.flatnonzero(m.ravel())
    top = flat[np.argsort(img.data.ravel()[flat])[-n:]]
    kji = np.stack(np.unravel_index(top, m.shape), axis=1)
    return img.geometry.index_to_world(kji[:, ::-1].astype(float))


def test_mri_marrow_flood_at_5mm(knee_templates):
    """On the knee with structured soft tissue (fat septa as bright as marrow), the earlier region
    growing under-segmented the femur silently (Dice 0.29) and dropped the fibula and patella."""
    img, lab, sk = knee_templates["mri"]
    assert guess_modality(img) == "mri"
    seg, rep = segment_bones(img, sk, seeds_from_labels(lab, sk))
    d = {b.name: dice(lab.data == b.label, seg.data == b.label) for b in sk.bones}
    # Measured over seeds 0-4 at this 5 mm grid: femur 0.93-0.94, tibia 0.90-0.92, patella 0.73-0.87, fibula
    # 0.50-0.77 (about 3 voxels across: its marrow is one partial-volume voxel, the rest cortex and rim).
    assert d["femur"] >= 0.85 and d["tibia"] >= 0.85, d
    assert d["patella"] >= 0.65 and d["fibula"] >= 0.4, d
    assert rep.warnings == [] and set(rep.parameters["thresholds"]) == set(sk.bone_names)


def test_mri_fibula_from_five_bright_seeds_at_2_5mm(phantom):
    """The failing case: five seeds in the fibula's brightest voxels, at a grid that resolves its marrow."""

    ph = phantom("knee", size="test", modality="mri", n_poses=1, seed=4, spacing=(2.5, 2.5, 2.5))
    img, lab = ph.template()
    sk = ph.skeleton
    seeds = {**seeds_from_labels(lab, sk), "fibula": _brightest(img, lab, sk, "fibula")}
    seg, rep = segment_bones(img, sk, seeds)
    d = {b.name: dice(lab.data == b.label, seg.data == b.label) for b in sk.bones}
    # Measured over seeds 0, 1, 4: femur and tibia 0.95-0.97, patella 0.91-0.94, fibula 0.86 (6 voxels across:
    # a third of its voxels are the partial-volume rim where the label map and any threshold differ); 1.25 mm
    # (Rhee's knee grid, too slow here): 0.98 / 0.98 / 0.98 / 0.89-0.95.
    assert min(d.values()) >= 0.8, d
    assert rep.warnings == []


def test_mri_seed_outside_a_bone_is_reported_and_dropped(knee_templates):
    """A 'fibula' seed in the subcutaneous fat floods to the skin at any threshold: reported, no voxels."""
    from scipy import ndimage

    img, lab, sk = knee_templates["mri"]
    body = ndimage.binary_erosion(img.data > 0.3 * img.data.max(), iterations=1)
    rim = body & ~ndimage.binary_erosion(body) & (lab.data == 0)
    kji = np.argwhere(rim)[0]
    seeds = {**seeds_from_labels(lab, sk), "fibula": img.geometry.index_to_world(kji[::-1][None].astype(float))}
    seg, rep = segment_bones(img, sk, seeds)
    assert rep.voxels["fibula"] == 0 and not (seg.data == sk.label_of("fibula")).any()
    assert any("'fibula'" in w and "floods out of the bone" in w for w in rep.warnings), rep.warnings


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


def test_mri_a_bright_seed_in_the_fat_is_left_out_not_the_bone(knee_templates):
    """A femur seed clicked in the subcutaneous fat (brighter than the marrow) beside its good seed: the seed is
    reported and left out, the femur is grown from the other as without it."""
    from scipy import ndimage

    img, lab, sk = knee_templates["mri"]
    good = seeds_from_labels(lab, sk)
    body = ndimage.binary_erosion(img.data > 0.3 * img.data.max(), iterations=1)
    rim = body & ~ndimage.binary_erosion(body) & (lab.data == 0)
    kji = np.argwhere(rim)
    fat = kji[np.argmax(img.data[rim])]  # the rim's brightest voxel: fat, brighter than the femur's seed
    assert (
        img.data[tuple(fat)] > img.data[tuple(np.rint(img.geometry.world_to_index(good["femur"])[0, ::-1]).astype(int))]
    )
    bad = {**good, "femur": np.vstack([good["femur"], img.geometry.index_to_world(fat[::-1][None].astype(float))])}
    seg_good, _ = segment_bones(img, sk, good)
    seg_bad, rep = segment_bones(img, sk, bad)
    assert np.array_equal(seg_bad.data, seg_good.data)
    assert any("'femur'" in w and "left out" in w for w in rep.warnings), rep.warnings
