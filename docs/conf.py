"""Sphinx configuration of the Articulated Volume Workbench's documentation (``make docs``).

Built nitpicky, with warnings as errors (``sphinx-build -n -W --keep-going``): every cross-reference must resolve.
The API pages come from the packages' docstrings (autodoc, numpydoc), the CLI reference from the argparse parser
(sphinx-argparse), the results pages from the ``workbench reproduce`` JSON under ``results/data/``
(``_ext/reproduce_tables.py``), and the Markdown pages through MyST.
"""

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))
sys.path.insert(0, str(HERE.parent))  # the packages of this checkout, installed or not

import workbench  # noqa: E402

project = "Articulated Volume Workbench"
author = "Articulated Volume Workbench developers"
copyright = "Articulated Volume Workbench developers"
release = version = workbench.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "sphinxarg.ext",
    "myst_parser",
    "cli_help",
    "reproduce_tables",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "results/data", "Thumbs.db", ".DS_Store"]
templates_path = ["_templates"]

# MyST: GitHub-style Markdown as the measurement pages are written; anchors for ## and ### headings, so that
# pages can link to each other's sections.
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

# autodoc / autosummary: one page per module, members in source order; type hints in the description.
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "member-order": "bysource"}
autodoc_typehints = "none"
autodoc_mock_imports = []
# numpydoc: the docstrings are prose with numpydoc sections where they have them; no per-member tables of
# class members (autodoc lists them), no validation of the docstrings' sections.
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_validation_checks = set()
numpydoc_xref_param_type = False

# Nitpicky (``-n``): every cross-reference must resolve.  The one exception: a dataclass's signature shows its
# fields' annotations as strings (``from __future__ import annotations``), and Sphinx splits an annotation such
# as ``'dict[str, JointCenterResult]'`` at its comma and looks up the piece ``'dict[str`` as a class.
nitpick_ignore_regex = [("py:class", r"'dict\[str")]

html_theme = "pydata_sphinx_theme"
html_title = "Articulated Volume Workbench"
html_static_path = []
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "header_links_before_dropdown": 7,
}
html_show_sourcelink = False
