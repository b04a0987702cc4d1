"""Leave one scan out: VBD against EVD built from the other scans' registrations (Rhee §5–6.2, Figs. 11–12).

Rhee Figs. 11–12 show, for a scan left out of the training set, the template
deformed to its pose by VBD (Rhee Eq. 2) and by EVD (Rhee Eq. 6) beside the
scan; here the same comparison is measured against the phantom's truth.  The
knee (4 poses) and hand (10 poses) studies are the ones of Tables 3 and 4
(:mod:`validation.protocols.registration`): their registrations are reused.

For each scan ``k``: an EVD model (Rhee Eq. 7) from the *other* scans'
registrations and estimated poses — the way the pipeline's ``model`` stage
builds it, template voxels the inverse did not find kept at VBD
(:func:`validation.leave_one_out.registration_training_positions`) — is asked for scan ``k``'s
estimated pose, and so is VBD with the same weights
(:func:`validation.leave_one_out.leave_one_out_correspondences`):

* MED: mean ``|F(v) − F_true(v)|`` over the template's body voxels (mm),
  ``F_true`` the phantom's exact template → scan map;
* CC: the posed template resampled onto scan ``k``'s grid, correlated with
  the scan (whole grid).

A third row builds EVD from the *true* correspondences of the other scans
(same estimated poses): the model's ceiling, which separates what the model
cannot interpolate from what the registrations got wrong.
"""

from __future__ import annotations

import numpy as np

from .registration import PHANTOMS
from .table import Column, Table

__all__ = ["loo", "COLUMNS"]

COLUMNS = [
    Column("med_mm", "MED", "mm"),
    Column("cc", "CC", "", 3),
    Column("evd_better_med", "EVD better on MED", "scans", 0),
    Column("evd_better_cc", "EVD better on CC", "scans", 0),
    Column("n_held_out", "held-out scans", "", 0),
]
REGIONS = (("knee", "table3"), ("hand", "table4"))


def _region_rows(runner, region: str, protocol: str) -> tuple[dict, dict]:
    from validation.leave_one_out import leave_one_out_correspondences, registration_training_positions

    study = runner.study(
        protocol,
        PHANTOMS[protocol],
        settings={"init": {"method": "vbd"}, "weights": {}, "register": {}},
        targets=("validate",),
    )
    template = study.template()
    g = template.geometry
    weights, body = study.weights()
    sk = study.skeleton()
    ids = study.scan_ids
    poses, positions = {}, {}
    for s in ids:
        poses[s], positions[s], _ = registration_training_positions(study, s, g, weights)
    truth = {s: study.truth_template_to_scan(s).data + g.world_coordinates() for s in ids}
    images = {s: study.scan(s) for s in ids}
    runner.say(f"loo {region}: {len(ids)} held-out scans, EVD from the registrations")
    reg = leave_one_out_correspondences(template, weights, body, sk, poses, positions, truth, images=images)
    runner.say(f"loo {region}: EVD from the true correspondences")
    tru = leave_one_out_correspondences(template, weights, body, sk, poses, truth, truth, images=images)
    return {r.scan: r for r in reg}, {r.scan: r for r in tru}


def loo(runner) -> Table:
    """The leave-one-out table (module docstring), knee and hand."""
    t = Table(
        "loo",
        "Leave one scan out: VBD vs EVD from the other scans' registrations (Rhee Figs. 11–12)",
        list(COLUMNS),
        definitions={
            "med_mm": "mean |predicted − true| template → scan position over the template's body "
            "voxels (mm), the truth the phantom's exact map",
            "cc": "Pearson correlation of the scan with the template posed by the predictor and "
            "resampled onto the scan's grid (whole grid)",
            "evd_better_med": "held-out scans on which EVD's MED is below VBD's",
            "evd_better_cc": "held-out scans on which EVD's CC is above VBD's",
            "VBD": "volume blend deformation (Rhee Eq. 2) at the held-out scan's estimated pose",
            "EVD": "example-based volume deformation (Rhee Eq. 6–7), normalised-RBF pose-space "
            "interpolation of the training scans' displacements, weighted per voxel as "
            "Kurihara's WPSD (Kurihara Eq. 16)",
        },
        notes=[
            "the paper shows these comparisons as pictures only (Figs. 11–12): no published numbers",
            "poses are the pose stage's estimates for training and held-out scans alike; the rest-pose "
            "scan is held out too",
        ],
    )
    meta = {}
    for region, protocol in REGIONS:
        reg, tru = _region_rows(runner, region, protocol)
        ids = list(reg)
        vbd = {
            "med_mm": float(np.mean([reg[s].med_vbd for s in ids])),
            "cc": float(np.mean([reg[s].cc_vbd for s in ids])),
        }
        t.add(f"{region}: VBD", "ours", {**vbd, "n_held_out": len(ids)})
        for name, res in (("EVD from the registrations", reg), ("EVD from the true correspondences", tru)):
            t.add(
                f"{region}: {name}",
                "ours",
                {
                    "med_mm": float(np.mean([res[s].med_evd for s in ids])),
                    "cc": float(np.mean([res[s].cc_evd for s in ids])),
                    "evd_better_med": sum(res[s].med_evd < res[s].med_vbd for s in ids),
                    "evd_better_cc": sum(res[s].cc_evd > res[s].cc_vbd for s in ids),
                    "n_held_out": len(ids),
                },
            )
        meta[region] = {"per_scan": {s: {"registrations": reg[s].to_dict(), "truth": tru[s].to_dict()} for s in ids}}
    t.meta = meta
    return t
