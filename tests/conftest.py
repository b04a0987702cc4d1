"""Shared fixtures of the whole suite: phantoms built once per test session (per xdist worker).

A phantom is expensive (seconds) and many test modules use the same few; :func:`phantom` builds each distinct set
of options once and hands every caller the same instance, which tests treat as read-only (the library functions
never modify their inputs, and the scans a test asks for are new arrays).  Tests of the phantom generator itself
(tests/validation/phantoms/) call :func:`validation.phantoms.make_phantom` directly: they test the building.
"""

from __future__ import annotations

import os

import pytest

# OpenMP threads that finish their share of a parallel loop wait for the next one by sleeping, not spinning.
# `make test` runs two workers on two cores, each with numba's OpenMP pool of two threads (and the stages'
# subprocesses inherit the setting): libgomp's default spin-wait burned the cores the other worker needed.
# Scheduling only: the same bits (each thread's share of a loop does not depend on how it waits).  Set before
# any test module loads libgomp (it reads the variable once); a value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


@pytest.fixture(scope="session")
def phantom():
    """``phantom(region, **options)``: :func:`validation.phantoms.make_phantom`'s phantom, built once a session."""
    from validation.phantoms import make_phantom

    built = {}

    def make(region: str, **options):
        key = (region, repr(sorted(options.items())))
        if key not in built:
            built[key] = make_phantom(region, **options)
        return built[key]

    return make


@pytest.fixture(scope="session")
def knee_ct_study(phantom, tmp_path_factory):
    """A small CT-like knee study with ground truth (3 poses, seed 3), written once a session."""
    from workbench.study import write_phantom_study

    ph = phantom("knee", size="test", modality="ct", n_poses=3, seed=3)
    return write_phantom_study(ph, tmp_path_factory.mktemp("knee-ct") / "study")
