"""The results pages, generated at build time from ``workbench reproduce``'s JSON tables.

Each ``results/data/<id>.json`` (written by :func:`workbench.reproduce.write_table`) becomes the page
``results/generated/<id>.md``: :func:`workbench.reproduce.format_markdown` of :meth:`Table.from_dict` — the
same text ``workbench reproduce`` prints, so the same figures — with its heading made the page's title,
followed by the run's settings (the table's ``meta``) and the provenance of the data
(``results/data/PROVENANCE.json``).  ``results/generated/toctree.txt`` lists the pages in the protocols' order
for ``results/index.md`` to include.  MyST renders the pages; nothing is copied by hand.
"""

import json
from pathlib import Path

from validation.protocols import Table
from workbench.reproduce import NAMES, format_markdown

DATA = Path("results") / "data"
OUT = Path("results") / "generated"


def page_text(doc: dict, provenance: dict | None = None) -> str:
    """The results page of one table (``doc``: the JSON of :meth:`Table.to_dict`), as MyST Markdown."""
    table = Table.from_dict(doc)
    text = format_markdown(table)
    assert text.startswith("## "), text[:40]
    lines = ["(results-" + table.id + ")=", "", text[1:].rstrip("\n"), "", "## This run", ""]
    meta = table.meta
    for key in ("size", "seed", "seconds"):
        if key in meta:
            lines.append(f"- **{key}**: {meta[key]}")
    if provenance:
        lines += [
            f"- **command**: `{provenance.get('command', '')}`",
            f"- **commit**: `{provenance.get('commit', '')}`",
            f"- **date**: {provenance.get('date', '')}",
        ]
    lines += [
        "",
        f"The table's data, with every setting of the run (its `meta`): "
        f"{{download}}`{table.id}.json <../data/{table.id}.json>`.",
    ]
    return "\n".join(lines) + "\n"


def tables(srcdir: Path) -> list[tuple[str, dict]]:
    """Every table under ``results/data``, in the protocols' order (:data:`workbench.reproduce.NAMES`)."""
    docs = {}
    for p in sorted((srcdir / DATA).glob("*.json")):
        doc = json.loads(p.read_text(encoding="utf-8"))
        if doc.get("format") == "avw-table":
            docs[doc["id"]] = doc
    order = [n for n in NAMES if n in docs] + sorted(set(docs) - set(NAMES))
    return [(n, docs[n]) for n in order]


def _write_if_changed(path: Path, text: str) -> None:
    if not path.exists() or path.read_text(encoding="utf-8") != text:
        path.write_text(text, encoding="utf-8")


def generate(app) -> None:
    srcdir = Path(app.srcdir)
    prov_path = srcdir / DATA / "PROVENANCE.json"
    provenance = json.loads(prov_path.read_text(encoding="utf-8")) if prov_path.exists() else None
    out = srcdir / OUT
    out.mkdir(parents=True, exist_ok=True)
    made = {f"{n}.md" for n, _ in tables(srcdir)}
    for n, doc in tables(srcdir):
        _write_if_changed(out / f"{n}.md", page_text(doc, provenance))
    for stale in out.glob("*.md"):
        if stale.name not in made:
            stale.unlink()
    # the results index includes this toctree: the pages in the protocols' order, whichever tables there are
    toc = ["```{toctree}", ":maxdepth: 1", ""] + [f"generated/{n}" for n, _ in tables(srcdir)] + ["```", ""]
    _write_if_changed(out / "toctree.txt", "\n".join(toc))


def setup(app):
    app.connect("builder-inited", generate)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
