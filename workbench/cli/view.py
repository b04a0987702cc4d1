"""``workbench view``: pose a study's model live in the browser."""

from __future__ import annotations

import argparse
from pathlib import Path

from workbench.cli.options import add_common, add_deform_method

DESCRIPTION = """Pose the study's model with sliders and watch the volume follow, in a web browser.

Starts a local web application (trame) and opens the browser on it.  One slider per
degree of freedom of the study's skeleton, grouped by joint, within its range of
motion (skeleton.json 'limits'); a menu of poses: the template at rest, each
scan's estimated pose, and the eigenposes of the scans' poses (Rhee §6.2).  The
volume is the template posed by EVD (Rhee Eq. 6-7) when the study has a model,
else by VBD (Rhee Eq. 2; the page says so), rendered as `workbench render` does,
the bones as surfaces.  While a slider moves, the maps are solved on every 2nd
voxel (as `workbench deform --map-factor 2`); when it stops, on every voxel.
The camera turns and zooms by its sliders; a menu picks the transfer function, and
the clipping plane's axis and place are set on the page.

What you make is saved into --out (made on the first save): pose-NNN.json (a
pose file: `workbench deform --pose`), view-NNN.png, and keyframes-NNN.json with
animation-NNN.mp4 (`workbench animate --keyframes` reads the keyframes).

The server listens on 127.0.0.1 (this machine only).  On a remote machine, run
it there with --no-browser and reach it through an SSH tunnel from yours:
  ssh -L 8080:127.0.0.1:8080 user@remote     # then open http://127.0.0.1:8080/
--host 0.0.0.0 exposes it to the network (a warning says so): anyone who can
reach the port can use it.  Ctrl-C stops it.

The study is read once, at start (its manifest is written atomically by the
stages, so a study another process is running stages on is read as it stood).
"""

EXAMPLES = """examples:
  workbench view knee-study                           # opens the browser
  workbench view knee-study --no-browser --port 8080  # on a remote machine (SSH tunnel, above)
  workbench view hand-study --preset ct --clip x:0.5 --out my-poses
"""

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "view",
        help="pose the study's model live in the browser (sliders per joint, EVD or VBD)",
        description=DESCRIPTION,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", type=Path, help="study folder (holding study.json), after `workbench weights`")
    p.add_argument("--port", type=int, default=8080, help="TCP port to listen on (0: any free one). Default: 8080")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on. Default: 127.0.0.1 (this machine only; see above for a remote machine)",
    )
    p.add_argument("--no-browser", action="store_true", help="do not open a browser (a remote machine, a test)")
    p.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="folder for saved poses, PNGs, keyframes and animations. Default: STUDY-view in the current folder",
    )
    add_deform_method(p)
    p.add_argument(
        "--preset", default="mri", metavar="mri|ct|FILE.json", help="transfer function (workbench render). Default: mri"
    )
    p.add_argument(
        "--clip",
        default="z:0.5",
        metavar="[+|-]AXIS:FRACTION|none",
        help="clipping plane, as `workbench render --clip`; 'none' for the whole volume. Default: z:0.5 (the "
        "interior shows)",
    )
    p.add_argument("--no-bones", action="store_true", help="no bone surfaces, the volume alone")
    p.add_argument("--size", default="800x600", metavar="WxH", help="the view's size in pixels. Default: 800x600")
    add_common(p)
    p.set_defaults(func=handle)


def _port_free(host: str, port: int) -> str | None:
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: a just-stopped viewer's
        try:  # connections in TIME_WAIT do not hold the port
            s.bind((host, port))
        except OSError as e:
            return e.strerror or str(e)
    return None


def handle(args) -> int:
    from workbench.cli.running import line_printer
    from workbench.errors import WorkbenchError
    from workbench.viz.view import ClipPlane, parse_size

    say = line_printer(args) or (lambda line: None)
    try:
        w, h = parse_size(args.size)  # even sizes: an exported animation is H.264
    except ValueError as e:
        raise WorkbenchError(str(e)) from None
    if not 0 <= args.port <= 65535:
        raise WorkbenchError(f"--port {args.port}: expected 0 (any free port) to 65535")
    clip = None if args.clip.lower() == "none" else ClipPlane.parse(args.clip)
    if args.host not in LOCAL_HOSTS:
        print(
            f"warning: --host {args.host} exposes the viewer beyond this machine: anyone who can reach port "
            f"{args.port} can pose the study and save files into --out. An SSH tunnel keeps it private "
            "(workbench view --help)."
        )
    if args.port:
        why = _port_free(args.host, args.port)
        if why:
            raise WorkbenchError(
                f"--port {args.port} on {args.host}: cannot listen there ({why}); another viewer may be running: "
                "choose another --port (or 0 for any free one)"
            )
    from workbench.viz.viewer import PoseSession
    from workbench.viz.viewer_app import build_app, serve

    session = PoseSession(
        args.study,
        out=args.out,
        method=args.method,
        transfer=args.preset,
        size=(w, h),
        clip=clip,
        bones=not args.no_bones,
        progress=say,
    )
    try:
        server = build_app(session)

        def ready(**_):
            port = server.port
            shown = f"[{args.host}]" if ":" in args.host else args.host
            print(f"workbench view: serving {session.study.root} at http://{shown}:{port}/  (Ctrl-C stops)", flush=True)

        server.controller.on_server_ready.add(ready)
        serve(server, host=args.host, port=args.port, open_browser=not args.no_browser)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    print("workbench view: stopped")
    return 0
