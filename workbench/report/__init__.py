"""The HTML validation report: one self-contained file a reviewer can open offline.

:func:`study_report` builds it for a study folder after the pipeline ran (the ``report`` stage calls it, so
``workbench run`` ends with it):

* **poses** — each scan's joint angles, each joint's Kurihara Eq. 1 residual, the bones the pose stage flagged;
* **registration** — per scan: similarity (SSD, CC, MI) of the start and the result, the folded voxels, the
  convergence of each level (each level's objective per taken step for the dense method, the metric per accepted
  step for Rhee's Algorithm 1), a control-point or correction map;
* **overlays** — the registered template (green) over its target (magenta) on three index planes, with a
  toggle/flicker between the two greyscale pictures, and the start beside it;
* **with ground truth** — the validate stage's rows (MED over body voxels, marker MED, SSD, CC, MI, folded
  fraction), MED maps as slices, each marker's error;
* **renders** — pictures and animations the user put in the study's ``renders/`` folder
  (``workbench render STUDY --out STUDY/renders/x.png``,
  ``workbench animate STUDY --out STUDY/renders/bend.mp4``), videos up to 3 MB embedded whole;
* **provenance** — software versions, every stage's settings, the study digest (SHA-256 over the recorded outputs
  of every stage).

The report holds no time, date, host or machine name (the times are in ``study.json``'s entries:
``workbench info``), so the same results give the same bytes.

:func:`tables_report` builds it for a ``workbench reproduce`` folder: every table with its definitions and notes,
then a compact section for each phantom study it ran on.
"""

from __future__ import annotations

import hashlib
import json
import platform
from pathlib import Path

import numpy as np

from . import figures as F
from .html import Page, esc, table_html

__all__ = [
    "study_report",
    "tables_report",
    "study_digest",
    "software_versions",
    "RENDER_SUFFIXES",
    "control_points",
    "renders_section",
]

MAX_SCANS_COMPACT = 1  # scans shown with pictures per study in a reproduce folder's report


