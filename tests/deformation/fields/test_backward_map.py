"""The exact backward map's machinery: where the template lands on the target grid (``_landing``), the same bits
for any number of threads, and the pull through the map."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deformation.fields import resample as R
from deformation.fields.interpolate import sample_array
from deformation.geometry import GridGeometry, Volume
from deformation.models.evd import vbd_forward
from deformation.models.skinning import distance_weights, stack_transforms
from validation.phantoms import make_phantom


@pytest.fixture(scope="module")
def hand():
    """The test-size hand posed by VBD at its most flexed pose: folds, air swept over the body, preimages leaving
    the template — every branch of the solver — with the body as the preferred mask."""
    ph = make_phantom("hand", size="test", noise=False, n_poses=3, seed=5, modality="mri")
    g = ph.geometry
    d = ph.anatomy.distances_fast(g.world_coordinates().reshape(-1, 3))
    w = distance_weights(d[:, :-1], ph.skeleton.bone_names)
    body = (d[:, -1] < 0).reshape(g.array_shape)
    t = stack_transforms(ph.pose_of(ph.poses[2][1]).transforms, w.bones)
    return g, vbd_forward(g, w, t), t, body, ph.template()[0]


def _landing(fwd, g, target, prio, n_chunks, tol, guess_dtype=np.int32):
    """``_landing``'s arrays as backward_map allocates them (cover, occ, priocov, guess on the target grid)."""
    shape = target.array_shape
    cover = np.zeros(shape, np.uint8)
    occ = np.zeros(shape, np.uint8)
    priocov = np.zeros(shape, np.uint8)
    guess = np.full(shape, -1, guess_dtype)
    R._landing(
        np.ascontiguousarray(fwd, np.float32),
        np.ascontiguousarray(target.world_to_index_matrix[:3]),
        np.ascontiguousarray(target.index_to_world_matrix[:3]),
        prio,
        prio.shape == g.array_shape,  # backward_map's use_prio: a (1, 1, 1) placeholder without a mask
        R._max_extent(g, target),
        tol,
        n_chunks,
        shape,
        cover.reshape(-1),
        occ,
        priocov.reshape(-1),
        guess.reshape(-1),
    )
    return cover, occ, priocov, guess


def test_backward_map_gives_the_same_bits_on_one_and_two_threads(hand):
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here (NUMBA_NUM_THREADS): nothing to compare")
    g, fwd, t, body, _ = hand
    n_threads = numba.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            bm = R.backward_map(fwd, g, transforms=t, prefer=body)
            out.append((bm.template_index, bm.residual_mm, bm.status))
    finally:
        numba.set_num_threads(n_threads)
    for a, b in zip(*out):
        np.testing.assert_array_equal(a, b)
    # the case exercises the solver's branches: folds, preimages outside the template, unconverged voxels
    counts = np.bincount(out[0][2].ravel(), minlength=4)
    assert counts[R.FOLDED] > 0 and counts[R.OUTSIDE] > 0 and counts[R.NOT_CONVERGED] > 0, counts


def test_landing_is_the_same_however_the_slabs_are_cut(hand):
    """Every write of ``_landing``'s runs of slabs is a 1 (the guess is one serial task): the runs its threads
    take do not show."""
    g, fwd, _, body, _ = hand
    prio = body.astype(np.uint8)
    ref = _landing(fwd, g, g, prio, 1, 0.01 * min(g.spacing))
    for n_chunks in (2, 7, g.size[2]):
        for a, b in zip(ref, _landing(fwd, g, g, prio, n_chunks, 0.01 * min(g.spacing))):
            np.testing.assert_array_equal(a, b)


def test_landing_guess_is_the_last_landing_voxel_a_preferred_one_first(hand):
    """The guess of each target voxel: among the template voxels whose forward position rounds to it, the last in
    array order, a preferred (body) voxel before any other."""
    g, fwd, _, body, _ = hand
    _, _, _, guess = _landing(fwd, g, g, body.astype(np.uint8), 4, 0.01 * min(g.spacing))
    tidx = (fwd.astype(np.float64) @ g.world_to_index_matrix[:3, :3].T + g.world_to_index_matrix[:3, 3]).astype(
        np.float32
    )
    r = np.floor(tidx.astype(np.float64) + 0.5).astype(np.int64).reshape(-1, 3)
    nx, ny, nz = g.size
    inside = np.all((r >= 0) & (r < [nx, ny, nz]), axis=1)
    n = g.n_voxels
    key = np.arange(n) + n * body.reshape(-1)
    expect = np.full(n, -1, np.int64)
    np.maximum.at(expect, (r[inside, 2] * ny + r[inside, 1]) * nx + r[inside, 0], key[inside])
    np.testing.assert_array_equal(guess.reshape(-1), np.where(expect >= n, expect - n, expect))


def _kernel(fwd, g, t, prio, occ, priocov, cover, guess, tol):
    """``backward_kernel`` on the template grid as backward_map calls it, with the given cover arrays; returns
    (template index, status) before ``_orient_status``."""
    shape = g.array_shape
    out_x = np.empty(shape + (3,), np.float32)
    out_res = np.empty(shape, np.float32)
    out_status = np.empty(shape, np.uint8)
    R.backward_kernel(
        np.ascontiguousarray(fwd, np.float32),
        np.ascontiguousarray(g.index_to_world_matrix[:3]),
        R._candidates(g, g, t),
        tol,
        12,  # backward_map's max_iter, max_step and n_restarts
        2.0,
        4,
        prio,
        occ,
        priocov,
        cover,
        guess,
        out_x,
        out_res,
        out_status,
    )
    return out_x, out_status


