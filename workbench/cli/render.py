"""``workbench render``: volume-render a volume, a study or a mesh off-screen to a PNG."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from workbench.cli.options import add_common, add_render_options, parse_background
from workbench.cli.running import line_printer

DESCRIPTION = """Render a volume (or a study's template, scan or registered template) off-screen to a PNG.

VTK volume ray casting without a display: EGL, else OSMesa (AVW_OPENGL=egl|osmesa
forces one); on software OpenGL the CPU ray caster (vtkFixedPointVolumeRayCastMapper),
with a GPU the GPU ray caster.  The volume is placed in world mm by its origin,
spacing and direction; the camera is fitted to the visible tissue.

presets (--preset): 'mri' (T1-like: fat and marrow bright; relative to the volume's
0.5-99.5 % intensity range, so any units work), 'ct' (Hounsfield units: bone
ivory and dense, soft tissue faint), or your own JSON file:
  {"color": [[value, r, g, b], ...], "opacity": [[value, alpha], ...],
   "relative": false, "unit_mm": 4.0, "shade": true}
with r, g, b in 0..1, alpha per unit_mm of ray, and values in intensity units
(or fractions of the robust range when "relative" is true).

views (--camera): auto (from the thinnest side of the anatomy, longest axis up, turned
30 deg / 15 deg), iso, or a world axis +x -x +y -y +z -z (ITK/LPS physical space);
--azimuth/--elevation turn it further, --zoom enlarges.

--clip AXIS:FRACTION cuts across a world axis at that fraction of the anatomy's
extent, removing the side facing the camera (Rhee Fig. 10); +AXIS keeps the larger
coordinates, -AXIS the smaller.  --bones draws the template's label map as opaque
surfaces; --overlay draws a second volume in magenta against the first in cyan
(Rhee Figs. 1, 8, 9, 11); --difference shows the signed difference (red: first
brighter, blue: darker).  --markers draws the ground truth's skin markers (white),
--control-points the control points a registration allocated, coloured by block
level (Rhee Fig. 9).  --mesh draws a mesh (world mm: `workbench surface`'s skins,
`surface-deform`'s posed skin) with the volume (opaque: it hides the tissue behind
it; --clip cuts both); a mesh file as the source is rendered alone (the camera
fitted to it).

examples:
  workbench render knee-study --out template.png
  workbench render knee-study --out interior.png --clip z:0.5 --bones
  workbench render knee-study --scan pose02 --out scan.png --preset mri --camera +z
  workbench render knee-study --registered pose02 --overlay pose02 --out overlay.png
  workbench render knee-study --registered pose02 --overlay pose02 --control-points --markers --out fig9.png
                                   # (--control-points: after `workbench register knee-study --preset paper`)
  workbench render bent.nii.gz --out bent.png --size 1280x960 --background white
  workbench render hand-study/surface/pose02_fitted.ply --out skin.png        # a mesh alone
  workbench render hand-study --scan pose02 --mesh hand-study/surface/pose02_fitted.ply --out fit.png
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="volume-render a volume or a study off-screen to a PNG (presets, clipping, overlays)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "source",
        type=Path,
        metavar="VOLUME_OR_STUDY",
        help="an image file (.nii.gz, .mha, .nrrd, a DICOM folder), a study folder (its template), or "
        "a mesh (.ply, .vtp, .stl, .obj: the mesh alone)",
    )
    p.add_argument(
        "--mesh",
        action="append",
        type=Path,
        metavar="MESH",
        help="a mesh in world mm (.ply, .vtp, .stl, .obj; e.g. `workbench surface` or "
        "`surface-deform` output) drawn over the volume; repeatable",
    )
    p.add_argument(
        "--mesh-opacity",
        type=float,
        default=1.0,
        metavar="A",
        help="the meshes' opacity, 0..1. VTK's CPU ray caster (software OpenGL) draws a translucent "
        "mesh behind the volume's tissue: clip the volume (--clip) to see a mesh inside it. "
        "Default: 1",
    )
    p.add_argument("--out", required=True, type=Path, metavar="IMAGE.png", help="the PNG to write")
    p.add_argument("--scan", metavar="ID", help="with a study: render this scan instead of the template")
    p.add_argument(
        "--registered",
        metavar="ID",
        help="with a study: render the template registered to scan ID (`workbench register`)",
    )
    p.add_argument(
        "--overlay",
        metavar="OTHER",
        help="a second volume (file, or a scan ID of the study) in magenta over the first in cyan",
    )
    p.add_argument(
        "--difference", metavar="OTHER", help="render the signed difference first − OTHER (file or scan ID) instead"
    )
    p.add_argument("--labels", type=Path, metavar="LABELS", help="a label map on the volume's grid, drawn as surfaces")
    p.add_argument("--bones", action="store_true", help="with a study's template: draw its bone labels")
    p.add_argument(
        "--markers",
        action="store_true",
        help="with a study: draw the skin markers of the ground truth (white; the scan's positions "
        "with --scan/--registered, the template's otherwise)",
    )
    p.add_argument(
        "--control-points",
        action="store_true",
        help="with --registered ID: draw the control points the registration allocated, coloured by "
        "block level (green 3, yellow 4, orange 5, ...; Rhee Fig. 9)",
    )
    add_render_options(p)
    p.add_argument("--force", action="store_true", help="replace an existing PNG")
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.viz.render import (
        SKIN_COLOUR,
        ClipPlane,
        label_colour,
        opengl_backend,
        parse_size,
        render_difference,
        render_overlay,
        render_volume,
        transfer_function,
        write_png,
    )

    say = line_printer(args) or (lambda line: None)
    size = parse_size(args.size)
    clip = ClipPlane.parse(args.clip) if args.clip else None
    cam = _camera(args)
    bg = parse_background(args.background)
    tf = transfer_function(args.preset)
    if args.out.suffix.lower() != ".png":
        raise ValueError(f"--out {args.out}: stills are PNG; name it *.png")
    from workbench.io.atomic import check_output_folder

    check_output_folder(args.out, "--out")
    if args.out.exists() and not args.force:
        from workbench.errors import OutputExistsError

        raise OutputExistsError(args.out, f"{args.out} exists; pass --force to replace it.")
    from workbench.io.meshes import MESH_SUFFIXES, read_mesh

    alone = args.source.name.lower().endswith(MESH_SUFFIXES)
    mesh_files = ([args.source] if alone else []) + list(args.mesh or [])
    opacity = args.mesh_opacity
    if not 0.0 < opacity <= 1.0:
        raise ValueError(f"--mesh-opacity must be in (0, 1], got {opacity}")
    if mesh_files and (args.overlay or args.difference):
        raise ValueError(
            f"{args.source} is a mesh: --overlay/--difference compare two volumes"
            if alone
            else "--mesh draws on a single-volume render; leave out --overlay/--difference"
        )
    if alone and any(getattr(args, k) for k in ("scan", "registered", "labels", "bones", "markers", "control_points")):
        raise ValueError(
            f"{args.source} is a mesh: --scan, --registered, --labels, --bones, --markers and "
            "--control-points need a volume or a study"
        )
    meshes = [
        (read_mesh(m), SKIN_COLOUR if k == 0 else label_colour(k + 1), opacity) for k, m in enumerate(mesh_files)
    ]  # every mesh read (and checked) before any rendering
    if alone:
        kw = dict(size=size, camera=cam, clip=clip, background=bg)
        t0 = time.perf_counter()
        img = render_volume(None, meshes=meshes, **kw)
        dt = time.perf_counter() - t0
        write_png(img, args.out, overwrite=args.force)
        print(f"rendered {size[0]}x{size[1]} in {dt:.2f} s; wrote {args.out}")
        return 0
    from workbench.viz.scene import render_inputs

    vol, labels, other, points = render_inputs(
        args.source,
        scan=args.scan,
        registered=args.registered,
        bones=args.bones,
        labels=args.labels,
        overlay=args.overlay,
        difference=args.difference,
        markers=args.markers,
        control_points=args.control_points,
        progress=say,
    )
    kw = dict(size=size, camera=cam, clip=clip, background=bg, mapper=args.mapper)
    b = opengl_backend()
    say(f"{b.describe()}; {b.mapper if args.mapper == 'auto' else args.mapper} mapper")
    t0 = time.perf_counter()
    if args.overlay:
        img = render_overlay(vol, other, transfer=tf, points=points, **kw)
    elif args.difference:
        if points:
            raise ValueError("--markers/--control-points are drawn on renders and overlays, not difference views")
        img = render_difference(vol, other, transfer=tf, **kw)
    else:
        img = render_volume(vol, labels=labels, points=points, meshes=meshes, transfer=tf, **kw)
    dt = time.perf_counter() - t0
    write_png(img, args.out, overwrite=args.force)
    print(f"rendered {size[0]}x{size[1]} in {dt:.2f} s; wrote {args.out}")
    return 0


def _camera(args):
    from workbench.viz.animate import camera_from

    return camera_from({}, view=args.camera, azimuth=args.azimuth, elevation=args.elevation, zoom=args.zoom)
