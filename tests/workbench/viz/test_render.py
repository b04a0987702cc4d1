"""Off-screen volume rendering: non-blank images, clipping, determinism, honest geometry, overlays."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deformation.geometry import GridGeometry, Volume
from workbench.viz.render import (
    Camera,
    ClipPlane,
    TransferFunction,
    VolumeRenderer,
    content_bounds,
    label_colour,
    offscreen_available,
    parse_size,
    render_difference,
    render_overlay,
    render_volume,
    write_png,
)

_skip_no_gl = pytest.mark.skipif(not offscreen_available(), reason="no off-screen OpenGL (EGL or OSMesa) here")


def needs_gl(test):
    """Rendering tests: marked ``render`` and skipped where no off-screen OpenGL context exists."""
    return pytest.mark.render(_skip_no_gl(test))


SIZE = (160, 120)  # small renders: tens of milliseconds each on software OpenGL


def _blob(
    shape_zyx=(20, 28, 32),
    spacing=(1.5, 1.0, 2.0),
    centre_mm=(0.0, 0.0, 0.0),
    radii_mm=(14.0, 9.0, 12.0),
    origin=None,
    value=900.0,
):
    """An ellipsoid of 'tissue' (smooth edge) in air, on an anisotropic grid with identity direction."""
    nz, ny, nx = shape_zyx
    if origin is None:
        origin = tuple(-0.5 * (n - 1) * s for n, s in zip((nx, ny, nz), spacing))
    g = GridGeometry((nx, ny, nz), spacing, origin)
    w = g.world_coordinates()
    r = np.sqrt(sum(((w[..., a] - centre_mm[a]) / radii_mm[a]) ** 2 for a in range(3)))
    data = value / (1.0 + np.exp((r - 1.0) * 12.0)) + 10.0
    return Volume(data.astype(np.float32), g)


def _foreground(img, level=12):
    return img.max(axis=2) > level


def test_parse_size_clip_camera_and_transfer_function_check_their_input(tmp_path):
    assert parse_size("640x480") == (640, 480)
    with pytest.raises(ValueError, match="even width and height; use 642x480"):
        parse_size("641x480")
    with pytest.raises(ValueError, match="WIDTHxHEIGHT"):
        parse_size("640")
    assert ClipPlane.parse("z:0.25") == ClipPlane("z", 0.25, "auto")
    assert ClipPlane.parse("+x:0.5").keep == "above" and ClipPlane.parse("-y:0.5").keep == "below"
    with pytest.raises(ValueError, match="AXIS:FRACTION"):
        ClipPlane.parse("w:0.5")
    with pytest.raises(ValueError, match="within"):
        ClipPlane.parse("x:1.5")
    with pytest.raises(ValueError, match="camera view"):
        Camera("sideways")
    with pytest.raises(ValueError, match="must increase"):
        TransferFunction("bad", color=((1, 0, 0, 0), (0, 1, 1, 1)), opacity=((0, 0), (1, 1)))
    # a user's JSON transfer function round-trips
    tf = TransferFunction(
        "mine", color=((0, 0, 0, 0), (500, 1, 0.5, 0.2)), opacity=((0, 0), (500, 0.3)), relative=False, unit_mm=2.0
    )
    p = tmp_path / "tf.json"
    p.write_text(json.dumps(tf.to_dict()))
    assert TransferFunction.from_json(p) == tf
    p.write_text(json.dumps({"color": [[0, 0, 0, 0]]}))
    with pytest.raises(Exception, match="opacity"):
        TransferFunction.from_json(p)


def test_content_bounds_find_the_tissue_not_the_noise():
    vol = _blob(centre_mm=(5.0, -3.0, 2.0))
    data = vol.data.copy()
    rng = np.random.default_rng(0)
    noise = rng.random(data.shape) < 0.002  # isolated bright voxels in the air
    data[noise] = 900.0
    b = np.asarray(content_bounds(data, vol.geometry, 450.0, margin_mm=0.0)).reshape(3, 2)
    # the ellipsoid's half-value surface is at r = 1: centre ± radius, within one voxel (2 mm at most)
    want = np.array([[5 - 14, 5 + 14], [-3 - 9, -3 + 9], [2 - 12, 2 + 12]], float)
    assert np.allclose(b, want, atol=2.0)


@needs_gl
def test_a_render_is_not_blank_and_is_deterministic():
    vol = _blob()
    a = render_volume(vol, size=SIZE, camera=Camera("+z"))
    b = render_volume(vol, size=SIZE, camera=Camera("+z"))
    assert a.shape == (SIZE[1], SIZE[0], 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)  # no time-driven sample distances: the same call gives the same pixels
    fg = _foreground(a)
    # The camera is fitted so that the box of the tissue's faintest visible fringe (r ≈ 1.17 radii here)
    # fits at its near face, 5 % margin: the bright core (r < 1) then covers about a third to a half of
    # the frame's height, ~0.05-0.3 of the pixels; blank would be 0, a saturated frame 1.
    assert 0.05 < fg.mean() < 0.5
    assert a.astype(float).var() > 200.0  # shaded tissue against black, not a flat image


@needs_gl
def test_the_clipping_plane_cuts_where_it_says():
    vol = _blob()
    cam = Camera("+z")  # looking down -z; up is the longer of x and y in the box (x: 28 mm vs y: 18 mm)
    full = render_volume(vol, size=SIZE, camera=cam)
    # '+y:0.5' keeps y above the box's middle; the plane y = centre contains the line of sight through
    # the image centre, so it projects onto the image's middle row: every kept pixel lies on one side.
    up_axis = "x"  # longest remaining axis of the box
    half = render_volume(vol, size=SIZE, camera=cam, clip=ClipPlane.parse(f"+{up_axis}:0.5"))
    rows = np.nonzero(_foreground(half))[0]
    assert rows.size > 0 and rows.max() <= SIZE[1] // 2 + 1  # +x is up: the kept half is the top half
    other = render_volume(vol, size=SIZE, camera=cam, clip=ClipPlane.parse(f"-{up_axis}:0.5"))
    rows = np.nonzero(_foreground(other))[0]
    assert rows.size > 0 and rows.min() >= SIZE[1] // 2 - 2
    assert np.abs(full.astype(int) - half).mean() > 1.0  # moving the plane changes the image
    gone = render_volume(vol, size=SIZE, camera=cam, clip=ClipPlane.parse("+z:1.0"))
    assert _foreground(gone).mean() < 0.002  # a plane beyond the tissue removes all of it
    # 'auto' removes the side facing the camera (+z here): the far half is what is left, so the image
    # shows the cut face and differs from keeping the near half
    auto = render_volume(vol, size=SIZE, camera=cam, clip=ClipPlane.parse("z:0.5"))
    below = render_volume(vol, size=SIZE, camera=cam, clip=ClipPlane.parse("-z:0.5"))
    assert np.array_equal(auto, below)


@needs_gl
def test_the_direction_matrix_is_honoured():
    """The same world object stored rotated by 90° about z (other array layout, direction matrix) renders alike."""
    a = _blob(centre_mm=(6.0, -2.0, 1.0))
    ga = a.geometry
    nx = ga.size[0]
    data_b = np.ascontiguousarray(a.data[:, :, ::-1].transpose(0, 2, 1))  # B[k, j, i] = A[k, i, nx-1-j]
    ox, oy, oz = ga.origin
    gb = GridGeometry(
        (ga.size[1], ga.size[0], ga.size[2]),
        (ga.spacing[1], ga.spacing[0], ga.spacing[2]),
        (ox + (nx - 1) * ga.spacing[0], oy, oz),
        ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    )
    b = Volume(data_b, gb)
    # self-check of the construction: the same voxel centres hold the same values
    for i, j, k in ((3, 5, 7), (10, 2, 4), (0, 0, 0)):
        wa = ga.index_to_world(np.array([[nx - 1 - j, i, k]], float))
        wb = gb.index_to_world(np.array([[i, j, k]], float))
        assert np.allclose(wa, wb)
        assert b.data[k, j, i] == a.data[k, i, nx - 1 - j]
    cam = Camera("+z")
    box = VolumeRenderer.grid_bounds(ga)  # one fixed world box for both: positions are not re-centred
    ra = render_volume(a, size=SIZE, camera=cam, bounds=box)
    rb = render_volume(b, size=SIZE, camera=cam, bounds=box)
    fa, fb = _foreground(ra), _foreground(rb)
    iou = (fa & fb).sum() / (fa | fb).sum()
    # same sample points, same trilinear values: only the rays' step positions inside the volume differ
    assert iou > 0.97
    assert np.abs(ra.astype(int) - rb).mean() < 2.0
    # and the object is where its world position says.  The box is centred on x = 0 and x (48 mm, the
    # longest axis) is up in this view: the blob at x = +6 mm sits above the image's middle row by
    # 6 mm / (visible half-height ≈ 30 mm at the blob's depth) × 60 px ≈ 12 px; its mirror below.
    mirror = render_volume(_blob(centre_mm=(-6.0, -2.0, 1.0)), size=SIZE, camera=cam, bounds=box)
    up, down = np.nonzero(fa)[0].mean(), np.nonzero(_foreground(mirror))[0].mean()
    assert up < SIZE[1] / 2 - 5 and down > SIZE[1] / 2 + 5
    assert abs((SIZE[1] / 2 - up) - (down - SIZE[1] / 2)) < 2.0  # symmetric about the centre


@needs_gl
def test_overlay_shows_each_volume_in_its_colour_and_difference_is_empty_for_equal_volumes():
    left = _blob(centre_mm=(-12.0, 0.0, 0.0), radii_mm=(8.0, 8.0, 8.0), shape_zyx=(20, 24, 40))
    right = _blob(centre_mm=(12.0, 0.0, 0.0), radii_mm=(8.0, 8.0, 8.0), shape_zyx=(20, 24, 40))
    img = render_overlay(left, right, size=SIZE, camera=Camera("+z"), background=(0, 0, 0))
    # view +z with x (the longest axis) up: the first volume (x < 0) is in the lower half, cyan (G, B ≫ R);
    # the second in the upper half, magenta (R, B ≫ G)
    fg = _foreground(img)
    top, bottom = fg.copy(), fg.copy()
    top[SIZE[1] // 2 :] = False
    bottom[: SIZE[1] // 2] = False
    assert top.sum() > 50 and bottom.sum() > 50
    t = img[top].astype(float).mean(axis=0)
    b = img[bottom].astype(float).mean(axis=0)
    assert t[0] > 2 * t[1] and t[2] > 2 * t[1]  # magenta
    assert b[1] > 2 * b[0] and b[2] > 2 * b[0]  # cyan
    same = render_difference(left, left, size=SIZE, camera=Camera("+z"))
    assert _foreground(same, 2).mean() == 0.0
    moved = render_difference(left, right, size=SIZE, camera=Camera("+z"))
    assert _foreground(moved).mean() > 0.05


@needs_gl
def test_bone_labels_are_drawn_as_surfaces_in_their_colours():
    vol = _blob()
    lab = np.zeros(vol.data.shape, np.uint8)
    lab[7:13, 10:18, 11:21] = 2  # a box of "bone" inside the tissue; label 2 is drawn blue
    labels = Volume(lab, vol.geometry)
    with VolumeRenderer(vol.geometry, size=SIZE, camera=Camera("+z"), transfer="mri") as r:
        plain = r.render(vol)
        assert r.add_labels(labels) == 1
        with_bone = r.render(vol)
    changed = np.abs(with_bone.astype(int) - plain).sum(axis=2) > 30
    assert changed.mean() > 0.02  # the bone shows through the translucent tissue
    # the tissue is warm (R > B everywhere in the MRI preset); where the bone shows, blue dominates
    assert np.asarray(label_colour(2))[2] > np.asarray(label_colour(2))[0]
    t = plain[_foreground(plain)].astype(float).mean(axis=0)
    c = with_bone[changed].astype(float).mean(axis=0)
    assert t[0] > t[2] and c[2] > c[0]


@needs_gl
def test_write_png_is_atomic_and_refuses_to_overwrite(tmp_path):
    import imageio.v3 as iio

    from workbench.errors import OutputExistsError

    img = render_volume(_blob(), size=SIZE)
    p = write_png(img, tmp_path / "a.png")
    assert np.array_equal(iio.imread(p), img)
    with pytest.raises(OutputExistsError):
        write_png(img, p)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.png"]  # no temporary left behind


@needs_gl
def test_an_orbit_keeps_the_distance_and_the_side_an_auto_clip_keeps():
    vol = _blob()
    cam = Camera("auto")
    with VolumeRenderer(vol.geometry, size=SIZE, camera=cam, clip=ClipPlane.parse("z:0.5")) as r:
        r.render(vol)
        normal, dist = r._plane.GetNormal(), r._ren.GetActiveCamera().GetDistance()
        from dataclasses import replace

        r.set_camera(replace(cam, azimuth=150.0))  # past 90°: the camera is now on the plane's other side
        r.render(vol)
        assert r._plane.GetNormal() == normal
        assert r._ren.GetActiveCamera().GetDistance() == pytest.approx(dist)


@needs_gl
def test_points_are_drawn_where_they_are_in_the_world():
    vol = _blob()
    box = VolumeRenderer.grid_bounds(vol.geometry)
    centre = np.asarray(box, float).reshape(3, 2).mean(axis=1)
    with VolumeRenderer(vol.geometry, size=SIZE, camera=Camera("+z"), bounds=box) as r:
        plain = r.render(vol)
        # a red sphere in front of the tissue on the line of sight through the image centre
        front = centre + np.array([0.0, 0.0, 20.0])
        assert r.add_points([front], colour=(1.0, 0.0, 0.0), radius_mm=3.0) == 1
        img = r.render(vol)
    h, w = SIZE[1] // 2, SIZE[0] // 2
    px = img[h - 1 : h + 2, w - 1 : w + 2].reshape(-1, 3).astype(float).mean(axis=0)
    assert px[0] > 150 and px[1] < 60 and px[2] < 60  # the point's colour, lit by the headlight
    changed = np.abs(img.astype(int) - plain).sum(axis=2) > 30
    rows, cols = np.nonzero(changed)
    assert abs(rows.mean() - (SIZE[1] - 1) / 2) < 2 and abs(cols.mean() - (SIZE[0] - 1) / 2) < 2
    with pytest.raises(ValueError, match="finite"):
        VolumeRenderer(vol.geometry, size=SIZE).add_points([[np.nan, 0, 0]])


def _sphere(centre, radius):
    """A closed sphere mesh (Open3D's, world mm)."""
    import open3d as o3d

    from deformation.meshes.mesh import SurfaceMesh

    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=30)
    return SurfaceMesh(np.asarray(m.vertices) + np.asarray(centre, float), np.asarray(m.triangles))


