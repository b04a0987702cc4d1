"""Off-screen volume rendering with VTK: stills, clipped views, overlays (Rhee Figures 1, 8–12).

Everything renders without a display, in the off-screen OpenGL context of
:mod:`workbench.viz.backend`.  Geometry is honest: the volume is placed in
world millimetres (ITK physical space) by its origin, spacing *and*
direction — the direction goes into the prop's matrix, so any mapper honours
it — and cameras, clipping planes and bounding boxes (:mod:`workbench.viz.view`)
are all in world mm; colours and opacities come from :mod:`workbench.viz.transfer`.

* :class:`VolumeRenderer` — one render window and pipeline, reused from
  frame to frame (animations);
* :func:`render_volume`, :func:`render_overlay` (two volumes in contrasting
  colours: Rhee's green/cyan template against the magenta target, Rhee
  Figs. 1, 8, 9, 11) and :func:`render_difference` — the one-call forms.

Images are ``(height, width, 3)`` uint8 arrays; :func:`write_png` writes one
atomically.  Rendering is deterministic: automatic sample-distance
adjustment (which depends on the time a frame took) is switched off.  The
names of the three modules above are re-exported here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deformation.geometry import GridGeometry, Volume
from workbench.viz.backend import Backend, RenderError, offscreen_available, opengl_backend
from workbench.viz.transfer import (
    CONTRAST_COLOURS,
    LEVEL_COLOURS,
    MARKER_COLOUR,
    PRESETS,
    SKIN_COLOUR,
    TransferFunction,
    first_visible,
    label_colour,
    robust_range,
    transfer_function,
)
from workbench.viz.view import (
    Camera,
    ClipPlane,
    content_bounds,
    content_mask,
    grid_bounds,
    parse_size,
    points_bounds,
    union_bounds,
)

__all__ = [
    "Backend",
    "RenderError",
    "opengl_backend",
    "offscreen_available",
    "TransferFunction",
    "PRESETS",
    "Camera",
    "ClipPlane",
    "VolumeRenderer",
    "render_volume",
    "render_overlay",
    "render_difference",
    "resampled_onto",
    "write_png",
    "parse_size",
    "label_colour",
    "content_mask",
    "points_bounds",
    "union_bounds",
    "content_bounds",
    "CONTRAST_COLOURS",
    "LEVEL_COLOURS",
    "transfer_function",
    "robust_range",
    "first_visible",
    "MARKER_COLOUR",
]


def _prop_matrix(g: GridGeometry):
    """The vtkMatrix4x4 taking the image's (spacing-scaled, origin 0) coordinates to world mm."""
    m = np.eye(4)
    m[:3, :3] = g.direction_matrix
    m[:3, 3] = np.asarray(g.origin, float)
    return _vtk_matrix(m)


def _vtk_matrix(m):
    """A 4×4 numpy matrix as a vtkMatrix4x4."""
    from vtkmodules.vtkCommonMath import vtkMatrix4x4

    m = np.asarray(m, float)
    vm = vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            vm.SetElement(i, j, float(m[i, j]))
    return vm


