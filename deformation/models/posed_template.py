"""A template posed to any pose: forward map (EVD or VBD), backward map, resampling.

:class:`TemplatePoser` holds a template, its skinning weights, body mask,
labels and (optionally) an EVD model, and deforms the template to a pose:
the forward map of every template voxel — EVD (Rhee Eq. 6) with a model, VBD
(Rhee Eq. 2) without — then the backward map onto a grid (Newton, seeded by
the bones' transforms; :func:`deformation.fields.resample.backward_map`) and
resampling (intensities trilinear, labels nearest).  ``workbench deform``
writes one posed volume, ``workbench animate`` renders many.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from deformation.fields.resample import backward_map, resample_forward
from deformation.geometry import Volume, every_nth
from deformation.models.evd import vbd_forward
from deformation.models.skinning import stack_transforms

__all__ = ["TemplatePoser", "PosedTemplate", "METHODS", "WEIGHTINGS"]

METHODS = ("vbd", "evd")
WEIGHTINGS = ("psd", "wpsd")


@dataclass
class PosedTemplate:
    """The template deformed to one pose, on the template's grid (or the target grid asked for)."""

    volume: Volume
    labels: Volume | None
    backward: (
        object  #: the :class:`~deformation.fields.resample.BackwardMap` (a ``CoarseBackwardMap`` at map factor > 1)
    )
    forward_seconds: float
    backward_seconds: float
    #: with ``pose(..., uncertainty=True)``: the model's expected error (mm) pulled onto the posed grid
    #: (:meth:`~deformation.models.evd.ExampleVolumeDeformation.expected_error`; where no template voxel lands, the
    #: map's largest), None otherwise
    uncertainty: Volume | None = None


