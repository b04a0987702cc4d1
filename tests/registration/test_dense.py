"""The dense articulated registration (registration.dense) recovers a known soft-tissue warp, keeps bones fixed.

Set-up: a textured volume (smooth random blobs, a "bone" block of its own
intensity) on an anisotropic grid with a rotated direction; the scan is the
texture sampled (cubic B-spline) through a known smooth displacement (2.5 mm
at most, σ 8 mm), zero on the bone.  Tolerances:

* the registration must remove ≥ 60 % of the start's mean error over the
  tissue (the warp is smooth and the texture has structure at every voxel, so
  only interpolation error and the regulariser's bias at the warp's peak are
  left — measured: 0.72 → 0.13 mm with the default membrane energy,
  0.11 without, 81 % removed);
* on the bone, fixed bones without refinement mean ``U = id``: the result
  equals the start exactly there (float32 round-off of the composition,
  < 1e-4 mm); with the bones' rigid refinement, a start whose bone is off
  by 3° and 1.5 mm ends with less than half that error on the bone;
* every step is one-to-one (det(I + ∇f) > min_jacobian), so no voxel folds;
* the method has no random choice: two runs give the same bits.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from deformation.filters import smooth
from deformation.geometry import GridGeometry, Volume
from registration.dense import DenseSettings, register_dense


@pytest.fixture(scope="module")
def case():
    return make_case()


def make_case(air: bool = False, bone_texture: bool = False):
    """The textured case, texture everywhere (no air: settings.tissue_only does not apply); ``air``: the body
    is an ellipsoid in air (intensity 0), so that the windows and the smoothing keep to the scan's tissue;
    ``bone_texture``: the bone has a texture of its own (as marrow has), not one intensity."""
    c, s = np.cos(np.deg2rad(15)), np.sin(np.deg2rad(15))
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    size, spacing = (36, 32, 24), (1.5, 1.8, 2.2)
    g = GridGeometry(size, spacing, (-20.0, -25.0, -24.0), tuple(rot.reshape(-1)))
    rng = np.random.default_rng(11)
    tex = ndimage.gaussian_filter(rng.normal(size=g.array_shape), 1.2)
    tex = 300.0 + 2000.0 * tex
    x = g.world_coordinates()
    centre = x.reshape(-1, 3).mean(axis=0)
    r = x - centre
    bone = (np.abs(r[..., 0]) < 6) & (np.abs(r[..., 1]) < 9) & (np.abs(r[..., 2]) < 6)
    tex[bone] = 900.0
    if bone_texture:
        tex[bone] += 1500.0 * ndimage.gaussian_filter(np.random.default_rng(12).normal(size=g.array_shape), 1.0)[bone]
    if air:
        tex[np.sum((r / np.array([22.0, 24.0, 22.0])) ** 2, axis=-1) > 1] = 0.0
    template = Volume(tex.astype(np.float32), g)
    labels = Volume(bone.astype(np.uint8), g)
    # the truth: smooth, zero on (and fading near) the bone
    u = np.stack([ndimage.gaussian_filter(rng.normal(size=g.array_shape), 8.0 / 1.8) for _ in range(3)], axis=-1)
    u *= 2.5 / np.abs(u).max()
    fade = np.clip(ndimage.distance_transform_edt(~bone, sampling=g.spacing[::-1]) / 6.0, 0, 1)
    u *= fade[..., None]
    truth = Volume(u.astype(np.float32), g)  # scan_to_template: scan voxel x came from x + u(x)
    # the scan: the texture at x + u(x) by cubic B-spline, as a scanner acquires the continuous object, not the
    # template's own trilinear interpolation (then the exact field would read the template through the very
    # interpolation that made the scan: a cusp of the LNCC at the truth, which no real scan has)
    w2i = g.world_to_index_matrix
    y = x + u
    ijk = [w2i[r, 0] * y[..., 0] + w2i[r, 1] * y[..., 1] + w2i[r, 2] * y[..., 2] + w2i[r, 3] for r in range(3)]
    scan = Volume(ndimage.map_coordinates(tex, [ijk[2], ijk[1], ijk[0]], order=3, mode="nearest").astype(np.float32), g)
    return template, labels, scan, truth, bone


def test_recovers_soft_tissue_warp_and_keeps_bone_fixed(case):
    template, labels, scan, truth, bone = case
    st = DenseSettings(
        shrink=(2, 1),
        iterations=(40, 30),
        window_mm=4.0,
        fluid_mm=4.0,
        elastic_mm=1.5,
        fluid_voxels=None,
        elastic_voxels=None,
        refine_bones=False,
    )
    before = [v.data.copy() for v in (scan, template, labels)]
    res = register_dense(scan, template, moving_labels=labels, settings=st)
    assert all(np.array_equal(b, v.data) for b, v in zip(before, (scan, template, labels)))  # inputs untouched
    err0 = np.linalg.norm(truth.data, axis=-1)
    err = np.linalg.norm(res.correspondence.data - truth.data, axis=-1)
    inner = np.zeros_like(bone)
    inner[3:-3, 3:-3, 3:-3] = True  # away from the border, where the warp leaves the grid
    soft = inner & ~bone
    assert err[soft].mean() < 0.4 * err0[soft].mean(), (err[soft].mean(), err0[soft].mean())
    assert np.abs(res.correspondence.data[bone]).max() < 1e-4
    from deformation.fields.displacement import folding_statistics

    assert folding_statistics(res.correspondence)["fraction_folded"] == 0.0
    again = register_dense(scan, template, moving_labels=labels, settings=st)
    assert np.array_equal(again.correspondence.data, res.correspondence.data)


def test_held_bone_with_an_erred_pose_is_refined_rigidly(case):
    """The start is the truth with the bone's region off by a rigid error (3° about an oblique axis through
    the bone's centre, 1.5 mm), fading to the truth over 6 mm (as a pose stage that erred would leave it).
    Without refinement the fixed bone keeps the error; with it the bone moves towards the scan's pose, as a
    rigid body; from the right start (the truth) nothing moves.

    Tolerances: the refined bone's mean error below half the start's (measured 1.54 → 0.55 mm).  Not
    lower: the scan here is the template resampled by trilinear interpolation, and the LNCC of the twice-
    interpolated template against it is not highest at the exact field (a 0.3 mm shift of the bone from the
    exact field raises it by 4e-4), so the optimum itself is a few tenths of a mm off on this uniform block.
    The bone's map stays rigid to 0.02 mm two voxels in; the gate (half a voxel) keeps the right
    start's bone to the bit.
    """
    from scipy.spatial.transform import Rotation

    from deformation.kinematics.rigid_fit import fit_rigid

    template, labels, scan, truth, bone = case
    g = scan.geometry
    x = g.world_coordinates()
    c = x[bone].mean(axis=0)
    r = Rotation.from_rotvec(np.deg2rad(3.0) * np.array([0.6, -0.48, 0.64])).as_matrix()
    err = (x - c) @ r.T + c + np.array([1.2, -0.6, 0.7]) - x  # 1.5 mm shift
    fade = np.clip(1.0 - ndimage.distance_transform_edt(~bone, sampling=g.spacing[::-1]) / 6.0, 0, 1)[..., None]
    start = Volume((truth.data + fade * err).astype(np.float32), g)
    st = DenseSettings(shrink=(2, 1), iterations=(40, 30), window_mm=4.0)
    off = register_dense(
        scan,
        template,
        initial=start,
        moving_labels=labels,
        settings=DenseSettings(**{**st.to_dict(), "refine_bones": False}),
    )
    on = register_dense(scan, template, initial=start, moving_labels=labels, settings=st)
    e_start = np.linalg.norm(start.data - truth.data, axis=-1)[bone].mean()
    e_off = np.linalg.norm(off.correspondence.data - truth.data, axis=-1)[bone].mean()
    e_on = np.linalg.norm(on.correspondence.data - truth.data, axis=-1)[bone]
    # held where the start put it: on the bone the held region is pulled through the erred start, so its edge
    # voxels are not the true bone's (measured 1.50 against 1.54 mm)
    assert abs(e_off - e_start) < 0.1, (e_off, e_start)
    assert e_on.mean() < e_start / 2.0, (e_on.mean(), e_start)
    # the bone's map stays rigid: over its voxels two layers in (the held region is the template's bone pulled
    # through the map, and the start is rigid on the scan's bone only, so where the map is still ~0.5 mm off
    # an edge voxel lands outside either); 0.02 mm: float32 sampling of the start and the composition
    core = ndimage.binary_erosion(bone, iterations=2)
    y = x[core] + on.correspondence.data[core]
    t = fit_rigid(x[core], y)
    assert np.linalg.norm(x[core] @ t[:3, :3].T + t[:3, 3] - y, axis=1).max() < 0.02
    rounds = on.levels[0]["bone_refinement"]
    assert rounds[0]["taken"] and rounds[0]["lncc_after"] > rounds[0]["lncc_before"]
    assert all(lv["bone_refinement"] is None for lv in off.levels)
    # from the truth the gate keeps the bone: the same bits as without refinement
    kw = dict(initial=truth, moving_labels=labels)
    right_on = register_dense(scan, template, settings=st, **kw)
    right_off = register_dense(scan, template, settings=DenseSettings(**{**st.to_dict(), "refine_bones": False}), **kw)
    assert np.array_equal(right_on.correspondence.data, right_off.correspondence.data)
    assert not any(rd["taken"] for lv in right_on.levels for rd in lv["bone_refinement"] or [])


def test_refining_one_bone_leaves_its_neighbour_held_and_keeps_u_one_to_one():
    """Two bones (the block cut in two, 4 mm apart: a joint space), only the first off in the start (3°, 1.5 mm,
    fading over 3 mm); the second is right.  The first is refined; the second, in the first's margin, keeps its
    own (rigid)
    start and never takes the first's motion; every bone round keeps det(I + ∇u) above min_jacobian, so the
    result's U has no fold.  Tolerance on the second bone's rigid fit: 0.02 mm, as the one-bone test's; the
    first bone's share of the margin is at most 0.5 of its motion, so a leak would show as ~1 mm.  The bones
    are textured (a uniform half-block's pose is not determined by its LNCC: its refinement runs to the bounds,
    and the Jacobian check refuses it)."""
    from scipy.spatial.transform import Rotation

    from deformation.kinematics.rigid_fit import fit_rigid

    template, labels, scan, truth, bone = make_case(bone_texture=True)
    g = scan.geometry
    x = g.world_coordinates()
    ry = x[..., 1] - x.reshape(-1, 3).mean(axis=0)[1]
    lab = np.zeros(bone.shape, np.uint8)
    lab[bone & (ry < -2)] = 1
    lab[bone & (ry > 2)] = 2
    b1, b2 = lab == 1, lab == 2
    c = x[b1].mean(axis=0)
    r = Rotation.from_rotvec(np.deg2rad(3.0) * np.array([0.6, -0.48, 0.64])).as_matrix()
    err = (x - c) @ r.T + c + np.array([1.2, -0.6, 0.7]) - x
    fade = np.clip(1.0 - ndimage.distance_transform_edt(~b1, sampling=g.spacing[::-1]) / 3.0, 0, 1)[..., None]
    start = Volume((truth.data + fade * err).astype(np.float32), g)
    # the significance gate off: this test is about the neighbour and the one-to-one floor.  With it (default 2)
    # the first bone (300 voxels, smoothed by a voxel for the test: 19 independent samples) is not moved: own
    # NCC 0.915 -> 0.974, z 1.7 (test_a_bone_first_moves_only_when_its_own_fit_rises_significantly tests the gate)
    res = register_dense(
        scan,
        template,
        initial=start,
        moving_labels=Volume(lab, g),
        settings=DenseSettings(shrink=(2, 1), iterations=(40, 30), window_mm=4.0, refine_significance=0.0),
    )
    moved = [set(rd["poses"]) for lv in res.levels for rd in lv["bone_refinement"] or [] if rd["taken"]]
    assert moved and all(m == {"1"} for m in moved), moved  # the first bone refined (by label), the second never
    # ... towards the scan's pose: less than half the start's error on it, as the one-bone test (measured 1.53 →
    # 0.25 mm)
    e1 = np.linalg.norm(res.correspondence.data[b1] - truth.data[b1], axis=-1).mean()
    assert e1 < 0.5 * np.linalg.norm(start.data[b1] - truth.data[b1], axis=-1).mean(), e1
    core2 = ndimage.binary_erosion(b2)
    y = x[core2] + res.correspondence.data[core2]
    t = fit_rigid(x[core2], y)
    assert np.linalg.norm(x[core2] @ t[:3, :3].T + t[:3, 3] - y, axis=1).max() < 0.02
    assert np.linalg.norm(res.correspondence.data[core2] - truth.data[core2], axis=-1).max() < 0.02
    assert res.folding["n_folded_u"] == 0


def test_settings_are_checked():
    with pytest.raises(ValueError, match="one entry per level"):
        DenseSettings(shrink=(2, 1), iterations=(10,))
    with pytest.raises(ValueError, match="bones"):
        DenseSettings(bones="loose")
    with pytest.raises(ValueError, match="fluid_voxels"):
        DenseSettings(fluid_voxels=-1.0)
    with pytest.raises(ValueError, match="air_weight"):
        DenseSettings(air_weight=0.0)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="skin_weight"):
            DenseSettings(skin_weight=bad)
        with pytest.raises(ValueError, match="stiffness"):
            DenseSettings(stiffness=bad)
    for bad in ({"radius_growth": 0.5}, {"max_halvings": -1}, {"max_halvings": 2.5}, {"max_halvings": None}):
        with pytest.raises(ValueError, match="radius_growth must be ≥ 1 and max_halvings ≥ 0"):
            DenseSettings(**bad)
    for bad in (
        {"refine_deg": -1.0},
        {"refine_deg": 0.0},
        {"refine_mm": float("nan")},
        {"refine_evaluations": 12},
        {"refine_evaluations": 50.0},
        {"refine_rounds": True},
    ):
        with pytest.raises(ValueError, match="refine_deg and refine_mm"):
            DenseSettings(**bad)
    for bad in (
        {"refine_min_move_voxels": -0.5},
        {"refine_min_voxels": 0.5},
        {"refine_margin_voxels": 0.0},
        {"bone_margin_mm": 0.0},
    ):
        with pytest.raises(ValueError, match="refine_min_move_voxels"):
            DenseSettings(**bad)


def test_rigid_bones_move_as_rigid_bodies(case):
    """bones="rigid": each step's motion on a bone is its least-squares rigid motion, so the composed map on
    the bone is rigid too.  What a rigid fit leaves is the trilinear resampling of the composed field near the
    bone's edge (the step is rigid on the bone's voxels, the field between them is interpolated) and the
    linearised rotation of each step (O(ω²·r)): < 0.05 mm, a fiftieth of a voxel."""
    from deformation.kinematics.rigid_fit import fit_rigid

    template, labels, scan, truth, bone = case
    st = DenseSettings(shrink=(2, 1), iterations=(20, 10), bones="rigid", bone_margin_mm=3.0)
    res = register_dense(scan, template, moving_labels=labels, settings=st)
    x = scan.geometry.world_coordinates()[bone]
    y = x + res.correspondence.data[bone]
    t = fit_rigid(x, y)
    resid = np.linalg.norm(x @ t[:3, :3].T + t[:3, 3] - y, axis=1)
    assert resid.max() < 0.05, resid.max()


_THREADS_SCRIPT = """
import sys, hashlib
sys.path.insert(0, sys.argv[1])
from test_dense import make_case
from registration.dense import DenseSettings, register_dense
for air in (False, True):
    template, labels, scan, truth, bone = make_case(air)
    r = register_dense(scan, template, moving_labels=labels, settings=DenseSettings(shrink=(2, 1), iterations=(20, 10)))
    print(hashlib.sha256(r.correspondence.data.tobytes()).hexdigest(), all(lv["tissue_only"] for lv in r.levels))
