"""Outputs whose folder is missing or cannot be written are refused before any work, naming the option."""

from __future__ import annotations

import errno
import tempfile

import pytest

from workbench.errors import OutputFolderError
from workbench.io.atomic import check_output_folder


def test_a_missing_folder_names_the_option_and_the_fix(tmp_path):
    with pytest.raises(OutputFolderError, match=r"--out .*missing.* does not exist; create it \(mkdir -p"):
        check_output_folder(tmp_path / "missing" / "x.png", "--out")
    assert check_output_folder(tmp_path / "x.png", "--out") == tmp_path / "x.png"
    assert list(tmp_path.iterdir()) == []  # the write test leaves nothing behind


def test_a_folder_that_refuses_writes_is_said_before_the_work(tmp_path, monkeypatch):
    # a read-only file system refuses root too (os.access does not see it): the check writes a probe file;
    # here the probe fails as it would there (EROFS)
    def refuse(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(OutputFolderError, match=r"--out .*cannot write in the folder .*Read-only file system"):
        check_output_folder(tmp_path / "anim.mp4", "--out")


def test_render_refuses_a_read_only_folder_before_rendering(tmp_path, monkeypatch, capsys):
    import numpy as np

    from deformation.meshes.mesh import SurfaceMesh
    from workbench.cli import main
    from workbench.io.meshes import write_mesh

    mesh = tmp_path / "m.ply"
    write_mesh(SurfaceMesh(np.eye(3), np.array([[0, 1, 2]])), mesh)

    def refuse(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    assert main(["render", str(mesh), "--out", str(tmp_path / "r.png")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and "Read-only file system" in err[0], err
    assert not (tmp_path / "r.png").exists()
