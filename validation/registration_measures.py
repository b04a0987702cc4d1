"""Accuracy of a registration against ground truth (Rhee et al. 2011, §6.1, Tables 2–4).

Every measure compares a recovered ``scan_to_template`` field with the
truth's field of the same convention (both on the scan grid, mm), so MED is
one subtraction:

* **MED** — mean Euclidean distance (mm) between recovered and true template
  positions, over the scan's *body* voxels: those whose true template
  position lies in the template's body (air has no correspondence to
  recover);
* **marker MED** — the same at the skin markers (Rhee Table 3): the recovered
  field is sampled trilinearly at each marker's scan position;
* **SSD, CC, MI** between the scan and the template resampled through the
  field, over the whole grid (:func:`registration.metrics.similarity`:
  mean squared difference, Pearson, nats with 32 bins);
* **folding** — the fraction of body voxels whose Jacobian determinant is
  ≤ 0 (:func:`deformation.fields.displacement.folding_statistics`).
"""

from __future__ import annotations

import numpy as np

from deformation.fields.displacement import folding_statistics
from deformation.fields.interpolate import sample, sample_displaced_array
from deformation.geometry import Volume
from registration.metrics import similarity

__all__ = [
    "uncertainty_calibration",
    "body_on_scan",
    "med",
    "marker_med",
    "marker_errors",
    "error_map",
    "registration_measures",
    "validation_rows",
    "MEASURE_KEYS",
]

MEASURE_KEYS = ("med_mm", "marker_med_mm", "ssd", "cc", "mi", "folded_fraction")


def body_on_scan(truth: Volume, template_body: Volume) -> np.ndarray:
    """Scan voxels whose true template position lies in the template's body mask (nearest voxel)."""
    inside = sample_displaced_array(
        template_body.data.astype(np.uint8),
        template_body.geometry.world_to_index_matrix,
        truth.geometry,
        truth.data,
        0,
        0,
    )
    return np.asarray(inside, bool)


def error_map(field: Volume, truth: Volume, mask: np.ndarray | None = None, *, dtype=np.float32) -> np.ndarray:
    """``|recovered − true|`` template position (mm; computed in float64, returned as ``dtype``) at every voxel
    of the fields' common grid; 0 outside ``mask`` when one is given."""
    field.geometry.check_same(truth.geometry, names=("registration field", "truth field"))
    err = np.linalg.norm(np.asarray(field.data, np.float64) - truth.data, axis=-1).astype(dtype, copy=False)
    if mask is not None:
        err[~np.asarray(mask, bool)] = 0.0
    return err


def med(field: Volume, truth: Volume, mask: np.ndarray) -> float:
    """Mean ``|recovered − true|`` template position (mm) over ``mask`` (fields on one grid; :func:`error_map`)."""
    mask = np.asarray(mask, bool)
    return float(error_map(field, truth, dtype=np.float64)[mask].mean()) if mask.any() else float("nan")


def marker_errors(field: Volume, markers: list) -> np.ndarray:
    """Distance (mm) between each marker's true template position and the field's, at its scan position
    (the field sampled trilinearly)."""
    if not markers:
        return np.zeros(0)
    scan = np.array([m["scan"] for m in markers], float)
    true = np.array([m["template"] for m in markers], float)
    rec = scan + sample(field, scan, order=1, fill=0.0)
    return np.linalg.norm(rec - true, axis=1)


def marker_med(field: Volume, markers: list) -> float:
    """Mean of :func:`marker_errors` (NaN without markers)."""
    return float(marker_errors(field, markers).mean()) if markers else float("nan")


def uncertainty_calibration(error: np.ndarray, sigma: np.ndarray, mask: np.ndarray, bins: int = 10) -> dict:
    """How well a registration's expected error ``sigma`` (mm, :mod:`registration.posterior`) predicts its true
    ``error`` (mm) over ``mask`` (issue R's three measures): the share of voxels whose error is within 2σ
    (σ is the RMS of the error's length, √tr C: a Gaussian error within 2σ 99 % of the time; issue R asks ≥ 85 %),
    RMS(error) / RMS(σ) (1: neither over- nor under-confident), Spearman's rank correlation of σ and the error
    (does σ say where the error is), and per σ decile its mean σ and RMS error (the calibration plot's
    points)."""
    from scipy.stats import spearmanr

    e = np.asarray(error, np.float64)[mask]
    s = np.asarray(sigma, np.float64)[mask]
    if e.size < 2:
        return {"within_2sigma": None, "rms_ratio": None, "spearman": None, "bins": []}
    edges = np.quantile(s, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, bins - 1)
    rows = [
        [float(s[which == b].mean()), float(np.sqrt(np.mean(e[which == b] ** 2)))]
        for b in range(bins)
        if np.any(which == b)
    ]
    rho = spearmanr(s, e).correlation
    return {
        "within_2sigma": float(np.mean(e <= 2.0 * s)),
        "rms_ratio": float(np.sqrt(np.mean(e**2) / max(np.mean(s**2), 1e-30))),
        "spearman": None if not np.isfinite(rho) else float(rho),
        "bins": rows,
    }


def registration_measures(
    scan: Volume,
    registered: Volume,
    field: Volume,
    *,
    truth: Volume | None = None,
    body: np.ndarray | None = None,
    markers: list | None = None,
) -> dict:
    """The measures of the module docstring for one registration (truth-dependent ones NaN without truth)."""
    sim = similarity(scan, registered)
    out = {
        "ssd": sim["ssd"],
        "cc": sim["cc"],
        "mi": sim["mi"],
        "med_mm": float("nan"),
        "marker_med_mm": float("nan"),
        "folded_fraction": float("nan"),
    }
    if truth is not None and body is not None:
        out["med_mm"] = med(field, truth, body)
        out["folded_fraction"] = folding_statistics(field, body)["fraction_folded"]
    if markers:
        out["marker_med_mm"] = marker_med(field, markers)
    return out


def validation_rows(
    scan: Volume,
    template: Volume,
    *,
    truth: Volume,
    template_body: Volume,
    markers: list,
    registered: Volume,
    field: Volume,
    initial: Volume | None = None,
) -> dict:
    """Rhee's Tables 2–4 rows for one scan: ``source`` (no deformation), ``initialised`` (when ``initial``
    is given) and ``registered``, each with the measures of the module docstring over the same body voxels."""
    from registration.metrics import warp_template

    body = body_on_scan(truth, template_body)
    zero = Volume(np.zeros(truth.data.shape, np.float32), truth.geometry)
    rows = {
        "source": registration_measures(
            scan,
            warp_template(template, zero),
            zero,
            truth=truth,
            body=body,
            markers=markers,
        )
    }
    if initial is not None:
        rows["initialised"] = registration_measures(
            scan,
            warp_template(template, initial),
            initial,
            truth=truth,
            body=body,
            markers=markers,
        )
    rows["registered"] = registration_measures(scan, registered, field, truth=truth, body=body, markers=markers)
    return rows
