"""One progress protocol for the command line: stage events to progress bars or plain lines, and logging.

Stages report :class:`workbench.stages.stage.Event` records to one
callback.  :class:`ProgressPrinter` is that callback for the CLI: on a
terminal, a tqdm bar per unit of work with a total (bones of a pose
estimate, scans of a model) and the unit's messages above it; elsewhere
(a log file, CI) plain lines, progress messages at most one every
``interval`` seconds.  Start, done and skip events are always printed unless
``quiet``.  :func:`setup_logging` routes ``logging.getLogger("workbench")``
to standard error at the level ``-v``/``--quiet`` choose.
"""

from __future__ import annotations

import logging
import sys
import time

__all__ = [
    "ProgressPrinter",
    "setup_logging",
    "compile_note",
    "announce_compilation",
    "compilation_announced",
    "tolerate_kernel_cache_failures",
]


def compile_note(*kernels) -> str | None:
    """A line to show before the first use of numba ``kernels`` that have no on-disk cache yet (the first run
    after installing, or after an upgrade: ~30 s of compiling with nothing else to show), else None.  The
    kernels are compiled with ``cache=True``: numba keeps them in the package's ``__pycache__`` (or, where that
    is not writable, in ``NUMBA_CACHE_DIR`` / the user's cache folder), so later runs load them in well under
    a second."""
    import os

    missing = []
    for k in kernels:
        cache = getattr(k, "_cache", None)
        try:
            index = cache._cache_file._index_path
        except AttributeError:  # not a cached dispatcher (or numba's internals moved): nothing to say
            continue
        if not os.path.exists(index):
            missing.append(getattr(k, "__name__", "kernel"))
    if not missing:
        return None
    return f"compiling {len(missing)} numba kernel(s) on first use (about 30 s, once; they are cached for later runs)"


def announce_compilation(stream=None) -> None:
    """One line on ``stream`` (standard error) the first time in this process that numba compiles a kernel it
    could not load from its on-disk cache — the first run after installing or upgrading, when a command spends a
    minute or so compiling with nothing else to show; later runs load the kernels from ``__pycache__`` and say
    nothing.  Listens to numba's ``numba:compile`` event, which fires on a cache miss only."""
    try:
        from numba.core import event
    except ImportError:  # numba's internals moved: nothing to say
        return
    if getattr(announce_compilation, "_registered", False):
        return
    said = []

    class _FirstCompile(event.Listener):
        def on_start(self, ev):
            if not said:
                said.append(True)
                print(
                    "compiling the numba kernels this command needs (first run after installing: a minute or "
                    "so, once; later runs load them from the cache)",
                    file=stream or sys.stderr,
                    flush=True,
                )

        def on_end(self, ev):
            pass

    event.register("numba:compile", _FirstCompile())
    announce_compilation._registered = True


def compilation_announced() -> bool:
    """Whether :func:`announce_compilation` listens in this process (every ``workbench`` command): a first
    compile is then announced once, whatever compiles it, and a note of one's own would say it twice."""
    return bool(getattr(announce_compilation, "_registered", False))


def tolerate_kernel_cache_failures() -> None:
    """Let a command go on when numba cannot save a compiled kernel (a full disk, a file-size limit): the kernel
    was compiled in memory and is used; the cache is only what saves the next run its compile time.  numba's own
    ``Cache.save_overload`` raises the OSError (it forgives only EACCES, on Windows), which would fail the
    user's command with a message about a file it never asked for.  One warning per process names the folder;
    numba removes its half-written temporary file itself, and a later run whose index names a missing data file
    compiles again."""
    try:
        from numba.core import caching

        original = caching.Cache.save_overload
    except (ImportError, AttributeError):  # numba's internals moved: its own behaviour stands
        return
    if getattr(original, "_workbench", False):
        return
    warned = []

    def save_overload(self, sig, data):
        try:
            original(self, sig, data)
        except OSError as e:
            if not warned:
                warned.append(True)
                where = getattr(self, "_cache_path", "numba's cache folder")
                print(
                    f"warning: could not save compiled numba kernels in {where} ({e.strerror or e}); going on "
                    "without the cache (the next run compiles them again)",
                    file=sys.stderr,
                    flush=True,
                )

    save_overload._workbench = True
    caching.Cache.save_overload = save_overload


def setup_logging(verbosity: int = 0) -> logging.Logger:
    """``verbosity`` −1 (``--quiet``: warnings only), 0 (default), 1 (``-v``: info), 2 (``-vv``: debug)."""
    log = logging.getLogger("workbench")
    level = {-1: logging.WARNING, 0: logging.WARNING, 1: logging.INFO}.get(verbosity, logging.DEBUG)
    log.setLevel(level)
    if not any(getattr(h, "_workbench", False) for h in log.handlers):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        h._workbench = True
        log.addHandler(h)
    return log


class ProgressPrinter:
    """The CLI's progress callback (see the module docstring)."""

    def __init__(self, *, quiet: bool = False, stream=None, interval: float = 2.0, bars: bool | None = None):
        self.quiet = quiet
        self.stream = stream or sys.stderr
        self.interval = interval
        self.bars = self.stream.isatty() if bars is None else bars
        self._bar = None
        self._bar_key = None
        self._last = 0.0

    def line(self, text: str) -> None:
        if self.quiet:
            return
        if self._bar is not None:
            self._bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def __call__(self, event) -> None:
        if self.quiet:
            if event.kind == "message" and event.message.startswith("warning:"):  # --quiet keeps warnings
                print(f"  {event.message}", file=self.stream, flush=True)
            return
        if event.kind == "message":
            self.line(f"  {event.message}")
            return
        if event.kind in ("start", "done", "skip"):
            self._close()
            self.line(event.message)
            self._last = 0.0
            return
        key = (event.stage, event.scan)
        if self.bars and event.total > 0:
            if self._bar_key != key or self._bar is None:
                from tqdm import tqdm

                self._close()
                self._bar = tqdm(
                    total=event.total,
                    desc=f"{event.stage}" + (f" {event.scan}" if event.scan else ""),
                    file=self.stream,
                    leave=False,
                )
                self._bar_key = key
            self._bar.n = min(event.done, event.total)
            self._bar.set_postfix_str(event.message[-60:], refresh=True)
            return
        now = time.perf_counter()
        if event.total > 0 and event.done >= event.total:
            self.line(f"  {event.message}")  # the last of a unit always shows
            self._last = now
        elif now - self._last >= self.interval:
            self.line(f"  {event.message}" + (f"  [{event.done}/{event.total}]" if event.total > 0 else ""))
            self._last = now

    def _close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
            self._bar_key = None

    def close(self) -> None:
        self._close()
