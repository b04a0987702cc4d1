"""Rhee et al. 2011's registration tables (§6.1, Tables 2–4), run through the study stages.

* :func:`table2` — Rhee Table 2: the knee bent 10° by VBD (the template
  image deformed by volume blend deformation, Rhee Eq. 2), registered from
  the identity (no initialisation); one scan.
* :func:`table3` — Rhee Table 3: the knee in 4 poses, the template registered
  to the 3 posed scans after VBD (Rhee Eq. 2) from the *estimated* poses
  (Rhee Eq. 1 bone registration); averaged over the 3 scans.
* :func:`table4` — Rhee Table 4: the hand in 10 poses, the same over the 9
  posed scans.

Each protocol writes (through ``runner``) a phantom study and runs the
pipeline's stages up to ``validate``; the table's rows are the means of the
validate stage's per-scan measures (:mod:`validation.registration_measures`),
with the paper's figures beside them (the ``paper:`` rows).  Beside the
register stage's default method every table has ``registered (Rhee
Algorithm 1, ours)``: :mod:`registration.adaptive` run as ``workbench
register --method adaptive`` would, from the same initialisation, on the
same scans; ``runner.with_peers`` adds elastix's and SimpleITK's B-spline
registrations (:mod:`registration.baselines`).  The template is the
phantom's rest pose, which the first posed scan repeats with its own noise;
Rhee registered the template to the *other* scans, so that scan is left out
of the means.
"""

from __future__ import annotations

import numpy as np

from .table import DEFINITIONS, Column, Table

__all__ = ["table2", "table3", "table4", "PAPER", "ALGORITHM1_ROW", "registration_table", "ssd_scale"]

# Rhee et al. 2011, Tables 2-4 (SSD, CC, MI as printed; MED in mm).
PAPER = {
    "table2": {
        "source": {"med_mm": 5.5, "ssd": 21.3, "cc": 0.63, "mi": 0.52},
        "registered": {"med_mm": 3.5, "ssd": 15.6, "cc": 0.80, "mi": 0.73},
    },
    "table3": {
        "source": {"marker_med_mm": 18.5, "ssd": 41.1, "cc": 0.31, "mi": 0.11},
        "initialised": {"marker_med_mm": 5.8, "ssd": 18.3, "cc": 0.72, "mi": 0.55},
        "registered": {"marker_med_mm": 3.8, "ssd": 15.7, "cc": 0.79, "mi": 0.65},
    },
    "table4": {
        "source": {"ssd": 31.6, "cc": 0.01, "mi": 0.07},
        "initialised": {"ssd": 19.4, "cc": 0.53, "mi": 0.23},
        "registered": {"ssd": 17.8, "cc": 0.60, "mi": 0.28},
    },
}
PAPER_SOURCE = "Rhee, Lewis, Neumann & Nayak 2011, §6.1"
COLUMNS = [
    Column("med_mm", "MED", "mm"),
    Column("marker_med_mm", "marker MED", "mm"),
    Column("ssd", "SSD", "", 1),
    Column("cc", "CC", "", 3),
    Column("mi", "MI", "nats", 3),
    Column("folded_fraction", "folded", "", 5),
    Column("seconds", "time", "s", 1),
]
STAGE_ROWS = {"source": "source (no deformation)", "initialised": "initialised", "registered": "registered (ours)"}
#: the row of Rhee's Algorithm 1 as implemented here (registration.adaptive), beside the default method's
ALGORITHM1_ROW = "registered (Rhee Algorithm 1, ours)"
PHANTOMS = {
    # Rhee §6.1: "the knee volume synthetically bent 10 degrees" by VBD; posing="vbd" deforms the template image
    "table2": dict(region="knee", posing="vbd", poses=(("bend10", {"knee": [10.0, 0.0, 0.0]}),)),
    "table3": dict(region="knee", n_poses=4),  # Rhee Table 3: four poses
    "table4": dict(region="hand", n_poses=10),  # Rhee Table 4: ten poses
}