# a start whose bone is off: the bones' refinement runs (NLopt, the significance test's images, the Jacobian
# checks); the gate at 0, as the uniform bone's shift is not significant at the default
import numpy as np
from deformation.geometry import Volume
start = Volume((truth.data + (bone[..., None] * np.array([1.2, -0.6, 0.7]))).astype(np.float32), truth.geometry)
r = register_dense(scan, template, initial=start, moving_labels=labels,
                   settings=DenseSettings(shrink=(2, 1), iterations=(20, 10), refine_significance=0.0))
print(hashlib.sha256(r.correspondence.data.tobytes()).hexdigest(),
      any(rd["taken"] for lv in r.levels for rd in lv["bone_refinement"] or []))
"""


def test_same_bits_with_one_and_two_threads():
    # numba kernels (sampling, Jacobians, the fold repair) and BLAS may split work by thread: every voxel's
    # arithmetic must not depend on it.  Each run is a fresh process, as the thread count is fixed at start.
    import os
    import subprocess
    import sys
    from pathlib import Path

    here = str(Path(__file__).resolve().parent)
    root = str(Path(__file__).resolve().parents[2])
    digests = []
    for n in ("1", "2"):
        env = dict(
            os.environ,
            NUMBA_NUM_THREADS=n,
            OMP_NUM_THREADS=n,
            OPENBLAS_NUM_THREADS=n,
            MKL_NUM_THREADS=n,
            PYTHONPATH=root,
        )
        out = subprocess.run(
            [sys.executable, "-c", _THREADS_SCRIPT, here],
            env=env,
            capture_output=True,
            text=True,
            encoding="utf-8",
            check=True,
            timeout=600,
        )
        digests.append(out.stdout.strip().splitlines()[-3:])  # without air, with it, from an erred bone
    assert digests[0] == digests[1] and all(len(d.split()[0]) == 64 for d in digests[0])
    # without air the plain path ran, with air the tissue-only one; from the erred start a bone round was taken
    assert [d.split()[1] for d in digests[0]] == ["False", "True", "True"]


def test_smoothing_split_into_slabs_gives_the_whole_arrays_bits():
    # three arrays on two threads: the third is cut into two slabs along its longest axis with a halo of the
    # kernel's reach; each output voxel must come from the same inputs in the same order as on the whole array
    # (anisotropic σ, the longest axis not the first, odd lengths so the cut is uneven)
    import numba

    from registration import dense

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here (NUMBA_NUM_THREADS=1): nothing is split")
    rng = np.random.default_rng(5)
    arrays = [rng.normal(size=(9, 31, 14)).astype(np.float32) for _ in range(3)]
    sigma = np.array([0.8, 2.5, 1.2])
    before = numba.get_num_threads()
    numba.set_num_threads(2)
    try:
        dense.POOLS.clear()
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(dense, "SMOOTH_SERIAL_BELOW", 0)  # these small arrays would be smoothed serially
            got = dense.smooth_all(arrays, sigma)
        assert dense.POOLS, "the threads did not run"
    finally:
        numba.set_num_threads(before)
    for a, g in zip(arrays, got):
        np.testing.assert_array_equal(g, ndimage.gaussian_filter(a, sigma, mode="nearest", truncate=3.0))


def test_rhee_table2_protocol_without_initialisation(phantom):
    """Rhee's Table 2 protocol (§6.1): the knee bent 10° by VBD, registered from the identity (no start).

    The shank's rotation moves the foot end by ~35 mm; the coarse level (4× subsampled) must carry it.
    Measured at test size: source MED 7.08 mm → 1.36 (seed 0) / 1.19 (seed 100) mm, elastix's B-spline 2.37
    / 1.95 in the same harness (benchmarks/bench_registration.py --cases table2,
    docs/measurements/registration-benchmarks.md).  Bound: under 30 % of the source's MED (1.36 is 19 %), no
    fold anywhere in the body.
    """
    from validation.registration_measures import body_on_scan, med

    ph = phantom("knee", size="test", posing="vbd", poses=(("bend10", {"knee": [10.0, 0.0, 0.0]}),), seed=3)
    template, _ = ph.template()
    sc = list(ph.scans())[-1]
    body_t = Volume(
        (ph.anatomy.distances_fast(ph.geometry.world_coordinates().reshape(-1, 3))[:, -1] < 0)
        .reshape(ph.geometry.array_shape)
        .astype(np.uint8),
        ph.geometry,
    )
    body = body_on_scan(sc.correspondence, body_t)
    zero = Volume(np.zeros(sc.correspondence.data.shape, np.float32), sc.correspondence.geometry)
    res = register_dense(sc.image, template)
    source = med(zero, sc.correspondence, body)
    assert source > 5.0  # the protocol's motion is there
    assert med(res.correspondence, sc.correspondence, body) < 0.3 * source
    from deformation.fields.displacement import folding_statistics

    assert folding_statistics(res.correspondence, body)["n_folded"] == 0


def _kernel_3d(sigma):
    """scipy's Gaussian kernel (truncate 3: radius int(3σ + 0.5), normalised per axis) as a 3-D array."""
    ks = []
    for sg in sigma:
        r = int(3.0 * sg + 0.5)
        x = np.arange(-r, r + 1, dtype=float)
        k = np.exp(-0.5 * (x / sg) ** 2)
        ks.append(k / k.sum())
    return ks[0][:, None, None] * ks[1][None, :, None] * ks[2][None, None, :]


