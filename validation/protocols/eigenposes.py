"""Eigenposes of a hand pose library (Rhee et al. 2011, §6.2).

Rhee §6.2: of "60 different meaningful poses from the Poser character
system", "the 10 dominant eigenposes covered more than 90 % of the
variation".  Here the library is :mod:`validation.protocols.hand_poses` (71
grasp, sign and gesture poses with their sources, within normal ranges of
motion); each pose is the vector of the hand skeleton's finger and thumb
joint rotations (degrees; the wrist and the 6-DOF joints' translations left
out, as Santello et al. 1998 analysed finger angles).  The eigenposes are the
principal components of the centred pose matrix (``numpy.linalg.svd``);
their share of the variance is ``σ_i² / Σ σ²``.

Besides the variance a generalisation figure: each pose left out in turn,
the components of the others reconstruct it from its projection onto the
first ``k``; the RMS joint-angle error (degrees) says how well ``k``
eigenposes describe a pose they were not computed from.
"""

from __future__ import annotations

import numpy as np

from .hand_poses import LIBRARY, check_range, library_angles
from .table import Column, Table

__all__ = ["eigenposes", "pose_matrix", "explained_variance", "loo_reconstruction_rms"]

PAPER_K = 10
PAPER_VARIANCE = 0.90  # "more than 90 %" — a lower bound


def pose_matrix(skeleton, library=None) -> tuple[np.ndarray, list[str], list[str]]:
    """``(n_poses, n_rotations)`` matrix of the library's finger and thumb joint rotations (degrees), with the
    pose names and the column names (``joint[axis]``)."""
    entries = library_angles(skeleton) if library is None else library
    cols = [(j.name, a) for j in skeleton.joints if j.name != "wrist" for a in range(3)]
    x = np.array([[np.asarray(ang[j], float)[a] for j, a in cols] for _, _, ang in entries])
    return x, [e[0] for e in entries], [f"{j}[{a}]" for j, a in cols]


def explained_variance(x: np.ndarray) -> np.ndarray:
    """Share of the total variance of each principal component of the rows of ``x`` (descending)."""
    s = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    v = s**2
    return v / v.sum()


def loo_reconstruction_rms(x: np.ndarray, k: int) -> float:
    """RMS error (the units of ``x``) of each row rebuilt from the first ``k`` components of the other rows."""
    err = []
    for i in range(len(x)):
        rest = np.delete(x, i, axis=0)
        mu = rest.mean(axis=0)
        _, _, vt = np.linalg.svd(rest - mu, full_matrices=False)
        basis = vt[:k]
        d = x[i] - mu
        err.append(d - basis.T @ (basis @ d))
    return float(np.sqrt(np.mean(np.square(err))))


def eigenposes(runner=None, *, skeleton=None) -> Table:
    """The eigenpose table (module docstring).  Needs no study: ``skeleton`` defaults to the hand phantom's."""
    if skeleton is None:
        from validation.phantoms import hand

        skeleton = hand.skeleton()
    entries = library_angles(skeleton)
    outside = {name: bad for name, _, ang in entries if (bad := check_range(ang))}
    if outside:
        raise ValueError(f"library poses outside the normal ranges of motion: {outside}")
    x, names, cols = pose_matrix(skeleton, entries)
    var = explained_variance(x)
    cum = np.cumsum(var)
    k90 = int(np.searchsorted(cum, 0.90) + 1)
    t = Table(
        "eigenposes",
        "Eigenposes of a hand pose library (Rhee §6.2)",
        [
            Column("n_poses", "poses", "", 0),
            Column("n_angles", "joint rotations", "", 0),
            Column("components_for_90", "eigenposes for 90 %", "", 0),
            Column("variance_10", "variance in 10 eigenposes", "", 3),
            Column("loo_rms_deg_10", "left-out pose rebuilt from 10 (RMS)", "deg", 2),
        ],
        definitions={
            "variance_10": "Σ of the 10 largest σ_i² over Σ σ² of the centred pose matrix",
            "components_for_90": "fewest principal components whose variance share reaches 0.90",
            "loo_rms_deg_10": "each pose left out, rebuilt from its projection on the first 10 "
            "components of the others: RMS joint-angle error, degrees",
            "library": "71 poses: 33 GRASP-taxonomy grasps (Feix et al. 2016), 26 ASL alphabet "
            "hand shapes, 12 gestures (validation.protocols.hand_poses)",
        },
        notes=[
            "Rhee's 60 poses came from the Poser character system, which is not available; this library's "
            "joint angles are our reading of the published illustrations, within AAOS normal ranges",
            "paper: 'the 10 dominant eigenposes covered more than 90 % of the variation' (a lower bound)",
        ],
    )
    t.add(
        "ours",
        "ours",
        {
            "n_poses": len(x),
            "n_angles": int(np.count_nonzero(x.std(axis=0) > 0)),
            "components_for_90": k90,
            "variance_10": float(cum[PAPER_K - 1]),
            "loo_rms_deg_10": loo_reconstruction_rms(x, PAPER_K),
        },
    )
    t.add(
        "paper (Rhee §6.2, Poser poses)",
        "paper",
        {"n_poses": 60, "variance_10": PAPER_VARIANCE},
        source="Rhee, Lewis, Neumann & Nayak 2011, §6.2",
    )
    t.meta = {
        "cumulative_variance": cum.tolist(),
        "poses": names,
        "sources": {e[0]: e[1] for e in LIBRARY},
        "columns": cols,
        "rms_deg_by_k": {str(k): loo_reconstruction_rms(x, k) for k in (1, 2, 5, 10, 15)},
    }
    return t