def ssd_scale(template) -> float:
    """The factor that puts a mean squared difference on the papers' 8-bit scale: ``(255 / range)²`` with
    ``range`` the template's 0.5–99.5th percentile span (both images scaled alike; an offset cancels)."""
    lo, hi = np.percentile(np.asarray(template.data, np.float64), [0.5, 99.5])
    return float((255.0 / (hi - lo)) ** 2) if hi > lo else 1.0


def _mean(rows: list[dict], key: str):
    v = np.array([r.get(key) if r.get(key) is not None else np.nan for r in rows], float)
    return float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else None


def _measured(study, sid, template, body, *, registered, field, seconds: float) -> dict:
    """A registration of scan ``sid`` (any method) scored as the validate stage scores the pipeline's: its
    ``registered`` row of :func:`validation.registration_measures.validation_rows`, with its time."""
    from deformation.geometry import Volume
    from validation.registration_measures import validation_rows

    # in float64, as the validate stage reads a stage's field back (workbench.io.volumes.read_displacement): the
    # markers' trilinear samples of a float32 field differ from those in the 9th digit
    field = Volume(np.asarray(field.data, np.float64), field.geometry)
    rows = validation_rows(
        study.scan(sid),
        template,
        truth=study.truth_correspondence(sid),
        template_body=body,
        markers=study.truth_markers(sid),
        registered=registered,
        field=field,
    )
    return {**rows["registered"], "seconds": seconds}


def _algorithm1_rows(runner, study, scans, *, settings: dict) -> tuple[list, dict | None]:
    """Rhee's Algorithm 1 (``runner.register_adaptive``: as ``workbench register --method adaptive`` with the
    register stage's ``settings``) from the study's initialisation, each scan's measures, and the
    :class:`~registration.adaptive.AdaptiveSettings` it ran with (as a dict)."""
    template = study.template()
    _, body = study.weights()
    out, used = [], None
    for sid in scans:
        r = runner.register_adaptive(study, sid, settings=settings)
        out.append(
            _measured(study, sid, template, body, registered=r.registered, field=r.correspondence, seconds=r.seconds)
        )
        used = r.settings.to_dict()
    return out, used


def _peer_rows(study, scans, *, seed: int) -> dict:
    """elastix's and SimpleITK's B-splines from the study's initialisation, each scan's measures."""
    from registration.baselines import elastix_available, elastix_bspline, sitk_bspline

    template = study.template()
    _, body = study.weights()
    peers = {
        "SimpleITK B-spline (MI)": lambda scan, init: sitk_bspline(scan, template, initial=init, metric="mi", seed=seed)
    }
    if elastix_available():
        peers["elastix B-spline (MI)"] = lambda scan, init: elastix_bspline(
            scan, template, initial=init, metric="mi", seed=seed
        )
    out = {name: [] for name in peers}
    for sid in scans:
        scan, init = study.scan(sid), study.init_field(sid)
        for name, run in peers.items():
            b = run(scan, init)
            out[name].append(
                _measured(
                    study, sid, template, body, registered=b.registered, field=b.correspondence, seconds=b.seconds
                )
            )
    return out


def registration_seconds(study, sid: str) -> float:
    """The registration's wall-clock seconds for a scan (the register stage's manifest entry, ``timings``; the
    stage's files hold no time)."""
    return study.stage_entry("register", sid)["timings"]["registration"]


