"""The first-use compile note (issue L: the first `deform` of a session spent ~29 s compiling in silence)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from workbench.progress import compile_note


def test_compile_note_until_the_kernel_is_cached(tmp_path, monkeypatch):
    (tmp_path / "fresh_kernel.py").write_text(
        "import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = importlib.import_module("fresh_kernel")
    try:
        note = compile_note(mod.twice)
        assert note is not None and "compiling 1 numba kernel" in note and "cached" in note
        assert mod.twice(21) == 42  # compiled and written to the module's __pycache__
        assert compile_note(mod.twice) is None
        assert compile_note(len) is None  # not a numba kernel: nothing to say
    finally:
        sys.modules.pop("fresh_kernel", None)


def test_the_deformation_kernels_are_cached_dispatchers():
    """deform's note looks at these two kernels' caches: they must be cached numba dispatchers."""
    from deformation.fields.resample import backward_kernel
    from deformation.models.evd import forward_kernel

    for k in (forward_kernel, backward_kernel):
        assert k._cache._cache_file._index_path.endswith(".nbi")


def test_a_kernel_cache_that_cannot_be_written_does_not_fail_the_command(tmp_path):
    """On a full disk numba's cache write raised EFBIG out of `workbench deform` (CI on a fresh clone, where no
    kernel was cached yet): with the guard the kernel runs from memory and one warning names the folder; without
    it the same child fails.  The cap (2 KiB) is below the size of the compiled kernel's data file, which numba
    writes before its index."""
    import os
    import resource
    import subprocess

    (tmp_path / "big_kernel.py").write_text(
        "import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n"
    )

    def run(guard: bool, cache: str) -> subprocess.CompletedProcess:
        code = (
            "import workbench.progress as p\n"
            + ("p.tolerate_kernel_cache_failures()\n" if guard else "")
            + "import big_kernel\nprint(big_kernel.twice(21))\n"
        )
        env = {
            **os.environ,
            "NUMBA_CACHE_DIR": str(tmp_path / cache),  # numba's first choice: fresh per run
            "PYTHONPATH": os.pathsep.join([str(tmp_path), str(Path(__file__).resolve().parents[2])]),
            "PYTHONDONTWRITEBYTECODE": "1",
        }
        return subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            encoding="utf-8",
            env=env,
            timeout=300,
            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048)),
        )

    bare = run(False, "bare")
    guarded = run(True, "guarded")
    assert bare.returncode != 0 and "File too large" in bare.stderr, bare.stderr
    assert guarded.returncode == 0 and guarded.stdout.strip() == "42", guarded.stderr
    warnings = [ln for ln in guarded.stderr.splitlines() if ln.startswith("warning: could not save compiled")]
    assert len(warnings) == 1 and str(tmp_path / "guarded") in warnings[0], guarded.stderr