def software_versions() -> dict:
    """The versions of Python and the packages the results depend on (not the machine's: the report of the same
    results is the same bytes on another kernel or host)."""
    from importlib import metadata

    from workbench import __version__

    out = {"workbench": __version__, "python": platform.python_version()}
    for pkg in ("numpy", "scipy", "SimpleITK", "vtk", "open3d", "matplotlib", "numba", "nlopt", "itk-elastix"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


def study_digest(study) -> str:
    """SHA-256 over every stage entry's ``outputs_digest`` (per scan where per scan) but the report's own,
    canonical JSON."""
    doc = {}
    for name, e in sorted((study.manifest.get("stages") or {}).items()):
        if name == "report":  # the report itself is not part of what it reports on
            continue
        if "scans" in e:
            doc[name] = {s: v.get("outputs_digest") for s, v in sorted(e["scans"].items())}
        else:
            doc[name] = e.get("outputs_digest")
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


# -- sections --------------------------------------------------------------------------------------
def _pose_section(page: Page, study) -> None:
    if not study.has_output("pose", "joints.json"):
        return
    parts = page.section("Bone poses and joints")
    joints = json.loads(study.output("pose", "joints.json").read_text(encoding="utf-8"))
    rep = study.pose_report()
    rms = rep.get("eq1_rms_mm")
    rms_text = "not estimated (no joint moved enough)" if rms is None else f"{rms:.2f} mm"
    parts.append(
        f"<p>Method: {esc(rep.get('method'))}; Kurihara Eq. 1 RMS residual over all joints and moving "
        f"scans: <b>{rms_text}</b> (Kurihara's hand: 0.91 mm).</p>"
    )
    rows = [
        [
            n,
            j["dof"],
            j.get("rms_mm"),
            j.get("n_motions"),
            "yes" if j.get("estimated") else "kept",
            "hinge" if j.get("is_hinge") else "",
        ]
        for n, j in joints["joints"].items()
    ]
    parts.append(
        table_html(
            ["joint", "DOF", "Kurihara Eq. 1 RMS (mm)", "scans", "centre estimated", "kind"],
            rows,
            decimals=[0, 0, 2, 0, 0, 0],
        )
    )
    ids = [s for s in study.scan_ids if study.has_pose(s)]
    if ids:
        names = [j.name for j in study.skeleton().joints]
        rows = []
        for n in names:
            row = [n]
            for s in ids:
                a = (study.pose(s).joint_angles or {}).get(n)
                row.append("" if a is None else " / ".join(f"{v:.1f}" for v in np.asarray(a, float)[:3]))
            rows.append(row)
        parts.append("<h3>Joint angles (degrees: flexion / abduction / twist, intrinsic XYZ in the joint frame)</h3>")
        parts.append(table_html(["joint", *ids], rows, decimals=[0] * (len(ids) + 1)))
    failures = rep.get("failures") or []
    if failures:
        parts.append('<p class="bad">Bones the pose stage flagged (not used for joint centres and angles):</p>')
        parts.append(
            table_html(
                ["scan", "bone", "status", "why"],
                [[f.get("scan"), f.get("bone"), f.get("status"), f.get("stop")] for f in failures],
                decimals=[0, 0, 0, 0],
            )
        )


def _convergence(log: dict) -> bytes | None:
    levels = (log.get("summary") or {}).get("levels")
    if levels and any("lncc" in lv for lv in levels):
        series = {
            f"level {lv['level']} (1/{lv['shrink']})": (np.arange(len(lv["lncc"])), lv["lncc"])
            for lv in levels
            if lv.get("lncc")
        }
        less = (["the skin's term"] if any(lv.get("skin_term") for lv in levels) else []) + (
            ["the membrane energy"] if any(lv.get("noise_share") is not None for lv in levels) else []
        )
        return F.line_plot(
            series,
            xlabel="taken step",
            ylabel=("LNCC" + (" less " + " and ".join(less) if less else "")) + " (higher is better)",
            title="dense registration: each level's objective per taken step",
        )
    steps = (log.get("log") or {}).get("steps") if isinstance(log.get("log"), dict) else None
    if steps:
        y = [s.get("block_after") for s in steps if s.get("accepted", True)]
        if y:
            return F.line_plot(
                {"accepted steps": (np.arange(len(y)), y)},
                xlabel="accepted step",
                ylabel="block metric after",
                title="Rhee Algorithm 1: block metric per step",
            )
    return None


def _scan_pictures(page: Page, study, sid: str, parts: list, *, truth: bool) -> None:
    from deformation.fields.displacement import jacobian_determinant
    from registration.metrics import warp_template

    scan = study.scan(sid)
    reg = study.registered(sid)
    corr = study.registration_correspondence(sid)
    init = study.init_field(sid)
    template = study.template()
    body = err = None
    if truth:  # the validate stage's maps: no stage but validate reads the truth
        err_vol, body_vol = study.validation_maps(sid)
        err, body = np.asarray(err_vol.data, np.float64), np.asarray(body_vol.data).astype(bool)
    lo_hi = F.robust(scan.data)
    content = np.asarray(scan.data) > lo_hi[0] + 0.15 * (lo_hi[1] - lo_hi[0])
    at = F.centre_index(body if body is not None and body.any() else content)
    sp = scan.geometry.spacing
    win_t = F.robust(template.data)
    start = warp_template(template, init) if init is not None else None
    figs = []
    for which in F.PLANES:
        ts, px = F.plane(scan.data, sp, which, at)
        rs, _ = F.plane(reg.data, sp, which, at)
        figs.append(
            page.image(
                F.encode_jpeg(F.overlay(ts, rs, px, (lo_hi, win_t))),
                f"{sid}, {which} plane: registered template (green) over the scan (magenta)",
            )
        )
        figs.append(
            page.toggle(
                F.encode_jpeg(F.grey(rs, px, win_t)),
                F.encode_jpeg(F.grey(ts, px, lo_hi)),
                f"{sid}, {which}: toggle or flicker between the registered template and the scan",
            )
        )
    if start is not None:
        ts, px = F.plane(scan.data, sp, "yz", at)
        ss, _ = F.plane(start.data, sp, "yz", at)
        figs.append(
            page.image(
                F.encode_jpeg(F.overlay(ts, ss, px, (lo_hi, win_t))),
                f"{sid}, yz plane: the start (articulated initialisation, green) over the scan",
            )
        )
    # where the registration moved the start: |correction| (a control-point map for Rhee's method)
    d = corr.data if init is None else corr.data - init.data
    mag = np.linalg.norm(np.asarray(d, np.float64), axis=-1)
    vmax = float(max(np.percentile(mag, 99.5), 1e-3))
    ms, px = F.plane(mag, sp, "yz", at)
    figs.append(
        page.image(
            F.encode_png(F.colour_map(ms, px, 0.0, vmax, cmap="viridis")),
            f"{sid}, yz plane: the registration's own displacement beyond its start, 0–{vmax:.1f} mm",
        )
    )
    det = jacobian_determinant(corr)
    folded = det <= 0
    ds, px = F.plane(np.clip(det, 0, 2), sp, "yz", at)
    figs.append(
        page.image(
            F.encode_png(F.colour_map(ds, px, 0.0, 2.0, cmap="coolwarm")),
            f"{sid}, yz plane: Jacobian determinant 0–2 (blue compresses, red expands); "
            f"{int(folded.sum())} voxels of the grid with det ≤ 0",
        )
    )
    sigma = study.registration_uncertainty(sid)
    if sigma is not None:  # the dense registration's expected error (registration.posterior)
        sv = np.asarray(sigma.data, np.float64)
        smax = float(max(np.percentile(sv, 99.5), 1e-3))
        ss, px = F.plane(sv, sp, "yz", at)
        cs, _ = F.plane(content, sp, "yz", at)
        ts, _ = F.plane(scan.data, sp, "yz", at)
        figs.append(
            page.image(
                F.encode_png(F.colour_map(ss, px, 0.0, smax, cmap="magma", mask=cs, background=ts, window=lo_hi)),
                f"{sid}, yz plane: the registration's expected error σ over the scan's tissue, 0–{smax:.2f} mm "
                "(magma; small where the images measured the correction, the prior's where they are silent)",
            )
        )
    if truth:
        emax = float(max(np.percentile(err[body], 99), 0.5)) if body.any() else 1.0
        for which in ("xy", "yz"):
            es, px = F.plane(err, sp, which, at)
            bs, _ = F.plane(body, sp, which, at)
            ts, _ = F.plane(scan.data, sp, which, at)
            figs.append(
                page.image(
                    F.encode_png(F.colour_map(es, px, 0.0, emax, mask=bs, background=ts, window=lo_hi)),
                    f"{sid}, {which}: error |recovered − true| template position over the body, "
                    f"0–{emax:.1f} mm (magma; grey outside the body)",
                )
            )
    if truth and sigma is not None:
        cal = (study.validation(sid) or {}).get("uncertainty") or {}
        if cal.get("bins") and cal.get("spearman") is not None:  # (a constant σ or error has no rank correlation)
            b = np.asarray(cal["bins"], float)
            top = float(max(b.max(), 1e-3)) * 1.05
            figs.append(
                page.image(
                    F.line_plot(
                        {"per σ decile": (b[:, 0], b[:, 1]), "calibrated (error = σ)": ([0.0, top], [0.0, top])},
                        xlabel="expected error σ (mm), decile mean",
                        ylabel="true error (mm), decile RMS",
                        title=f"calibration: {100 * cal['within_2sigma']:.0f} % within 2σ,\nRMS error / RMS σ "
                        f"{cal['rms_ratio']:.2f}, rank correlation {cal['spearman']:.2f}",
                    ),
                    f"{sid}: the expected error against the true error over the body, binned by σ",
                )
            )
    parts.append('<div class="figs">' + "".join(figs) + "</div>")


def _registration_section(page: Page, study, scans, *, pictures: bool = True, heading: str = "Registration") -> None:
    parts = page.section(heading)
    rows = []
    for sid in scans:
        if not study.has_registration(sid):
            continue
        log = study.registration_log(sid)
        s = log.get("summary") or {}
        b, a = s.get("similarity_before") or {}, s.get("similarity_after") or {}
        f = s.get("folding") or {}
        rows.append(
            [
                sid,
                s.get("init"),
                b.get("ssd"),
                a.get("ssd"),
                b.get("cc"),
                a.get("cc"),
                b.get("mi"),
                a.get("mi"),
                f.get("n_folded"),
            ]
        )
    parts.append(
        "<p>Similarity of the scan and the template resampled through the start (before) and the result "
        "(after), over the whole scan grid: SSD mean squared difference (intensity units²), CC Pearson, MI "
        "nats with 32 bins. Folded: voxels with Jacobian determinant ≤ 0 as the registration counted them "
        "(over the scan's body for the dense method, the whole grid for Rhee's).</p>"
    )
    parts.append(
        table_html(
            ["scan", "start", "SSD before", "SSD after", "CC before", "CC after", "MI before", "MI after", "folded"],
            rows,
            decimals=[0, 0, 1, 1, 3, 3, 3, 3, 0],
        )
    )
    for sid in scans:
        if not study.has_registration(sid):
            continue
        truth = study.has_truth(sid) and study.has_output("validate", "error_mm.nii.gz", sid)
        parts.append(f"<h3>{esc(sid)}</h3>")
        if truth:
            v = study.validation(sid)["rows"]
            names = [k for k in ("source", "initialised", "registered") if k in v]
            parts.append(
                table_html(
                    ["volume", "MED (mm)", "marker MED (mm)", "SSD", "CC", "MI (nats)", "folded"],
                    [
                        [
                            n,
                            v[n].get("med_mm"),
                            v[n].get("marker_med_mm"),
                            v[n].get("ssd"),
                            v[n].get("cc"),
                            v[n].get("mi"),
                            v[n].get("folded_fraction"),
                        ]
                        for n in names
                    ],
                    decimals=[0, 2, 2, 1, 3, 3, 5],
                    caption="against the ground truth (validate stage): MED over the scan's body "
                    "voxels; folded = fraction of body voxels with det ≤ 0",
                )
            )
        figs = []
        conv = _convergence(study.registration_log(sid))
        if conv is not None:
            figs.append(page.image(conv, f"{sid}: convergence"))
        markers = study.validation(sid).get("markers") if truth else None
        if markers:
            e = [m["error_mm"] for m in markers]
            figs.append(
                page.image(
                    F.bar_plot(
                        [m["name"] for m in markers],
                        e,
                        ylabel="error (mm)",
                        reference=float(np.mean(e)),
                        title=f"{sid}: marker errors (dashed: their mean)",
                    ),
                    f"{sid}: each skin marker's |recovered − true| template position",
                )
            )
        if pictures:
            cp = control_points(study, sid)
            if cp is not None:
                figs.append(page.image(*cp))
        if figs:
            parts.append('<div class="figs">' + "".join(figs) + "</div>")
        if pictures:
            _scan_pictures(page, study, sid, parts, truth=truth)


def control_points(study, sid: str):
    """``(png, caption)``: the control points of every accepted step of Rhee's Algorithm 1, coloured by block
    level and projected on the scan's yz plane through its centre (Rhee Fig. 9), or None (another method)."""
    from registration.adaptive import control_points_from_log

    log = study.registration_log(sid)
    inner = log.get("log")
    if not isinstance(inner, dict) or not inner.get("steps") or "settings" not in inner:
        return None
    scan = study.scan(sid)
    g = scan.geometry
    cps = control_points_from_log(inner, g)
    if not cps:
        return None
    levels = np.concatenate([np.full(len(p), lv) for lv, p in cps])
    ijk = g.world_to_index(np.concatenate([p for _, p in cps]))
    lo_hi = F.robust(scan.data)
    at = F.centre_index(np.asarray(scan.data) > lo_hi[0] + 0.15 * (lo_hi[1] - lo_hi[0]))
    sl, px = F.plane(scan.data, g.spacing, "yz", at)
    png = F.points_plot(
        sl,
        px,
        F.plane_point_coordinates(ijk, g.spacing, "yz"),
        levels,
        lo_hi,
        title=f"{sid}: control points of the accepted steps",
    )
    return png, (
        f"{sid}: the 8 control points of each accepted step of Rhee's Algorithm 1 ({len(cps)} steps), "
        f"by block level, projected on the yz plane over the scan's middle slice (Rhee Fig. 9)"
    )


#: what the report embeds from a study's renders/ folder (workbench render / workbench animate outputs)
RENDER_SUFFIXES = (".png", ".jpg", ".jpeg", ".gif", ".mp4")


def renders_section(page: Page, study) -> None:
    folder = study.root / "renders"
    files = sorted(p for p in folder.glob("*") if p.suffix.lower() in RENDER_SUFFIXES) if folder.is_dir() else []
    if not files:
        return
    parts = page.section("Renders")
    figs = []
    for p in files:
        data = p.read_bytes()
        if len(data) > 3 * 2**20:
            parts.append(f'<p class="note">{esc(p.name)}: {len(data) / 2**20:.1f} MB, not embedded (over 3 MB)</p>')
            continue
        try:
            figs.append(page.video(data, p.name) if p.suffix.lower() == ".mp4" else page.image(data, p.name))
        except ValueError:  # named .png but not a picture: said in the report, the rest still built
            parts.append(f'<p class="bad">{esc(p)}: not a PNG, JPEG or GIF picture or an MP4 video; not embedded</p>')
    parts.append('<div class="figs">' + "".join(figs) + "</div>")


def _provenance(page: Page, study=None, extra: dict | None = None) -> None:
    parts = page.section("Software, parameters and digest")
    v = software_versions()
    parts.append(table_html(["software", "version"], [[k, val] for k, val in v.items()], decimals=[0, 0]))
    if study is not None:
        rows = []
        for name, e in (study.manifest.get("stages") or {}).items():
            entries = e.get("scans", {}) if "scans" in e else {None: e}
            settings = next((x.get("settings") for x in entries.values() if x.get("settings") is not None), None)
            rows.append(
                [
                    name,
                    json.dumps(settings, sort_keys=True) if settings is not None else "",
                    len(entries) if "scans" in e else "",
                ]
            )
        parts.append(table_html(["stage", "settings", "scans"], rows, decimals=[0, 0, 0]))
        parts.append(
            f"<p>Study digest (SHA-256 over every stage's recorded outputs): <code>{study_digest(study)}</code></p>"
        )
    for k, val in (extra or {}).items():
        parts.append(f"<p>{esc(k)}: <code>{esc(val)}</code></p>")
    page.footer.append(
        f"Articulated Volume Workbench {esc(v['workbench'])} — Kurihara &amp; Miyata 2004; "
        "Rhee, Lewis, Neumann &amp; Nayak 2011."
    )


def study_report(study, *, scans=None, pictures: bool = True) -> str:
    """The report of one study (module docstring) as an HTML string."""
    ids = list(scans) if scans is not None else study.scan_ids
    truth = any(study.has_truth(s) for s in ids)
    g = study.template().geometry
    page = Page(
        f"Validation report: {study.manifest.get('name') or study.root.name}",
        f"{len(ids)} scans; template {g.describe()}; {'with' if truth else 'without'} ground truth",
    )
    _pose_section(page, study)
    _registration_section(page, study, ids, pictures=pictures)
    renders_section(page, study)
    _provenance(page, study)
    return page.html()


def _table_section(page: Page, doc: dict) -> None:
    from validation.protocols import Table  # the protocols (and what they import) only for a reproduce folder

    t = Table.from_dict(doc)
    parts = page.section(t.title)
    classes = [r["kind"] if r["kind"] != "ours" else "" for r in t.rows]
    parts.append(
        table_html(
            ["", *[f"{c.label} ({c.unit})" if c.unit else c.label for c in t.columns]],
            [[r["label"], *[r.get(c.key) for c in t.columns]] for r in t.rows],
            decimals=[0, *[c.decimals for c in t.columns]],
            classes=classes,
        )
    )
    if t.definitions:
        parts.append(
            "<dl>" + "".join(f"<dt>{esc(k)}</dt><dd>{esc(v)}</dd>" for k, v in t.definitions.items()) + "</dl>"
        )
    if t.notes:
        parts.append("<ul>" + "".join(f'<li class="note">{esc(n)}</li>' for n in t.notes) + "</ul>")
    cum = t.meta.get("cumulative_variance")
    if cum:
        parts.append(
            page.image(
                F.line_plot(
                    {"library": (np.arange(1, len(cum) + 1), cum)},
                    xlabel="eigenposes",
                    ylabel="share of the variance",
                    title="cumulative variance (Rhee: 10 > 0.90)",
                ),
                "cumulative variance of the hand pose library's principal components",
            )
        )


def tables_report(folder: Path) -> str:
    """The report of a ``workbench reproduce`` folder (module docstring) as an HTML string."""
    from validation.protocols import PROTOCOLS
    from workbench.study import read_study

    folder = Path(folder)
    docs, unreadable = [], []
    for p in sorted(folder.glob("*.json")):
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:  # a table cut short (a run stopped while writing?): named, not fatal
            unreadable.append(f"{p.name}: {e}")
            continue
        if isinstance(d, dict) and d.get("format") == "avw-table":
            docs.append(d)
    order = list(PROTOCOLS)  # the tables in the protocols' order, as `workbench reproduce all` makes them
    docs.sort(key=lambda d: order.index(d["id"]) if d["id"] in order else len(order))
    page = Page(f"Reproduced tables: {folder.name}", f"{len(docs)} tables from {folder}")
    if unreadable:
        parts = page.section("Files not read")
        parts.append(
            '<p class="bad">These JSON files of the folder could not be read and are not in the report '
            "(rerun <code>workbench reproduce</code> for their tables):</p><ul>"
            + "".join(f"<li>{esc(u)}</li>" for u in unreadable)
            + "</ul>"
        )
    for d in docs:
        _table_section(page, d)
    studies = (
        sorted(p.parent for p in (folder / "studies").glob("*/study.json")) if (folder / "studies").is_dir() else []
    )
    for root in studies:
        study = read_study(root)
        done = [s for s in study.scan_ids if study.has_registration(s)]
        if not done:
            continue
        _registration_section(page, study, done[-MAX_SCANS_COMPACT:], heading=f"Study {root.name}")
        page.sections[-1][2].insert(
            0,
            f"<p>{len(done)} registered scans; below, the last ({esc(done[-1])}); the "
            f"whole study's report: <code>workbench report {esc(root)} --out {esc(root.name)}.html</code>.</p>",
        )
    _provenance(page, extra={"folder": str(folder)})
    return page.html()
