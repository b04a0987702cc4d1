"""The plain-text (Markdown) table of a study's registrations that ``workbench register``, ``validate`` and
``run`` print."""

from __future__ import annotations

__all__ = ["format_registration_table"]


def format_registration_table(study, scans) -> str:
    """One row per scan and volume (source / initialised / registered): the validate stage's measures when the
    scan has truth, else the registration's similarity before and after (MED columns empty)."""
    lines = [
        "| scan | volume | MED mm | marker MED mm | SSD | CC | MI | folded | control pts | s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def num(v, fmt):
        return "" if v is None or v != v else format(v, fmt)

    for sid in scans:
        if not study.has_registration(sid):
            continue
        log = study.registration_log(sid)["summary"]
        e = study.stage_entry("register", sid)
        if study.has_output("validate", "measures.json", sid):
            rows = study.validation(sid)["rows"]
        else:
            b, a = log["similarity_before"], log["similarity_after"]
            rows = {"before": dict(b), "registered": {**a, "folded_fraction": log["folding"].get("fraction_folded")}}
        for name in [k for k in ("source", "before", "initialised", "registered") if k in rows]:
            r, last = rows[name], name == "registered"
            lines.append(
                f"| {sid} | {name} | {num(r.get('med_mm'), '.2f')} | {num(r.get('marker_med_mm'), '.2f')} | "
                f"{num(r.get('ssd'), '.1f')} | {num(r.get('cc'), '.3f')} | {num(r.get('mi'), '.3f')} | "
                f"{num(r.get('folded_fraction'), '.4f')} | {num(log.get('control_points'), 'd') if last else ''} | "
                f"{e['seconds'] if last else ''} |"
            )
    lines.append(
        "(MED: mean |recovered − true| template position over the scan's body voxels; folded: fraction of "
        "body voxels with det ≤ 0 when validated, else as the registration counted it: over the scan's body (dense) "
        "or the whole grid (adaptive); MI in nats, 32 bins)"
    )
    return "\n".join(lines)
