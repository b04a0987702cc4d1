"""What every benchmark times with (imported by the scripts of this folder, which run as scripts)."""

from __future__ import annotations

import time

import numpy as np


def best_of(fn, repeat: int = 3):
    """``(seconds, result)``: the least wall time of ``repeat`` calls of ``fn`` (the one least disturbed by
    other work on a shared machine) and the last call's result."""
    best, out = np.inf, None
    for _ in range(int(repeat)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out
