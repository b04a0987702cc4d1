"""Articulated initialisation of the registration (Rhee §3.2, Rhee Eq. 2).

:func:`polyrigid_initial_field` — the one-to-one alternative: the bones'
motions blended as a flow (:mod:`deformation.models.polyrigid`), whose backward
map has no fold in the crease where VBD's must fold, and keeps every bone
exactly rigid.

:func:`vbd_initial_field` — VBD (Rhee Eq. 2) of the template to a scan's
pose, as the ``scan_to_template`` field on the scan grid that
:func:`registration.adaptive.register_adaptive` starts from, by the Newton
backward map of :mod:`deformation.fields.resample` (seeded by the bones' rigid
transforms, so large articulated motions converge).  The inverse of a
registration's field is :func:`deformation.fields.resample.invert_scan_to_template`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from deformation.fields.displacement import unfold as unfold_field
from deformation.fields.resample import backward_map
from deformation.geometry import GridGeometry, Volume, from_every
from deformation.models.evd import vbd_forward

if TYPE_CHECKING:
    from deformation.models.polyrigid import PolyrigidFlow

__all__ = ["vbd_initial_field", "polyrigid_initial_field", "mapped_voxels"]


def polyrigid_initial_field(
    template_labels: Volume,
    bone_labels: dict,
    parents: dict,
    transforms: dict,
    scan_geometry: GridGeometry,
    *,
    power: float = 4.0,
    falloff_mm: float = 20.0,
    factor: int = 1,
    progress=None,
) -> tuple[Volume, PolyrigidFlow]:
    """``scan_to_template`` field of the polyrigid flow on the scan grid, and the flow (for its forward map).

    ``bone_labels`` ``{bone: label id}`` and ``parents`` ``{bone: parent bone or None}`` describe the
    skeleton; ``transforms`` ``{bone: 4x4 template → scan}`` the scan's (estimated) pose.  The weights are
    the distance weights of :func:`deformation.models.skinning.distance_weights` (``power``, ``falloff_mm``), taken
    to the bones where they are at each moment of the motion.  ``factor`` and ``progress``: see
    :meth:`deformation.models.polyrigid.PolyrigidFlow.scan_to_template` (a big scan grid).
    """
    from deformation.models.polyrigid import PolyrigidFlow, bone_distance_maps

    order = list(bone_labels)
    missing = [b for b in order if b not in transforms]
    if missing:
        raise ValueError(f"the pose has no transform for bones {missing}")
    # parents before children, as the flow composes the skeleton's motions from the root down
    ranked, seen = [], set()
    while len(ranked) < len(order):
        progressed = False
        for b in order:
            p = parents.get(b)
            if b not in seen and (p is None or p in seen):
                ranked.append(b)
                seen.add(b)
                progressed = True
        if not progressed:
            raise ValueError(f"the skeleton's parents form a cycle or name unknown bones: {parents}")
    maps = bone_distance_maps(template_labels, {b: bone_labels[b] for b in ranked})
    par = tuple(-1 if parents.get(b) is None else ranked.index(parents[b]) for b in ranked)
    flow = PolyrigidFlow(
        np.stack([np.asarray(transforms[b], float) for b in ranked]),
        par,
        maps,
        template_labels.geometry,
        power=power,
        falloff_mm=falloff_mm,
    )
    return flow.scan_to_template(scan_geometry, factor=factor, progress=progress), flow


def vbd_initial_field(
    template_geometry: GridGeometry,
    scan_geometry: GridGeometry,
    weights,
    transforms,
    *,
    body=None,
    unfold: bool = False,
    factor: int = 1,
) -> tuple[Volume, dict]:
    """``scan_to_template`` field of VBD (Rhee Eq. 2) on the scan grid, and the backward map's summary.

    ``transforms`` ``(n_bones, 4, 4)`` template → scan, in ``weights.bones``
    order; ``body`` (template-grid bool array) prefers tissue where the blend
    is not one-to-one.

    Where the linear blend is many-to-one (the crease of a flexed joint) its
    inverse must jump between the two sheets of tissue, and the field folds
    (on a fraction of a percent of the body's voxels: registration-settings.md, "initialise").
    ``unfold=True`` repairs those voxels with :func:`deformation.fields.displacement.unfold`
    (the summary gains an ``unfold`` entry) wherever the map sends a voxel
    into the template (the others, below, are left as they are); this makes the field one-to-one there
    at a cost in accuracy, since the repaired band maps to tissue between the
    two sheets (most where the creases lie between thin fingers; the
    measurements: docs/measurements/pose-and-initialisation.md).

    Scan voxels the map finds no preimage for (status OUTSIDE: beyond the posed template's box, or in a gap of
    the blend's image) take the displacement of the nearest voxel it did not leave outside (Euclidean distance in
    mm, SciPy's distance transform), not the position a search happened to end at; with ``factor`` f > 1 they
    keep the coarse map's clamped positions.

    ``factor`` f > 1: ``weights`` and ``body`` are on every f-th template voxel
    (``workbench weights --grid-factor``, a big template); the maps are solved
    on every f-th voxel of both grids and the field blended up to the scan's
    full grid a slab at a time (:class:`deformation.fields.resample.CoarseBackwardMap`).
    """
    f = int(factor)
    t = np.asarray(transforms, float)
    fwd = vbd_forward(template_geometry.every(f), weights, t)  # Rhee Eq. 2: every template voxel posed by VBD
    bm = backward_map(
        fwd,
        template_geometry.every(f),
        scan_geometry.every(f),
        transforms=t,
        prefer=None if body is None else np.asarray(body, bool),
    )
    del fwd
    coarse = bm
    if f > 1:
        from deformation.fields.resample import CoarseBackwardMap

        bm = CoarseBackwardMap(bm, f, template_geometry, scan_geometry)
    field, summary = bm.scan_to_template(), bm.summary()
    if f == 1:  # on every f-th voxel the coarse map's blend decides the fine voxels' status: not extended there
        _extend_outside(field, bm.status)
    if unfold:
        # the folds repaired are those of the map where it has a preimage: where it has none (status OUTSIDE,
        # extended from the nearest voxel that has one, or clamped at f > 1) and next to such voxels the field
        # is not the blend's (registration-settings.md, "initialise")
        mapped = mapped_voxels(coarse, f, scan_geometry)
        del bm, coarse  # the map (17 B a voxel at f = 1) is not needed by the repair
        field, summary["unfold"] = unfold_field(field, mask=mapped)
    return field, summary


def _extend_outside(field: Volume, status: np.ndarray) -> None:
    """Where the backward map left a scan voxel OUTSIDE (no preimage in the template: beyond the posed template's
    box, or in a gap of the blend's image), the field takes the displacement of the nearest voxel it did not
    (Euclidean distance in mm; in place): the start continues the map it knows instead of whatever position a
    search ended at."""
    from scipy import ndimage as ndi

    from deformation.fields.resample import OUTSIDE

    outside = status == OUTSIDE
    if not outside.any() or outside.all():
        return
    # sampling in the array's axis order (z, y, x)
    idx = ndi.distance_transform_edt(
        outside, sampling=field.geometry.spacing[::-1], return_distances=False, return_indices=True
    )
    field.data[outside] = field.data[tuple(i[outside] for i in idx)]


def mapped_voxels(coarse_map, f: int, scan_geometry: GridGeometry) -> np.ndarray:
    """Scan voxels the backward map sends into the template, less one voxel around those it does not
    (solved on every f-th voxel: each coarse voxel's answer given to the f³ fine voxels from it onwards)."""
    from scipy import ndimage as ndi

    from deformation.fields.resample import OUTSIDE

    inside = ~ndi.binary_dilation(coarse_map.status == OUTSIDE, structure=np.ones((3, 3, 3), dtype=bool))
    return inside if f == 1 else from_every(inside, f, scan_geometry.array_shape)
