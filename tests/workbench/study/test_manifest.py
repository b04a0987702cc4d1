"""The checks of a study's manifest (workbench.study.manifest.read_manifest): each malformed manifest is one error
that names the file and the fix; a minimal valid one passes."""

from __future__ import annotations

import json
import re

import pytest

from workbench.errors import InputFileError, MissingFileError, UnreadableFileError
from workbench.study.manifest import MANIFEST, MANIFEST_VERSION, STUDY_FORMAT, StudyError, read_manifest


def _minimal() -> dict:
    return {
        "format": STUDY_FORMAT,
        "version": MANIFEST_VERSION,
        "template": "template.nii.gz",
        "skeleton": "skeleton.json",
        "scans": [{"id": "pose00", "image": "scans/pose00.nii.gz"}],
    }


def _study(tmp_path, manifest) -> tuple:
    """A study folder holding ``manifest`` and the files of the minimal one (read_manifest checks only that they
    exist, not what they hold)."""
    root = tmp_path / "study"
    (root / "scans").mkdir(parents=True)
    (root / "truth").mkdir()
    for f in ("template.nii.gz", "skeleton.json", "scans/pose00.nii.gz", "labels.nii.gz"):
        (root / f).write_bytes(b"x")
    for f in ("c.mha", "p.json", "m.json"):
        (root / "truth" / f).write_bytes(b"x")
    text = manifest if isinstance(manifest, str) else json.dumps(manifest)
    (root / MANIFEST).write_text(text, encoding="utf-8")
    return root, root / MANIFEST


def test_a_minimal_manifest_passes_and_is_returned_as_read(tmp_path):
    root, _ = _study(tmp_path, _minimal())
    assert read_manifest(root) == _minimal()


def test_optional_parts_pass_labels_truth_and_a_missing_version(tmp_path):
    m = _minimal()
    del m["version"]  # a hand-written manifest may leave it out
    m["template_labels"] = "labels.nii.gz"
    m["scans"][0]["truth"] = {"correspondence": "truth/c.mha", "pose": "truth/p.json", "markers": "truth/m.json"}
    m["scans"][0]["pose"] = "poses/pose00_pose.json"  # written by `workbench pose`: need not exist
    m["scans"].append({"id": "pose01", "image": "scans/pose00.nii.gz"})
    root, _ = _study(tmp_path, m)
    assert read_manifest(root) == m


def _error(tmp_path, manifest, kind=StudyError) -> str:
    root, path = _study(tmp_path, manifest)
    with pytest.raises(kind) as e:
        read_manifest(root)
    message = str(e.value)
    assert message.startswith(f"{path}: ") or message.startswith(f"{root}/"), message
    assert "\n" not in message
    return message


def test_no_folder_and_no_manifest_say_how_to_make_one(tmp_path):
    with pytest.raises(MissingFileError, match=r"no such study folder\. Create one with `workbench phantom`"):
        read_manifest(tmp_path / "nowhere")
    with pytest.raises(
        MissingFileError, match=rf"^{re.escape(str(tmp_path))}: not a study folder \(study\.json is missing\)\.$"
    ):
        read_manifest(tmp_path)


def test_a_manifest_that_is_not_json_names_the_line(tmp_path):
    message = _error(tmp_path, '{"format": "avw-study",\n}', InputFileError)
    assert "invalid JSON at line 2" in message


def test_a_manifest_that_is_not_an_object_shows_what_a_manifest_is(tmp_path):
    message = _error(tmp_path, [_minimal()], UnreadableFileError)
    assert "the top level is a JSON list, but a study manifest" in message
    assert "docs/user-guide/study-folders.md" in message


def test_no_format_says_what_to_add(tmp_path):
    m = _minimal()
    del m["format"]
    message = _error(tmp_path, m)
    assert 'no \'format\' key; add "format": "avw-study", "version": 1 at the top of the manifest' in message


