"""What ``workbench render`` draws: the volume, labels, second volume and point sets, resolved from files or a study."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from workbench.io.volumes import read_labels, read_volume
from workbench.study import MANIFEST, read_study
from workbench.viz.render import LEVEL_COLOURS, MARKER_COLOUR

__all__ = ["render_inputs"]


def render_inputs(
    source,
    *,
    scan=None,
    registered=None,
    bones: bool = False,
    labels=None,
    overlay=None,
    difference=None,
    markers: bool = False,
    control_points: bool = False,
    progress=None,
) -> tuple:
    """``(volume, labels, other, points)`` to render: an image file, or a study's template / scan (``scan``) /
    registered template (``registered``), its bone labels (``bones``) or a label file (``labels``), a second
    volume for ``overlay`` or ``difference`` (a file or a scan id), and the point sets to draw: the truth's
    skin ``markers`` and a registration's ``control_points`` (Rhee Fig. 9), coloured by block level.

    Every combination is checked before any volume is read; the messages name the command-line options.
    """
    say = progress or (lambda line: None)
    source = Path(source)
    study = read_study(source) if (source / MANIFEST).is_file() else None
    if study is None:
        for flag in ("scan", "registered", "bones"):
            if {"scan": scan, "registered": registered, "bones": bones}[flag]:
                raise ValueError(f"--{flag} needs a study folder; {source} is not one (no {MANIFEST})")
    if scan and registered:
        raise ValueError("--scan and --registered each choose the volume to render: pass one")

    def resolve(ref):
        if study is not None and ref in study.scan_ids:
            return study.scan(ref)
        p = Path(ref)
        if not p.exists():
            hint = f" nor a scan of the study ({', '.join(study.scan_ids)})" if study is not None else ""
            raise FileNotFoundError(f"{ref}: no such file{hint}")
        return read_volume(p)

    label_file, labels = labels, None
    if study is None:
        vol = read_volume(source)
        what = str(source)
    elif scan:
        vol, what = study.scan(scan), f"scan {scan}"
    elif registered:
        study.check_scan_ids([registered])
        if not study.has_registration(registered):
            raise ValueError(
                f"scan {registered!r} has no registration; run `workbench register "
                f"{study.root} --scan {registered}` first"
            )
        vol, what = study.registered(registered), f"template registered to {registered}"
    else:
        vol, what = study.template(), "template"
        if bones:
            if not study.has_template_labels:
                raise ValueError(f"{study.root}: the study has no template label map for --bones")
            labels = study.template_labels()
    if bones and (scan or registered):
        raise ValueError(
            "--bones draws the template's labels: render the template (no --scan/--registered), "
            "or pass --labels FILE on the volume's grid"
        )
    if label_file:
        labels = read_labels(label_file)
    if overlay and difference:
        raise ValueError("--overlay and --difference are two kinds of picture: pass one")
    if (overlay or difference) and labels is not None:
        raise ValueError(
            "--bones/--labels draw surfaces on a single-volume render; leave them out with --overlay or --difference"
        )
    other = resolve(overlay or difference) if (overlay or difference) else None
    say(f"{what}: {vol.geometry.describe()}")
    points = []
    if markers or control_points:
        if study is None:
            raise ValueError("--markers and --control-points need a study folder")
    if markers:
        sid = scan or registered
        ids = [sid] if sid else [s for s in study.scan_ids if study.has_truth(s)]
        if not ids or not study.has_truth(ids[0]):
            raise ValueError(f"--markers: {'scan ' + repr(sid) if sid else 'the study'} has no ground-truth markers")
        key = "scan" if sid else "template"
        pts = np.array([m[key] for m in study.truth_markers(ids[0])], float).reshape(-1, 3)
        points.append((pts, MARKER_COLOUR, 0.8 * max(vol.geometry.spacing)))
        say(f"{len(pts)} skin markers ({key} positions)")
    if control_points:
        if not registered:
            raise ValueError("--control-points draws a registration's control points: pass --registered ID")
        from registration.adaptive import control_points_from_log

        reg_log = study.registration_log(registered)
        if "log" not in reg_log:
            raise ValueError(
                f"scan {registered!r} was registered by {reg_log.get('method', 'a method')}, which has "
                "no control points: --control-points needs `workbench register --method adaptive`"
            )
        cps = control_points_from_log(reg_log["log"], vol.geometry)
        levels = sorted({lv for lv, _ in cps})
        for lv in levels:
            pts = np.concatenate([p for l_, p in cps if l_ == lv])
            colour = LEVEL_COLOURS[(lv - 3) % len(LEVEL_COLOURS)] if lv >= 3 else LEVEL_COLOURS[-1]
            points.append((pts, colour, 0.4 * max(vol.geometry.spacing)))
            say(f"level {lv}: {len(pts)} control points")
    return vol, labels, other, points
