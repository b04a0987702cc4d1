"""Deformation models: skinning weights and blends, the polyrigid flow, EVD, pose-space deformation.

* :mod:`~deformation.models.skinning` — sparse bone weights, linear blend skinning (Kurihara Eq. 2–3);
* :mod:`~deformation.models.harmonic` — automatic skinning weights, harmonic on a tetrahedral mesh;
* :mod:`~deformation.models.polyrigid` — the bones' motions blended as a one-to-one flow;
* :mod:`~deformation.models.evd` — volume blend deformation and example-based volume deformation (Rhee Eq. 2, 6–7);
* :mod:`~deformation.models.posespace` — RBF pose weights, PSD and WPSD (Kurihara Eq. 6–8, 12–16);
* :mod:`~deformation.models.surface_model` — Kurihara's skeleton-driven surface model;
* :mod:`~deformation.models.posed_template` — a template posed to any pose: forward map, backward map, resampling.
"""
