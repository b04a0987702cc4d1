"""The first-use compile note (issue L: the first `deform` of a session spent ~29 s compiling in silence)."""

from __future__ import annotations

import importlib
import sys

from workbench.progress import compile_note


def test_compile_note_until_the_kernel_is_cached(tmp_path, monkeypatch):
    (tmp_path / "fresh_kernel.py").write_text(
        "import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
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
    from deformation.evd import _forward_kernel
    from deformation.resample import _backward_kernel

    for k in (_forward_kernel, _backward_kernel):
        assert k._cache._cache_file._index_path.endswith(".nbi")
