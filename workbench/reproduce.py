"""``workbench reproduce``: the papers' tables, through the pipeline's stages, written as CSV, Markdown and JSON.

:class:`StudyRunner` is the runner the protocols of :mod:`validation.protocols`
ask for studies: it writes each phantom study once under ``OUT/studies/``
(``<name>-<size>``), runs the stages a protocol needs with the protocol's
settings (everything else at its defaults, whatever the study last ran with),
and hands the study back.  A second ``reproduce`` into the same folder
reuses every stage that is up to date (the stage mechanism's digests), so
``reproduce all`` after ``reproduce table3`` does not register the knee again.

:func:`write_table` writes one table as ``<id>.csv`` (one row per table row:
label, kind, every column), ``<id>.md`` (the table, the definitions of its
measures, the notes) and ``<id>.json`` (``Table.to_dict()``), each
atomically; :func:`format_markdown` is the text printed.
"""

from __future__ import annotations

import csv
import io
import math
import time
from pathlib import Path

from validation.protocols import PROTOCOLS, Table
from workbench.errors import WorkbenchError
from workbench.scale import check_cluster_options, same_bits

__all__ = ["StudyRunner", "reproduce", "write_table", "format_markdown", "format_csv", "NAMES", "same_poses"]

NAMES = tuple(PROTOCOLS)


class StudyRunner:
    """Writes and runs the protocols' phantom studies under ``out / "studies"`` (see the module docstring)."""

    def __init__(
        self, out: Path, *, size: str = "test", seed: int = 0, with_peers: bool = False, progress=None, say=None
    ):
        self.out = Path(out)
        self.size = size
        self.seed = seed
        self.with_peers = with_peers
        self._progress = progress
        self._say = say or (lambda m: None)

    def say(self, message: str) -> None:
        self._say(message)

    def study(self, name: str, phantom: dict, *, settings: dict, targets):
        from validation.phantoms import Phantom, PhantomSpec
        from workbench.stages import STAGES
        from workbench.stages.run import run_stages
        from workbench.study import read_study, write_phantom_study

        spec = PhantomSpec(size=self.size, seed=self.seed, **phantom)
        folder = self.out / "studies" / f"{name}-{self.size}"
        if folder.exists():
            study = read_study(folder)
            got = study.manifest.get("phantom") or {}
            want = spec.to_dict()
            differ = [k for k in want if got.get(k) != want[k]]
            if spec.poses is not None and not same_poses(got.get("poses"), spec.poses):
                differ.append("poses")
            if differ:
                raise WorkbenchError(
                    f"{folder}: a study of another phantom is in the way (its "
                    f"{', '.join(f'{k}={got.get(k)!r}' if k != 'poses' else 'poses' for k in differ)}"
                    f"; wanted {', '.join(f'{k}={want[k]!r}' for k in differ if k != 'poses')}"
                    f"{' other poses' if 'poses' in differ else ''}); remove the folder or give "
                    f"another --out"
                )
        else:
            self.say(f"{name}: writing the {spec.region} phantom study ({self.size} size) to {folder}")
            t0 = time.perf_counter()
            study = write_phantom_study(Phantom(spec), folder, name=f"{name} protocol ({spec.region}, {self.size})")
            self.say(f"{name}: phantom written in {time.perf_counter() - t0:.0f} s")
        # every stage at the protocol's settings or its defaults: what a user ran on this folder before is not used
        given = {s: st.settings_type(**settings.get(s, {})) for s, st in STAGES.items()}
        t0 = time.perf_counter()
        run_stages(study, list(targets), settings=given, progress=self._progress)
        self.say(f"{name}: stages up to {', '.join(targets)} done in {time.perf_counter() - t0:.0f} s")
        return study.reload()

    def register_adaptive(self, study, scan_id: str, *, settings: dict):
        """Rhee's Algorithm 1 on a study's scan exactly as ``workbench register --method adaptive`` runs it
        (:func:`workbench.stages.register.adaptive_registration`: the init stage's start, the register stage's
        ``settings`` with ``method="adaptive"``), in memory: the study is not changed, so its register stage
        keeps the default method's results (and ``loo`` reuses those).  Run again on every call (no stage
        caches it).  Returns the :class:`~registration.adaptive.AdaptiveResult`."""
        from workbench.stages.register import RegisterSettings, adaptive_registration

        s = RegisterSettings(**{**settings, "method": "adaptive"})
        t0 = time.perf_counter()
        result = adaptive_registration(study, scan_id, s)
        self.say(
            f"{study.root.name} {scan_id}: Rhee's Algorithm 1 (--method adaptive) in {time.perf_counter() - t0:.0f} s"
        )
        return result


