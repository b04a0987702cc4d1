"""Atomic output: write to a temporary name beside the target, then rename.

A reader of the output folder sees either the old file (or none) or the
complete new file, never a half-written one; after any failure no temporary
file remains.  Existing outputs are refused unless ``overwrite=True``.

Two context managers:

* :func:`atomic_path` for formats that write one file (NIfTI, MHA, NRRD,
  PLY, JSON, ...).  The temporary name keeps the target's suffix, including
  compound suffixes such as ``.nii.gz``, because writers such as SimpleITK
  and Open3D choose the format from the suffix.
* :func:`atomic_file_group` for formats whose header names a companion data
  file (``.mhd`` + ``.raw``, ``.nhdr`` + ``.raw.gz``).  The writer writes into
  a private temporary folder under the final file name, so the header refers
  to the final data-file name; every file is then moved beside the target,
  the header last.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path

from workbench.errors import OutputExistsError, OutputWriteError, WorkbenchError

__all__ = [
    "atomic_path",
    "atomic_file_group",
    "write_text_atomic",
    "split_suffix",
    "replace_dir",
    "commit_file",
    "check_output_folder",
    "naming_failures",
    "naming_staged",
]

# Suffixes that only make sense together with the one before them.
_COMPRESSION_SUFFIXES = {".gz", ".bz2", ".xz", ".zst"}


def split_suffix(name: str) -> tuple[str, str]:
    """Split a file name into stem and (possibly compound) suffix.

    ``"scan.v2.nii.gz"`` → ``("scan.v2", ".nii.gz")``; ``"bones.ply"`` →
    ``("bones", ".ply")``; ``"README"`` → ``("README", "")``.  Only a
    compression suffix (``.gz``, ``.bz2``, ``.xz``, ``.zst``) joins the one
    before it.
    """
    path = Path(name)
    suffixes = path.suffixes
    if not suffixes:
        return name, ""
    n = 2 if len(suffixes) >= 2 and suffixes[-1].lower() in _COMPRESSION_SUFFIXES else 1
    suffix = "".join(suffixes[-n:])
    stem = path.name[: -len(suffix)]
    if not stem:  # a name that is all suffix, e.g. ".gz"
        return name, ""
    return stem, suffix


def check_output_folder(path: str | os.PathLike, option: str) -> Path:
    """Before any work: the folder an output file ``path`` goes into exists and this process may write in it.
    ``option`` names the command-line option that gave the path (the message's fix).  Returns the path."""
    from workbench.errors import OutputFolderError

    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if folder.exists() and not folder.is_dir():
        raise OutputFolderError(f"{option} {p}: {folder} is a file, not a folder; give {option} a path in a folder.")
    if not folder.is_dir():
        raise OutputFolderError(
            f"{option} {p}: the folder {folder} does not exist; create it (mkdir -p {folder}) "
            f"or give {option} a path in an existing folder."
        )
    import tempfile

    try:  # a real write, not os.access: a read-only file system refuses root too
        fd, probe = tempfile.mkstemp(prefix=".avw-write-test-", dir=folder)
    except OSError as e:
        raise OutputFolderError(
            f"{option} {p}: cannot write in the folder {folder} ({e.strerror or e}); give "
            f"{option} a path in a folder you can write to."
        ) from None
    os.close(fd)
    os.unlink(probe)
    return p


def _check_target(final: Path, overwrite: bool) -> None:
    if final.is_dir():
        raise IsADirectoryError(f"{final}: output path is a folder; give a file name inside it.")
    if final.exists() and not overwrite:
        raise OutputExistsError(final)
    if not final.parent.is_dir():
        raise FileNotFoundError(f"{final}: the output folder {final.parent} does not exist; create it first.")


def _fsync_file(path: Path) -> None:
    """Flush a file written by a third-party writer to disk before it is renamed."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _commit(tmp: Path, final: Path, overwrite: bool) -> None:
    """Move ``tmp`` to ``final``; without ``overwrite`` never clobber a file created meanwhile."""
    if overwrite:
        os.replace(tmp, final)
        return
    try:
        # link() fails if the target exists: a no-clobber rename without a race.
        os.link(tmp, final)
    except FileExistsError:
        raise OutputExistsError(final) from None
    except OSError:
        # File systems without hard links: check, then rename (a small race remains).
        if final.exists():
            raise OutputExistsError(final) from None
        os.replace(tmp, final)
    else:
        os.unlink(tmp)


@contextlib.contextmanager
def naming_failures(final: str | os.PathLike) -> Iterator[None]:
    """Turn an :class:`OSError` raised inside (a full disk, a file-size limit, an I/O error — often without a
    file name, or naming a temporary file) into :class:`~workbench.errors.OutputWriteError` naming ``final``.
    The workbench's own errors (an existing output, a missing folder) pass through as they are."""
    try:
        yield
    except OSError as e:
        if isinstance(e, WorkbenchError) and not isinstance(e, OutputWriteError):
            raise
        raise OutputWriteError.of(final, e) from e


@contextlib.contextmanager
def naming_staged(staging: str | os.PathLike, final: str | os.PathLike) -> Iterator[None]:
    """Like :func:`naming_failures` for files written into a staging folder that becomes ``final`` when whole:
    a failed write is named by the path it would have had under ``final`` (``skinning/weights_value.mha``,
    not ``.skinning.partial-…/weights_value.mha``)."""
    staging, final = Path(staging), Path(final)
    try:
        yield
    except OSError as e:
        if isinstance(e, WorkbenchError) and not isinstance(e, OutputWriteError):
            raise
        inner = Path(getattr(e, "path", None) or getattr(e, "filename", None) or staging)
        where = final / inner.relative_to(staging) if staging in inner.parents else final
        raise OutputWriteError.of(where, e) from e


def _unlink_quietly(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        path.unlink()


@contextlib.contextmanager
def atomic_path(final_path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write; rename it to ``final_path`` on success.

    Parameters
    ----------
    final_path : str or os.PathLike
        Where the file must end up.  Its folder must exist.
    overwrite : bool, optional
        Replace an existing file.  Without it an existing ``final_path`` raises
        :class:`~workbench.errors.OutputExistsError` before anything is written.

    Yields
    ------
    pathlib.Path
        ``<folder>/.<stem>.tmp-<random><suffix>``: same folder (so the rename
        is atomic) and same suffix, e.g. ``.scan.tmp-3f9c2a1b.nii.gz``.

    Raises
    ------
    OutputExistsError
        ``final_path`` exists and ``overwrite`` is false.
    FileNotFoundError
        The output folder does not exist.
    FileNotFoundError
        The body wrote no file.
    OutputWriteError
        Writing, flushing or renaming the file failed (a full disk, a
        file-size limit): the error names ``final_path``.

    Notes
    -----
    If the body raises, the temporary file is deleted and the exception
    propagates; ``final_path`` is untouched.  A writer that fails without
    raising (niftilib) must be checked by the body (see
    :mod:`workbench.io.volumes`).
    """
    final = Path(final_path)
    _check_target(final, overwrite)
    stem, suffix = split_suffix(final.name)
    tmp = final.parent / f".{stem}.tmp-{secrets.token_hex(4)}{suffix}"
    try:
        with naming_failures(final):
            yield tmp
        if not tmp.is_file():  # a writer's bug, not a fault of the disk
            raise FileNotFoundError(f"{final}: the writer produced no file (expected {tmp.name}).")
        with naming_failures(final):
            _fsync_file(tmp)
            _commit(tmp, final, overwrite)
    finally:
        _unlink_quietly(tmp)


@contextlib.contextmanager
def atomic_file_group(final_path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Like :func:`atomic_path` for a header file written together with companion files.

    The body writes ``<tmpdir>/<final name>``; the writer may put companion
    files (e.g. the ``.raw`` of a ``.mhd``) next to it.  On success every file
    in the temporary folder is moved beside ``final_path`` — companions first,
    ``final_path`` last — and the folder is removed.

    Parameters
    ----------
    final_path : str or os.PathLike
        The header file's final path.
    overwrite : bool, optional
        Replace existing files (the header and its companions).

    Yields
    ------
    pathlib.Path
        ``<folder>/.<name>.tmp-<random>/<name>``.

    Raises
    ------
    OutputExistsError
        ``final_path`` or one of the companions exists and ``overwrite`` is
        false (checked for the header before writing, for companions before
        moving anything).

    Notes
    -----
    Each file is moved atomically; the group as a whole is not.  If a move
    fails, the files already moved by this call are removed again when they
    did not exist before.
    """
    final = Path(final_path)
    _check_target(final, overwrite)
    tmpdir = final.parent / f".{final.name}.tmp-{secrets.token_hex(4)}"
    with naming_failures(final):
        tmpdir.mkdir()
    try:
        with naming_failures(final):
            yield tmpdir / final.name
        written = sorted(p for p in tmpdir.iterdir())
        if tmpdir / final.name not in written:
            raise FileNotFoundError(f"{final}: the writer produced no file.")
        with naming_failures(final):
            # Header last, so that a reader never finds a header without its data.
            order = [p for p in written if p.name != final.name] + [tmpdir / final.name]
            targets = [final.parent / p.name for p in order]
            if not overwrite:
                for t in targets:
                    if t.exists():
                        raise OutputExistsError(t)
            moved: list[Path] = []
            try:
                for src, dst in zip(order, targets):
                    if not src.is_file():
                        raise IsADirectoryError(f"{final}: the writer produced a folder {src.name}.")
                    _fsync_file(src)
                    existed = dst.exists()
                    _commit(src, dst, overwrite)
                    if not existed:
                        moved.append(dst)
            except BaseException:
                for dst in moved:
                    _unlink_quietly(dst)
                raise
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def write_text_atomic(path: str | os.PathLike, text: str, *, overwrite: bool = False, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file.
    text : str
        Content to write (written as is; add the final newline yourself).
    overwrite : bool, optional
        Replace an existing file; otherwise :class:`~workbench.errors.OutputExistsError`.
    encoding : str, optional
        Text encoding, UTF-8 by default.

    Returns
    -------
    pathlib.Path
        The destination path.
    """
    final = Path(path)
    with atomic_path(final, overwrite=overwrite) as tmp:
        with open(tmp, "w", encoding=encoding, newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
    return final


def replace_dir(staging: str | os.PathLike, final: str | os.PathLike) -> Path:
    """Move the complete folder ``staging`` to ``final``, replacing an old ``final`` only once the new one is complete.

    The old folder is renamed aside (``.<name>.old-<host>-<pid>-<random>``)
    and removed last; if the move fails it is put back.  A reader sees the old
    folder or the new one, never a mixture — and, for the instant between the
    two renames, none (POSIX has no atomic exchange of two folders).
    """
    import socket

    staging, final = Path(staging), Path(final)
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.old-{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(4)}"
        os.replace(final, old)
    try:
        os.replace(staging, final)
    except BaseException:
        if old is not None:
            os.replace(old, final)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return final


def commit_file(tmp: str | os.PathLike, final: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Flush the complete file ``tmp`` to disk and rename it to ``final`` (no clobber without ``overwrite``).

    For writers that cannot go through :func:`atomic_path` (a video encoder
    that streams frames into its own temporary file).
    """
    tmp, final = Path(tmp), Path(final)
    with naming_failures(final):
        _fsync_file(tmp)
        _commit(tmp, final, overwrite)
    return final
