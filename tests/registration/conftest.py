"""Shared fixtures: a small CT-like knee study with ground truth (written once per test session)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def knee_ct_study(tmp_path_factory):
    from validation.phantoms import make_phantom
    from workbench.study import write_phantom_study

    phantom = make_phantom("knee", size="test", modality="ct", n_poses=3, seed=3)
    return write_phantom_study(phantom, tmp_path_factory.mktemp("knee-ct") / "study")