def same_poses(recorded, poses) -> bool:
    """Whether a manifest's recorded phantom poses (``[{"id", "angles_deg"}]``) are the explicit ``poses``."""
    import numpy as np

    try:
        rec = {p["id"]: p["angles_deg"] for p in recorded}
    except (TypeError, KeyError):
        return False
    if list(rec) != [str(pid) for pid, _ in poses]:
        return False
    for pid, a in poses:
        r = rec[str(pid)]
        for k, v in a.items():
            want = np.ravel(np.asarray(v, float))
            got = np.ravel(np.asarray(r.get(k, []), float))
            # the phantom records every DOF (complete_angles): a wanted joint given with fewer values is
            # compared on those and the rest must be 0
            if (
                got.size < want.size
                or not np.allclose(got[: want.size], want, atol=1e-9)
                or not np.allclose(got[want.size :], 0.0, atol=1e-9)
            ):
                return False
    return True


def _cell(v, decimals: int) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int) or decimals == 0:
        return f"{int(round(v))}"
    return f"{v:.{decimals}f}"


def format_markdown(table: Table) -> str:
    """The table as Markdown: a heading, the table (units in the headings), definitions and notes."""
    head = ["", *[f"{c.label} ({c.unit})" if c.unit else c.label for c in table.columns]]
    lines = [f"## {table.title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table.rows:
        lines.append("| " + " | ".join([r["label"], *[_cell(r.get(c.key), c.decimals) for c in table.columns]]) + " |")
    if table.definitions:
        lines += ["", "Definitions:", ""] + [f"- **{k}**: {v}" for k, v in table.definitions.items()]
    if table.notes:
        lines += ["", "Notes:", ""] + [f"- {n}" for n in table.notes]
    return "\n".join(lines) + "\n"


def format_csv(table: Table) -> str:
    """One line per row: label, kind, then every column's value at full precision (empty where none)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["label", "kind", *[c.key for c in table.columns]])
    for r in table.rows:
        w.writerow(
            [
                r["label"],
                r["kind"],
                *[
                    "" if r.get(c.key) is None else repr(r[c.key]) if isinstance(r[c.key], float) else r[c.key]
                    for c in table.columns
                ],
            ]
        )
    return buf.getvalue()


def write_table(table: Table, out: Path) -> list[Path]:
    """``<id>.csv``, ``<id>.md`` and ``<id>.json`` in ``out`` (replacing older ones), each written atomically."""
    from workbench.io.atomic import write_text_atomic
    from workbench.io.jsonio import to_jsonable, write_json

    out = Path(out)
    # every text is made before any file is written: a table that cannot be written leaves none of its files
    doc = to_jsonable(table.to_dict(), where=f"{table.id}")
    texts = {"csv": format_csv(table), "md": format_markdown(table)}
    out.mkdir(parents=True, exist_ok=True)
    return [
        write_json(doc, out / f"{table.id}.json", overwrite=True),
        *(write_text_atomic(out / f"{table.id}.{ext}", text, overwrite=True) for ext, text in texts.items()),
    ]


#: protocols that reuse other protocols' studies (loo: table3's and table4's registrations): with several
#: workers they run after the others, in the main process
REUSES = {"loo": ("table3", "table4"), "kurihara_skin": ("kurihara",)}


def _protocol_task(job: tuple) -> tuple[dict, float]:
    return _protocol_in_worker(*job)


def _protocol_in_worker(
    name: str, out: str, size: str, seed: int, with_peers: bool, quiet: bool = False
) -> tuple[dict, float]:
    """One protocol in a worker process (``reproduce(..., workers > 1)``): its table as a dict, its seconds.
    Progress goes to the worker's stderr, a line per event, prefixed with the protocol's name (none when
    ``quiet``)."""
    import sys

    def say(m):
        if not quiet:
            print(f"reproduce [{name}]: {m}", file=sys.stderr, flush=True)

    runner = StudyRunner(Path(out), size=size, seed=seed, with_peers=with_peers, say=say)
    t0 = time.perf_counter()
    t = PROTOCOLS[name](runner)
    return t.to_dict(), time.perf_counter() - t0


def reproduce(
    names,
    out: Path,
    *,
    size: str = "test",
    seed: int = 0,
    with_peers: bool = False,
    progress=None,
    say=None,
    emit=None,
    workers: int = 1,
    scheduler: str | None = None,
) -> dict[str, Table]:
    """Run the protocols ``names`` (``"all"`` = every one) into ``out``; each table is written as soon as it is
    done and passed to ``emit(table, seconds)``.  Returns ``{name: Table}``.

    ``workers`` > 1 (or ``scheduler``, an existing Dask cluster's address): the protocols that make their own
    studies run side by side as Dask tasks (:mod:`workbench.scale`, a ``LocalCluster`` of that many
    processes), the biggest first, then those that reuse them (``REUSES``) here; each study is one
    task's, so the tables are the same as with one worker.  Each table is written and emitted as its task
    finishes (a failure in one cancels the others; the studies done so far are reused by a rerun).
    """
    names = list(NAMES) if "all" in names else list(dict.fromkeys(names))
    unknown = [n for n in names if n not in PROTOCOLS]
    if unknown:
        raise WorkbenchError(f"unknown protocol {unknown}; choose from {list(NAMES)} or all")
    if int(workers) < 1:
        raise WorkbenchError(f"--workers must be at least 1, got {workers}")
    check_cluster_options(int(workers), scheduler)  # before any study is made
    runner = StudyRunner(out, size=size, seed=seed, with_peers=with_peers, progress=progress, say=say)
    tables = {}

    def finish(n, t, seconds):
        t.meta = {**t.meta, "size": size, "seed": seed, "seconds": round(seconds, 1)}
        write_table(t, out)
        tables[n] = t
        if emit is not None:
            emit(t, seconds)

    side = [n for n in names if n not in REUSES]
    done = {}
    if (int(workers) > 1 or scheduler) and len(side) > 1:
        from workbench.scale import open_runner

        # the longest first (their times: docs/measurements/workbench.md): the workers take the tasks in the order
        # they were given
        order = sorted(
            side,
            key=lambda n: (
                ("table4", "kurihara", "table3", "table2").index(n)
                if n in ("table4", "kurihara", "table3", "table2")
                else 9
            ),
        )

        def arrived(k, result):  # written and shown as each arrives
            d, sec = result
            done[order[k]] = True
            finish(order[k], Table.from_dict(d), sec)

        with open_runner(None if scheduler else min(int(workers), len(order)), scheduler) as pool:
            if say is not None:
                say(f"{', '.join(order)} side by side on {pool.description}")
            pool.map(
                _protocol_task,
                [(n, str(Path(out).resolve()), size, seed, with_peers, say is None) for n in order],
                name="reproduce",
                on_result=arrived,
            )
    for n in names:
        if n in done:
            continue
        t0 = time.perf_counter()
        with same_bits():  # as in a worker's task
            t = PROTOCOLS[n](runner)
        finish(n, t, time.perf_counter() - t0)
    return {n: tables[n] for n in names}
