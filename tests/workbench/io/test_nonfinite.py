"""workbench.io.nonfinite: an image's NaN and infinite voxels replaced, the rest and the geometry kept."""

from __future__ import annotations

import numpy as np
import pytest

from deformation.geometry import GridGeometry, Volume
from workbench.errors import OutputExistsError
from workbench.io.nonfinite import clean_image, fill_nonfinite
from workbench.io.volumes import read_volume, write_volume

GEOMETRY = GridGeometry((4, 3, 2), (1.0, 1.5, 2.0), (-3.0, 2.0, 7.0))


def _volume() -> Volume:
    data = np.arange(24, dtype=np.float32).reshape(2, 3, 4) - 5.0  # finite minimum -5 at voxel 0
    data[0, 0, 0], data[1, 2, 3], data[0, 1, 2] = np.nan, np.inf, -np.inf
    return Volume(data, GEOMETRY)


def test_bad_voxels_take_the_lowest_finite_value_or_the_given_one_and_nothing_else_changes():
    v = _volume()
    good = np.isfinite(v.data)
    clean, n, fill = fill_nonfinite(v)
    assert n == 3 and fill == -4.0  # the finite minimum once voxel 0 (-5) is NaN
    assert clean.data.dtype == np.float32 and clean.geometry == GEOMETRY
    assert np.array_equal(clean.data[good], v.data[good]) and np.all(clean.data[~good] == -4.0)
    clean, n, fill = fill_nonfinite(v, 7.5)
    assert n == 3 and fill == 7.5 and np.all(clean.data[~good] == 7.5)
    with pytest.raises(ValueError, match="no finite voxel at all"):
        fill_nonfinite(Volume(np.full((2, 3, 4), np.nan, np.float32), GEOMETRY))


def test_clean_image_writes_a_copy_and_checks_the_output_before_reading(tmp_path):
    src, out = tmp_path / "in.nii.gz", tmp_path / "out.nii.gz"
    write_volume(_volume(), src, allow_nonfinite=True)
    s = clean_image(src, out)
    assert s == {"replaced": 3, "voxels": 24, "fill": -4.0, "out": out}
    back = read_volume(out)
    assert np.isfinite(back.data).all() and back.geometry.is_close(GEOMETRY)
    with pytest.raises(OutputExistsError):
        clean_image(src, out)
    with pytest.raises(ValueError, match="is the input"):
        clean_image(src, src)
    with pytest.raises(ValueError, match="finite number"):
        clean_image(src, tmp_path / "x.nii.gz", value=float("nan"))
    assert not (tmp_path / "x.nii.gz").exists()
