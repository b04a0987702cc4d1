"""The ``workbench`` command line.

Thin entry points (nibabel ``cmdline`` style): one module per command holds its help, its parser
(``add_parser``) and its handler (``handle``), which parses its arguments, calls the library, writes or
prints, and returns an exit status; the option groups several commands share are in
:mod:`workbench.cli.options`.  Heavy imports happen inside the handlers so ``--help`` is fast.
:func:`build_parser` builds the whole parser (the CLI reference is generated from it).
"""

from __future__ import annotations

import argparse
import sys

from workbench import __version__
from workbench.cli import (
    animate,
    bones,
    clean_image,
    deform,
    info,
    model,
    phantom,
    pose,
    register,
    render,
    report,
    reproduce,
    run,
    surface,
    surface_deform,
    validate,
    view,
    weights,
)

__all__ = ["build_parser", "main", "COMMANDS"]

DESCRIPTION = """\
Articulated Volume Workbench: posable, person-specific volume models of an
articulated body region (hand, knee) from a few CT/MRI scans in different
poses, validated against synthetic ground truth.  Implements Kurihara &
Miyata 2004 and Rhee et al. 2011.

A *study* is a folder with a study.json manifest naming the template scan, its
bone label map, the skeleton and the posed scans (the user guide's "Study folders": docs/user-guide/study-folders.md).
"""

EPILOG = """\
examples:
  workbench phantom knee --out knee-study                 # small MRI-like knee, 4 poses
  workbench run knee-study                                # all nine stages: bones ... register ... report
  workbench phantom hand --out hand --size paper --modality ct
  workbench phantom knee --out bend10 --posing vbd --poses-file bend10.json
  workbench info knee-study
  workbench pose knee-study                               # bone poses, joint centres and angles
  workbench pose knee-study --method surface --force
  workbench weights knee-study                            # harmonic skinning weights (tet mesh kept in the study)
  workbench model knee-study                              # EVD model from the registrations (Rhee Eq. 7)
  workbench deform knee-study --pose bend.json --out bent.nii.gz
  workbench register knee-study                           # polyrigid start + dense registration
  workbench render knee-study --out knee.png --clip z:0.5 --bones
  workbench animate knee-study --out knee.mp4             # bend and straighten (ready keyframes)
  workbench view knee-study                               # pose it live in the browser
  workbench reproduce all --out tables                    # the papers' tables on phantoms
  workbench report knee-study --out report.html           # HTML validation report
"""

#: The commands' modules, in the order ``workbench --help`` lists them.
COMMANDS = (
    phantom,
    info,
    clean_image,
    pose,
    weights,
    model,
    surface,
    surface_deform,
    deform,
    render,
    animate,
    view,
    register,
    bones,
    validate,
    run,
    report,
    reproduce,
)


def build_parser() -> argparse.ArgumentParser:
    """The ``workbench`` parser: every command (its ``help`` and ``description``) and every option."""
    p = argparse.ArgumentParser(
        prog="workbench", description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    import signal

    from workbench.errors import WorkbenchError

    def terminate(signum, frame):  # SIGTERM: unwind like Ctrl-C, so staging folders are removed
        raise KeyboardInterrupt

    from workbench.progress import announce_compilation, tolerate_kernel_cache_failures

    tolerate_kernel_cache_failures()
    announce_compilation()
    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        return args.func(args)
    except (WorkbenchError, ValueError, OSError) as e:
        print(f"workbench {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            f"workbench {args.command}: interrupted; nothing was left half-written (run it again to resume).",
            file=sys.stderr,
        )
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
