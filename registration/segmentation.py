"""Template bone segmentation from seeds (Rhee §3.1; Kurihara §2).

The pose pipeline needs each bone's voxels in the template.  When the study
has a label map it is used as it is.  Otherwise the bones are segmented from
the template image and a **seeds file** (read by
:func:`workbench.io.inputs.read_seeds`): one or more world points (mm) inside
each bone, the manual step both papers had (Rhee segmented MRI by graph cut
from user strokes, Kurihara thresholded CT)::

    {"format": "avw-seeds", "version": 1, "units": "mm",
     "seeds": {"femur": [[x, y, z], ...], "tibia": [[x, y, z]], ...}}

* **CT-like** (:func:`segment_ct`): a threshold (bone is the brightest tissue;
  400 HU by default, so that partial-volume voxels count as bone when they are
  more than half bone), the marrow cavities filled, each connected component
  (SimpleITK) given to the bone whose seed it holds; bones that touch share a
  component, split by a marker-controlled watershed of the negated distance
  to the mask's edge, whose ridges run through the necks where bones touch.
* **MRI-like** (:func:`segment_mri`): the marrow, bright inside the dark
  cortex but no brighter than the fat around the bone, is flooded from its
  seeds at the lowest threshold at which the flood stays inside the cortex;
  the dark voxels within ``cortex_mm`` of the marrow are the cortex.

Both return a label map on the image's grid with the skeleton's label ids.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from deformation.filters import smooth
from deformation.geometry import Volume

__all__ = [
    "SEEDS_FORMAT",
    "seeds_from_labels",
    "segment_ct",
    "segment_mri",
    "segment_bones",
    "SegmentationReport",
    "guess_modality",
    "segment_body",
    "skin_surface",
]

SEEDS_FORMAT = "avw-seeds"


@dataclass
class SegmentationReport:
    method: str
    voxels: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    parameters: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"method": self.method, "voxels": self.voxels, "warnings": self.warnings, "parameters": self.parameters}


def seeds_from_labels(labels: Volume, skeleton) -> dict[str, np.ndarray]:
    """One seed per bone: the voxel deepest inside it (world mm) — to write a seeds file from a label map."""
    lab = np.asarray(labels.data)
    g = labels.geometry
    out = {}
    for b in skeleton.bones:
        m = lab == b.label
        if not m.any():
            raise ValueError(f"bone {b.name!r} (label {b.label}) is absent from the label map")
        d = ndimage.distance_transform_edt(m, sampling=np.asarray(g.spacing)[::-1])
        k, j, i = np.unravel_index(int(np.argmax(d)), d.shape)
        out[b.name] = g.index_to_world(np.array([[i, j, k]], float))
    return out


def guess_modality(image: Volume) -> str:
    """``"ct"`` when the image holds Hounsfield-like values (air below −500), else ``"mri"``."""
    return "ct" if float(np.percentile(image.data, 1)) < -500 else "mri"


def _seed_indices(image: Volume, seeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    g = image.geometry
    out = {}
    for b, pts in seeds.items():
        ijk = np.rint(g.world_to_index(pts)).astype(int)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(g.size)), axis=1)
        if not inside.all():
            raise ValueError(
                f"seed(s) of bone {b!r} at {pts[~inside].tolist()} mm lie outside the image "
                f"({g.describe()}); seeds are world coordinates in mm"
            )
        out[b] = ijk
    return out


def _fill_cavities(mask: np.ndarray) -> np.ndarray:
    """Fill enclosed cavities (the marrow inside the cortex): in 3-D, and slice by slice along each axis, so
    that a long bone leaving the field of view, whose marrow tube is open at the image edge, is filled too."""
    out = ndimage.binary_fill_holes(mask)
    for axis in range(3):
        moved = np.moveaxis(out, axis, 0)
        filled = np.stack([ndimage.binary_fill_holes(s) for s in moved])
        out = out | np.moveaxis(filled, 0, axis)
    return out


def segment_ct(
    image: Volume, skeleton, seeds: dict[str, np.ndarray], *, threshold: float = 400.0, smoothing_voxels: float = 1.0
) -> tuple[Volume, SegmentationReport]:
    """Threshold, fill, connected components, split shared components by watershed (see module doc)."""
    import SimpleITK as sitk

    rep = SegmentationReport(
        "ct threshold + components + watershed",
        parameters={"threshold": threshold, "smoothing_voxels": smoothing_voxels},
    )
    idx = _seed_indices(image, seeds)
    data = np.asarray(image.data, dtype=np.float32)
    mask = _fill_cavities(data > threshold)
    comp, n = ndimage.label(mask)
    label_of = {b.name: b.label for b in skeleton.bones}
    markers = np.zeros(data.shape, np.uint16)
    for b, ijk in idx.items():
        markers[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = label_of[b]
    out = np.zeros(data.shape, np.uint16)
    # Flooding relief: the negated distance to the mask's edge (mm).  Bone interiors are deep basins; where two
    # bones touch, the mask narrows to a neck, a ridge of the relief, and the fronts from the seeds meet there.
    # (The negated intensity fails: a seed next to the bright cortex floods every touching bone's cortex first.)
    relief = -ndimage.distance_transform_edt(mask, sampling=np.asarray(image.geometry.spacing)[::-1])
    for c in range(1, n + 1):
        inside = comp == c
        present = np.unique(markers[inside & (markers > 0)])
        if len(present) == 0:
            continue  # a bright structure without a seed (a calcification, the table): not a bone of ours
        if len(present) == 1:
            out[inside] = present[0]
            continue
        # Several bones in one component: watershed of the gradient from their seeds, inside the component.
        bb = ndimage.find_objects(inside.astype(np.uint8))[0]
        g = np.where(inside[bb], relief[bb], 1.0).astype(np.float32)
        mk = np.where(inside[bb], markers[bb], 0).astype(np.uint16)
        mk[~ndimage.binary_dilation(inside[bb], iterations=1)] = 0
        bg = np.uint16(max(present) + 1)
        mk[~inside[bb]] = bg  # everything outside the component is its own basin
        ws = sitk.GetArrayFromImage(
            sitk.MorphologicalWatershedFromMarkers(
                sitk.GetImageFromArray(g), sitk.GetImageFromArray(mk), markWatershedLine=False, fullyConnected=True
            )
        )
        sub = out[bb]
        sel = inside[bb] & (ws != bg)
        sub[sel] = ws[sel]
    for b in skeleton.bones:
        rep.voxels[b.name] = int((out == b.label).sum())
        if rep.voxels[b.name] == 0:
            rep.warnings.append(
                f"bone {b.name!r}: its seed is not above the threshold {threshold}; "
                "move the seed into the bone or lower --threshold"
            )
    return Volume(out, image.geometry), rep


def segment_mri(
    image: Volume,
    skeleton,
    seeds: dict[str, np.ndarray],
    *,
    max_volume_ml: float = 1500.0,
    cortex_mm: float = 2.5,
    tolerance: float = 0.01,
) -> tuple[Volume, SegmentationReport]:
    """Each bone's bright marrow inside its dark cortex, flooded from its seeds, then the cortex (module doc).

    For a threshold ``t`` the flood (SimpleITK ``ConnectedThreshold``) from a seed takes every voxel at
    least ``t`` connected to it.  Low ``t``: the flood crosses the cortex into the soft tissue; high ``t``: it
    stops short of the marrow's darker parts.  The flood shrinks as ``t`` rises, so a bisection finds, per
    seed, the lowest ``t`` (within ``tolerance`` of the range) at which it stays in the bone: under the volume
    limit (``max_volume_ml``, and a quarter of the body) and touching no air.  Seeds whose floods meet are one
    marrow; the bone is the marrow with the most seeds (ties: the deepest), the others reported and left out,
    as is a seed that floods out at its own intensity.  The cortex is then the voxels below the lowest such
    ``t`` within ``cortex_mm`` of the marrow, and its face neighbours.
    """
    import SimpleITK as sitk

    rep = SegmentationReport(
        "mri marrow flood inside the cortex (ConnectedThreshold, bisected threshold)",
        parameters={"max_volume_ml": max_volume_ml, "cortex_mm": cortex_mm, "tolerance": tolerance},
    )
    idx = _seed_indices(image, seeds)
    img = sitk.Cast(image.to_sitk(), sitk.sitkFloat32)
    img = sitk.CurvatureFlow(img, timeStep=0.0625, numberOfIterations=5)  # edge-preserving denoising
    data = sitk.GetArrayFromImage(img)
    voxel_ml = float(np.prod(image.geometry.spacing)) / 1000.0
    spacing = np.asarray(image.geometry.spacing)[::-1]
    # Air: outside the body (segment_body: its cavities filled, so the cortex, as dark as air in MRI, is
    # inside).  A bone never touches air, so a flood that does has leaked (into the subcutaneous fat, typically).
    air = segment_body(image).data == 0
    air_level = float(np.percentile(data[air], 99)) if air.any() else float(data.min())
    near_air = ndimage.binary_dilation(air)
    limit_ml = min(max_volume_ml, 0.25 * float((~air).sum()) * voxel_ml)  # no bone is a quarter of the body
    rep.parameters["volume_limit_ml"] = round(limit_ml, 1)
    rep.parameters["thresholds"] = {}

    def flood(seed_list, t):
        return sitk.GetArrayFromImage(
            sitk.ConnectedThreshold(img, seedList=seed_list, lower=float(t), upper=float(np.inf), replaceValue=1)
        ).astype(bool)

    def contained(r):
        return bool(r.any()) and r.sum() * voxel_ml <= limit_ml and not (r & near_air).any()

    g = image.geometry
    grown = {}
    used = dict(idx)  # the seeds each bone grew from (those left out are not its seeds below)
    depth = None
    for b in skeleton.bones:
        ijk = idx[b.name]
        values = data[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        seed_list = [tuple(int(v) for v in p) for p in ijk]
        # each seed's own flood, at the lowest threshold that keeps it in the bone (bisection: the flood only
        # shrinks as the threshold rises); a seed whose flood leaks even at its own intensity is not in marrow
        regions = []
        for p, v in zip(seed_list, values):
            xyz = np.round(g.index_to_world(np.asarray(p, float)), 1).tolist()
            r = flood([p], v)
            if not contained(r):
                rep.warnings.append(
                    f"bone {b.name!r}: the seed at {xyz} mm floods out of the bone even at its "
                    f"own intensity ({v:.0f}): it is not in the marrow, and was left out"
                )
                continue
            hi, lo = float(v), air_level
            while hi - lo > tolerance * (float(v) - air_level):
                t = 0.5 * (lo + hi)
                rt = flood([p], t)
                if contained(rt):
                    hi, r = t, rt
                else:
                    lo = t
            regions.append((p, xyz, hi, r))
        if not regions:
            rep.warnings.append(
                f"bone {b.name!r}: every seed floods out of the bone (into the air, or past the "
                "volume limit); its voxels are dropped — move the seeds into the marrow, or give "
                "a label map"
            )
            grown[b.name] = np.zeros(data.shape, bool)
            continue
        # one bone, one marrow: seeds whose regions meet form a group; the bone is the group with the most
        # seeds, ties going to the deepest seeds (bones lie deep, fat under the skin).  A seed of another group
        # (a bright fat lobule clicked beside the bone) is reported and left out.
        groups = []
        for x in regions:
            joined = [grp for grp in groups if any((x[3] & y[3]).any() for y in grp)]
            merged = [x] + [y for grp in joined for y in grp]
            groups = [grp for grp in groups if not any(grp is j for j in joined)] + [merged]
        if len(groups) > 1 and depth is None:  # distance from the air, for the tie-break (once)
            depth = ndimage.distance_transform_edt(~air, sampling=spacing)
        kept = (
            groups[0]
            if len(groups) == 1
            else max(groups, key=lambda grp: (len(grp), max(depth[x[0][2], x[0][1], x[0][0]] for x in grp)))
        )
        for x in regions:
            if not any(x is k for k in kept):
                rep.warnings.append(
                    f"bone {b.name!r}: the seed at {x[1]} mm lies in a region apart from the "
                    "marrow its other seeds reach (fat beside the bone?): it was left out"
                )
        main = min(kept, key=lambda x: x[2])
        used[b.name] = np.asarray([x[0] for x in kept])
        hi = main[2]
        r = np.logical_or.reduce([x[3] for x in kept])
        rep.parameters["thresholds"][b.name] = round(hi, 1)
        if r.sum() < 8:
            rep.warnings.append(
                f"bone {b.name!r}: only {int(r.sum())} marrow voxels flooded from its seeds; the "
                "marrow may not be resolved at this spacing"
            )
        # the cortex: voxels darker than the flood's threshold within cortex_mm of the marrow, and its face
        # neighbours (at least one voxel, however coarse or anisotropic the grid)
        near = (ndimage.distance_transform_edt(~r, sampling=spacing) <= cortex_mm) | ndimage.binary_dilation(r)
        cortex = near & (data < hi) & ~air
        grown[b.name] = ndimage.binary_fill_holes(r | cortex)
    out = np.zeros(image.geometry.array_shape, np.uint16)
    dist = np.full(out.shape, np.inf)
    for b in skeleton.bones:
        seed_mask = np.zeros(out.shape, bool)
        ijk = used[b.name]
        seed_mask[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = True
        d = ndimage.distance_transform_edt(~seed_mask, sampling=spacing)  # overlaps go to the nearer seed
        take = grown[b.name] & (d < dist)
        out[take] = b.label
        dist[take] = d[take]
    for b in skeleton.bones:
        rep.voxels[b.name] = int((out == b.label).sum())
    return Volume(out, image.geometry), rep


def segment_bones(
    image: Volume, skeleton, seeds: dict[str, np.ndarray], *, modality: str | None = None, **kwargs
) -> tuple[Volume, SegmentationReport]:
    """Segment with the method for the modality (``"ct"``/``"mri"``; guessed from the intensities if None)."""
    modality = modality or guess_modality(image)
    if modality == "ct":
        return segment_ct(image, skeleton, seeds, **kwargs)
    if modality == "mri":
        return segment_mri(image, skeleton, seeds, **kwargs)
    raise ValueError(f"modality must be 'ct' or 'mri', got {modality!r}")


def _smoothed(image: Volume, smooth_voxels: float):
    """The image as a float32 SimpleITK image in voxel units (spacing 1), smoothed by SimpleITK's recursive
    Gaussian of ``smooth_voxels`` voxels (0: as it is)."""
    import SimpleITK as sitk

    data = np.asarray(image.data, dtype=np.float32)
    return sitk.GetImageFromArray(smooth(data, max(float(smooth_voxels), 0.0), method="recursive"))


def _air_tissue_level(img) -> float:
    """Half-way between the median air and the median tissue intensity of Otsu's two classes (SimpleITK)."""
    import SimpleITK as sitk

    f = sitk.OtsuThresholdImageFilter()
    f.SetInsideValue(0)
    f.SetOutsideValue(1)
    f.Execute(img)
    arr = sitk.GetArrayViewFromImage(img)
    otsu = f.GetThreshold()
    lo, hi = arr[arr <= otsu], arr[arr > otsu]
    if not lo.size or not hi.size:
        raise ValueError("the image has a single intensity level: there is no air/tissue boundary to find")
    return 0.5 * (float(np.median(lo)) + float(np.median(hi)))


