"""A protocol's table (validation.protocols.table): rows of numbers, their kinds, definitions, and the JSON form."""

from __future__ import annotations

import json

import pytest

from validation.protocols.table import DEFINITIONS, ROW_KINDS, Column, Table


def _table() -> Table:
    t = Table(
        "table3",
        "Registration accuracy",
        [Column("med_mm", "MED", "mm"), Column("cc", "CC", decimals=3)],
        definitions={k: DEFINITIONS[k] for k in ("med_mm", "cc")},
        notes=["3 scans"],
        meta={"seed": 3, "spacing": [1.0, 1.0, 2.5]},
    )
    t.add("ours", "ours", {"med_mm": 1.25, "cc": 0.9876, "seconds": 12.5})
    t.add("Rhee 2011", "paper", {"med_mm": 0.91, "cc": None}, source="Rhee Table 3")
    t.add("SimpleITK B-spline", "peer", {"med_mm": float("nan"), "cc": 0.5})
    return t


def test_to_dict_from_dict_round_trip_is_exact_and_survives_json():
    t = _table()
    d = t.to_dict()
    assert d["format"] == "avw-table" and d["version"] == 1
    assert Table.from_dict(d) == t
    # through JSON text too (what the workbench writes): the numbers come back the same floats
    again = Table.from_dict(json.loads(json.dumps(d)))
    assert again.to_dict() == d
    assert again.columns == t.columns  # columns come back as Column, not dicts


def test_from_dict_copies_its_lists_and_dicts():
    d = _table().to_dict()
    t = Table.from_dict(d)
    t.add("another", "ours", {"med_mm": 2.0})
    t.notes.append("x")
    t.meta["y"] = 1
    assert len(d["rows"]) == 3 and d["notes"] == ["3 scans"] and "y" not in d["meta"]


def test_from_dict_defaults_the_optional_parts():
    t = Table.from_dict(
        {"format": "avw-table", "id": "t", "title": "T", "columns": [{"key": "cc", "label": "CC"}], "rows": []}
    )
    assert (t.definitions, t.notes, t.meta) == ({}, [], {})
    assert t.columns == [Column("cc", "CC", "", 2)]


def test_from_dict_refuses_another_format_naming_it():
    with pytest.raises(ValueError, match=r"not a protocol table \(format 'avw-study', expected 'avw-table'\)"):
        Table.from_dict({"format": "avw-study", "id": "t"})
    with pytest.raises(ValueError, match=r"format None"):
        Table.from_dict({})


def test_rows_hold_numbers_with_label_kind_and_extras():
    t = _table()
    assert t.row("ours") == {"label": "ours", "kind": "ours", "med_mm": 1.25, "cc": 0.9876, "seconds": 12.5}
    assert t.row("Rhee 2011") == {
        "label": "Rhee 2011",
        "kind": "paper",
        "med_mm": 0.91,
        "cc": None,
        "source": "Rhee Table 3",
    }
    # NaN (no value) is stored as None, so that the table is valid JSON
    assert t.value("SimpleITK B-spline", "med_mm") is None
    assert t.value("SimpleITK B-spline", "cc") == 0.5
    assert t.value("ours", "mi") is None  # a column the row does not have
    json.dumps(t.to_dict(), allow_nan=False)


def test_add_returns_the_row_it_appended_and_keeps_numbers_unformatted():
    t = Table("t", "T", [Column("ssd", "SSD")])
    row = t.add("a", "ours", {"ssd": 1 / 3, "n": 7})
    assert row is t.rows[-1]
    assert row["ssd"] == 1 / 3 and isinstance(row["n"], int)  # never rounded to the column's decimals


def test_add_refuses_an_unknown_kind():
    t = Table("t", "T", [])
    with pytest.raises(ValueError, match=r"row kind must be one of \('ours', 'paper', 'peer'\), got 'theirs'"):
        t.add("x", "theirs", {})
    assert t.rows == []
    assert ROW_KINDS == ("ours", "paper", "peer")


def test_row_of_a_missing_label_names_the_table_and_its_rows():
    with pytest.raises(KeyError, match=r"table 'table3' has no row 'nope'; its rows are \['ours', 'Rhee 2011', "):
        _table().row("nope")


def test_column_defaults_and_dict():
    c = Column("mi", "MI")
    assert c.to_dict() == {"key": "mi", "label": "MI", "unit": "", "decimals": 2}
    assert Column(**c.to_dict()) == c


def test_every_measure_is_defined_with_its_unit_or_base():
    assert set(DEFINITIONS) == {"med_mm", "marker_med_mm", "ssd", "cc", "mi", "folded_fraction", "seconds"}
    assert all(isinstance(v, str) and v for v in DEFINITIONS.values())
    assert "(mm)" in DEFINITIONS["med_mm"] and "(mm)" in DEFINITIONS["marker_med_mm"]
    assert "Rhee Eq. 4" in DEFINITIONS["ssd"] and "Rhee Eq. 5" in DEFINITIONS["mi"]
    assert "32 × 32" in DEFINITIONS["mi"] and "nats" in DEFINITIONS["mi"]
    assert "≤ 0" in DEFINITIONS["folded_fraction"]