def registration_table(runner, protocol: str, *, title: str, init: str, notes=()) -> Table:
    """Run one of Rhee's registration protocols (module docstring) through ``runner`` and tabulate it."""
    register = {}  # the register stage's settings: its defaults (the dense method); Algorithm 1's row adds method
    study = runner.study(
        protocol,
        PHANTOMS[protocol],
        settings={"init": {"method": init}, "weights": {}, "register": register},
        targets=("validate",),
    )
    scans = study.scan_ids if protocol == "table2" else study.scan_ids[1:]
    measures = [study.validation(s)["rows"] for s in scans]
    seconds = [registration_seconds(study, s) for s in scans]  # as the peers
    scale = ssd_scale(study.template())
    t = Table(
        protocol, title, list(COLUMNS), definitions={c.key: DEFINITIONS[c.key] for c in COLUMNS}, notes=list(notes)
    )
    for stage, label in STAGE_ROWS.items():
        per = [m[stage] for m in measures if stage in m]
        if not per:
            continue
        vals = {k: _mean(per, k) for k in ("med_mm", "marker_med_mm", "ssd", "cc", "mi", "folded_fraction")}
        vals["ssd"] = None if vals["ssd"] is None else vals["ssd"] * scale
        vals["seconds"] = float(np.mean(seconds)) if stage == "registered" else None
        t.add(label, "ours", vals, n_scans=len(per))

    def means(per):
        vals = {k: _mean(per, k) for k in ("med_mm", "marker_med_mm", "ssd", "cc", "mi", "folded_fraction", "seconds")}
        vals["ssd"] = None if vals["ssd"] is None else vals["ssd"] * scale
        return vals

    runner.say(f"{protocol}: Rhee's Algorithm 1 from the same start on {len(scans)} scan(s)")
    per, alg1 = _algorithm1_rows(runner, study, scans, settings=register)
    t.add(ALGORITHM1_ROW, "ours", means(per), n_scans=len(per))
    if alg1 is not None:
        t.notes.append(
            f"{ALGORITHM1_ROW}: Rhee's Algorithm 1 (§4) as this project implements it "
            f"(registration.adaptive), run as `workbench register --method adaptive` would from the same "
            f"start on the same scans (block levels {alg1['levels'][0]}–{alg1['levels'][1]}, "
            f"{alg1['optimizer']}; meta.algorithm1_settings); our run of the algorithm, not the paper's "
            f"figures (the 'paper:' rows)"
        )
    if getattr(runner, "with_peers", False):
        for name, per in _peer_rows(study, scans, seed=0).items():
            t.add(name, "peer", means(per), n_scans=len(per))
    for stage, vals in PAPER[protocol].items():
        t.add(f"paper: {stage}", "paper", {c.key: vals.get(c.key) for c in COLUMNS}, source=PAPER_SOURCE)
    t.meta = {
        "study": str(study.root),
        "scans": list(scans),
        "phantom": study.manifest.get("phantom"),
        "settings": {
            s: study.recorded_settings(s)
            for s in ("pose", "weights", "init", "register")
            if study.recorded_settings(s) is not None
        },
        "ssd_scale": scale,
        "algorithm1_settings": alg1,
    }
    return t


def table2(runner) -> Table:
    """Rhee Table 2 (module docstring)."""
    return registration_table(
        runner,
        "table2",
        init="identity",
        title="Rhee Table 2: the knee bent 10° by VBD, registered without initialisation",
        notes=[
            "one scan: the phantom template deformed by VBD (Rhee Eq. 2) to 10° of knee flexion; the "
            "registration starts from the identity (no initialisation)",
            "MED over the scan's body voxels; the paper's volume was 1.25×1.25×1.2 mm, ours is the phantom's "
            "grid (meta.phantom)",
        ],
    )


def table3(runner) -> Table:
    """Rhee Table 3 (module docstring)."""
    return registration_table(
        runner,
        "table3",
        init="vbd",
        title="Rhee Table 3: the knee in 4 poses, template registered to the other 3 after VBD",
        notes=[
            "initialised: VBD (Rhee Eq. 2) with the estimated bone poses (Rhee Eq. 1) and the pipeline's "
            "skinning weights; rows are means over the 3 posed scans",
            "marker MED over the phantom's 12 skin markers per scan (the paper: 8 MR markers); the paper "
            "reports no MED over the body",
        ],
    )


def table4(runner) -> Table:
    """Rhee Table 4 (module docstring)."""
    return registration_table(
        runner,
        "table4",
        init="vbd",
        title="Rhee Table 4: the hand in 10 poses, template registered to the other 9 after VBD",
        notes=[
            "initialised: VBD (Rhee Eq. 2) with the estimated bone poses (Rhee Eq. 1) and the pipeline's "
            "skinning weights; rows are means over the 9 posed scans",
            "the paper reports SSD, CC and MI only (no MED: a real hand has no ground truth)",
        ],
    )
