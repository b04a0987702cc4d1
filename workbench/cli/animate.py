"""``workbench animate``: the template (or Kurihara's skin mesh) through keyframe poses, as a video."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common, add_deform_method, add_render_options, parse_background, positive_int
from workbench.cli.running import line_printer

DESCRIPTION = """Animate the study's template through keyframe poses and write a video.

Each frame: joint angles interpolated between keyframes, the template deformed
(EVD, Rhee Eq. 6-7, when the study has a model - `workbench model` - else VBD,
Rhee Eq. 2), volume-rendered off-screen (see `workbench render --help`) and encoded:
.mp4 (H.264 through the ffmpeg binary of imageio-ffmpeg; no system ffmpeg needed),
.gif, or .png (numbered frames NAME_0000.png ...).  The camera is fitted once to
the anatomy over all keyframe poses, so nothing leaves the picture.

keyframes (--keyframes FILE, JSON; ready files for the knee - bend to 60 deg and
straighten - and the hand - open, fist, point with the index finger - are used
when it is omitted; see workbench/viz/keyframes/):
  {"format": "avw-keyframes", "version": 1, "skeleton": "knee",
   "interpolation": "smooth",      # smoothstep between keyframes, or "linear"
   "fps": 24, "camera": {"view": "auto", "azimuth": 0, "elevation": 0, "zoom": 1, "orbit": 0},
   "keyframes": [{"time": 0.0, "angles": {"knee": [0, 0, 0]}},
                 {"time": 1.25, "angles": {"knee": [60, 0, 0]}}]}
Joints left out of a keyframe stay at 0; angles in degrees (then mm for 6-DOF joints).
--keyframes scans goes from the rest pose through every scan's estimated pose and
back (Kurihara Fig. 9).  --skin ssd|psd|wpsd animates Kurihara's skin mesh
(`workbench surface`) instead of the volume: milliseconds a frame.

examples:
  workbench animate knee-study --out knee.mp4
  workbench animate hand-study --out hand.gif --fps 12 --size 480x360
  workbench animate knee-study --keyframes my.json --out frames/knee.png --clip z:0.5 --orbit 90
  workbench animate hand-study --skin wpsd --out skin.mp4     # Kurihara's skin mesh, same keyframes
  workbench animate hand-study --skin psd --keyframes scans --out fig9.mp4   # through the example poses
"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "animate",
        help="animate the template through keyframe poses to MP4, GIF or PNG frames",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (with skinning weights: `workbench weights`)")
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="ANIM",
        help="anim.mp4, anim.gif, or frames/anim.png (numbered frames)",
    )
    p.add_argument(
        "--keyframes",
        type=Path,
        metavar="KEYS.json",
        help="keyframe poses (default: the ready ones); 'scans': rest, each scan's estimated pose, "
        "rest (Kurihara Fig. 9's interpolation between the example poses)",
    )
    add_deform_method(p)
    p.add_argument("--weighting", choices=["psd", "wpsd"], default="psd", help="EVD pose weights. Default: psd")
    p.add_argument(
        "--map-factor",
        type=positive_int,
        default=1,
        metavar="F",
        help="each frame's maps solved on every F-th voxel and blended up (as `workbench deform "
        "--map-factor`): F=2 is about 3x faster per frame. Default: 1 (exact), or the weights' "
        "--grid-factor when they lie on a coarse grid",
    )
    p.add_argument("--fps", type=float, metavar="FPS", help="frames per second (default: the file's, else 24)")
    p.add_argument("--frames", type=positive_int, metavar="N", help="number of frames (default: duration × fps + 1)")
    p.add_argument("--orbit", type=float, metavar="DEG", help="turn the camera by DEG of azimuth over the animation")
    p.add_argument("--bones", action="store_true", help="draw the posed bone labels as surfaces")
    p.add_argument(
        "--skin",
        choices=["ssd", "psd", "wpsd"],
        metavar="ssd|psd|wpsd",
        help="animate Kurihara's skin mesh (`workbench surface`) posed by this method instead of the "
        "volume, through the same keyframes (--method, --weighting and --preset are the "
        "volume's and do not apply)",
    )
    add_render_options(p, camera_default=None)
    p.add_argument("--force", action="store_true", help="replace existing output")
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.viz.animate import animate_study
    from workbench.viz.render import ClipPlane, parse_size

    size = parse_size(args.size)
    clip = ClipPlane.parse(args.clip) if args.clip else None
    bg = parse_background(args.background)
    from workbench.study import read_study
    from workbench.viz.animate import builtin_keyframes, camera_from, read_keyframes

    study = read_study(args.study)
    sk = study.skeleton()
    if args.keyframes is not None and str(args.keyframes) == "scans":
        from workbench.viz.animate import scan_keyframes

        kf = scan_keyframes(study)
    else:
        kf = read_keyframes(args.keyframes, sk) if args.keyframes else builtin_keyframes(sk)
    cam = camera_from(kf.camera, view=args.camera, azimuth=args.azimuth, elevation=args.elevation, zoom=args.zoom)
    s = animate_study(
        args.study,
        args.out,
        keyframes=kf,
        method=args.method,
        weighting=args.weighting,
        fps=args.fps,
        size=size,
        n_frames=args.frames,
        transfer=args.preset,
        camera=cam,
        orbit=args.orbit,
        clip=clip,
        bones=args.bones,
        background=bg,
        mapper=args.mapper,
        skin=args.skin,
        overwrite=args.force,
        map_factor=args.map_factor,
        progress=line_printer(args),
    )
    n = s["frames"]
    print(
        f"{n} frames {s['size'][0]}x{s['size'][1]} at {s['fps']:g} fps ({s['method'].upper()}, {s['mapper']} "
        f"mapper): deformation {s['deform_seconds']:.1f} s ({s['deform_seconds_per_frame']:.3f} s/frame), "
        f"rendering {s['render_seconds']:.1f} s ({s['render_seconds_per_frame']:.3f} s/frame), encoding "
        f"{s['encode_seconds']:.1f} s; total {s['total_seconds']:.1f} s"
    )
    print(f"wrote {s['out']}" + (f" ({s['files']} files)" if s["files"] > 1 else ""))
    return 0