def skin_surface(
    image: Volume, *, target_triangles: int | None = 100_000, smooth_voxels: float = 1.0, level: float | None = None
):
    """The skin of a scan as a closed triangle mesh in world mm (Kurihara §3–4's skin isosurface).

    The air/tissue isosurface (``level``, default :func:`segment_body`'s half-way level) of the image
    smoothed by ``smooth_voxels`` (noise would make the surface rough), with the body's interior — its
    mask (:func:`segment_body`) eroded by two voxels — raised above the level so that no inner surface
    remains (dark MRI cortex, gas): the skin keeps the image's sub-voxel edge, the inside has none.  The
    image is padded with air (a limb cut by the field of view gets a cap), pieces under 5 % of the largest
    dropped (:func:`deformation.meshes.isosurface.largest_components`), and the rest decimated to about
    ``target_triangles`` (:func:`deformation.meshes.isosurface.decimate`; None: as extracted).
    """
    import SimpleITK as sitk
    from scipy import ndimage

    from deformation.meshes.isosurface import decimate, isosurface, largest_components

    img = _smoothed(image, smooth_voxels)
    lvl = _air_tissue_level(img) if level is None else float(level)
    data = sitk.GetArrayFromImage(img)
    body = segment_body(image, smooth_voxels=smooth_voxels, threshold=lvl).data > 0
    inner = ndimage.binary_erosion(body, iterations=2)
    hi = float(data.max())
    data[inner] = np.maximum(data[inner], hi)
    low = float(min(data.min(), lvl - 1.0))
    mesh = largest_components(isosurface(Volume(data, image.geometry), lvl, pad_value=low))
    if mesh.n_triangles == 0:
        raise ValueError(f"no skin surface at the air/tissue level {lvl:g}: is the image empty?")
    return decimate(mesh, int(target_triangles)) if target_triangles else mesh