class TemplatePoser:
    """Deform a template to poses (see the module docstring).

    Parameters
    ----------
    template : Volume
    weights : SkinningWeights on the body mask's grid: the template's, or every f-th voxel of it
        (:meth:`~deformation.geometry.GridGeometry.every`; ``workbench weights --grid-factor``, for a template
        too big for full-grid weights) — then the maps are always solved on that coarse grid (``map_factor`` f)
    body : Volume, the template's body mask (preferred where the map is many-to-one; its outside gives the
        air value that fills voxels no tissue reaches), on the weights' grid
    labels : Volume, optional, the template's bone labels (posed too)
    model : ExampleVolumeDeformation, optional — with it the method is EVD, without it VBD
    weighting : "psd" (one set of pose weights, Rhee) or "wpsd" (per voxel, Kurihara Eq. 16); EVD only
    """

    def __init__(
        self,
        template: Volume,
        weights,
        body: Volume,
        *,
        labels: Volume | None = None,
        model=None,
        weighting: str = "psd",
        progress=None,
    ):
        if weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
        self.template, self.weights, self.body, self.template_labels = template, weights, body, labels
        self.model = model
        self.weights_factor = _grid_factor(template.geometry, body.geometry)
        if self.weights_factor > 1 and model is not None:
            raise ValueError(
                "an EVD model needs skinning weights on the template's grid (these are on "
                f"{every_nth(self.weights_factor)} voxel)"
            )
        self.method = "evd" if model is not None else "vbd"
        self.weighting = weighting
        f = self.weights_factor
        air = np.asarray(template.data)[::f, ::f, ::f][body.data == 0]
        self.fill = float(np.median(air)) if air.size else float(np.min(template.data))  # the template's air
        self._say = progress or (lambda line: None)

    def forward(self, pose, factor: int | None = None) -> np.ndarray:
        """Posed world positions ``(nz, ny, nx, 3)`` (EVD or VBD) of the template voxels — of every
        ``factor``-th one along each axis (:meth:`~deformation.geometry.GridGeometry.every`) when ``factor`` > 1
        (default: the weights' grid, as ``body``)."""
        factor = self.weights_factor if factor is None else int(factor)
        g = self.template.geometry
        weights, model = self.weights, self.model
        if factor != self.weights_factor:
            g, weights, model = self._coarse(factor)
        elif factor > 1:
            g = g.every(factor)
        if self.method == "evd":
            return model.forward(pose, weighting=self.weighting)  # Rhee Eq. 6
        return vbd_forward(g, weights, stack_transforms(pose.transforms, weights.bones))  # Rhee Eq. 2

    def _coarse(self, factor: int):
        """(grid, weights, model) on every ``factor``-th template voxel, made once per factor (an animation
        poses many frames; the model's subset is 1/factor³ of its displacements)."""
        cache = self.__dict__.setdefault("_coarse_cache", {})
        key = (factor, id(self.weights), id(self.model))  # new weights or model: a new subset
        if key not in cache:
            from deformation.models.skinning import SkinningWeights

            if self.weights_factor != 1:
                raise ValueError(
                    f"the skinning weights are on {every_nth(self.weights_factor)} template voxel: the "
                    f"maps are solved there (map factor {self.weights_factor}, not {factor})"
                )

            shape = self.template.geometry.array_shape  # weights and displacements are rows in array order
            flat = np.arange(int(np.prod(shape))).reshape(shape)[::factor, ::factor, ::factor].ravel()
            g = self.template.geometry.every(factor)
            w = SkinningWeights(self.weights.bones, self.weights.index[flat], self.weights.value[flat])
            model = None
            if self.model is not None:
                model = type(self.model)(
                    g, w, self.model.space, self.model.displacements[flat], template_example=self.model.template_example
                )
            cache[key] = (g, w, model)
        return cache[key]

    def pose(
        self, pose, *, labels: bool = True, target=None, map_factor: int = 1, uncertainty: bool = False
    ) -> PosedTemplate:
        """The template (and labels) posed, on the template's grid or on ``target`` (a GridGeometry); with
        ``uncertainty`` (EVD only) the model's expected error posed too.

        ``map_factor`` f > 1: the forward and backward maps are solved on every f-th voxel of the grids
        (f³ fewer voxels), and the template is pulled at full resolution through the blend of that map
        (:class:`deformation.fields.resample.CoarseBackwardMap`, which never makes the fine map).  With weights on a
        coarse grid, ``map_factor`` 1 means theirs.
        """
        f = int(map_factor)
        if f < 1:
            raise ValueError(f"map_factor must be a positive integer, got {map_factor!r}")
        if uncertainty and self.model is None:
            raise ValueError("the expected error of a posed volume needs an EVD model (VBD has none)")
        sigma = None
        if uncertainty:
            err = self.model.expected_error(pose)
            sigma = Volume(err, self.template.geometry)
            sigma_fill = float(err.max()) if err.size else 0.0
        if self.weights_factor > 1:
            if f not in (1, self.weights_factor):
                raise ValueError(
                    f"map_factor {f} (--map-factor): the study's skinning weights are on "
                    f"{every_nth(self.weights_factor)} template voxel (workbench weights --grid-factor), so the "
                    f"maps are solved there; leave --map-factor out or give {self.weights_factor}"
                )
            f = self.weights_factor
        g = self.template.geometry
        tgt = g if target is None else target
        if f > 1 and min(min(g.every(f).size), min(tgt.every(f).size)) < 2:
            raise ValueError(
                f"map_factor {f} (--map-factor) leaves fewer than 2 voxels along an axis of the "
                f"template {g.size} or target {tgt.size} grid: use a smaller factor"
            )
        t = stack_transforms(pose.transforms, self.weights.bones)
        t0 = time.perf_counter()
        self._say(
            f"forward map ({self.method.upper()}) of {g.every(f).n_voxels:,} "
            f"template voxels{f' ({every_nth(f)} along each axis)' if f > 1 else ''} ..."
        )
        fwd = self.forward(pose, f)
        t1 = time.perf_counter()
        self._say("backward map and resampling ...")
        prefer = self.body.data.astype(bool)
        if f > 1:
            from deformation.fields.resample import CoarseBackwardMap

            if self.weights_factor == 1:
                prefer = prefer[::f, ::f, ::f]
            coarse = backward_map(fwd, g.every(f), tgt.every(f), transforms=t, prefer=prefer)
            del fwd
            bm = CoarseBackwardMap(coarse, f, g, tgt)
            vol = bm.pull(self.template, fill=self.fill)
            lab = bm.pull(self.template_labels, labels=True) if labels and self.template_labels is not None else None
            if sigma is not None:
                sigma = bm.pull(sigma, fill=sigma_fill)
        else:
            bm = backward_map(fwd, g, target, transforms=t, prefer=prefer)
            vol = resample_forward(bm, self.template, fill=self.fill)
            lab = (
                resample_forward(bm, self.template_labels, labels=True)
                if labels and self.template_labels is not None
                else None
            )
            if sigma is not None:
                sigma = resample_forward(bm, sigma, fill=sigma_fill)
        t2 = time.perf_counter()
        return PosedTemplate(vol, lab, bm, t1 - t0, t2 - t1, sigma)


def _grid_factor(template, grid) -> int:
    """``f`` when ``grid`` is ``template.every(f)`` (1: the template's own grid), else a ValueError."""
    f = template.factor_of(grid)
    if f is None:
        template.check_same(
            grid,
            names=("template", "skinning weights / body mask"),
            remedy="recompute the weights: workbench weights --force",
        )
    return f