class VolumeRenderer:
    """One off-screen window rendering volumes on one grid, reused from frame to frame.

    ``geometry`` fixes the grid (every volume passed to :meth:`render` must
    be on it); ``transfer`` a preset name, a :class:`TransferFunction` or a
    JSON file — relative functions are resolved once against
    ``reference`` (default: the first volume rendered), so an animation's
    colours do not flicker; ``transfers`` (a list) renders that many volumes
    at once, each with its own transfer function, blended (overlays).
    ``mapper``: ``auto`` (:attr:`Backend.mapper`), ``fixed`` or ``gpu``.  The
    camera and clipping plane are placed on ``bounds`` (world mm), by default
    the box of the visible tissue of every volume of the first render
    (:func:`content_bounds`), and of the meshes added (:meth:`add_mesh`).
    ``geometry`` None: no volume at all, meshes only (``render()`` with no
    argument).
    """

    def __init__(
        self,
        geometry: GridGeometry | None,
        *,
        size=(640, 480),
        transfer="mri",
        transfers=None,
        reference=None,
        camera: Camera | None = None,
        clip: ClipPlane | None = None,
        background=(0.0, 0.0, 0.0),
        mapper: str = "auto",
        sample_mm: float | None = None,
        bounds=None,
    ):
        import vtkmodules.vtkRenderingOpenGL2 as gl
        import vtkmodules.vtkRenderingVolumeOpenGL2  # noqa: F401 - registers the OpenGL volume mappers
        from vtkmodules.vtkCommonDataModel import vtkPlane
        from vtkmodules.vtkRenderingCore import vtkRenderer, vtkWindowToImageFilter

        self.backend = opengl_backend()
        if mapper not in ("auto", "fixed", "gpu"):
            raise ValueError(f"mapper must be 'auto', 'fixed' or 'gpu', got {mapper!r}")
        self.mapper_name = self.backend.mapper if mapper == "auto" else mapper
        w, h = (int(v) for v in size)
        if w < 1 or h < 1:
            raise ValueError(f"size must be positive, got {size!r}")
        self.size = (w, h)
        self.geometry = geometry
        self.camera = camera or Camera()
        self.clip = clip
        tfs = (
            []
            if geometry is None
            else [transfer_function(t) for t in (transfers if transfers is not None else [transfer])]
        )
        self.n_components = len(tfs)
        self._tfs, self._resolved = tfs, None
        self._reference = reference
        self.bounds = None if bounds is None else tuple(float(v) for v in bounds)
        self._mesh_bounds = []
        self._ren = vtkRenderer()
        self._ren.SetBackground(*(float(c) for c in background))
        self._plane = vtkPlane() if clip is not None else None
        self._clipping = clip is not None
        if geometry is not None:
            self._volume_actor(geometry, tfs, sample_mm)
        self._win = getattr(gl, self.backend.window_class)()
        self._win.SetOffScreenRendering(1)
        self._win.SetSize(w, h)
        self._win.SetMultiSamples(0)
        self._win.AddRenderer(self._ren)
        self._grab = vtkWindowToImageFilter()
        self._grab.SetInput(self._win)
        self._grab.SetInputBufferTypeToRGB()
        self._grab.ReadFrontBufferOff()
        self._surfaces = []
        self._placed = False
        self._distance = None

    def _volume_actor(self, geometry: GridGeometry, tfs, sample_mm) -> None:
        """The ray-cast volume of ``geometry``'s grid with one transfer function per component."""
        from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPiecewiseFunction
        from vtkmodules.vtkRenderingCore import vtkColorTransferFunction, vtkVolume, vtkVolumeProperty

        self._img = vtkImageData()
        self._img.SetDimensions(*(int(v) for v in geometry.size))
        self._img.SetSpacing(*(float(v) for v in geometry.spacing))
        self._img.SetOrigin(0.0, 0.0, 0.0)
        if self.mapper_name == "fixed":
            from vtkmodules.vtkRenderingVolume import vtkFixedPointVolumeRayCastMapper

            self._mapper = vtkFixedPointVolumeRayCastMapper()
            self._mapper.AutoAdjustSampleDistancesOff()  # time-driven: would make renders differ
            self._mapper.LockSampleDistanceToInputSpacingOff()
            self._mapper.SetImageSampleDistance(1.0)
        else:
            from vtkmodules.vtkRenderingVolume import vtkGPUVolumeRayCastMapper

            self._mapper = vtkGPUVolumeRayCastMapper()
            self._mapper.AutoAdjustSampleDistancesOff()
        self._sample_mm = float(sample_mm or 0.5 * min(geometry.spacing))
        self._mapper.SetSampleDistance(self._sample_mm)
        self._mapper.SetInputData(self._img)
        self._prop = vtkVolumeProperty()
        self._prop.SetInterpolationTypeToLinear()
        self._prop.SetIndependentComponents(True)
        self._ctf = [vtkColorTransferFunction() for _ in tfs]
        self._otf = [vtkPiecewiseFunction() for _ in tfs]
        for c in range(len(tfs)):
            self._prop.SetColor(c, self._ctf[c])
            self._prop.SetScalarOpacity(c, self._otf[c])
            self._prop.SetScalarOpacityUnitDistance(c, tfs[c].unit_mm)
        self._prop.SetShade(bool(all(t.shade for t in tfs)))
        self._prop.SetAmbient(0.35)
        self._prop.SetDiffuse(0.75)
        self._prop.SetSpecular(0.15)
        self._volume = vtkVolume()
        self._volume.SetMapper(self._mapper)
        self._volume.SetProperty(self._prop)
        self._volume.SetUserMatrix(_prop_matrix(geometry))
        self._ren.AddVolume(self._volume)
        if self._plane is not None:
            self._mapper.AddClippingPlane(self._plane)

    @staticmethod
    def grid_bounds(geometry: GridGeometry) -> tuple:
        """The world box of a grid's voxel centres (any direction): a fixed ``bounds`` for the camera."""
        return grid_bounds(geometry)

    # -- inputs --
    def _set_scalars(self, arrays) -> None:
        from vtkmodules.util.numpy_support import numpy_to_vtk

        shape = self.geometry.array_shape
        cols = []
        for a in arrays:
            a = np.asarray(a.data if isinstance(a, Volume) else a)
            if a.shape != shape:
                raise ValueError(
                    f"render: a volume of shape {a.shape} on a renderer for grid {shape} "
                    "(resample it onto the renderer's grid first)"
                )
            cols.append(np.asarray(a, np.float32).reshape(-1))
        flat = np.ascontiguousarray(np.stack(cols, axis=1) if len(cols) > 1 else cols[0])
        self._keep = flat  # VTK shares the buffer
        arr = numpy_to_vtk(flat, deep=False)
        arr.SetName("intensity")
        self._img.GetPointData().SetScalars(arr)
        self._img.Modified()

    def _resolve(self, arrays) -> None:
        if self._resolved is not None:
            return
        refs = self._reference if self._reference is not None else arrays
        if isinstance(refs, (Volume, np.ndarray)):
            refs = [refs] * len(self._tfs)
        self._resolved = []
        for c, tf in enumerate(self._tfs):
            r = refs[c] if c < len(refs) else refs[0]
            lo, hi = robust_range(r.data if isinstance(r, Volume) else r)
            t = tf.resolved(lo, hi)
            self._resolved.append(t)
            self._ctf[c].RemoveAllPoints()
            for v, rr, gg, bb in t.color:
                self._ctf[c].AddRGBPoint(float(v), float(rr), float(gg), float(bb))
            self._otf[c].RemoveAllPoints()
            for v, a in t.opacity:
                self._otf[c].AddPoint(float(v), float(a))

    def add_labels(self, labels, *, smooth: int = 15, opacity: float = 1.0) -> int:
        """Draw the label map's boundaries (e.g. bones) as smooth opaque surfaces, one colour per label.

        ``labels``: a Volume (or array) on the renderer's grid.  The surfaces
        (VTK's discrete flying edges, windowed-sinc smoothed) are clipped by
        the same plane as the volume.  Returns the number of labels drawn.
        """
        from vtkmodules.vtkFiltersCore import vtkWindowedSincPolyDataFilter

        from deformation.meshes.isosurface import flying_edges

        lab = np.asarray(labels.data if isinstance(labels, Volume) else labels)
        if isinstance(labels, Volume):
            self.geometry.check_same(
                labels.geometry,
                names=("volume", "labels"),
                remedy="resample the labels onto the volume's grid (nearest neighbour)",
            )
        if lab.shape != self.geometry.array_shape:
            raise ValueError(f"labels of shape {lab.shape} on a grid of shape {self.geometry.array_shape}")
        ids = [int(v) for v in np.unique(lab) if v != 0]
        for lid in ids:
            sm = vtkWindowedSincPolyDataFilter()
            sm.SetInputData(flying_edges(lab, lid, discrete=True))  # index space
            sm.SetNumberOfIterations(int(smooth))
            sm.SetPassBand(0.05)
            sm.NormalizeCoordinatesOn()
            sm.Update()
            # the surface is in voxel indices: the grid's index → world matrix places it
            self._add_surface(
                sm.GetOutput(),
                label_colour(lid),
                opacity=opacity,
                matrix=_vtk_matrix(self.geometry.index_to_world_matrix),
            )
        return len(ids)

    def add_points(self, points, *, colour=(1.0, 0.85, 0.1), radius_mm: float | None = None) -> int:
        """Draw world points ``(n, 3)`` mm as small opaque spheres (markers, control points), clipped too.

        ``radius_mm`` defaults to one voxel (the largest spacing).  Returns the number drawn.
        """
        from vtkmodules.vtkCommonCore import vtkPoints
        from vtkmodules.vtkCommonDataModel import vtkPolyData
        from vtkmodules.vtkFiltersCore import vtkGlyph3D
        from vtkmodules.vtkFiltersSources import vtkSphereSource

        p = np.asarray(points, float).reshape(-1, 3)
        if not np.all(np.isfinite(p)):
            raise ValueError("add_points: the points must be finite world coordinates (mm)")
        pts = vtkPoints()
        for x in p:
            pts.InsertNextPoint(*x)
        poly = vtkPolyData()
        poly.SetPoints(pts)
        sphere = vtkSphereSource()
        sphere.SetRadius(float(radius_mm or (max(self.geometry.spacing) if self.geometry is not None else 1.0)))
        sphere.SetThetaResolution(12)
        sphere.SetPhiResolution(8)
        glyph = vtkGlyph3D()
        glyph.SetInputData(poly)
        glyph.SetSourceConnection(sphere.GetOutputPort())
        glyph.ScalingOff()
        glyph.Update()
        self._add_surface(glyph.GetOutput(), colour)  # already in world mm
        return int(p.shape[0])

    def add_mesh(self, mesh, *, colour=SKIN_COLOUR, opacity: float = 1.0) -> int:
        """Draw a triangle mesh in world mm (``SurfaceMesh``: a skin of ``workbench surface``, a posed model),
        smooth-shaded, clipped by the renderer's plane; with no volume it alone sets the camera's box.  Returns
        its triangle count."""
        from vtkmodules.vtkFiltersCore import vtkPolyDataNormals

        from deformation.meshes.isosurface import vtk_polydata

        nrm = vtkPolyDataNormals()
        nrm.SetInputData(vtk_polydata(mesh.vertices, mesh.triangles))
        nrm.SplittingOff()  # smooth shading across the whole skin
        nrm.ConsistencyOn()
        nrm.Update()
        self._add_surface(nrm.GetOutput(), colour, opacity=opacity)
        self._mesh_bounds.append(points_bounds(mesh.vertices, 0.0))
        return int(mesh.n_triangles)

    def _add_surface(self, polydata, colour, *, opacity: float = 1.0, matrix=None) -> None:
        """An opaque (or ``opacity``) surface actor, clipped by the renderer's plane."""
        from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

        mp = vtkPolyDataMapper()
        mp.SetInputData(polydata)
        mp.ScalarVisibilityOff()
        if self._plane is not None and self._clipping:
            mp.AddClippingPlane(self._plane)
        act = vtkActor()
        act.SetMapper(mp)
        if matrix is not None:
            act.SetUserMatrix(matrix)
        act.GetProperty().SetColor(*(float(c) for c in colour))
        act.GetProperty().SetOpacity(float(opacity))
        act.GetProperty().SetSpecular(0.2)
        self._ren.AddActor(act)
        self._surfaces.append(act)

    def set_draft(self, on: bool) -> None:
        """Draft renders (``on``) cast a ray every 2nd pixel each way and sample it every 2nd step, about a
        quarter of the work, for an image that follows a moving slider; off, the full quality again."""
        if self.geometry is None:
            return
        f = 2.0 if on else 1.0
        self._mapper.SetImageSampleDistance(f)
        self._mapper.SetSampleDistance(f * self._sample_mm)

    def move_clip(self, clip: ClipPlane) -> None:
        """Put the clipping plane at ``clip`` (axis, fraction, side) on the same anatomy box; a renderer made
        without a plane gets one (turned on by :meth:`set_clipping`)."""
        from vtkmodules.vtkCommonDataModel import vtkPlane

        if self._plane is None:
            self._plane = vtkPlane()
        self.clip = clip
        if self.bounds is not None:
            o, nrm = clip.plane(self.bounds, self._ren.GetActiveCamera().GetPosition())
            self._plane.SetOrigin(*o)
            self._plane.SetNormal(*nrm)

    @property
    def clipping(self) -> bool:
        """Whether the view is cut by the clipping plane now."""
        return self._plane is not None and self._clipping

    def set_clipping(self, on: bool) -> None:
        """Cut by the clipping plane (given at construction or by :meth:`move_clip`), or show the whole volume;
        without a plane, nothing to do."""
        if self._plane is None:
            return
        self._clipping = bool(on)
        volume = [self._mapper] if self.geometry is not None else []
        for m in volume + [a.GetMapper() for a in self._surfaces]:
            m.RemoveAllClippingPlanes()
            if self._clipping:
                m.AddClippingPlane(self._plane)

    def clear_surfaces(self) -> None:
        """Remove every label surface, mesh and point set added so far (an animation's bones or skin, frame by
        frame; the camera's box stays)."""
        for act in self._surfaces:
            self._ren.RemoveActor(act)
        self._surfaces = []
        self._mesh_bounds = []

    def _place(self, volumes) -> None:
        """Camera and clipping plane on the anatomy's world box (``bounds``, or the union of every volume's tissue)."""
        if self.bounds is None:  # the union of every component's visible tissue and of the meshes
            self.bounds = union_bounds(
                [
                    content_bounds(v.data if isinstance(v, Volume) else v, self.geometry, first_visible(t))
                    for v, t in zip(volumes, self._resolved or ())
                ]
                + self._mesh_bounds
            )
        cam = self._ren.GetActiveCamera()
        first = self._distance is None
        self._distance = self.camera.place(cam, self.bounds, self.size[0] / self.size[1], self._distance)
        if self._plane is not None and first:  # the side an 'auto' plane keeps is chosen once, from here
            o, nrm = self.clip.plane(self.bounds, cam.GetPosition())
            self._plane.SetOrigin(*o)
            self._plane.SetNormal(*nrm)
        self._placed = True

    def set_camera(self, camera: Camera) -> None:
        """A new camera (e.g. the next azimuth of an orbit) on the same world box, at the first fit's distance.

        The clipping plane stays where the first placement put it: an orbit
        does not flip the side an ``auto`` plane keeps.
        """
        self.camera = camera
        self._placed = False

    def render(self, *volumes) -> np.ndarray:
        """Render ``volumes`` (one per component, on the renderer's grid); ``(height, width, 3)`` uint8."""
        if len(volumes) != self.n_components:
            raise ValueError(f"render: {len(volumes)} volumes for a renderer of {self.n_components} components")
        for v in volumes:
            if isinstance(v, Volume):
                self.geometry.check_same(
                    v.geometry, names=("renderer grid", "volume"), remedy="resample the volume onto one grid first"
                )
        if volumes:
            self._resolve(volumes)
            self._set_scalars(volumes)
        elif self.bounds is None and not self._mesh_bounds:
            raise ValueError("render: nothing to render (no volume and no mesh added)")
        if not self._placed:
            self._place(volumes)
        return self.capture()

    def capture(self) -> np.ndarray:
        """Render the window as it is set and read its pixels, ``(height, width, 3)`` uint8."""
        from vtkmodules.util.numpy_support import vtk_to_numpy

        self._win.Render()
        self._grab.Modified()
        self._grab.Update()
        out = self._grab.GetOutput()
        w, h, _ = out.GetDimensions()
        px = vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, -1)[::-1, :, :3]
        return np.ascontiguousarray(px)

    def close(self) -> None:
        self._win.Finalize()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# -- one-call forms ------------------------------------------------------------------------------------