def test_cover_holds_every_voxel_that_converges_without_it(hand):
    """The two promises the solver relies on to skip work, against the solver without them (every voxel solved,
    the preferred restarts tried wherever a preferred voxel lands): a voxel that converges there is in the cover,
    and a voxel whose preimage there is preferred is in ``priocov``."""
    g, fwd, t, body, _ = hand
    tol = 0.01 * min(g.spacing)
    prio = body.astype(np.uint8)
    cover, occ, priocov, guess = _landing(fwd, g, g, prio, 4, tol)
    everywhere = np.ones(g.array_shape, np.uint8)
    x, status = _kernel(fwd, g, t, prio, occ, everywhere, everywhere, guess, tol)
    converged = status <= R.FOLDED
    assert np.all(cover[converged]), int(np.sum(converged & (cover == 0)))
    nx, ny, nz = g.size
    near = np.clip(np.floor(x.astype(np.float64) + 0.5).astype(int), 0, [nx - 1, ny - 1, nz - 1])
    preferred = converged & body[near[..., 2], near[..., 1], near[..., 0]]
    assert preferred.sum() > 1000
    assert np.all(priocov[preferred]), int(np.sum(preferred & (priocov == 0)))
    # and the cover only skips work: the solver with it gives the same answers
    x2, status2 = _kernel(fwd, g, t, prio, occ, priocov, cover, guess, tol)
    solved = cover == 1
    np.testing.assert_array_equal(status2[solved], status[solved])
    np.testing.assert_array_equal(x2[solved], x[solved])


def test_an_int64_guess_gives_the_int32_guess_bits(hand):
    """Templates of 2³¹ voxels or more index their guesses in int64: the same kernels, the same answers."""
    g, fwd, t, body, _ = hand
    tol = 0.01 * min(g.spacing)
    prio = body.astype(np.uint8)
    a = _landing(fwd, g, g, prio, 4, tol)
    b = _landing(fwd, g, g, prio, 4, tol, guess_dtype=np.int64)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)
    for u, v in zip(
        _kernel(fwd, g, t, prio, *a[1:3], a[0], a[3], tol), _kernel(fwd, g, t, prio, *b[1:3], b[0], b[3], tol)
    ):
        np.testing.assert_array_equal(u, v)


def test_cover_stops_at_the_posed_faces_of_the_template_box():
    """An affine map: the template box's image is a parallelepiped whose faces are the planes of the border cells'
    faces, so a target voxel farther than the tolerance beyond any face is outside without a solve, and every
    voxel inside is covered and found."""
    g = GridGeometry((20, 17, 13), (1.5, 1.2, 2.0), origin=(3.0, -4.0, 1.0))
    rot = Rotation.from_euler("xyz", [10.0, -7.0, 25.0], degrees=True).as_matrix()
    shift = np.array([2.3, -1.1, 0.7])
    centre = g.index_to_world(np.array([(n - 1) / 2 for n in g.size]))
    fwd = ((g.world_coordinates() - centre) @ rot.T + centre + shift).astype(np.float32)
    target = GridGeometry((30, 28, 24), (1.0, 1.0, 1.0), origin=(-5.0, -13.0, -6.0))
    tol = 0.01 * min(g.spacing)
    cover, *_ = _landing(fwd, g, target, np.zeros((1, 1, 1), np.uint8), 3, tol)
    y = target.world_coordinates()
    u = g.world_to_index((y - centre - shift) @ rot + centre)  # the exact preimage (template index)
    # signed distance (mm) beyond the nearest face, per axis: the faces are at index 0 and n - 1
    sp = np.asarray(g.spacing)
    beyond = np.max(np.maximum(-u, u - (np.asarray(g.size) - 1)) * sp, axis=-1)
    # float32 positions: the planes are exact to ~1e-5 mm
    assert np.all(cover[beyond > tol + 1e-4] == 0)
    inside = beyond <= 0
    assert inside.sum() > 1000 and np.all(cover[inside] == 1)
    bm = R.backward_map(fwd, g, target)
    assert np.all(bm.status[inside] == R.OK)
    assert np.all(bm.status[beyond > tol + 1e-4] == R.OUTSIDE)


@pytest.mark.parametrize("kind", ["float32", "labels", "bool", "int16"])
def test_the_pull_is_sample_array_through_the_map_with_fill_outside(hand, kind):
    """``resample_forward``'s kernel samples only the voxels that are not OUTSIDE: the values are sample_array's at
    the template index (the identity world → index map), bit for bit, and the fill elsewhere."""
    g, fwd, t, body, template = hand
    bm = R.backward_map(fwd, g, transforms=t, prefer=body)
    intensity = np.asarray(template.data, np.float32)
    labels = kind in ("labels", "bool")
    src = {
        "float32": intensity,
        "labels": (intensity > np.median(intensity)).astype(np.uint8) * 3,
        "bool": body,
        "int16": intensity.astype(np.int16),
    }[kind]
    fill = {"float32": -7.5, "labels": 2, "bool": True, "int16": 1.0}[kind]
    got = R.resample_forward(bm, Volume(src, g), labels=labels, fill=fill).data
    data = src if labels else src.astype(np.float32)
    ref = sample_array(data, np.eye(4), bm.template_index, order=0 if labels else 1)
    ref[bm.status == R.OUTSIDE] = fill
    assert got.dtype == ref.dtype
    np.testing.assert_array_equal(got, ref)