def segment_body(
    image: Volume, *, labels: Volume | None = None, smooth_voxels: float = 1.0, threshold: float | None = None
) -> Volume:
    """The body (everything but the air around it) as a uint8 mask on the image's grid.

    Gaussian smoothing (``smooth_voxels``, SimpleITK), a threshold between air
    and tissue unless ``threshold`` is given — the half-way level between the
    median air and the median tissue intensity of Otsu's two classes
    (SimpleITK), where a blurred step edge is at its true position — the largest
    connected component, then the enclosed cavities filled (also slice by
    slice, for a limb that leaves the field of view) and the bones of
    ``labels``, when given, added — dark MRI cortex and dark fat-free regions
    lie inside the skin.  Used for the skinning mesh (the body's skin surface)
    and as the preferred region of the backward map.
    """
    import SimpleITK as sitk

    img = _smoothed(image, smooth_voxels)
    if threshold is None:
        threshold = _air_tissue_level(img)
    mask = sitk.Cast(img > float(threshold), sitk.sitkUInt8)
    cc = sitk.RelabelComponent(sitk.ConnectedComponent(mask), sortByObjectSize=True)
    body = sitk.GetArrayFromImage(cc) == 1
    if not body.any():
        raise ValueError("no tissue found above the air threshold: is this image empty? Pass threshold=")
    if labels is not None:
        image.geometry.check_same(labels.geometry, names=("image", "labels"))
        body |= np.asarray(labels.data) > 0
    return Volume(_fill_cavities(body).astype(np.uint8), image.geometry)
