"""``workbench reproduce``: the papers' tables on phantoms with exact ground truth."""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from workbench.cli.options import add_common
from workbench.cli.running import progress_printer

DESCRIPTION = """Reproduce the papers' tables on phantoms with exact ground truth.

Each table runs the pipeline's stages (bones, pose, weights, init, register,
validate) on a phantom study written under DIR/studies/, then writes
DIR/<table>.csv, .md and .json with the paper's figures beside ours and the
definition of every measure, and prints it:

  table2      Rhee Table 2: the knee bent 10 deg by VBD, registered without initialisation
  table3      Rhee Table 3: knee, 4 poses, template registered to the other 3 after VBD
              from the estimated poses; MED (body, markers), SSD, CC, MI, folded
  table4      Rhee Table 4: hand, 10 poses, the same over 9 registrations
              (tables 2-4: the pipeline's registration and, beside it, Rhee's
              Algorithm 1 as implemented here, run as --method adaptive would
              from the same start; rerun every time, no stage keeps it)
  loo         leave one scan out: VBD against EVD built from the other scans'
              registrations, both against the held-out truth (knee and hand)
  eigenposes  principal components of 71 documented grasp/sign/gesture hand poses
  kurihara    Kurihara Eq. 1 joint centres of a CT hand in 5 poses (ICP of bones)
  kurihara_skin  Kurihara §4-5 on the same study: fitted skin meshes against the true
              skin, touching fingers (nearest vs regularised fit), leave one pose out
              and one finger alone by SSD, PSD and WPSD
  all         every one of them

A second run into the same DIR reuses every finished stage (loo reuses the
registrations of table3 and table4).  --size test takes minutes, --size paper
(Rhee's grids) hours.

examples:
  workbench reproduce all --out tables
  workbench reproduce table3 loo --out tables --with-peers
"""


class TableNames(Sequence):
    """The tables ``reproduce`` takes: the names of ``validation.protocols.PROTOCOLS``, in its order, then
    "all".  Read on first use (checking the arguments, ``reproduce --help``), so that ``workbench --help`` and
    the other commands do not import the protocols."""

    @functools.cached_property
    def _names(self) -> list[str]:
        from validation.protocols import PROTOCOLS

        return [*PROTOCOLS, "all"]

    def __getitem__(self, i):
        return self._names[i]

    def __len__(self) -> int:
        return len(self._names)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "reproduce",
        help="reproduce the papers' tables on phantoms (CSV, Markdown, JSON per table)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "tables",
        nargs="+",
        metavar="TABLE",
        choices=TableNames(),
        help="table2, table3, table4, loo, eigenposes, kurihara, kurihara_skin, or all",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="folder for the tables (<table>.csv/.md/.json) and the phantom studies they run on "
        "(DIR/studies/); an existing folder's finished stages are reused",
    )
    p.add_argument(
        "--size",
        choices=["test", "paper"],
        default="test",
        help="phantom grid: test (minutes for all) or paper (Rhee's grids; hours). Default: test",
    )
    p.add_argument("--seed", type=int, default=0, help="phantom seed (noise, texture, pose jitter). Default: 0")
    p.add_argument(
        "--with-peers",
        action="store_true",
        help="add elastix's and SimpleITK's B-spline registrations from the same start (tables 2-4)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="run the protocols' phantom studies side by side in N processes (Dask); the tables are "
        "the same. Default: 2 at --size test on a machine with 2 or more cores (all tables: "
        "11 min against 15.5 in one process here), 1 at --size paper (memory)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run the protocols' studies as tasks on an existing Dask cluster instead (e.g. "
        "tcp://head-node:8786; docs/user-guide/dask.md); workers must see --out at the "
        "same path",
    )
    add_common(p)
    p.set_defaults(func=handle)


def handle(args) -> int:
    from workbench.reproduce import format_markdown, reproduce

    args.out.mkdir(parents=True, exist_ok=True)
    printer = progress_printer(args)
    say = (lambda m: None) if args.quiet else (lambda m: print(f"reproduce: {m}", file=sys.stderr, flush=True))
    t0 = time.perf_counter()

    def emit(table, seconds):
        print(format_markdown(table))
        print(f"({table.id}: {seconds:.0f} s; written to {args.out}/{table.id}.csv, .md, .json)\n", flush=True)

    if args.with_peers:
        from registration.baselines import elastix_available

        if not elastix_available():
            say("itk-elastix is not installed (make bench): --with-peers adds SimpleITK's B-spline only")
    try:
        workers = (
            args.workers
            if args.workers is not None
            else (1 if args.scheduler else min(2, os.cpu_count() or 1) if args.size == "test" else 1)
        )
        reproduce(
            args.tables,
            args.out,
            size=args.size,
            seed=args.seed,
            with_peers=args.with_peers,
            progress=printer,
            say=say,
            emit=emit,
            workers=workers,
            scheduler=args.scheduler,
        )
    finally:
        printer.close()
    print(f"reproduce: {', '.join(args.tables)} in {time.perf_counter() - t0:.0f} s")
    return 0