def render_volume(
    volume: Volume | None, *, labels: Volume | None = None, points=(), meshes=(), transfer="mri", **kw
) -> np.ndarray:
    """A still of ``volume``, optionally with ``labels`` as bone surfaces, ``points`` and ``meshes``.

    ``points``: ``[(world points (n, 3) mm, (r, g, b)[, radius mm]), ...]``
    drawn as small spheres (skin markers, registration control points);
    ``meshes``: ``[SurfaceMesh or (SurfaceMesh, (r, g, b)[, opacity]), ...]``
    in world mm.  ``volume`` None: the meshes alone.  See :class:`VolumeRenderer`.
    """
    with VolumeRenderer(None if volume is None else volume.geometry, transfer=transfer, **kw) as r:
        if labels is not None:
            r.add_labels(labels)
        _add_point_sets(r, points)
        for m in meshes:
            m, colour, opacity = (m, SKIN_COLOUR, 1.0) if not isinstance(m, tuple) else (*m, 1.0)[:3]
            r.add_mesh(m, colour=colour, opacity=opacity)
        return r.render() if volume is None else r.render(volume)


def _add_point_sets(r: VolumeRenderer, points) -> None:
    for item in points:
        pts, colour = item[0], item[1]
        r.add_points(pts, colour=colour, radius_mm=item[2] if len(item) > 2 else None)


