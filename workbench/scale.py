"""Per-scan work as Dask tasks: a ``LocalCluster`` (``--workers N``) or an existing cluster (``--scheduler ADDRESS``).

A :class:`Runner` maps a function over items, in this process (the synchronous path, no Dask at all) or as Dask
tasks, and hands each result back to the coordinator as it arrives.

What runs where:

* **per-scan stages** (``init``, ``register``, ``validate``): one task per scan
  (:func:`workbench.stages.mechanism.execute`).  A task gets the study folder, the stage's declaration, its
  settings as JSON and the scan id — paths and plain data, never ITK objects — runs the stage, writes the scan's
  folder and swaps it in itself, and returns the file names and their digest.  Only the coordinator writes
  ``study.json``, each scan as its task finishes, so an interrupted run resumes from the scans left over.
* **whole-study stages with per-scan work inside** (``pose``: every bone of a scan, before Kurihara Eq. 1 pools
  the scans; ``surface``: each scan's consistent mesh): one task per scan, given the study folder, the scan id and
  the settings, returning plain arrays to the coordinator, which pools them and writes the stage's folder as
  usual.
* **validation sweeps** (``workbench reproduce``): one task per protocol (:mod:`workbench.reproduce`).

Every task is the same code on the same inputs as the synchronous path, so the results are bit-identical for any
number of workers (tested on a ``LocalCluster`` of 2 workers and against a ``dask scheduler`` with two
``dask worker`` processes).  Workers must see the study folder at the same path (one machine, or a shared file
system on a cluster).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import uuid
from collections.abc import Callable

from workbench.errors import WorkbenchError

__all__ = [
    "Runner",
    "open_runner",
    "check_cluster_options",
    "SchedulerError",
    "same_bits",
    "task_reporter",
    "local_processes",
    "LOCAL_PROCESSES",
]

log = logging.getLogger("workbench")

#: how long to wait for a --scheduler to answer
CONNECT_TIMEOUT = "15s"


class SchedulerError(WorkbenchError):
    """The Dask scheduler asked for cannot be reached, or the options contradict each other."""


#: ITK's threads in every stage and task.  ITK sums a metric per work unit, and its work units follow its
#: threads, so its last bits change with the thread count (the pose stage's rigid fits: a metric value moved in
#: the 13th digit between 1, 2 and 4 threads); a fixed count makes them the same on any machine.
ITK_THREADS = 2

_LOCK = threading.Lock()
_ACTIVE = {"depth": 0, "restore": None}


@contextlib.contextmanager
def same_bits():
    """A context in which BLAS runs on one thread and ITK on ``ITK_THREADS``, on any machine.

    A BLAS dot or matrix product sums in an order set by its thread count, so its last bits differ between a
    2-core coordinator and a 1-thread worker (seen: the surface fit's conjugate gradients and the validation's
    CC, 1e-12 apart); so does ITK's.  Every stage runs inside one (:func:`workbench.stages.mechanism.execute`),
    and so does every task.  The heavy kernels are numba's, whose results do not depend on their threads; BLAS
    here only sees small matrices.  Both settings are process-wide: nested or concurrent contexts (a worker
    running two tasks in two threads) share one, restored when the last leaves.
    """
    with _LOCK:
        if _ACTIVE["depth"] == 0:
            import SimpleITK as sitk
            from threadpoolctl import threadpool_limits

            itk_before = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
            sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(ITK_THREADS)
            blas = threadpool_limits(limits=1, user_api="blas")
            _ACTIVE["restore"] = (blas, itk_before)
        _ACTIVE["depth"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _ACTIVE["depth"] -= 1
            if _ACTIVE["depth"] == 0:
                import SimpleITK as sitk

                blas, itk_before = _ACTIVE["restore"]
                blas.restore_original_limits()
                sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(itk_before)
                _ACTIVE["restore"] = None


def _task(fn, *args):
    from workbench.progress import tolerate_kernel_cache_failures

    tolerate_kernel_cache_failures()  # a worker process compiles its own kernels: the CLI's guard is not there
    with same_bits():
        return fn(*args)


class Runner:
    """Maps a function over items, here (``client`` None) or as Dask tasks on ``client``'s cluster."""

    def __init__(self, client=None, description: str = "in this process"):
        self.client = client
        self.description = description

    @property
    def distributed(self) -> bool:
        return self.client is not None

    @contextlib.contextmanager
    def forwarding(self, emit: Callable):
        """A topic name for tasks' progress (:func:`task_reporter`); each message they send reaches ``emit``
        here (on the client's thread, as it arrives).  None without a cluster."""
        if self.client is None:
            yield None
            return
        topic = f"workbench-progress-{uuid.uuid4().hex[:8]}"

        def handler(event):
            _, message = event
            try:
                emit(message)
            except Exception:  # a progress line must never break the run
                log.debug("progress message not shown: %r", message, exc_info=True)

        self.client.subscribe_topic(topic, handler)
        try:
            yield topic
        finally:
            self.client.unsubscribe_topic(topic)

    def map(
        self,
        fn: Callable,
        items,
        *,
        shared=None,
        name: str = "task",
        on_result: Callable | None = None,
        processes: int = 1,
    ) -> list:
        """``[fn(item)]`` (``fn(shared, item)`` when ``shared`` is given), in the items' order.

        ``fn`` must be a module-level function (it is pickled to the
        workers); ``shared`` is sent to each worker once.
        ``on_result(index, result)`` runs in this process as each result
        arrives (in completion order on a cluster).  The first task to fail
        cancels the others and its exception is raised here; so does Ctrl-C.
        Without a cluster, ``processes`` > 1 spreads the items over that many
        processes of this machine (:func:`local_processes`), each task the
        same code as here: the same results.
        """
        items = list(items)
        call = (lambda it: _task(fn, it)) if shared is None else (lambda it: _task(fn, shared, it))
        if self.client is None and processes > 1 and len(items) > 1:
            return _map_processes(fn, items, shared, min(int(processes), len(items)), on_result)
        if self.client is None:
            out = []
            for i, it in enumerate(items):
                out.append(call(it))
                if on_result is not None:
                    on_result(i, out[-1])
            return out
        from distributed import as_completed

        client = self.client
        args = () if shared is None else (client.scatter(shared, broadcast=True),)
        token = uuid.uuid4().hex[:8]
        futures = [
            client.submit(_task, fn, *args, it, key=f"{name}-{i}-{token}", pure=False) for i, it in enumerate(items)
        ]
        index = {f.key: i for i, f in enumerate(futures)}
        results: dict = {}
        try:
            for fut in as_completed(futures):
                r = fut.result()  # a task's exception is raised here, with its own traceback
                results[index[fut.key]] = r
                if on_result is not None:
                    on_result(index[fut.key], r)
        except BaseException:
            client.cancel(futures)
            raise
        return [results[i] for i in range(len(items))]