@needs_gl
def test_a_mesh_alone_is_framed_where_it_is_and_a_mesh_over_a_volume_in_its_colour():
    from workbench.viz.render import SKIN_COLOUR

    # alone: the camera is fitted to the mesh wherever it is in the world: a round disc in the middle
    img = render_volume(None, meshes=[_sphere((40.0, -25.0, 60.0), 10.0)], size=SIZE, camera=Camera("+z"))
    fg = _foreground(img)
    rows, cols = np.nonzero(fg)
    assert abs(rows.mean() - (SIZE[1] - 1) / 2) < 2 and abs(cols.mean() - (SIZE[0] - 1) / 2) < 2
    h, w = rows.max() - rows.min() + 1, cols.max() - cols.min() + 1
    assert abs(h - w) <= 2 and h > 0.5 * SIZE[1]  # a sphere seen along +z: a disc filling most of the height
    px = img[SIZE[1] // 2, SIZE[0] // 2].astype(float) / 255.0
    assert np.argmax(px) == np.argmax(SKIN_COLOUR) and px.min() > 0.2  # lit skin tone, red highest
    # over a volume: an opaque green sphere in front of the tissue covers the image centre
    vol = _blob()
    box = VolumeRenderer.grid_bounds(vol.geometry)
    centre = np.asarray(box, float).reshape(3, 2).mean(axis=1)
    img = render_volume(
        vol,
        meshes=[(_sphere(centre + [0.0, 0.0, 20.0], 3.0), (0.0, 1.0, 0.0), 1.0)],
        size=SIZE,
        camera=Camera("+z"),
        bounds=box,
    )
    px = img[SIZE[1] // 2 - 1 : SIZE[1] // 2 + 2, SIZE[0] // 2 - 1 : SIZE[0] // 2 + 2].reshape(-1, 3).mean(axis=0)
    assert px[1] > 150 and px[0] < 60 and px[2] < 60
    with pytest.raises(ValueError, match="nothing to render"):
        with VolumeRenderer(None, size=SIZE) as r:
            r.render()
