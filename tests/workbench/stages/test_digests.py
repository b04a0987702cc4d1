"""Digests of a stage's inputs and settings (workbench.stages.digests): stable, and changed by what changes the work.

``stage_status`` and ``digests_of_needs`` read a study's recorded stages: the pipeline tests cover them
(tests/workbench/stages/test_stages.py); here the digests themselves.
"""

from __future__ import annotations

import hashlib
import os
import shutil

from workbench.stages.digests import dir_digest, file_digest, need_units, unit_digest
from workbench.stages.run import STAGES


def _write(path, data: bytes, *, mtime_ns: int | None = None):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    if mtime_ns is not None:
        os.utime(path, ns=(mtime_ns, mtime_ns))
    return path


def test_file_digest_is_the_sha256_of_the_content(tmp_path):
    data = bytes(range(256)) * 1000
    p = _write(tmp_path / "scan.nii.gz", data)
    assert file_digest(p) == hashlib.sha256(data).hexdigest()
    assert file_digest(str(p)) == file_digest(p)  # a string path too
    assert file_digest(_write(tmp_path / "empty", b"")) == hashlib.sha256(b"").hexdigest()


def test_file_digest_is_stable_and_ignores_name_place_and_time(tmp_path):
    p = _write(tmp_path / "a" / "scan.mha", b"voxels" * 100)
    d = file_digest(p)
    assert file_digest(p) == d
    os.utime(p, ns=(10**18, 10**18))  # touched: same content
    assert file_digest(p) == d
    q = tmp_path / "b" / "other.mha"
    q.parent.mkdir()
    shutil.copyfile(p, q)
    assert file_digest(q) == d


def test_file_digest_changes_with_one_byte_of_the_same_size(tmp_path):
    data = bytearray(b"\0" * 4096)
    p = _write(tmp_path / "x.raw", bytes(data), mtime_ns=1_000_000_000)
    before = file_digest(p)
    data[2048] = 1
    _write(p, bytes(data), mtime_ns=2_000_000_000)  # a rewrite gets a new modification time
    assert file_digest(p) != before
    assert file_digest(p) == hashlib.sha256(bytes(data)).hexdigest()


def test_folder_digest_is_over_the_names_and_contents_of_its_files(tmp_path):
    series = tmp_path / "series"
    _write(series / "IM0001.dcm", b"slice 1")
    _write(series / "IM0002.dcm", b"slice 2")
    d = file_digest(series)
    expected = hashlib.sha256()
    for name, data in (("IM0001.dcm", b"slice 1"), ("IM0002.dcm", b"slice 2")):
        expected.update(name.encode() + b"\0" + hashlib.sha256(data).hexdigest().encode())
    assert d == expected.hexdigest()

    # the same files elsewhere, under another folder name: the same digest
    shutil.copytree(series, tmp_path / "moved")
    assert file_digest(tmp_path / "moved") == d
    # sub-folders are not part of the series
    (series / "thumbs").mkdir()
    _write(series / "thumbs" / "t.png", b"png")
    assert file_digest(series) == d


def test_folder_digest_changes_with_a_file_added_renamed_or_changed(tmp_path):
    series = tmp_path / "series"
    _write(series / "IM0001.dcm", b"slice 1")
    d = file_digest(series)
    _write(series / "IM0002.dcm", b"slice 2")
    added = file_digest(series)
    assert added != d
    (series / "IM0002.dcm").rename(series / "IM0003.dcm")
    assert file_digest(series) not in (d, added)
    _write(series / "IM0003.dcm", b"slice 3", mtime_ns=3_000_000_000)
    assert file_digest(series) not in (d, added)


def test_dir_digest_is_of_relative_names_and_contents_in_any_listing_order(tmp_path):
    out = tmp_path / "register" / "pose00"
    files = [_write(out / "log.json", b"{}"), _write(out / "fields" / "correspondence.mha", b"field")]
    d = dir_digest(files, out)
    assert dir_digest(list(reversed(files)), out) == d
    expected = hashlib.sha256()
    for rel, data in (("fields/correspondence.mha", b"field"), ("log.json", b"{}")):
        expected.update(rel.encode())
        expected.update(hashlib.sha256(data).hexdigest().encode())
    assert d == expected.hexdigest()

    # the folder moved (the relative names and contents kept): the same digest
    moved = tmp_path / "elsewhere"
    shutil.copytree(out, moved)
    assert dir_digest([moved / "log.json", moved / "fields" / "correspondence.mha"], moved) == d


def test_dir_digest_changes_with_a_byte_a_file_added_or_a_name(tmp_path):
    out = tmp_path / "o"
    a = _write(out / "a.json", b"[1]", mtime_ns=1_000_000_000)
    b = _write(out / "b.json", b"[2]")
    d = dir_digest([a, b], out)
    c = _write(out / "c.json", b"[3]")
    assert dir_digest([a, b, c], out) != d
    _write(a, b"[7]", mtime_ns=2_000_000_000)
    assert dir_digest([a, b], out) != d
    _write(a, b"[1]", mtime_ns=3_000_000_000)
    assert dir_digest([a, b], out) == d  # the same bytes again: the same digest
    a.rename(out / "z.json")
    assert dir_digest([out / "z.json", b], out) != d


def test_unit_digest_is_stable_and_changes_with_settings_inputs_needs_and_the_stage():
    stage = STAGES["register"]
    settings = {"method": "dense", "seed": 0, "levels": [3, 5]}
    inputs = {"scan": {"path": "scans/pose00.nii.gz", "sha256": "a" * 64}}
    needs = {"init/pose00": "b" * 64}
    d = unit_digest(stage, settings, inputs, needs)
    assert len(d) == 64 and int(d, 16) >= 0
    assert unit_digest(stage, dict(reversed(list(settings.items()))), inputs, needs) == d  # key order does not matter
    # where an input lies does not matter, its content does
    assert unit_digest(stage, settings, {"scan": {"path": "moved/pose00.nii.gz", "sha256": "a" * 64}}, needs) == d
    assert unit_digest(stage, settings, {"scan": {"path": "scans/pose00.nii.gz", "sha256": "c" * 64}}, needs) != d
    assert unit_digest(stage, {**settings, "seed": 1}, inputs, needs) != d
    assert unit_digest(stage, {**settings, "levels": [3, 4]}, inputs, needs) != d
    assert unit_digest(stage, settings, inputs, {"init/pose00": "c" * 64}) != d
    assert unit_digest(stage, settings, inputs, {}) != d
    assert unit_digest(STAGES["init"], settings, inputs, needs) != d


def test_need_units_are_the_study_the_same_scan_or_every_scan():
    per_scan, whole = STAGES["register"], STAGES["weights"]
    assert per_scan.per_scan and not whole.per_scan
    assert need_units(whole, "pose00", ["pose00", "pose01"]) == [None]
    assert need_units(per_scan, "pose01", ["pose00", "pose01"]) == ["pose01"]
    assert need_units(per_scan, None, ("pose00", "pose01")) == ["pose00", "pose01"]
