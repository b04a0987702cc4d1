"""The option groups several commands share, and their parsing helpers."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = [
    "STAGE_NAMES",
    "positive_int",
    "parse_background",
    "add_common",
    "add_scale_options",
    "add_bones_options",
    "add_render_options",
]

#: workbench.stages.ORDER, written out so that ``--help`` does not import every stage (a test keeps them equal).
STAGE_NAMES = ("bones", "pose", "weights", "init", "register", "model", "surface", "validate", "report")


def positive_int(text: str) -> int:
    """An argparse ``type``: a whole number ≥ 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def parse_background(text: str) -> tuple:
    """``--background``: black, white, grey, or R,G,B with each in 0..1, as an RGB tuple."""
    named = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "grey": (0.5, 0.5, 0.5), "gray": (0.5, 0.5, 0.5)}
    if text.lower() in named:
        return named[text.lower()]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise ValueError(f"--background {text!r}: expected black, white, grey or R,G,B with each in 0..1")
    return rgb


def add_deform_method(p) -> None:
    """--method auto|vbd|evd: how a command that poses the study's template deforms it (deform, animate, view)."""
    p.add_argument(
        "--method",
        choices=["auto", "vbd", "evd"],
        default="auto",
        help="'auto': EVD when the study has a model, else VBD. Default: auto",
    )


def add_common(p) -> None:
    """--quiet / -v on every subcommand."""
    p.add_argument("--quiet", action="store_true", help="no progress lines (warnings still show)")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log lines (-vv: debug)")


def add_scale_options(p) -> None:
    """--workers / --scheduler on the commands with per-scan work (workbench.scale)."""
    g = p.add_argument_group("many scans (Dask)")
    g.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        metavar="N",
        help="run the per-scan work (pose, init, register, surface, validate) as Dask tasks on a local "
        "cluster of N processes; the results are the same bits as with one. Default: 1 (no Dask)",
    )
    g.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run the per-scan work on an existing Dask cluster (e.g. tcp://head-node:8786, started with "
        "`dask scheduler` and `dask worker ADDRESS`, or by dask-jobqueue on Slurm/PBS); every "
        "worker must see the study folder at the same path",
    )


def add_bones_options(p) -> None:
    """--seeds / --modality / --threshold: the bones segmented from seeds (bones, pose)."""
    p.add_argument(
        "--seeds",
        type=Path,
        metavar="FILE",
        help="seeds file (one or more world points in mm inside each bone): segment the template's "
        "bones from it instead of using the study's label map",
    )
    p.add_argument(
        "--modality",
        choices=["ct", "mri"],
        help="segmentation method for --seeds (default: guessed from the intensities: CT if air is "
        "below -500 HU; a CT cropped to the limb, with no air, needs --modality ct and "
        "--bias-correction off)",
    )
    p.add_argument("--threshold", type=float, metavar="HU", help="bone threshold for CT segmentation (default 400)")


def add_render_options(p, camera_default="auto") -> None:
    """The transfer function, clipping, camera, size, background and mapper (render, animate)."""
    p.add_argument(
        "--preset", default="mri", metavar="mri|ct|FILE.json", help="transfer function (see above). Default: mri"
    )
    p.add_argument("--clip", metavar="[+|-]AXIS:FRACTION", help="clipping plane, e.g. z:0.5 (see above)")
    p.add_argument(
        "--camera",
        default=camera_default,
        metavar="VIEW",
        help="auto, iso, +x, -x, +y, -y, +z, -z"
        + (" (default: the keyframe file's, else auto)" if camera_default is None else ". Default: auto"),
    )
    p.add_argument("--azimuth", type=float, default=None, metavar="DEG", help="turn the camera about the view-up axis")
    p.add_argument("--elevation", type=float, default=None, metavar="DEG", help="turn the camera up or down")
    p.add_argument("--zoom", type=float, default=None, metavar="Z", help="> 1 enlarges. Default: 1")
    p.add_argument(
        "--size",
        default="640x480",
        metavar="WxH",
        help="image size in pixels, both even (video encoders need it). Default: 640x480",
    )
    p.add_argument("--background", default="black", metavar="COLOUR", help="black, white, or R,G,B in 0..1")
    p.add_argument(
        "--mapper",
        choices=["auto", "fixed", "gpu"],
        default="auto",
        help="'auto': the CPU ray caster on software OpenGL, the GPU one otherwise",
    )
