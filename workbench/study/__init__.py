"""Study folders and their ``study.json`` manifest.

* :mod:`workbench.study.manifest` — the manifest's format (with an example), its errors, reading and checking it;
* :mod:`workbench.study.folder` — :class:`Study`, a study opened through its manifest: the inputs, the stages'
  outputs and the one (locked) writer of ``study.json``; :func:`read_study` opens one;
* :mod:`workbench.study.phantom` — :func:`write_phantom_study`, a phantom written as a study with its truth;
* :mod:`workbench.study.summary` — :func:`summarize`, what ``workbench info`` prints, and
  :func:`recorded_times`, the stages' times from the manifest;
* :mod:`workbench.study.checks` — :func:`check_study_images` and :func:`study_warnings`, what ``workbench info
  --check`` says of a study before any work.
"""

from workbench.study.checks import check_study_images, study_warnings
from workbench.study.folder import Study, read_study
from workbench.study.manifest import (
    MANIFEST,
    MANIFEST_VERSION,
    STAGE_COMMANDS,
    STUDY_FORMAT,
    StageOutputMissing,
    StudyError,
)
from workbench.study.phantom import write_phantom_study
from workbench.study.summary import recorded_times, summarize

__all__ = [
    "Study",
    "StudyError",
    "StageOutputMissing",
    "STAGE_COMMANDS",
    "read_study",
    "write_phantom_study",
    "summarize",
    "recorded_times",
    "check_study_images",
    "study_warnings",
    "STUDY_FORMAT",
    "MANIFEST",
    "MANIFEST_VERSION",
]