#: the most processes a run without a cluster spreads a stage's per-scan tasks over (:func:`local_processes`)
LOCAL_PROCESSES = 2
_PROCESS_SHARED: dict = {}  #: in a pool's worker: whether the tasks get a shared value, and the value


def local_processes() -> int:
    """How many processes of this machine a run without a cluster may use for tasks that run mostly on one core
    (the pose stage's bone registrations): the cores, at most ``LOCAL_PROCESSES``; one inside a Dask task or a
    process pool's worker (a worker of ``workbench reproduce`` already shares the cores with the others), and one
    in a script without the ``if __name__ == "__main__":`` guard (a spawned process would run it again)."""
    import multiprocessing

    if multiprocessing.current_process().name != "MainProcess" or not _main_guarded():
        return 1
    try:
        from distributed import get_worker

        get_worker()
        return 1  # inside a Dask task
    except (ImportError, ValueError):
        pass
    return max(1, min(LOCAL_PROCESSES, os.cpu_count() or 1))


def _main_guarded() -> bool:
    """Whether a spawned process may import this program's main module: a spawned process imports it again, and a
    script whose work is not under ``if __name__ == "__main__":`` would run it again there (the workbench's command,
    ``python -m``, pytest, an interpreter or ``-c`` are safe)."""
    import sys

    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if path is None or getattr(main, "__spec__", None) is not None:  # interactive, -c, or python -m: safe
        return True
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read()
    except OSError:
        return False
    return "__name__" in text and "__main__" in text


def _start_process(has_shared: bool, shared, threads: int) -> None:
    import signal

    import numba

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the coordinator's: it stops the pool (_map_processes)
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))  # the cores shared out
    _PROCESS_SHARED.update(has=has_shared, value=shared)