def resampled_onto(vol: Volume, g: GridGeometry) -> Volume:
    """``vol`` resampled (linear, world coordinates) onto ``g``; itself when it is already on ``g``."""
    if vol.geometry.is_close(g):
        return vol
    import SimpleITK as sitk

    img = vol.to_sitk()
    ref = sitk.Image([int(v) for v in g.size], sitk.sitkFloat32)
    g.apply_to_sitk(ref)
    fill = float(np.percentile(np.asarray(vol.data), 0.5))
    out = sitk.Resample(sitk.Cast(img, sitk.sitkFloat32), ref, sitk.Transform(), sitk.sitkLinear, fill)
    return Volume(sitk.GetArrayFromImage(out), g)


def render_overlay(a: Volume, b: Volume, *, colours=CONTRAST_COLOURS, transfer="mri", points=(), **kw) -> np.ndarray:
    """``a`` and ``b`` in contrasting colours (default cyan and magenta, as Rhee Figs. 1, 8, 9, 11).

    Where the two agree the colours mix (lavender for cyan and magenta);
    where ``a`` has tissue and ``b`` not the image is cyan, and magenta the
    other way.
    ``b`` is resampled onto ``a``'s grid when the grids differ (world
    coordinates, linear).  ``points`` as in :func:`render_volume` (Rhee
    Fig. 9: the registration's control points over the overlay).
    """
    tf = transfer_function(transfer)
    b = resampled_onto(b, a.geometry)
    with VolumeRenderer(
        a.geometry, transfers=[tf.tinted(colours[0]), tf.tinted(colours[1])], reference=[a, b], **kw
    ) as r:
        _add_point_sets(r, points)
        return r.render(a, b)


