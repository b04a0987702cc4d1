"""Randomised acquisition of the phantoms (``acquisition="random"``).

Tolerances
----------
Noise is measured on the knee's test grid, whose voxels carry independent
noise, so every statistic's standard error follows from its sample count N:

* Gaussian noise in air (``v = air + offset + n``): the sample standard
  deviation has relative standard error 1/sqrt(2N), the mean σ/sqrt(N).
* Rician noise in air is Rayleigh: mean σ·sqrt(π/2), standard deviation
  σ·sqrt((4 − π)/2).
* Everywhere, with the known clean image ``A = gain · bias · (clean − air)``:
  Gaussian ``v − air − offset − A`` is N(0, σ²); Rician ``E[(v − air)²] =
  A² + 2σ²`` with variance 4A²σ² + 4σ⁴.  These check that the bias field
  :meth:`Phantom.bias_field` returns and the drawn gain are the ones applied.
* SNR in tissue (muscle, its clean texture divided out): the Rician mean
  exceeds A by less than σ²/(2A), i.e. a relative 1/(2·SNR_min²) with SNR_min
  the lowest local SNR in the region.

Every bound is 5 standard errors (plus that Rician bias where it applies).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from validation.phantoms import Phantom, PhantomSpec, make_phantom
from validation.phantoms.anatomy import CONTRASTS
from validation.phantoms.generate import (
    ANISOTROPY_RANGE,
    BIAS_RANGE,
    GAIN_RANGE,
    MIN_AXIS_VOXELS,
    OFFSET_FRACTION,
    REGIONS,
    SNR_RANGE,
    TISSUE_JITTER,
    TISSUES,
    draw_acquisition,
)

COARSE = (9.0, 9.0, 9.0)  # a knee of 35 x 35 x 16 voxels: the truth in a fraction of a second
Z = 5.0  # standard errors


def _relative(c, t):
    return (getattr(c, t) - c.air) / (c.muscle - c.air)


# -- the default path ------------------------------------------------------------------------------------


def test_default_spec_records_no_acquisition_and_draws_nothing():
    """The default writes the manifest keys it always did (so studies written before compare equal in
    reproduce's check) and uses the modality's own table."""
    assert set(PhantomSpec().to_dict()) == {"region", "size", "modality", "n_poses", "posing", "seed", "noise"}
    ph = make_phantom("knee", spacing=COARSE, n_poses=1)
    assert ph.acquisition is None and ph.contrast is CONTRASTS["mri"]
    assert PhantomSpec(acquisition="random").to_dict()["acquisition"] == "random"
    with pytest.raises(ValueError, match="acquisition must be one of"):
        PhantomSpec(acquisition="varied")


def test_spec_round_trips_through_its_dict_and_json():
    d = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).ravel()
    for spec in (
        PhantomSpec(),
        PhantomSpec(region="hand", modality="ct", n_poses=3, seed=7, acquisition="random"),
        PhantomSpec(spacing=(6.0, 5.0, 4.5), direction=tuple(d), noise=False, posing="vbd"),
    ):
        assert PhantomSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec


# -- the draws -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("region", ["knee", "hand"])
def test_drawn_parameters_are_within_their_ranges_over_20_seeds(region):
    weights, fat, noises = [], [], set()
    for seed in range(20):
        for modality in ("mri", "ct"):
            spec = PhantomSpec(region=region, modality=modality, seed=seed, n_poses=3, acquisition="random")
            a = draw_acquisition(spec)
            st, base = a["study"], CONTRASTS[modality]
            span = base.muscle - base.air
            w = st["contrast_weight_ct"]
            assert 0.0 <= w <= 1.0
            if modality == "mri":  # the draws are the seed's whatever the modality (which sets the units)
                weights.append(w)
            c = st["contrast"]
            assert c["air"] == base.air and c["muscle"] == base.muscle
            for t in TISSUES:
                j = st["tissue_jitter"][t]
                assert j == 1.0 if t == "muscle" else 1 - TISSUE_JITTER <= j <= 1 + TISSUE_JITTER
                lo, hi = sorted((_relative(CONTRASTS["mri"], t), _relative(CONTRASTS["ct"], t)))
                rel = (c[t] - c["air"]) / span
                assert lo * j - 1e-12 <= rel <= hi * j + 1e-12, (t, rel, lo, hi, j)
            fat.append((c["fat"] - c["air"]) / span)
            # anisotropic spacing: the field of view is kept, every axis keeps MIN_AXIS_VOXELS voxels, the voxel
            # volume is kept but where the slice was capped, the slice/in-plane ratio is the drawn one (or less)
            size, base_sp = REGIONS[region].GRIDS["test"]
            extent = np.asarray(size) * np.asarray(base_sp)
            sp = np.asarray(st["spacing"])
            r = st["anisotropy"]
            assert ANISOTROPY_RANGE[0] <= r <= ANISOTROPY_RANGE[1]
            k = "xyz".index(st["slice_axis"])
            assert np.all(np.round(extent / sp) >= MIN_AXIS_VOXELS)
            assert np.prod(sp) <= np.prod(base_sp) * (1 + 1e-3)
            factor = sp / np.asarray(base_sp)
            others = np.delete(factor, k)
            np.testing.assert_allclose(others, r ** (-1 / 3), rtol=1e-3)
            assert factor[k] <= r ** (2 / 3) * (1 + 1e-3)
            ph = Phantom(spec)  # the grid (no image): the drawn spacing on the same field of view
            assert ph.geometry.spacing == tuple(sp)
            assert np.all(np.abs(np.asarray(ph.geometry.size) * sp - extent) <= sp / 2 + 1e-9)
            # an explicit spacing is kept: nothing drawn for it, the rest the same
            given = draw_acquisition(replace(spec, spacing=COARSE))
            assert given["study"]["spacing"] is None and given["study"]["slice_axis"] is None
            assert given["study"]["contrast"] == c and given["images"] == a["images"]
            assert len(a["images"]) == 4
            for im in a["images"]:
                noises.add(im["noise"])
                assert im["noise"] in ("rician", "gaussian")
                assert SNR_RANGE[0] <= im["snr"] <= SNR_RANGE[1]
                assert GAIN_RANGE[0] <= im["gain"] <= GAIN_RANGE[1]
                assert BIAS_RANGE[0] <= im["bias_amplitude"] <= BIAS_RANGE[1]
                assert im["noise_sigma"] == pytest.approx(im["gain"] * span / im["snr"], rel=1e-12)
                if im["noise"] == "rician":
                    assert im["offset"] == 0.0
                else:
                    assert abs(im["offset"]) <= OFFSET_FRACTION * span
            # an image's draws do not depend on how many images there are
            assert draw_acquisition(spec, n_images=2)["images"] == a["images"][:2]
    # every seed its own draw; the contrasts run from bright fat (T1-like) through fat ≈ muscle to CT's
    assert len(set(weights)) == len(weights)
    assert min(weights) < 0.15 and max(weights) > 0.85
    assert max(fat) > 1.8 and min(fat) < 0.95 and any(1.1 < f < 1.6 for f in fat)
    assert noises == {"rician", "gaussian"}


def test_same_seed_same_bits_other_seed_other_draws():
    a = make_phantom("knee", seed=3, n_poses=2, acquisition="random", spacing=COARSE)
    b = make_phantom("knee", seed=3, n_poses=2, acquisition="random", spacing=COARSE)
    c = make_phantom("knee", seed=4, n_poses=2, acquisition="random", spacing=COARSE)
    assert a.acquisition == b.acquisition and a.acquisition != c.acquisition
    assert list(a.acquisition["images"]) == ["template", "pose00", "pose01"]
    ta, tb, tc = (p.template()[0].data for p in (a, b, c))
    assert np.array_equal(ta, tb) and not np.array_equal(ta, tc)
    for x, y in zip(a.scans(), b.scans()):
        assert np.array_equal(x.image.data, y.image.data)
    # the images of a study differ in their acquisitions (not only in their noise)
    drawn = list(a.acquisition["images"].values())
    assert len({d["snr"] for d in drawn}) == 3 and len({d["gain"] for d in drawn}) == 3


# -- the images: noise, SNR, bias and gain as drawn --------------------------------------------------------


def _seed_with(noise: str, modality: str) -> int:
    """The first seed whose template draws ``noise`` and a bias field of at least 10 % (draws only, no image)."""
    for seed in range(100):
        spec = PhantomSpec(modality=modality, seed=seed, n_poses=1, acquisition="random")
        d = draw_acquisition(spec, n_images=1)["images"][0]
        if d["noise"] == noise and d["bias_amplitude"] >= 0.1:
            return seed
    raise AssertionError(f"no seed below 100 draws {noise} noise")


@pytest.mark.parametrize("noise, modality", [("rician", "mri"), ("gaussian", "ct")])
def test_measured_noise_snr_and_bias_match_the_draws(noise, modality):
    seed = _seed_with(noise, modality)
    grid = REGIONS["knee"].GRIDS["test"][1]  # the test grid itself (explicit: the clean twin has the same)
    ph = make_phantom("knee", modality=modality, seed=seed, n_poses=1, acquisition="random", spacing=grid)
    d = ph.acquisition["images"]["template"]
    assert d["noise"] == noise
    v = ph.template()[0].data.astype(float).ravel()
    x = ph.geometry.world_coordinates().reshape(-1, 3)
    clean = ph.render(x)  # the noise-free image of this study's contrast
    c = ph.contrast
    span = c.muscle - c.air
    sigma, gain, offset = d["noise_sigma"], d["gain"], d["offset"]

    # the bias field: smooth, max |bias − 1| the drawn amplitude
    bias = ph.bias_field(0).ravel()
    assert np.abs(bias - 1).max() == pytest.approx(d["bias_amplitude"], rel=1e-9)
    assert np.abs(bias - 1).max() <= d["bias_amplitude"] + 1e-12

    # air far from the skin: tanh(8) leaves < 1e-6 of a tissue's signal, so only noise (and offset)
    dist = ph.anatomy.distances_fast(x)
    air = dist[:, -1] > 8 * ph.edge_mm
    n = int(air.sum())
    assert n > 20_000
    b = v[air] - c.air
    if noise == "gaussian":
        assert b.std() == pytest.approx(sigma, rel=Z / np.sqrt(2 * n))
        assert abs(b.mean() - offset) < Z * sigma / np.sqrt(n)
        sigma_hat = b.std()
    else:  # Rayleigh: mean σ·sqrt(π/2), standard deviation σ·sqrt((4 − π)/2)
        assert b.mean() == pytest.approx(sigma * np.sqrt(np.pi / 2), abs=Z * sigma * np.sqrt((4 - np.pi) / 2 / n))
        assert np.sqrt(np.mean(b**2) / 2) == pytest.approx(sigma, rel=Z / np.sqrt(n))  # E b² = 2σ²
        sigma_hat = b.mean() / np.sqrt(np.pi / 2)

    # everywhere: the image is noise(gain · bias · (clean − air)) + air + offset
    a = gain * bias * (clean - c.air)
    if noise == "gaussian":
        r = v - c.air - offset - a
        assert r.std() == pytest.approx(sigma, rel=Z / np.sqrt(2 * len(r)))
        assert abs(r.mean()) < Z * sigma / np.sqrt(len(r))
    else:
        q = (v - c.air) ** 2 - a**2 - 2 * sigma**2
        assert abs(q.mean()) < Z * np.sqrt(np.mean(4 * a**2 * sigma**2 + 4 * sigma**4) / len(q))

    # SNR in muscle: deep in the body, away from bone, at about the muscle's level; its texture divided out
    deep = dist[:, -1] < -(ph.anatomy.skin_mm + ph.anatomy.fat_mm + 3 * ph.edge_mm)
    deep &= dist[:, :-1].min(axis=1) > 3 * ph.edge_mm
    rel = (clean - c.air) / span
    muscle = deep & (np.abs(rel - 1) < 0.3)
    m = int(muscle.sum())
    assert m > 500
    flat = (v[muscle] - c.air - offset) / (bias[muscle] * rel[muscle])  # ≈ gain · (muscle − air) + noise
    snr = flat.mean() / sigma_hat
    lowest = d["snr"] * (bias[muscle] * rel[muscle]).min()  # the lowest local SNR in the region
    tol = Z * (1 / np.sqrt(2 * n) + flat.std() / flat.mean() / np.sqrt(m))
    if noise == "rician":
        tol += 1 / (2 * lowest**2)
    assert snr == pytest.approx(d["snr"], rel=tol)


def test_noise_free_random_acquisition_keeps_the_study_contrast_only():
    ph = make_phantom("knee", seed=2, n_poses=1, acquisition="random", spacing=COARSE, noise=False)
    assert ph.acquisition["images"] == {} and ph.contrast.name == "mri-random"
    tpl = ph.template()[0].data
    x = ph.geometry.world_coordinates().reshape(-1, 3)
    np.testing.assert_array_equal(tpl, ph.render(x).reshape(tpl.shape).astype(np.float32))
    assert np.all(ph.bias_field(0) == 1.0)


# -- the truth does not depend on the acquisition ---------------------------------------------------------


@pytest.mark.parametrize("region", ["knee", "hand"])
def test_truth_is_independent_of_the_acquisition(region):
    spacing, n = (COARSE, 2) if region == "knee" else ((5.5, 5.5, 5.5), 1)  # the hand's spread pose
    fixed = make_phantom(region, seed=6, n_poses=n, spacing=spacing)
    drawn = make_phantom(region, seed=6, n_poses=n, spacing=spacing, acquisition="random")
    assert drawn.geometry == fixed.geometry
    assert [(i, {k: np.asarray(v).tolist() for k, v in a.items()}) for i, a in drawn.poses] == [
        (i, {k: np.asarray(v).tolist() for k, v in a.items()}) for i, a in fixed.poses
    ]
    (tf, lf), (td, ld) = fixed.template(), drawn.template()
    assert np.array_equal(lf.data, ld.data) and not np.array_equal(tf.data, td.data)
    for a, b in zip(fixed.scans(), drawn.scans()):
        assert np.array_equal(a.correspondence.data, b.correspondence.data)
        assert np.array_equal(a.template_to_scan.data, b.template_to_scan.data)
        assert a.markers == b.markers
        for bone, t in a.pose.transforms.items():
            assert np.array_equal(np.asarray(t), np.asarray(b.pose.transforms[bone]))
        assert not np.array_equal(a.image.data, b.image.data)


# -- the study records it, and is regenerated from its record -------------------------------------------


def test_study_records_the_draws_and_regenerates_from_its_spec(tmp_path):
    from workbench.cli import main
    from workbench.study import read_study

    out = tmp_path / "knee"
    assert (
        main(
            ["phantom", "knee", "--out", str(out), "--poses", "1", "--seed", "9", "--acquisition", "random", "--quiet"]
        )
        == 0
    )
    study = read_study(out)
    rec = study.manifest["phantom"]
    spec = PhantomSpec.from_dict(rec)
    assert spec == PhantomSpec(region="knee", n_poses=1, seed=9, acquisition="random")
    # reproduce's check that a folder holds the wanted phantom compares spec.to_dict()'s keys
    assert all(rec.get(k) == v for k, v in spec.to_dict().items())
    again = Phantom(spec)
    assert rec["acquisition_drawn"] == again.acquisition
    assert set(rec["acquisition_drawn"]["images"]) == {"template", "pose00"}
    tpl = study.template()
    assert tpl.geometry.spacing == pytest.approx(tuple(again.acquisition["study"]["spacing"]), rel=1e-6)  # float32
    assert np.array_equal(tpl.data, again.template()[0].data)
    scan = next(again.scans())
    assert np.array_equal(study.scan(scan.id).data, scan.image.data)


def test_cli_help_names_the_option(capsys):
    from workbench.cli import main

    with pytest.raises(SystemExit):
        main(["phantom", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--acquisition {fixed,random}" in text and "SNR of 8-40" in text and "0-20% bias" in text
