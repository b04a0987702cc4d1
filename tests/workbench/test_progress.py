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


def test_the_first_kernel_compiled_in_a_process_is_announced_once():
    """announce_compilation: numba's first compile in the process (a cache miss) prints one line; later compiles
    and calls print nothing more (run in a fresh interpreter: the listener is process-wide)."""
    import subprocess
    import sys

    code = (
        "import numba\n"
        "from workbench.progress import announce_compilation\n"
        "announce_compilation()\n"
        "announce_compilation()\n"  # a second call registers nothing more
        "f = numba.njit(lambda x: x + 1)\n"
        "g = numba.njit(lambda x: x * 2)\n"
        "assert f(1) == 2 and f(2) == 3 and g(3) == 6 and g(1.5) == 3.0\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("compiling the numba kernels"), proc.stderr


def test_a_kernel_loaded_from_the_cache_is_not_announced(tmp_path):
    """The second run of a cached kernel loads it from __pycache__: no compile, no line."""
    import subprocess
    import sys

    (tmp_path / "cached_kernel.py").write_text(
        "import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n"
    )
    code = (
        "import sys\n"
        f"sys.path.insert(0, {str(tmp_path)!r})\n"
        "from workbench.progress import announce_compilation\n"
        "announce_compilation()\n"
        "import cached_kernel\n"
        "assert cached_kernel.twice(21) == 42\n"
    )
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120) for _ in (1, 2)]
    assert all(r.returncode == 0 for r in runs), runs[0].stderr + runs[1].stderr
    assert "compiling the numba kernels" in runs[0].stderr  # the first run compiled it
    assert runs[1].stderr.strip() == ""  # the second loaded it


def test_deform_leaves_its_own_compile_note_to_the_command_wide_announcement(tmp_path):
    """`workbench deform` printed two lines on a first run: its note on the deformation kernels and the command's
    announcement.  With the announcement listening, the note says nothing; without it (a library caller), it
    still speaks (an empty NUMBA_CACHE_DIR: no kernel cached)."""
    import os
    import subprocess

    code = (
        "import sys\n"
        "from workbench.progress import announce_compilation\n"
        "if sys.argv[1] == 'announced':\n"
        "    announce_compilation()\n"
        "from workbench.deform import say_if_compiling\n"
        "said = []\n"
        "say_if_compiling(said.append)\n"
        "print(len(said))\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = {
        mode: subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True, timeout=120, env=env)
        for mode in ("announced", "library")
    }
    assert all(p.returncode == 0 for p in out.values()), [p.stderr for p in out.values()]
    assert out["announced"].stdout.strip() == "0" and out["library"].stdout.strip() == "1"