#: signed difference: blue where the first volume is darker, red where brighter; |difference| sets opacity
DIFFERENCE = TransferFunction(
    "difference",
    relative=False,
    shade=False,
    color=(
        (-1.0, 0.15, 0.35, 1.0),
        (-0.1, 0.6, 0.7, 1.0),
        (0.0, 1.0, 1.0, 1.0),
        (0.1, 1.0, 0.7, 0.5),
        (1.0, 1.0, 0.2, 0.1),
    ),
    opacity=((-1.0, 0.5), (-0.15, 0.08), (-0.05, 0.0), (0.05, 0.0), (0.15, 0.08), (1.0, 0.5)),
)


def render_difference(a: Volume, b: Volume, *, transfer="mri", **kw) -> np.ndarray:
    """The signed difference ``a − b`` (``b`` resampled onto ``a``'s grid), scaled by ``a``'s robust range.

    Red where ``a`` is brighter, blue where darker, transparent where they
    agree within 5 % of the range: the misregistered edges stand out.  The
    camera is fitted to the tissue of both volumes as ``transfer`` shows it,
    so the view matches :func:`render_volume` and :func:`render_overlay`.
    """
    b = resampled_onto(b, a.geometry)
    lo, hi = robust_range(a.data)
    d = (np.asarray(a.data, np.float64) - np.asarray(b.data, np.float64)) / (hi - lo)
    diff = Volume(np.clip(d, -1.0, 1.0).astype(np.float32), a.geometry)
    if kw.get("bounds") is None:
        tf = transfer_function(transfer)
        kw["bounds"] = union_bounds(
            [content_bounds(v.data, a.geometry, first_visible(tf.resolved(*robust_range(v.data)))) for v in (a, b)]
        )
    with VolumeRenderer(a.geometry, transfer=DIFFERENCE, **kw) as r:
        return r.render(diff)


def write_png(image: np.ndarray, path, *, overwrite: bool = False) -> Path:
    """Write an ``(h, w, 3)`` uint8 image as PNG, atomically (temporary file, then rename)."""
    import imageio.v3 as iio

    from workbench.io.atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: stills are written as PNG; name the file *.png")
    # encoded in memory, written from Python: imageio writing the file itself repeats a failed write's error
    # from its finaliser ("Exception ignored ...") after the one that is raised
    data = iio.imwrite("<bytes>", np.asarray(image, np.uint8), extension=".png")
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return path