def test_another_format_is_not_a_study(tmp_path):
    message = _error(tmp_path, {**_minimal(), "format": "avw-table"})
    assert "'format' is 'avw-table', not a study manifest; a study's is 'avw-study'." in message


@pytest.mark.parametrize("version", [2, 0, "1", 1.0, True, None])
def test_another_version_is_refused_with_the_one_this_workbench_reads(tmp_path, version):
    message = _error(tmp_path, {**_minimal(), "version": version})
    assert f"unsupported manifest version {json.dumps(version)} (this workbench reads 1)" in message
    assert 'set "version": 1' in message


@pytest.mark.parametrize("key", ["template", "skeleton", "scans"])
def test_a_missing_key_is_named(tmp_path, key):
    m = _minimal()
    del m[key]
    assert _error(tmp_path, m).endswith(f"the manifest lacks the key {key!r}.")


@pytest.mark.parametrize(
    "scans, said",
    [
        ({"id": "pose00"}, "'scans' must be a list of {'id', 'image'[, 'truth']}."),
        (["scans/pose00.nii.gz"], "scans[0] needs 'id' and 'image'."),
        ([{"id": "pose00", "image": "scans/pose00.nii.gz"}, {"id": "pose01"}], "scans[1] needs 'id' and 'image'."),
        (
            [{"id": "pose00", "image": "scans/pose00.nii.gz"}, {"id": "pose00", "image": "scans/pose00.nii.gz"}],
            "scan id 'pose00' appears twice.",
        ),
        (
            [{"id": "pose00", "image": "scans/pose00.nii.gz", "truth": {"correspondence": "truth/c.mha"}}],
            "scans[0]['truth'] must name 'correspondence', 'pose' and 'markers' files.",
        ),
        (
            [{"id": "pose00", "image": "scans/pose00.nii.gz", "truth": "truth/c.mha"}],
            "scans[0]['truth'] must name 'correspondence', 'pose' and 'markers' files.",
        ),
    ],
)
def test_malformed_scans_are_named_by_position(tmp_path, scans, said):
    assert _error(tmp_path, {**_minimal(), "scans": scans}).endswith(said)


def test_file_entries_must_be_strings(tmp_path):
    assert _error(tmp_path, {**_minimal(), "skeleton": 3}).endswith("file entries must be strings (paths), got 3.")


@pytest.mark.parametrize("path", ["/data/template.nii.gz", "../template.nii.gz", "scans/../../template.nii.gz"])
def test_a_file_outside_the_folder_is_refused_with_the_symbolic_link_fix(tmp_path, path):
    message = _error(tmp_path, {**_minimal(), "template": path})
    assert f"{path!r} must be a path inside the study folder (no '..', not absolute)" in message
    assert "ln -s /data/scan.nii.gz scans/scan.nii.gz" in message


@pytest.mark.parametrize(
    "change",
    [
        {"template": "missing.nii.gz"},
        {"template_labels": "missing.nii.gz"},
        {"scans": [{"id": "pose00", "image": "missing.nii.gz"}]},
        {
            "scans": [
                {
                    "id": "pose00",
                    "image": "scans/pose00.nii.gz",
                    "truth": {"correspondence": "truth/c.mha", "pose": "truth/p.json", "markers": "missing.nii.gz"},
                }
            ]
        },
    ],
)
def test_a_named_file_that_is_missing_is_named_with_the_manifest(tmp_path, change):
    root, path = _study(tmp_path, {**_minimal(), **change})
    with pytest.raises(MissingFileError) as e:
        read_manifest(root)
    assert str(e.value) == f"{root / 'missing.nii.gz'}: named in {path} but missing."
    assert e.value.path == root / "missing.nii.gz"


def test_study_errors_carry_the_manifest_path_and_are_value_errors(tmp_path):
    root, path = _study(tmp_path, {**_minimal(), "format": "x"})
    with pytest.raises(ValueError) as e:
        read_manifest(root)
    assert isinstance(e.value, StudyError) and e.value.path == path