def _process_task(job):
    import pickle

    fn, index, item = job
    try:
        if _PROCESS_SHARED["has"]:
            return index, _task(fn, _PROCESS_SHARED["value"], item)
        return index, _task(fn, item)
    except Exception as e:
        try:  # an error that does not survive pickling would stop the pool's result thread: the pool would hang
            pickle.loads(pickle.dumps(e))
        except Exception:
            raise WorkbenchError(f"{type(e).__name__}: {e}") from None
        raise


def _map_processes(fn, items: list, shared, n: int, on_result) -> list:
    """:meth:`Runner.map` over ``n`` new processes of this machine (spawned: no thread state is copied);
    ``shared`` is sent to each once; results handed to ``on_result`` as they arrive; the first failure (or
    Ctrl-C, which the processes leave to this one) stops the processes and is raised here."""
    import multiprocessing
    import signal

    threads = max(1, (os.cpu_count() or 1) // n)
    results: dict = {}
    # the processes start with Ctrl-C ignored (inherited through the spawn; their initializer keeps it so): it is
    # this process's to handle
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        pool = multiprocessing.get_context("spawn").Pool(
            n, initializer=_start_process, initargs=(shared is not None, shared, threads)
        )
    finally:
        if main:  # a handler set outside Python reads as None: Python's own then
            signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
    try:
        for i, r in pool.imap_unordered(_process_task, [(fn, i, it) for i, it in enumerate(items)]):
            results[i] = r  # a task's exception is raised by the iterator, here
            if on_result is not None:
                on_result(i, r)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()
    return [results[i] for i in range(len(items))]


def task_reporter(topic: str | None, *, every_s: float = 2.0) -> Callable:
    """Inside a task: ``send(message)`` to the coordinator's :meth:`Runner.forwarding` topic (progress
    messages at most one every ``every_s`` seconds; ``message`` a dict with ``"kind"``).  A no-op outside a
    Dask worker or without a topic."""
    if topic is None:
        return lambda message: None
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return lambda message: None
    import time

    last = [-float("inf")]

    def send(message: dict) -> None:
        now = time.monotonic()
        if message.get("kind") == "progress":
            if now - last[0] < every_s:
                return
            last[0] = now
        worker.log_event(topic, message)

    return send


def _threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // workers)


def check_cluster_options(workers: int | None, scheduler: str | None) -> None:
    """One clear error for ``--workers N`` (N > 1) together with ``--scheduler``."""
    if scheduler and workers not in (None, 1):
        raise SchedulerError(
            "--workers starts a cluster on this machine and --scheduler uses an existing one: give "
            "one of them (the existing cluster's size is set where its workers start)"
        )


@contextlib.contextmanager
def open_runner(workers: int | None = None, scheduler: str | None = None):
    """A :class:`Runner`: synchronous (``workers`` None or 1), a ``LocalCluster`` of ``workers`` processes, or
    the cluster of the Dask scheduler at ``scheduler`` (e.g. ``tcp://10.0.0.5:8786``).  Closed on exit."""
    check_cluster_options(workers, scheduler)
    if not scheduler and (workers is None or workers <= 1):
        yield Runner()
        return
    import dask
    from distributed import Client, LocalCluster

    cluster = None
    with dask.config.set(
        {
            "distributed.worker.daemon": False,  # a task may start processes (ffmpeg)
            "logging.distributed": "error",
        }
    ):
        if scheduler:
            try:
                client = Client(scheduler, timeout=CONNECT_TIMEOUT)
            except (OSError, TimeoutError, ValueError) as e:
                raise SchedulerError(
                    f"--scheduler {scheduler}: no Dask scheduler answers there ({e}); start one "
                    "with `dask scheduler` and workers with `dask worker ADDRESS` (docs/user-guide/dask.md), "
                    "or leave --scheduler out"
                ) from None
            n = len(client.scheduler_info().get("workers", {}))
            desc = f"the Dask cluster at {scheduler} ({n} worker{'s' if n != 1 else ''} now)"
        else:
            threads = _threads_per_worker(workers)
            # one thread per task and the cores shared out between the workers' numba / BLAS threads
            env = {
                k: str(threads)
                for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
            }
            # memory_limit 0: no per-worker cap (Dask's default, the machine's memory / N, would pause or kill
            # a worker whose paper-size study outgrows its share while the others need little)
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
                env=env,
                memory_limit=0,
            )
            client = Client(cluster)
            desc = f"a local Dask cluster of {workers} worker processes ({threads} thread(s) each)"
        try:
            log.info("per-scan work runs on %s", desc)
            yield Runner(client, desc)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
