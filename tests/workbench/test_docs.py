"""The documentation's results pages show the figures ``workbench reproduce`` printed.

The pages are generated from the committed JSON tables (``docs/results/data``) by ``docs/_ext/reproduce_tables.py``
when Sphinx builds the site; here each page is generated the same way and rendered by MyST, and its table's cells
are compared with :func:`workbench.reproduce.format_markdown` of the same JSON and with what ``workbench
reproduce`` prints for that table (its ``reproduce`` replaced by one that hands back the JSON's table, so no
pipeline runs).
"""

import importlib.util
import json
from pathlib import Path

import pytest

from validation.protocols import Table
from workbench import cli
from workbench.reproduce import NAMES, format_markdown

DOCS = Path(__file__).resolve().parents[2] / "docs"
DATA = DOCS / "results" / "data"
TABLES = sorted(DATA.glob("*.json"))
TABLES = [p for p in TABLES if p.name != "PROVENANCE.json"]


def _extension():
    spec = importlib.util.spec_from_file_location("reproduce_tables", DOCS / "_ext" / "reproduce_tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _markdown_rows(text: str) -> list[list[str]]:
    """The cells of a Markdown table's header and body rows (the separator row left out)."""
    rows = []
    for line in text.splitlines():
        if line.startswith("|") and not set(line) <= set("|-: "):
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def _rendered_rows(markdown: str) -> list[list[str]]:
    """The cells of the first table MyST renders from ``markdown``, as docutils sees them."""
    pytest.importorskip("myst_parser")
    from docutils import nodes
    from docutils.core import publish_doctree
    from myst_parser.parsers.docutils_ import Parser

    # the page's Sphinx-only roles ({download}) are unknown to plain docutils: reported, not raised
    doctree = publish_doctree(markdown, parser=Parser(), settings_overrides={"report_level": 5, "halt_level": 5})
    table = next(iter(doctree.findall(nodes.table)))
    return [[entry.astext().strip() for entry in row.findall(nodes.entry)] for row in table.findall(nodes.row)]


def test_every_protocol_has_its_table_and_the_data_its_provenance():
    ids = {json.loads(p.read_text(encoding="utf-8"))["id"] for p in TABLES}
    assert ids == set(NAMES)
    provenance = json.loads((DATA / "PROVENANCE.json").read_text(encoding="utf-8"))
    assert {"command", "commit", "date"} <= set(provenance)
    assert "workbench reproduce" in provenance["command"]


@pytest.mark.parametrize("path", TABLES, ids=[p.stem for p in TABLES])
def test_results_page_shows_the_figures_reproduce_printed(path, tmp_path, monkeypatch, capsys):
    doc = json.loads(path.read_text(encoding="utf-8"))
    table = Table.from_dict(doc)
    expected = _markdown_rows(format_markdown(table))
    assert len(expected) == len(table.rows) + 1  # the header and one line per row

    page = _extension().page_text(doc, {"command": "workbench reproduce", "commit": "0" * 40, "date": "today"})
    assert _markdown_rows(page) == expected
    assert _rendered_rows(page) == expected

    # what `workbench reproduce` prints for the same table
    import workbench.reproduce

    def replay(names, out, *, emit, **kwargs):
        emit(table, 1.0)
        return {table.id: table}

    monkeypatch.setattr(workbench.reproduce, "reproduce", replay)
    assert cli.main(["reproduce", table.id, "--out", str(tmp_path), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert _markdown_rows(printed) == expected