def test_lncc_over_the_tissue_only_ignores_the_air():
    """tissue_only's LNCC (settings.tissue_only): each window's statistics are over the mask's voxels, so the
    similarity and its gradient in the tissue do not depend on what the air holds (bit for bit: the air's
    values enter multiplied by 0), the air feels no force, and a voxel's local correlation is the weighted
    correlation over its window's tissue voxels, computed here by brute force with scipy's kernel (float32
    smoothing against a float64 sum: 1e-4 relative)."""
    from registration import dense

    rng = np.random.default_rng(2)
    shape, sig = (26, 24, 22), np.array([1.5, 2.0, 1.2])
    f = rng.normal(size=shape).astype(np.float32)
    w = (0.6 * f + 0.8 * rng.normal(size=shape)).astype(np.float32)
    zz, yy, xx = np.indices(shape)
    tissue = ((zz - 13) ** 2 / 64 + (yy - 12) ** 2 / 49 + (xx - 11) ** 2 / 36 < 1).astype(np.float32)
    stats = dense.local_stats(f, sig, tissue)
    cc, dcc = dense.lncc_force(f, w, sig, stats)
    air = tissue == 0
    f2, w2 = f.copy(), w.copy()
    f2[air] = rng.normal(size=int(air.sum())) * 5
    w2[air] = rng.normal(size=int(air.sum())) * 5
    cc2, dcc2 = dense.lncc_force(f2, w2, sig, dense.local_stats(f2, sig, tissue))
    assert np.array_equal(dcc, dcc2) and cc == cc2
    assert np.all(dcc[air] == 0)
    # brute force at voxels on the ellipsoid's edge (their windows half air), away from the grid's edge
    k = _kernel_3d(sig)
    r = [(n - 1) // 2 for n in k.shape]
    edge = np.argwhere((tissue > 0) & (ndimage.binary_dilation(air) > 0))
    edge = [p for p in edge if all(r[a] <= p[a] < shape[a] - r[a] for a in range(3))][:5]
    assert len(edge) == 5
    mf, sff, _ = stats
    for p in edge:
        box = tuple(slice(p[a] - r[a], p[a] + r[a] + 1) for a in range(3))
        g = k * tissue[box]
        g = g / g.sum()
        a, b = f[box].astype(float), w[box].astype(float)
        ma, mb = (g * a).sum(), (g * b).sum()
        cov = (g * (a - ma) * (b - mb)).sum()
        va, vb = (g * (a - ma) ** 2).sum(), (g * (b - mb) ** 2).sum()
        np.testing.assert_allclose([mf[tuple(p)], sff[tuple(p)]], [ma, va], rtol=1e-4, atol=1e-5)
        # the gradient's factor at the voxel (Avants 2008, Eq. 5, with the window's tissue statistics)
        want = 2.0 * cov / (va * vb) * ((a[tuple(r)] - ma) - cov / vb * (b[tuple(r)] - mb))
        np.testing.assert_allclose(dcc[tuple(p)], want, rtol=1e-3, atol=1e-5)


def test_smoothing_of_u_over_the_tissue():
    """The smoothing of U with tissue_only (normalised convolution, weight 1 in the tissue, ε in the air): a
    field equal to c in the tissue stays within ε(1 − m)/(m + ε(1 − m))·max|air − c| of c at a tissue voxel
    whose kernel holds a share m of tissue (the weighted-mean bound; at the skin m ≈ 0.65, the bound 0.08),
    while the plain Gaussian moves the skin by more than half a unit (a third of the kernel is air, 2–3 off);
    with weight 1 everywhere it is the plain Gaussian."""
    from registration import dense

    rng = np.random.default_rng(4)
    shape, sig, eps = (20, 22, 18), np.array([1.0, 1.3, 0.8]), np.float32(0.05)
    tissue = np.zeros(shape, np.float32)
    tissue[:, :11] = 1.0  # a flat skin between rows 10 and 11
    air = tissue == 0
    u = [np.where(air, 3.0 + rng.random(shape), 1.0).astype(np.float32) for _ in range(3)]  # c = 1
    wt = tissue + eps * (1.0 - tissue)
    out = dense.weighted_smooth(u, wt, 1.0 / smooth(wt, sig, **dense.GAUSSIAN), sig)
    m = smooth(tissue, sig, **dense.GAUSSIAN)
    bound = eps * (1 - m) / (m + eps * (1 - m)) * 3.0  # max |air − c| < 3 (air in [3, 4), c = 1)
    for a in range(3):
        assert np.all(np.abs(out[a] - 1.0)[~air] <= bound[~air] * (1 + 1e-4) + 1e-6)
    skin = np.zeros(shape, bool)
    skin[:, 10] = True
    assert np.abs(smooth(u[0], sig, **dense.GAUSSIAN)[skin] - 1.0).min() > 0.5  # the plain Gaussian: the air drags it
    one = np.ones(shape, np.float32)
    np.testing.assert_allclose(
        dense.weighted_smooth(u, one, 1.0 / smooth(one, sig, **dense.GAUSSIAN), sig)[1],
        smooth(u[1], sig, **dense.GAUSSIAN),
        rtol=1e-6,
        atol=1e-6,
    )


def test_tissue_only_applies_when_air_surrounds_the_body(case):
    """Without air the segmentation's "body" is the brighter half of the texture (46 % of the grid's faces
    outside it): keeping to it would drop the rest of the tissue, so the plain path runs (the same bits as
    tissue_only=False); with air around the body (every face voxel) the tissue-only one runs, and it differs."""
    from registration.dense import share_of_air_around

    template, labels, scan, truth, bone = case
    st = dict(shrink=(2, 1), iterations=(6, 4))
    on = register_dense(scan, template, moving_labels=labels, settings=DenseSettings(**st))
    off = register_dense(scan, template, moving_labels=labels, settings=DenseSettings(**st, tissue_only=False))
    assert not any(lv["tissue_only"] for lv in on.levels)
    assert np.array_equal(on.correspondence.data, off.correspondence.data)
    t2, l2, s2, _, _ = make_case(air=True)
    on = register_dense(s2, t2, moving_labels=l2, settings=DenseSettings(**st))
    off = register_dense(s2, t2, moving_labels=l2, settings=DenseSettings(**st, tissue_only=False))
    assert all(lv["tissue_only"] for lv in on.levels)
    assert not np.array_equal(on.correspondence.data, off.correspondence.data)
    ring = np.zeros((6, 7, 8), bool)
    ring[1:-1, 1:-1, 1:-1] = True
    assert share_of_air_around(ring) == 1.0 and share_of_air_around(np.ones_like(ring)) == 0.0


@pytest.mark.parametrize("air", [False, True])
def test_each_level_objective_never_falls_at_a_taken_step(air):
    """A step is taken only when it raises the level's LNCC (a trust region: otherwise its radius
    halves), and a level stops on convergence (10 taken steps gaining < tolerance, or no step of the smallest
    radius raising it) rather than on its trial cap.  The cap here (200) is far above what the case needs."""
    template, labels, scan, truth, bone = make_case(air=air)
    res = register_dense(
        scan, template, moving_labels=labels, settings=DenseSettings(shrink=(2, 1), iterations=(200, 200))
    )
    for lv in res.levels:
        h = np.asarray(lv["lncc"])
        # strictly: an equal objective is not a taken step (fails if a refused candidate were ever recorded)
        assert np.all(np.diff(h) > 0), (lv["level"], h)
        assert lv["stop"] in ("converged", "no better step"), lv["stop"]
        assert lv["iterations"] == len(h) - 1 and lv["lncc_after"] >= lv["lncc_before"]
    assert res.levels[-1]["lncc_after"] > res.levels[-1]["lncc_before"]  # the fine level did improve


def test_interpolation_noise_on_a_noisy_pair_keeps_the_trust_region_and_registers():
    """settings.interpolation_noise end to end: the textured case in air with white noise of SD 50 added to
    both images (the texture's SD is ~220).  The template's noise is measured in its air (SD 50: within 10 %,
    the air's pseudo-residual over ~9 000 voxels), every level's objective rises at every taken step, and the
    registration removes at least 40 % of the start's error over the tissue (measured 0.81 → 0.44 mm, the
    option off 0.44 too; with SD 100, 0.59 against 0.54 off).  Same bits twice."""
    template, labels, scan, truth, bone = make_case(air=True)
    rng = np.random.default_rng(21)
    noisy = [
        Volume((v.data + 50.0 * rng.normal(size=v.data.shape)).astype(np.float32), v.geometry) for v in (template, scan)
    ]
    # the skin's term and the membrane energy off: the figures above are the LNCC's alone
    st = DenseSettings(shrink=(2, 1), iterations=(200, 200), interpolation_noise=True, skin_weight=0.0, stiffness=0.0)
    res = register_dense(noisy[1], noisy[0], moving_labels=labels, settings=st)
    again = register_dense(noisy[1], noisy[0], moving_labels=labels, settings=st)
    assert np.array_equal(res.correspondence.data, again.correspondence.data)
    off = register_dense(
        noisy[1],
        noisy[0],
        moving_labels=labels,
        settings=DenseSettings(**{**st.to_dict(), "interpolation_noise": False}),
    )
    # the term is in the objective: the fine level's LNCC at its start differs from the plain one's
    assert res.levels[-1]["lncc"][0] != off.levels[-1]["lncc"][0] and off.levels[-1]["template_noise_sd"] is None
    for lv in res.levels:
        assert lv["template_noise_sd"] == pytest.approx(50.0, rel=0.1)
        assert np.all(np.diff(np.asarray(lv["lncc"])) > 0), lv["lncc"]
    tissue = (scan.data > 0) & ~bone
    err0 = np.linalg.norm(truth.data, axis=-1)[tissue].mean()
    err = np.linalg.norm(res.correspondence.data - truth.data, axis=-1)[tissue].mean()
    assert err < 0.6 * err0


def _bone_in_a_box():
    """A 24³ grid of 1 mm, a bone 10 voxels a side inside its 16-voxel box (array slices 4:20), a texture (the
    scan) and the sampler of the template: that texture shifted by 1.5 mm along x (array axis 2), so that
    ``u = +1.5 mm`` along x on the bone is right.  Returns shape, spacing, geometry, index grid, grid in mm, box,
    the bone's mask in its box, its centre (mm), the scan and the template's sampler."""
    from registration.dense import TemplateSampler

    shape, sp = (24, 24, 24), np.ones(3)
    g = GridGeometry(shape[::-1], (1.0, 1.0, 1.0))
    grid = np.indices(shape, dtype=np.float32)
    grid_mm = [grid[a] * sp[a] for a in range(3)]
    box = tuple(slice(4, 20) for _ in range(3))
    m = np.zeros((16, 16, 16), bool)
    m[3:13, 3:13, 3:13] = True
    rng = np.random.default_rng(5)
    tex = ndimage.gaussian_filter(rng.normal(size=shape), 1.5).astype(np.float32)
    moved = ndimage.shift(tex, (0.0, 0.0, 1.5), order=3, mode="nearest")  # template(x) = scan(x - s)
    sample_w = TemplateSampler(
        Volume(moved, g), Volume(np.zeros(shape + (3,), np.float32), g), 1.0, tuple(slice(0, n) for n in shape)
    ).level(1, 0.0, shape)[1]
    return shape, sp, g, grid, grid_mm, box, m, np.full(3, 11.5), tex, sample_w


def test_a_bone_first_moves_only_when_its_own_fit_rises_significantly():
    """registration.dense.bone_fit_improves, the refinement's test of a first move: the bone's own NCC (its
    voxels and one around) must rise by more than 2 standard errors of Fisher's z.  A textured bone whose
    template is off by 1.5 mm: the correcting shift passes (measured: NCC 0.76 → 0.91 over 1600 voxels, z 15).
    The same bone under noise, off by 0.1 mm: the correction's gain is within the noise, and passes only a
    test that accepts any rise."""
    from registration.dense import TemplateSampler, bone_fit_improves

    shape, sp, g, grid, grid_mm, box, m, centre, tex, sample_w = _bone_in_a_box()
    rng = np.random.default_rng(5)
    rng.normal(size=shape)  # the texture's draw (_bone_in_a_box): the noise below is the stream's next
    wgt = m.astype(np.float32)
    u = np.zeros((3,) + shape, np.float32)
    st = DenseSettings()
    fix = np.array([0, 0, 0, 0.0, 0.0, 1.5])  # u = +s: the scan at x is the template at x + s
    assert bone_fit_improves(fix, 1, box, m, wgt, u, tex, sample_w, centre, grid_mm, sp, st)
    # the same gain over 100 times fewer independent samples (the noise correlated over ~4.6 voxels along each
    # axis): z 1.4 (measured), not significant; over 3 or fewer, never
    assert not bone_fit_improves(fix, 1, box, m, wgt, u, tex, sample_w, centre, grid_mm, sp, st, 100.0)
    assert not bone_fit_improves(
        fix, 1, box, m, wgt, u, tex, sample_w, centre, grid_mm, sp, DenseSettings(refine_significance=0.0), 1700.0
    )
    # the same bone under independent noise in scan and template, its template off by 0.1 mm only: the correcting
    # shift raises its own NCC by less than the noise can (measured 0.728 → 0.737, z 0.6): it passes a test that
    # accepts any rise, not the default's two standard errors
    noisy = tex + 0.5 * float(tex.std()) * rng.normal(size=shape).astype(np.float32)
    templ = ndimage.shift(tex, (0.0, 0.0, 0.1), order=3, mode="nearest") + 0.5 * float(tex.std()) * rng.normal(
        size=shape
    ).astype(np.float32)
    sample_w = TemplateSampler(
        Volume(templ, g), Volume(np.zeros(shape + (3,), np.float32), g), 1.0, tuple(slice(0, n) for n in shape)
    ).level(1, 0.0, shape)[1]
    small = np.array([0, 0, 0, 0.0, 0.0, 0.1])
    assert bone_fit_improves(
        small, 1, box, m, wgt, u, noisy, sample_w, centre, grid_mm, sp, DenseSettings(refine_significance=0.0)
    )
    assert not bone_fit_improves(small, 1, box, m, wgt, u, noisy, sample_w, centre, grid_mm, sp, st)


def test_template_sampler_reads_the_template_through_the_composed_map_on_another_grid():
    """registration.dense.TemplateSampler against a direct computation in world mm: a template on its own grid
    (other spacing per axis, origin), a scan box whose corner is not the grid's, an affine start, level 2 with
    its pre-smoothing (0.5 scan voxel, carried to the template's axes in mm) and a constant u.  ``warp`` and
    ``sample`` must read the template smoothed by σ = 0.5 · scan spacing / template spacing per axis at
    x + u + φ₀(x + u).  Tolerance 1e-4 of the image's range: float32 sampling; interior level voxels only
    (φ₀ continues by its edge values beyond the box, which the affine reference does not)."""
    from registration.dense import TemplateSampler

    gs = GridGeometry((20, 18, 16), (1.2, 1.5, 2.0), (-5.0, 3.0, 1.0))
    gt = GridGeometry((44, 40, 34), (0.8, 1.1, 1.6), (-12.0, -6.0, -9.0))
    rng = np.random.default_rng(3)
    tdata = ndimage.gaussian_filter(rng.normal(size=gt.array_shape), 2.0).astype(np.float32)
    tdata = tdata - tdata.min() + 0.1
    a = np.array([[0.02, -0.01, 0.0], [0.01, 0.015, 0.005], [0.0, -0.01, 0.02]])
    b = np.array([0.7, -0.4, 0.3])
    xs = gs.world_coordinates()
    phi = Volume((xs @ a.T + b).astype(np.float32), gs)  # affine scan_to_template displacement
    crop = (slice(2, 14), slice(4, 16), slice(6, 18))  # array axes (z, y, x)
    s, sig_pre = 2, 0.5
    shape = tuple(len(range(c.start, c.stop, s)) for c in crop)
    warp, sample = TemplateSampler(Volume(tdata, gt), phi, 1.0, crop).level(s, sig_pre, shape)
    u = np.zeros((3,) + shape, np.float32)
    u[0], u[1], u[2] = 0.3, -0.2, 0.5  # mm along z, y, x
    # the reference: smoothed on the template's grid, σ per array axis (z, y, x) in its voxels
    sigma = sig_pre * np.asarray(gs.spacing)[::-1] / np.asarray(gt.spacing)[::-1]
    ref_img = ndimage.gaussian_filter(tdata.astype(np.float64), sigma, mode="nearest", truncate=3.0)
    kk, jj, ii = np.meshgrid(*[np.arange(c.start, c.stop, s) for c in crop], indexing="ij")
    x = np.stack([ii, jj, kk, np.ones_like(ii)], axis=-1) @ gs.index_to_world_matrix.T
    y = x[..., :3] + np.array([0.5, -0.2, 0.3])  # u along x, y, z (identity direction)
    y = y + y @ a.T + b  # + φ₀(x + u)
    t = np.concatenate([y, np.ones(y.shape[:-1] + (1,))], axis=-1) @ gt.world_to_index_matrix.T
    ref = ndimage.map_coordinates(ref_img, [t[..., 2], t[..., 1], t[..., 0]], order=1)
    inner = (slice(1, -1),) * 3
    tol = 1e-4 * float(tdata.max() - tdata.min())
    assert np.abs(warp(u)[0][inner] - ref[inner]).max() < tol
    idx = np.indices(shape).astype(np.float64)
    got = sample([idx[a_] + u[a_] / (np.asarray(gs.spacing)[::-1][a_] * s) for a_ in range(3)])
    assert np.abs(got[inner] - ref[inner]).max() < tol


def test_noise_correlation_factor_counts_the_samples_smoothing_leaves():
    """registration.dense.noise_correlation_factor (Bartlett's variance of a correlation between two
    autocorrelated fields): white noise in both images carries one sample per voxel; both smoothed by a Gaussian
    of σ = 1.5 voxels, ρ(k) = exp(−k²/4σ²) each, Σ_k ρ_f(k) ρ_w(k) = Σ_k exp(−k²/2σ²) ≈ √(2π)·1.5 = 3.76 per axis,
    53 over three.  Measured in the air (a 40³ grid around a 12³ body: ~62 000 voxels); the tolerance (±20 %)
    covers the discrete filter's lag-1 correlation against the continuous formula's, cubed with the sum (a 1 %
    error in ρ₁ moves the factor by ~7 %), and its sampling error (~0.4 % of ρ₁).  Without enough air, the
    stated smoothing's value."""
    from registration.dense import noise_correlation_factor

    rng = np.random.default_rng(11)
    shape = (40, 40, 40)
    air = np.ones(shape, bool)
    air[14:26, 14:26, 14:26] = False
    white_f, white_w = rng.normal(size=shape), rng.normal(size=shape)
    assert noise_correlation_factor(white_f, white_w, air, 0.0) == pytest.approx(1.0, abs=0.1)
    sm_f, sm_w = (ndimage.gaussian_filter(x, 1.5) for x in (white_f, white_w))
    expected = float(np.exp(-(np.arange(-12, 13) ** 2) / (2 * 1.5**2)).sum()) ** 3
    assert noise_correlation_factor(sm_f, sm_w, air, 0.0) == pytest.approx(expected, rel=0.2)
    # one image white: no shared correlation, one sample per voxel whatever the other's smoothing
    assert noise_correlation_factor(white_f, sm_w, air, 0.0) == pytest.approx(1.0, abs=0.1)
    # no air: white noise smoothed by the stated σ, the same formula
    assert noise_correlation_factor(sm_f, sm_w, None, 1.5) == pytest.approx(expected, rel=1e-6)


def test_bone_refinement_runs_where_u_already_sits_under_the_jacobian_floor():
    """registration.dense.refine_bone's one-to-one floor is strict: where ``u`` already compresses a voxel of the
    bone's box below ``min_jacobian`` (det 0.15 here, in a corner the bone's fade does not reach), a candidate
    that leaves that voxel as it is stays one-to-one as ``u`` is and must be searched; with ``≤`` every candidate
    scored below the start and the bone kept its error.  A textured bone whose template is off by 1.5 mm along x:
    the refinement must gain and move it most of the way (tolerance 0.5 mm, a third of the error: the LNCC's
    optimum over the bone and the tissue around is a few tenths of a mm off on this 16-voxel box, measured 1.81
    mm; a refused search stays at 0)."""
    from registration.dense import jacobian_min, refine_bone

    shape, sp, g, grid, grid_mm, box, m, centre, tex, sample_w = _bone_in_a_box()
    # the fade: 1 on the bone, 0 three voxels out (the box's faces and corners)
    wgt = np.clip(1.0 - ndimage.distance_transform_edt(~m) / 3.0, 0.0, 1.0).astype(np.float32)
    # u compresses the box's corner at (5, 5, 5) along z: det(I + ∇u) 0.15 there (central differences)
    r2 = sum((grid[a] - 5.0) ** 2 for a in range(3))
    u = np.zeros((3,) + shape, np.float32)
    u[0] = (-1.4 * (grid[0] - 5.0) * np.exp(-r2 / 2.0)).astype(np.float32)
    assert wgt[1, 1, 1] == 0.0  # the corner (5, 5, 5) is beyond the bone's fade
    det_corner = jacobian_min(u[:, 3:8, 3:8, 3:8], sp)
    assert det_corner < DenseSettings().min_jacobian
    p, gain, _ = refine_bone(
        np.zeros(6), centre, box, wgt, u, tex, sample_w, np.full(3, 1.5), None, None, grid_mm, sp, DenseSettings()
    )
    assert gain > 0, gain
    assert abs(p[5] - 1.5) < 0.5 and np.all(np.abs(p[3:5]) < 0.5), p


def test_a_voxel_of_one_grid_in_voxels_of_another_follows_both_directions():
    """registration.dense.voxel_in_voxels (how much the bones' test smooths for a coarser template): a template
    whose index axes are a cycle of the scan's (its i along world y, j along z, k along x) with anisotropic
    (0.5, 2.0, 1.0) mm voxels, against a scan of (1.0, 0.8, 3.0) mm: along the scan's x its voxel is 1.0 mm (k) =
    1 scan voxel, along y 0.5 / 0.8, along z 2.0 / 3.0: 1.0.  The cycle is not its own transpose and the spacings
    are not palindromes, so a transposed direction (2.0), a reversed template spacing (1.25) or a reversed scan
    spacing (2.0) would show.  Unrotated: 2.0 / 0.8 = 2.5 along y.  Exact to rounding."""
    from registration.dense import voxel_in_voxels

    scan = GridGeometry((8, 8, 8), (1.0, 0.8, 3.0))
    cycled = GridGeometry((8, 8, 8), (0.5, 2.0, 1.0), direction=(0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0))
    assert np.array_equal(np.asarray(cycled.direction_matrix)[:, 0], [0.0, 1.0, 0.0])  # i along world y
    assert voxel_in_voxels(cycled, scan) == pytest.approx(1.0, abs=1e-12)
    plain = GridGeometry((8, 8, 8), (0.5, 2.0, 1.0))
    assert voxel_in_voxels(plain, scan) == pytest.approx(2.5, abs=1e-12)
    assert voxel_in_voxels(scan, scan) == pytest.approx(1.0, abs=1e-12)


def test_the_noise_that_sampling_averages_away_is_counted_back():
    """settings.interpolation_noise: a noisy template sampled half a voxel off its centres on every axis keeps
    1/8 of its white noise's variance, and a plain LNCC rises with that alone (the interpolation artefact);
    with every position given the noise of the average one (interpolation_noise_variance) it behaves as the noise-free
    template's does.  Signal: a smooth random field (σ 3 voxels, unit SD) in both images; independent white
    noise of SD 1 in the scan and in the noisy template (an SNR of 1: the noise rules the windows' variance, as
    in flat soft tissue).  Measured (seeds 11-15): the noise-free template's LNCC at the half-voxel shift is
    0.93 of the aligned one; the noisy template's plain LNCC 2.3-2.5× (log-ratio artefact +0.95 ± 0.03),
    corrected 0.83-0.91× (the artefact −0.03 to −0.12: the chance correlation, larger at the centres where the
    template keeps its whole noise, is not evened out).  So: the plain artefact > 0.5 and the corrected one
    below a fifth of it."""
    from registration import dense

    rng = np.random.default_rng(11)
    rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # a permuted, non-identity direction
    g = GridGeometry((38, 36, 34), (1.0, 1.3, 0.8), (4.0, -7.0, 2.0), tuple(rot.ravel()))
    signal = ndimage.gaussian_filter(rng.normal(size=g.array_shape), 3.0)
    signal /= signal.std()
    noisy = (signal + rng.normal(size=g.array_shape)).astype(np.float32)
    scan = (signal + rng.normal(size=g.array_shape)).astype(np.float32)
    crop = tuple(slice(0, n) for n in g.array_shape)
    zero = Volume(np.zeros(g.array_shape + (3,), np.float32), g)
    sp = np.asarray(g.spacing, float)[::-1]
    win = 2.0 * np.ones(3)
    stats = dense.local_stats(scan, win)
    inner = np.zeros(g.array_shape, np.float32)
    inner[4:-4, 4:-4, 4:-4] = 1.0  # away from the grid's edge, where the shifted sampling reads the edge
    lncc = {}
    for name, template in (("clean", signal.astype(np.float32)), ("noisy", noisy)):
        sampler = dense.TemplateSampler(Volume(template, g), zero, 1.0, crop, None)
        if name == "noisy":  # its noise variance (1) estimated: the smooth signal hardly reaches the residual
            assert sampler.noise_var == pytest.approx(1.0, rel=0.1)
        warp, _ = sampler.level(1, 0.0, g.array_shape)
        for frac in (0.0, 0.5):
            u = np.stack([np.full(g.array_shape, frac * sp[a], np.float32) for a in range(3)])
            w, v = warp(u)
            lncc[name, frac, "plain"] = dense.lncc_force(scan, w, win, stats, inner)[0]
            lncc[name, frac, "counted"] = dense.lncc_force(scan, w, win, stats, inner, v)[0]
            if name == "noisy":  # white noise keeps all of its variance at the centres, 1/8 midway, (2/3)³ on average
                kept = 1.0 if frac == 0.0 else 0.125
                np.testing.assert_allclose(v, sampler.noise_var * ((2.0 / 3.0) ** 3 - kept), rtol=1e-4)

    def log_ratio(name, kind):
        return np.log(lncc[name, 0.5, kind] / lncc[name, 0.0, kind])

    plain = log_ratio("noisy", "plain") - log_ratio("clean", "plain")
    counted = log_ratio("noisy", "counted") - log_ratio("clean", "plain")
    assert plain > 0.5
    assert abs(counted) < 0.2 * plain


def test_kernel_noise_is_the_smoothed_white_noises():
    """registration.dense.kernel_noise against white noise smoothed by the same filter (10⁶ samples along one
    axis: the variance and lag-1 correlation to ±1 %, several standard errors)."""
    from registration.dense import kernel_noise

    rng = np.random.default_rng(5)
    x = rng.normal(size=1_000_000)
    for sigma in (0.6, 1.5):
        y = ndimage.gaussian_filter1d(x, sigma, truncate=3.0)
        var, rho = kernel_noise(sigma)
        assert var == pytest.approx(y.var(), rel=0.01)
        assert rho == pytest.approx(np.corrcoef(y[1:], y[:-1])[0, 1], abs=0.01)
    assert kernel_noise(0.0) == (1.0, 0.0)


@pytest.mark.parametrize("air", ["gaussian", "rayleigh", "half constant fill", "clipped gaussian", "none"])
def test_the_template_noise_is_measured_in_its_air(air):
    """registration.dense.voxel_noise_variance: a 40³ image, a ball of textured tissue (radius 12 voxels,
    a smooth texture of SD ~30 under Gaussian noise of σ 20) in air of the given kind.  The tissue's variance
    returned is σ² within 10 % (the median's sampling error over ~40 000 air stencils is ~1 %; the air's
    noise is white): Gaussian air (offset −1000, as CT's) is the tissue's noise; a magnitude image's Rayleigh air
    (|complex Gaussian| of σ) has (2 − π/2) σ² and is converted back; a constant fill over half the air is
    left out; Gaussian air clipped at 0 (40 ± 20: mean over SD 2, as a Rayleigh's 1.91, but its median over mean
    is ~1 against 0.94) is not taken for Rayleigh.
    Without air, the tissue's own pseudo-residual (the texture adds to it: within 25 %)."""
    from registration.dense import voxel_noise_variance

    rng = np.random.default_rng(8)
    shape, sigma = (40, 40, 40), 20.0
    zz, yy, xx = np.indices(shape)
    r2 = (zz - 19.5) ** 2 + (yy - 19.5) ** 2 + (xx - 19.5) ** 2
    body = r2 < 12**2 if air != "none" else np.ones(shape, bool)
    tex = 500.0 + 30.0 * ndimage.gaussian_filter(rng.normal(size=shape), 3.0) / 0.04
    img = tex + sigma * rng.normal(size=shape)
    out = ~body
    if air == "gaussian":
        img[out] = -1000.0 + sigma * rng.normal(size=int(out.sum()))
    elif air == "rayleigh":
        img[out] = np.abs(sigma * rng.normal(size=int(out.sum())) + 1j * sigma * rng.normal(size=int(out.sum())))
    elif air == "half constant fill":
        img[out] = -1000.0 + sigma * rng.normal(size=int(out.sum()))
        img[out & (xx < 20)] = -1024.0
    elif air == "clipped gaussian":
        img[out] = np.maximum(40.0 + sigma * rng.normal(size=int(out.sum())), 0.0)
    tissue, in_air = voxel_noise_variance(img.astype(np.float32), body)
    if air == "none":
        assert tissue == in_air and tissue == pytest.approx(sigma**2, rel=0.25)
        return
    assert tissue == pytest.approx(sigma**2, rel=0.1)
    if air == "rayleigh":
        assert in_air == pytest.approx((2.0 - np.pi / 2.0) * sigma**2, rel=0.1)
    elif air != "clipped gaussian":
        assert in_air == tissue


def test_interpolation_noise_follows_each_template_axis():
    """registration.dense.interpolation_noise_variance as the sampler computes it on a smoothed level, against the
    closed form with the template index positions found independently (GridGeometry.world_to_index of the sampled world
    points): the scan and the template on different spacings, the template's axes a permutation of the scan's,
    a level of shrink 2 with pre-smoothing (σ 0.5 scan voxel, so a different noise correlation ρ_a along each
    template axis) and a shift giving each axis its own fraction.  A swapped axis in the fractions, ρ or the
    smoothing's σ changes the values by far more than the float32 tolerance (1e-5 of the variance)."""
    from registration import dense

    gs = GridGeometry((20, 18, 16), (1.0, 1.2, 1.5), (0.0, 0.0, 0.0))
    perm = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # template axis i along world y, ...
    gt = GridGeometry((30, 28, 26), (0.8, 1.1, 1.4), (-6.0, -5.0, -7.0), tuple(perm.ravel()))
    rng = np.random.default_rng(4)
    sampler = dense.TemplateSampler(
        Volume(rng.normal(size=gt.array_shape).astype(np.float32), gt),
        Volume(np.zeros(gs.array_shape + (3,), np.float32), gs),
        1.0,
        tuple(slice(0, n) for n in gs.array_shape),
        None,
    )
    sampler.noise_var = 1.0
    s, sig_pre = 2, 0.5
    shape = tuple(len(range(0, n, s)) for n in gs.array_shape)
    warp, _ = sampler.level(s, sig_pre, shape)
    u = np.stack([np.full(shape, v, np.float32) for v in (0.37, 0.21, 0.13)])  # mm along z, y, x
    _, v = warp(u)
    # the closed form: the sampled world points, their template indices, the level's ρ per template axis
    kk, jj, ii = np.meshgrid(*[np.arange(0, n, s) for n in gs.array_shape], indexing="ij")
    x = np.stack([ii, jj, kk], axis=-1) * np.asarray(gs.spacing) + np.asarray(gs.origin) + np.array([0.13, 0.21, 0.37])
    p = gt.world_to_index(x.reshape(-1, 3)).reshape(x.shape)
    sig_scan_mm = sig_pre * np.asarray(gs.spacing)  # along world x, y, z (identity direction)
    dt = np.asarray(gt.direction_matrix)
    sigma_t = np.sqrt((dt**2).T @ sig_scan_mm**2) / np.asarray(gt.spacing)  # per template axis i, j, k
    kern = [dense.kernel_noise(float(v_)) for v_ in sigma_t]
    assert len({round(k[1], 3) for k in kern}) == 3  # three different correlations: the test can tell the axes
    kappa = np.prod([k[0] for k in kern])
    t = p - np.floor(p)
    f = np.prod([1.0 - 2.0 * (1.0 - kern[a][1]) * t[..., a] * (1.0 - t[..., a]) for a in range(3)], axis=0)
    mean = np.prod([1.0 - (1.0 - k[1]) / 3.0 for k in kern])
    np.testing.assert_allclose(v, kappa * (mean - f), atol=1e-5 * kappa)


def test_data_fission_splits_the_noise_into_independent_copies():
    """registration.dense.fission (settings.holdout): an image ``s + n`` (white Gaussian noise of σ 20 over a
    textured ball in Gaussian air) becomes ``s + n + a z`` and ``s + n − z / a`` with ``z`` of the measured σ.
    Their noises are uncorrelated: ``E[(n + a z)(n − z / a)] = σ² − σ_z²``.  σ_z, measured in the air's ~40 000
    stencils (the median's sampling error ~1 %), must be σ within 3 %; then ``|σ² − σ_z²| ≤ 0.061 σ²`` and the
    correlation is at most 0.061 / 2.5 = 0.025 for a = 0.5, plus 0.012 (three sampling errors over 64 000
    voxels): under 0.04, against 1 for the image used twice.  The variances: (1 + a²) σ² within 5 % (σ_z's
    error moves it ≤ 1.2 %), (1 + 1 / a²) σ² within 7 % (≤ 4.9 %), the rest sampling error.  The inputs are not
    changed; the same seed gives the same bits, another seed another draw.  (Measured: SDs within 0.3 %,
    correlations under 0.01, variances within 2 %.)"""
    from registration.dense import fission

    rng = np.random.default_rng(5)
    shape, sigma, a = (40, 40, 40), 20.0, 0.5
    zz, yy, xx = np.indices(shape)
    body = (zz - 19.5) ** 2 + (yy - 19.5) ** 2 + (xx - 19.5) ** 2 < 12**2
    signal = np.where(body, 500.0 + 30.0 * ndimage.gaussian_filter(rng.normal(size=shape), 3.0) / 0.04, -1000.0)
    noise = [sigma * rng.normal(size=shape) for _ in range(2)]
    f = (signal + noise[0]).astype(np.float32)
    g = GridGeometry(shape[::-1], (1.0, 1.2, 1.5), (0.0, 0.0, 0.0), tuple(np.eye(3).reshape(-1)))
    moving = Volume((signal + noise[1]).astype(np.float32), g)
    f_in, m_in = f.copy(), moving.data.copy()
    st = DenseSettings(holdout=True, holdout_share=a)
    (f_held, m_held, sds), f_steps, m_steps = fission(f, body, moving, body, st)
    assert np.array_equal(f, f_in) and np.array_equal(moving.data, m_in)
    assert sds[0] == pytest.approx(sigma, rel=0.03) and sds[1] == pytest.approx(sigma, rel=0.03)
    for steps, held, _n in ((f_steps, f_held, noise[0]), (m_steps.data, m_held.data, noise[1])):
        e1, e2 = (steps - signal).ravel(), (held - signal).ravel()
        assert abs(np.corrcoef(e1, e2)[0, 1]) < 0.04
        assert e1.var() == pytest.approx((1 + a * a) * sigma**2, rel=0.05)
        assert e2.var() == pytest.approx((1 + 1 / (a * a)) * sigma**2, rel=0.07)
    again = fission(f, body, moving, body, st)
    assert np.array_equal(again[1], f_steps) and np.array_equal(again[0][1].data, m_held.data)
    other = fission(f, body, moving, body, DenseSettings(holdout=True, holdout_share=a, holdout_seed=1))
    assert not np.array_equal(other[1], f_steps)


def test_holdout_returns_the_map_its_held_out_copy_scores_highest():
    """settings.holdout end to end on the textured case in air, white noise of SD 50 on both images (the
    texture's SD is ~220), from the truth: every level returns the map of its taken steps whose held-out LNCC is
    the highest (the record's ``best_step``, its objective the level's ``lncc_after``), the objective still
    rises at every taken step, and the map drifts from the truth less than the plain registration's, which
    fits the noise (measured: 0.00 mm, every level kept its input, against 0.15; with SD 100, 0.28 against
    0.30; from the identity start, 0.81 mm off, SD 50: 0.52 against 0.44 — the option's cost where there is
    motion to recover).  Same bits twice."""
    template, labels, scan, truth, bone = make_case(air=True)
    rng = np.random.default_rng(21)
    noisy = [
        Volume((v.data + 50.0 * rng.normal(size=v.data.shape)).astype(np.float32), v.geometry) for v in (template, scan)
    ]
    # the skin's term and the membrane energy off: the paths measured below are the LNCC's alone
    st = DenseSettings(shrink=(2, 1), iterations=(200, 200), holdout=True, skin_weight=0.0, stiffness=0.0)
    res = register_dense(noisy[1], noisy[0], initial=truth, moving_labels=labels, settings=st)
    again = register_dense(noisy[1], noisy[0], initial=truth, moving_labels=labels, settings=st)
    assert np.array_equal(res.correspondence.data, again.correspondence.data)
    plain = register_dense(
        noisy[1],
        noisy[0],
        initial=truth,
        moving_labels=labels,
        settings=DenseSettings(shrink=(2, 1), iterations=(200, 200), skin_weight=0.0, stiffness=0.0),
    )
    assert plain.levels[-1]["held_out"] is None
    for lv in res.levels:
        held = np.asarray(lv["held_out"]["lncc"])
        assert len(held) == len(lv["lncc"])  # one held-out score per taken step and the level's input
        best = lv["held_out"]["best_step"]
        assert held[best] == pytest.approx(held.max(), abs=1e-6)  # the record rounds to 6 digits: ties allowed
        assert lv["lncc_after"] == pytest.approx(lv["lncc"][best], abs=1e-6)  # the record rounds to 6 digits
        assert np.all(np.diff(np.asarray(lv["lncc"])) > 0), lv["lncc"]
    tissue = (scan.data > 0) & ~bone
    drift = [np.linalg.norm(r.correspondence.data - truth.data, axis=-1)[tissue].mean() for r in (res, plain)]
    assert drift[0] < drift[1], drift
    # From the identity (0.81 mm off) the levels go back to an earlier map and stop on the patience (measured:
    # level 0 returns step 9 of 15; level 1 stops after 10 taken steps without a new highest and returns its input)
    ident = register_dense(noisy[1], noisy[0], moving_labels=labels, settings=st)
    coarse, fine = ident.levels
    assert 0 < coarse["held_out"]["best_step"] < coarse["iterations"]
    assert coarse["lncc_after"] == pytest.approx(coarse["lncc"][coarse["held_out"]["best_step"]], abs=1e-6)
    assert fine["stop"] == "held-out" and fine["input_kept"]
    assert fine["iterations"] - fine["held_out"]["best_step"] == st.holdout_patience


@pytest.mark.parametrize(
    "outcome, calls_frozen, taken, attempts",
    [
        ("all fail", [True, True, False, False], None, [[1, 9], [None, 9]]),
        ("1 layer succeeds", [True], 1, [[1, 0]]),
        ("nothing frozen and 2 layers succeed", [True, True, False, True], 2, [[1, 9], [None, 0], [2, 0]]),
        (
            "nothing frozen alone succeeds",
            [True, True, False, True, True, True, True],
            None,
            [[1, 9], [None, 0], [2, 9], [3, 9]],
        ),
    ],
)
def test_fold_repair_skips_the_freezing_attempts_when_nothing_frozen_fails(
    monkeypatch, outcome, calls_frozen, taken, attempts
):
    """The final repair's attempts (register_dense, settings.unfold): 1 bone layer released first, then nothing
    frozen; the attempts that freeze more (2, 3 layers) run only when nothing frozen removed every fold (freezing
    takes freedom from the smoothing: they would fail too, each spending unfold's whole budget), and the first
    that removes every fold in the order 1, 2, 3, nothing is taken (``taken`` None: nothing frozen, or none when
    all fail).  ``unfold`` is replaced by a stand-in that records each call (whether something was frozen), tags
    the field it returns with its call's number, and succeeds as ``outcome`` says; the start folds the body (the
    halves above and below a plane each moved 3 mm towards the other), so the repair runs."""
    import registration.dense as dense

    template, labels, scan, truth, bone = make_case(air=True)
    start = np.zeros(truth.data.shape, np.float32)
    z = scan.geometry.world_coordinates()[..., 2]
    start[..., 2] = np.where(z > np.median(z), -3.0, 3.0)  # the voxels across the plane overlap: det < 0
    calls = []

    def fake_unfold(field, *, mask=None, frozen=None, **kernel):
        calls.append(frozen is not None)
        kind = "frozen" if frozen is not None else "none"
        layer = {1: 1, 2: 1, 3: None, 4: 2, 5: 2, 6: 3, 7: 3}.get(len(calls)) if outcome != "1 layer succeeds" else 1
        ok = {
            "all fail": False,
            "1 layer succeeds": True,
            "nothing frozen and 2 layers succeed": kind == "none" or layer == 2,
            "nothing frozen alone succeeds": kind == "none",
        }[outcome]
        tagged = Volume(np.full(field.data.shape, 1000.0 * len(calls), np.float32), field.geometry)
        return tagged, {
            "iterations": 200,
            "n_folded_before": 9,
            "n_folded_after": 0 if ok else 9,
            "n_changed": 0,
            "n_restored": 0,
            "max_change_mm": 0.0,
        }

    monkeypatch.setattr(dense, "unfold", fake_unfold)
    res = register_dense(
        scan,
        template,
        initial=Volume(start, scan.geometry),
        moving_labels=labels,
        settings=DenseSettings(shrink=(2,), iterations=(3,)),
    )
    rep = res.unfold
    assert calls == calls_frozen and rep["attempts"] == attempts
    assert rep["taken"] == (outcome != "all fail")
    if rep["taken"]:
        assert rep["bone_layers_released"] == taken
        # the field returned is the successful attempt's own (its call's tag)
        first_ok = {1: 1, 2: 4, None: 3}[taken]
        assert np.all(res.correspondence.data == 1000.0 * first_ok)
    else:  # the folds stay: the registered field, not a stand-in's
        assert np.abs(res.correspondence.data).max() < 1000.0


def test_the_skin_term_leaves_out_where_the_template_has_no_grid():
    """A limb that leaves the template's field of view: beyond the template's grid its body is unknown, and the
    term must not read the grid's end as a skin.  The scan is the template's cylinder (along y, through both
    grids' ends) on a grid 12.6 mm longer, started at the truth (identity).  The LNCC alone drifts near the
    template's cut end (it reads the template's air beyond it: 1.11 mm at most, measured); the term adds nothing
    to that (0.97 mm with it).  Read as air, the template's end pulls the cylinder by 2.1 mm (measured)."""
    g, r = _rotated_grid((30, 40, 26), (-22.0, -36.0, -28.0))
    rng = np.random.default_rng(6)
    scan = _flat_body(g, r, (12.0, 1e3, 11.0), rng)
    short = GridGeometry((30, 40 - 7, 26), g.spacing, g.origin, g.direction)  # 7 voxels (12.6 mm) fewer along y
    template = Volume(np.ascontiguousarray(scan.data[:, :33, :]), short)
    st = dict(shrink=(2, 1), iterations=(200, 200), bones="free")
    on = register_dense(scan, template, settings=DenseSettings(**st))
    off = register_dense(scan, template, settings=DenseSettings(**st, skin_weight=0.0))
    assert all(lv["skin_term"] for lv in on.levels)
    moved = [float(np.linalg.norm(res.correspondence.data, axis=-1).max()) for res in (on, off)]
    assert moved[0] <= moved[1] + 0.05, moved  # 0.05 mm: the two runs' steps differ; the pull adds ~1 mm


def _rotated_grid(size, origin):
    """An anisotropic grid rotated 15° about z, and its voxels' positions from the grid's centre (mm)."""
    c, s = np.cos(np.deg2rad(15)), np.sin(np.deg2rad(15))
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    g = GridGeometry(size, (1.5, 1.8, 2.2), origin, tuple(rot.reshape(-1)))
    x = g.world_coordinates()
    return g, x - x.reshape(-1, 3).mean(axis=0)


def _flat_body(g, r, radii, rng):
    """An ellipsoid of one intensity (1000) in air (0), its edge blurred over about a mm, noise of SD 30."""
    q = np.sqrt(np.sum((r / np.asarray(radii)) ** 2, axis=-1))
    img = 1000.0 * 0.5 * (1.0 - np.tanh((q - 1.0) * min(radii))) + 30.0 * rng.normal(size=q.shape)
    return Volume(img.astype(np.float32), g)


def test_membrane_energy_and_its_derivative():
    """membrane_energy: Σ m |∇u|² by forward differences (each pair weighed by both voxels' m) against a direct sum on
    a small anisotropic case, and its derivative against central finite differences of the energy (float64: the
    energy is quadratic in u, so the difference quotient is exact up to round-off)."""
    from registration.dense import membrane_energy

    rng = np.random.default_rng(3)
    sp = np.array([1.5, 2.0, 0.8])
    u = rng.normal(size=(3, 5, 6, 4))
    m = (rng.uniform(size=(5, 6, 4)) > 0.3).astype(float)
    e, g = membrane_energy(u, m, sp)
    direct = 0.0
    for a in range(3):
        for z in range(5):
            for y in range(6):
                for x in range(4):
                    for b, (dz, dy, dx) in enumerate(((1, 0, 0), (0, 1, 0), (0, 0, 1))):
                        if z + dz < 5 and y + dy < 6 and x + dx < 4:
                            d = (u[a, z + dz, y + dy, x + dx] - u[a, z, y, x]) / sp[b]
                            direct += m[z, y, x] * m[z + dz, y + dy, x + dx] * d * d
    assert e == pytest.approx(direct, rel=1e-12)
    h = 1e-4
    for idx in [(0, 2, 3, 1), (1, 0, 0, 0), (2, 4, 5, 3), (1, 2, 1, 2)]:
        up, dn = u.copy(), u.copy()
        up[idx] += h
        dn[idx] -= h
        assert g[idx] == pytest.approx(
            (membrane_energy(up, m, sp)[0] - membrane_energy(dn, m, sp)[0]) / (2 * h), rel=1e-6, abs=1e-9
        )


def test_stiffness_keeps_the_start_where_the_scan_shows_only_noise():
    """settings.stiffness: the template and the scan are the same flat body (one intensity, two independent noise
    draws of SD 30), on an anisotropic, rotated grid, started at the truth (identity).  Without the energy the
    steps fit the noise and move the body's tissue by 1.16 mm on average (measured); with the default the move
    costs where the windows hold noise only (the windows within ~10 mm of the edge see it, so a share of the body
    stays free) and falls to 0.70 (measured; asserted: under 0.7 of the unstiffened).  The levels record the
    energy's mean weight, and every level's objective still rises at every taken step."""
    g, r = _rotated_grid((36, 40, 28), (-26.0, -36.0, -30.0))
    rng = np.random.default_rng(8)
    template = _flat_body(g, r, (15.0, 18.0, 14.0), rng)
    scan = _flat_body(g, r, (15.0, 18.0, 14.0), rng)
    inside = scan.data > 500.0
    st = dict(shrink=(2, 1), iterations=(200, 200), bones="free", posterior=False)  # the energy alone
    moved = []
    for res in (
        register_dense(scan, template, settings=DenseSettings(**st, stiffness=0.0)),
        register_dense(scan, template, settings=DenseSettings(**st)),
    ):
        moved.append(float(np.linalg.norm(res.correspondence.data, axis=-1)[inside].mean()))
        for lv in res.levels:
            assert np.all(np.diff(np.asarray(lv["lncc"])) > 0), lv["lncc"]
    assert res.levels[-1]["noise_share"] > 0 and DenseSettings().stiffness > 0
    assert moved[1] < 0.7 * moved[0], moved


def test_penalties_and_their_ascent_match_finite_differences():
    """penalties (the skin's term and the membrane energy the level's objective subtracts): their ascents along
    ``b`` and along ``u``, times the region's voxel count (as the LNCC's force), against central finite differences
    of minus the penalties (float64: both are quadratic, so the difference quotient is exact up to round-off).  A
    sign or scale error in either force fails here."""
    from registration.dense import penalties

    rng = np.random.default_rng(4)
    shape, sp = (5, 6, 4), np.array([1.5, 2.0, 0.8])
    b, s = rng.uniform(size=shape), rng.uniform(size=shape)
    band = 4.0 * s * (1.0 - s)
    region = (rng.uniform(size=shape) > 0.2).astype(float)
    checked = [(0, 0, 0), (2, 3, 1), (4, 5, 3)]
    for idx in checked:  # the skin's checks below read inside the region (outside it the term is 0)
        region[idx] = 1.0
    u, m = rng.normal(size=(3,) + shape), rng.uniform(size=shape) * region
    n = float(np.count_nonzero(region))

    def objective(b_, u_):  # the objective's part these terms make
        return -sum(penalties(b_, s, band, region, 1.7, u_, m, sp, 2.5, n)[0])

    _, skin, membrane = penalties(b, s, band, region, 1.7, u, m, sp, 2.5, n)
    h = 1e-5
    for idx in checked:
        up, dn = b.copy(), b.copy()
        up[idx] += h
        dn[idx] -= h
        assert skin[idx] / n == pytest.approx((objective(up, u) - objective(dn, u)) / (2 * h), rel=1e-6)
    for idx in [(0, 2, 3, 1), (1, 1, 1, 1), (2, 4, 5, 3)]:
        up, dn = u.copy(), u.copy()
        up[idx] += h
        dn[idx] -= h
        assert membrane[idx] / n == pytest.approx((objective(b, up) - objective(b, dn)) / (2 * h), rel=1e-6, abs=1e-12)
    off = penalties(None, s, band, region, 1.7, u, None, sp, 2.5, n)
    assert off == ((0.0, 0.0), None, None)


def test_the_skin_term_alone_moves_an_outline_the_lncc_cannot_see():
    """Two bodies of one intensity with sharp edges and no noise: inside the scan's tissue (the LNCC's windows) the
    scan is constant, so the LNCC has no force anywhere, and without the skin's term nothing moves (the level
    stops with no force, the map stays the start's: the same bits).  With it the registered template's body comes
    onto the scan's (stretched by 4 mm along y on each side): the voxels where the two bodies disagree fall to
    under half the start's (measured 572 → 44).  No noise: the membrane energy is off by itself."""
    from registration.segmentation import segment_body

    g, r = _rotated_grid((36, 40, 28), (-26.0, -36.0, -30.0))

    def sharp(radii):
        q = np.sqrt(np.sum((r / np.asarray(radii)) ** 2, axis=-1))
        return Volume(np.where(q <= 1.0, 1000.0, 0.0).astype(np.float32), g)

    template, scan = sharp((15.0, 18.0, 14.0)), sharp((15.0, 22.0, 14.0))
    scan_body = segment_body(scan).data > 0
    start = int(((segment_body(template).data > 0) ^ scan_body).sum())
    # one level: a coarser one's pre-smoothing would blur the scan's edge into its tissue's windows
    st = dict(shrink=(1,), iterations=(200,), bones="free")
    off = register_dense(scan, template, settings=DenseSettings(**st, skin_weight=0.0))
    on = register_dense(scan, template, settings=DenseSettings(**st))
    assert not np.any(off.correspondence.data) and not any(lv["skin_term"] for lv in off.levels)
    assert all(lv["tissue_only"] and lv["skin_term"] and lv["noise_share"] is None for lv in on.levels)
    for lv in on.levels:  # the objective (the LNCC, 0 here, less the term) rises at every taken step
        assert lv["iterations"] > 0 and np.all(np.diff(np.asarray(lv["lncc"])) > 0), lv["lncc"]
    assert on.folding["n_folded"] == 0
    after = int(((segment_body(on.registered).data > 0) ^ scan_body).sum())
    assert after < 0.5 * start, (start, after)


def test_the_posterior_keeps_the_start_where_the_images_carry_nothing_and_closes_a_clear_offset():
    """settings.posterior with its mean (issue R): the textured case with noise raised until the images carry nothing
    (SD 20× the texture's, independent draws in the template and the scan), started at the truth: the result equals
    the start within 0.05 mm over the tissue (the issue's bound; measured 0.001 mm, 0.12 without the posterior),
    each level keeps under a tenth of its change, and the record says that the images measured no correction (the
    finest level's prior SD at its bound). Moderate noise (SD 100, the texture's SD ~250) and the start at the
    identity, the true warp 2.5 mm at most away: the offset is still closed (≥ 60 % of the start's error removed, as
    the noiseless test asks; measured 0.83 → 0.27 mm, 0.29 without the posterior) and most of the finest level's
    change is kept (measured 80 %)."""
    template, labels, scan, truth, bone = make_case()
    rng = np.random.default_rng(21)
    tissue = ~bone
    sd_tex = float(np.std(template.data[tissue]))
    st = DenseSettings(shrink=(2, 1), iterations=(100, 100), bones="free", posterior_mean=True)
    loud = 20.0 * sd_tex
    t_noisy = Volume((template.data + loud * rng.normal(size=bone.shape)).astype(np.float32), template.geometry)
    s_noisy = Volume((template.data + loud * rng.normal(size=bone.shape)).astype(np.float32), template.geometry)
    res = register_dense(s_noisy, t_noisy, settings=st)  # the start (identity) is the truth here
    moved = np.linalg.norm(res.correspondence.data, axis=-1)[tissue]
    assert float(moved.mean()) < 0.05, float(moved.mean())
    assert max(res.posterior["kept_levels"]) < 0.1
    # no correction was measured: the evidence puts the finest level's prior SD at its lower bound, and says so
    assert res.posterior["prior_at_bound"]

    t_mod = Volume((template.data + 100.0 * rng.normal(size=bone.shape)).astype(np.float32), template.geometry)
    s_mod = Volume((scan.data + 100.0 * rng.normal(size=bone.shape)).astype(np.float32), scan.geometry)
    res = register_dense(s_mod, t_mod, settings=st)
    err0 = np.linalg.norm(truth.data, axis=-1)[tissue].mean()
    err = np.linalg.norm(res.correspondence.data - truth.data, axis=-1)[tissue].mean()
    assert err < 0.4 * err0, (err, err0)
    assert res.posterior["kept"] > 0.5


def test_a_held_bones_expected_error_is_its_rigid_poses(case):
    """settings.posterior: on a held bone the map is the bone's rigid motion, and its expected error is that of
    its rigid pose (the Cramér–Rao bound from the bone's voxels and one around, on the finest level only: a
    coarse level's bone is a few voxels and would add the refinement's bounds as its error).  The textured case's
    bone is a uniform block with sharp edges: its pose is fixed to a few hundredths of a mm (measured: σ 0.04 mm
    median, 0.07 at its corners, 30 mm from its centre), while the soft tissue's σ carries the share of its
    correction (0.30 mm median).  Bounds: the bone's σ under 0.1 mm everywhere and under a third of the tissue's
    median; the record holds the bone's SDs (rotation °, translation mm)."""
    template, labels, scan, truth, bone = case
    res = register_dense(
        scan, template, moving_labels=labels, settings=DenseSettings(shrink=(2, 1), iterations=(60, 60))
    )
    sigma = res.uncertainty.data
    assert sigma[bone].max() < 0.1
    assert np.median(sigma[bone]) < np.median(sigma[~bone]) / 3.0
    rot_deg, shift_mm = res.posterior["bone_sd"]["1"]
    assert 0 < shift_mm < 0.1 and 0 < rot_deg < 1.0


def test_without_the_posterior_mean_the_map_is_the_steps_and_sigma_is_still_given(case):
    """settings.posterior_mean False (the default): every level keeps the steps' own change (the same bits as with
    the posterior off) and the result still carries its expected error."""
    template, labels, scan, truth, bone = case
    st = dict(shrink=(2, 1), iterations=(30, 30))
    off = register_dense(scan, template, moving_labels=labels, settings=DenseSettings(**st, posterior=False))
    sigma_only = register_dense(scan, template, moving_labels=labels, settings=DenseSettings(**st))
    assert not DenseSettings().posterior_mean  # the default
    np.testing.assert_array_equal(off.correspondence.data, sigma_only.correspondence.data)
    assert off.uncertainty is None and sigma_only.uncertainty is not None
    assert np.all(np.isfinite(sigma_only.uncertainty.data)) and float(sigma_only.uncertainty.data.min()) > 0


def test_sigma_counts_the_steps_change_the_posterior_doubts():
    """settings.posterior_offset (the default, issue R): the map keeps each level's own change Δ, whose expected
    squared error under the level's posterior N(û, C) is tr C + |Δ − û|².  On the textured case with noise raised
    until the images carry nothing, started at the truth, the steps still move (their fit of the noise) while each
    posterior mean keeps under a tenth of the change: the variance the offset adds is then about Σ_levels |Δ|²,
    which by Cauchy–Schwarz over the 2 levels is at least 0.81·|u|²/2 summed over the tissue (u = Σ Δ, the map's
    error here; the levels' variances are resampled from level to level, so the sum, not each voxel, is asserted:
    0.4 × Σ|u|², measured 1.13 ×).  The map is the same bits either way."""
    template, labels, scan, truth, bone = make_case()
    rng = np.random.default_rng(21)
    tissue = ~bone
    loud = 20.0 * float(np.std(template.data[tissue]))
    t_noisy = Volume((template.data + loud * rng.normal(size=bone.shape)).astype(np.float32), template.geometry)
    s_noisy = Volume((template.data + loud * rng.normal(size=bone.shape)).astype(np.float32), template.geometry)
    st = dict(shrink=(2, 1), iterations=(100, 100), bones="free")
    plain = register_dense(s_noisy, t_noisy, settings=DenseSettings(**st, posterior_offset=False))
    offset = register_dense(s_noisy, t_noisy, settings=DenseSettings(**st))
    assert DenseSettings().posterior_offset  # the default
    np.testing.assert_array_equal(plain.correspondence.data, offset.correspondence.data)
    added = offset.uncertainty.data.astype(np.float64) ** 2 - plain.uncertainty.data.astype(np.float64) ** 2
    assert added.min() >= -1e-6  # float32 σ squared: the offset only adds
    u2 = np.sum(plain.correspondence.data.astype(np.float64) ** 2, axis=-1)
    assert u2[tissue].mean() > 0.005  # the steps did fit the noise (mean |u| 0.12 mm measured)
    assert added[tissue].sum() >= 0.4 * u2[tissue].sum(), (added[tissue].sum(), u2[tissue].sum())


def test_the_whole_corrections_posterior_only_raises_sigma_in_the_soft_tissue(case):
    """settings.posterior_total (the default, issue R): the whole correction from the start is weighed against
    the start on the finest level, and in the soft tissue σ² is at least that posterior's expected squared error.
    It changes σ only (the map is the same bits), never lowers it anywhere (float32: 1e-6 mm), and leaves the
    held bone's σ (its rigid pose's) alone."""
    template, labels, scan, truth, bone = case
    st = dict(shrink=(2, 1), iterations=(30, 30))
    plain = register_dense(scan, template, moving_labels=labels, settings=DenseSettings(**st, posterior_total=False))
    total = register_dense(scan, template, moving_labels=labels, settings=DenseSettings(**st))
    assert DenseSettings().posterior_total
    np.testing.assert_array_equal(plain.correspondence.data, total.correspondence.data)
    a, b = plain.uncertainty.data.astype(np.float64), total.uncertainty.data.astype(np.float64)
    assert np.all(b >= a - 1e-6)
    core = ndimage.binary_erosion(bone, iterations=3)  # the bone away from its fade (bone_margin_mm)
    np.testing.assert_allclose(b[core], a[core], atol=1e-6)
