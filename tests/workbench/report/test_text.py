"""The Markdown table of a study's registrations (workbench.report.text.format_registration_table).

The study is a stand-in holding what the function reads: the registration log's summary, the register stage's
entry (its seconds) and, for a validated scan, the validate stage's rows.
"""

from __future__ import annotations

from workbench.report.text import format_registration_table

HEADER = "| scan | volume | MED mm | marker MED mm | SSD | CC | MI | folded | control pts | s |"


class _Study:
    def __init__(self, logs: dict, seconds: dict, validated: dict):
        self.logs, self.seconds, self.validated = logs, seconds, validated

    def has_registration(self, sid):
        return sid in self.logs

    def registration_log(self, sid):
        return {"summary": self.logs[sid]}

    def stage_entry(self, stage, sid):
        assert stage == "register"
        return {"seconds": self.seconds[sid], "digest": "0" * 64}

    def has_output(self, stage, name, sid):
        return stage == "validate" and name == "measures.json" and sid in self.validated

    def validation(self, sid):
        return {"rows": self.validated[sid]}


def _study() -> _Study:
    logs = {
        "pose00": {  # validated (truth): the validate stage's rows
            "control_points": 1234,
            "similarity_before": {"ssd": 1.0, "cc": 0.1, "mi": 0.1},
            "similarity_after": {"ssd": 1.0, "cc": 0.1, "mi": 0.1},
            "folding": {"fraction_folded": 0.5},
        },
        "pose01": {  # no truth: the similarity before and after, no MED
            "control_points": None,  # the dense method has none
            "similarity_before": {"ssd": 812.345, "cc": 0.81234, "mi": 0.45678},
            "similarity_after": {"ssd": 101.25, "cc": 0.98765, "mi": 1.23456, "nmi": 0.5},
            "folding": {"fraction_folded": 0.000125},
        },
    }
    validated = {
        "pose00": {
            "source": {
                "med_mm": 9.8765,
                "marker_med_mm": 10.5,
                "ssd": 900.04,
                "cc": 0.7,
                "mi": 0.3,
                "folded_fraction": 0.0,
            },
            "initialised": {
                "med_mm": 2.345,
                "marker_med_mm": float("nan"),
                "ssd": 300.0,
                "cc": 0.9,
                "mi": 0.8,
                "folded_fraction": 0.00123,
            },
            "registered": {
                "med_mm": 0.875,
                "marker_med_mm": 1.005,
                "ssd": 50.55,
                "cc": 0.99949,
                "mi": 1.5,
                "folded_fraction": 0.0,
            },
        }
    }
    return _Study(logs, {"pose00": 12.5, "pose01": 3.25}, validated)


def test_validated_scan_rows_carry_the_validate_stage_measures():
    lines = format_registration_table(_study(), ["pose00"]).splitlines()
    assert lines[0] == HEADER
    assert lines[1] == "|---|---|---|---|---|---|---|---|---|---|"
    assert lines[2:5] == [
        "| pose00 | source | 9.88 | 10.50 | 900.0 | 0.700 | 0.300 | 0.0000 |  |  |",
        # NaN (a measure without value) is an empty cell
        "| pose00 | initialised | 2.35 |  | 300.0 | 0.900 | 0.800 | 0.0012 |  |  |",
        # only the registered row has the control points and the seconds
        "| pose00 | registered | 0.88 | 1.00 | 50.5 | 0.999 | 1.500 | 0.0000 | 1234 | 12.5 |",
    ]
    assert len(lines) == 6 and lines[5].startswith("(MED: mean ")


def test_unvalidated_scan_rows_are_the_similarity_before_and_after_without_med():
    lines = format_registration_table(_study(), ["pose01"]).splitlines()
    assert lines[2:4] == [
        "| pose01 | before |  |  | 812.3 | 0.812 | 0.457 |  |  |  |",
        "| pose01 | registered |  |  | 101.2 | 0.988 | 1.235 | 0.0001 |  | 3.25 |",
    ]
    assert len(lines) == 5


def test_one_block_per_scan_in_the_order_given_and_unregistered_scans_left_out():
    text = format_registration_table(_study(), ["pose01", "pose07", "pose00"])
    scans = [ln.split("|")[1].strip() for ln in text.splitlines()[2:-1]]
    assert scans == ["pose01", "pose01", "pose00", "pose00", "pose00"]
    assert "pose07" not in text


def test_no_registration_leaves_the_header_and_the_legend():
    lines = format_registration_table(_study(), []).splitlines()
    assert lines[0] == HEADER and len(lines) == 3
    legend = lines[2]
    assert "MI in nats, 32 bins" in legend and "det ≤ 0" in legend


def test_every_row_has_the_header_s_ten_cells():
    for line in format_registration_table(_study(), ["pose00", "pose01"]).splitlines()[:-1]:
        assert line.count("|") == 11, line
