"""A protocol's result: a table of numbers with the paper's figures beside ours and every measure defined.

A :class:`Table` holds numbers, never formatted text: ``rows`` are dicts of
column key → float (``None`` where a row has no value, e.g. the paper did not
report it), each row labelled and marked by ``kind`` — ``"ours"``,
``"paper"`` (the published figure, with its source) or ``"peer"`` (a
general-purpose registration run in the same harness on the same input).
``definitions`` says what each column measures (over which voxels, in which
units, bins and logarithm base), so that a table read on its own cannot be
misread.  Formatting (Markdown, CSV) and writing belong to the workbench
(:mod:`workbench.reproduce`); here the table is only data (``to_dict()``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["Column", "Table", "DEFINITIONS", "ROW_KINDS"]

ROW_KINDS = ("ours", "paper", "peer")

# One definition per measure, used by every protocol (the measures themselves are computed in
# validation.registration_measures, registration.metrics and validation.leave_one_out).
DEFINITIONS = {
    "med_mm": "MED: mean Euclidean distance (mm) between recovered and true template positions over the scan's body "
    "voxels (scan voxels whose true template position lies in the template's body mask)",
    "marker_med_mm": "marker MED: the same distance (mm) at the phantom's skin markers (12 per scan, drawn near the "
    "joints; Rhee Table 3 used eight MR markers), the recovered field sampled trilinearly at each "
    "marker's scan position",
    "ssd": "SSD: mean squared intensity difference (Rhee Eq. 4 divided by the voxel count) between the scan and the "
    "template resampled through the field, over the whole scan grid, after both images are scaled by the "
    "one factor that maps the template's 0.5–99.5th percentile range onto 0–255 (the papers' 8-bit scale; "
    "the offset does not change a difference)",
    "cc": "CC: Pearson correlation of the scan and the resampled template over the whole scan grid",
    "mi": "MI: mutual information (Rhee Eq. 5) of the scan and the resampled template over the whole scan grid, "
    "32 × 32 equal-width bins over each image's range, natural logarithm (nats); the papers do not state "
    "their bins or base, so only the trend compares",
    "folded_fraction": "folded: fraction of the scan's body voxels whose Jacobian determinant (central differences) "
    "is ≤ 0",
    "seconds": "wall-clock seconds of the registration on this machine (2 cores)",
}


@dataclass(frozen=True)
class Column:
    """One column: its key in the rows, a heading, the unit, and how many decimals a reader needs."""

    key: str
    label: str
    unit: str = ""
    decimals: int = 2

    def to_dict(self) -> dict:
        return {"key": self.key, "label": self.label, "unit": self.unit, "decimals": self.decimals}


@dataclass
class Table:
    """A protocol's table (see the module docstring)."""

    id: str  #: the protocol's name, e.g. "table3"
    title: str
    columns: list[Column]
    rows: list[dict] = field(default_factory=list)  #: {"label", "kind", <column key>: float | None, ...}
    definitions: dict = field(default_factory=dict)  #: column key (or other term) → its definition
    notes: list[str] = field(default_factory=list)  #: what a reader must know (protocol, sizes, deviations)
    meta: dict = field(default_factory=dict)  #: phantom spec, settings, scans, seconds (JSON-ready)

    def add(self, label: str, kind: str, values: dict, **extra) -> dict:
        """Append a row; ``values`` may hold more keys than there are columns (kept, not shown)."""
        if kind not in ROW_KINDS:
            raise ValueError(f"row kind must be one of {ROW_KINDS}, got {kind!r}")
        row = {"label": label, "kind": kind}
        for k, v in values.items():
            row[k] = None if v is None or (isinstance(v, float) and math.isnan(v)) else v
        row.update(extra)
        self.rows.append(row)
        return row

    def row(self, label: str) -> dict:
        for r in self.rows:
            if r["label"] == label:
                return r
        raise KeyError(f"table {self.id!r} has no row {label!r}; its rows are {[r['label'] for r in self.rows]}")

    def value(self, label: str, key: str):
        return self.row(label).get(key)

    def to_dict(self) -> dict:
        return {
            "format": "avw-table",
            "version": 1,
            "id": self.id,
            "title": self.title,
            "columns": [c.to_dict() for c in self.columns],
            "rows": self.rows,
            "definitions": self.definitions,
            "notes": self.notes,
            "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Table:
        if d.get("format") != "avw-table":
            raise ValueError(f"not a protocol table (format {d.get('format')!r}, expected 'avw-table')")
        return cls(
            d["id"],
            d["title"],
            [Column(**c) for c in d["columns"]],
            list(d["rows"]),
            dict(d.get("definitions", {})),
            list(d.get("notes", [])),
            dict(d.get("meta", {})),
        )
