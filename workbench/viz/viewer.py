"""Posing a study's model interactively: the state and work behind ``workbench view`` (no web code here).

A :class:`PoseSession` holds one study's poser (EVD, Rhee Eq. 6–7, when the study has a model; VBD, Rhee
Eq. 2, otherwise — :func:`workbench.deform.study_poser` says which), the skeleton's joint angles, and one
reused off-screen :class:`~workbench.viz.render.VolumeRenderer`.  Setting an angle and calling
:meth:`PoseSession.update` poses the template by forward kinematics and renders it: ``exact=False`` solves the
backward maps on every second voxel and blends them up (``workbench deform --map-factor 2``) and renders a
draft (a ray every 2nd pixel), for a slider being dragged; ``exact=True`` solves every voxel and renders in
full, once the slider stops.

The poses offered (:meth:`PoseSession.presets`): the template at rest, each scan's estimated pose (the pose
stage's joint angles), and the eigenposes of the scans' poses (Rhee §6.2: the principal components of the
joint-rotation vectors in degrees; the mean pose ± 1.5 standard deviations along each of the first three).  What a user
makes is kept as files the command line reads: a pose file (``workbench deform --pose``), a PNG, and keyframes
(``workbench animate --keyframes``) with their animation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deformation.geometry import covering_grid
from workbench.errors import InputFileError

__all__ = ["PoseSession", "Dof", "EIGEN_SIGMAS", "COARSE_FACTOR"]

COARSE_FACTOR = 2  # the maps while a slider moves: every 2nd voxel (workbench deform --map-factor 2)
EIGEN_SIGMAS = 1.5  # eigenposes: the mean pose ± this many standard deviations along a component
N_EIGEN = 3


@dataclass(frozen=True)
class Dof:
    """One slider: joint ``joint``'s value ``index`` (degrees; mm for a 6-DOF joint's 4th–6th)."""

    joint: str
    index: int
    low: float
    high: float

    @property
    def key(self) -> str:
        """A name safe as a web page's state variable."""
        return "dof_" + "".join(c if c.isalnum() else "_" for c in self.joint) + f"_{self.index}"

    @property
    def label(self) -> str:
        """The joint frame's name for it (deformation.kinematics.skeleton: flex, abd, twist, then mm)."""
        return ("flexion °", "abduction °", "twist °", "x mm", "y mm", "z mm")[self.index]


def _limits(joint, k: int) -> tuple[float, float]:
    if joint.limits is not None:
        return joint.limits[k]
    return (-180.0, 180.0) if k < 3 else (-20.0, 20.0)


class PoseSession:
    """One study posed interactively (module docstring).  ``out`` is the folder saved files go to (made on the
    first save); nothing is written into the study."""

    def __init__(
        self,
        folder,
        *,
        out=None,
        method: str = "auto",
        transfer="mri",
        size=(800, 600),
        clip=None,
        bones: bool = True,
        mapper: str = "auto",
        progress=None,
    ):
        from workbench.deform import say_if_compiling, study_poser
        from workbench.study import read_study
        from workbench.viz.animate import Keyframes, builtin_keyframes, motion_bounds
        from workbench.viz.render import VolumeRenderer, content_mask, first_visible, robust_range, transfer_function

        self._talk = True  # the set-up's lines; the poser's per-pose lines are not a viewer's business
        said = progress or (lambda line: None)

        def say(line):
            if self._talk:
                said(line)

        self.study = read_study(folder)
        self.skeleton = sk = self.study.skeleton()
        self.out = Path(out) if out is not None else Path(f"{self.study.root.name}-view")
        say_if_compiling(say)
        self.poser = study_poser(self.study, method=method, progress=say)
        self.method = self.poser.method
        self.bones = bool(bones) and self.poser.template_labels is not None
        self.dofs = [Dof(j.name, k, *_limits(j, k)) for j in sk.joints for k in range(j.dof)]
        self.rest = {k: np.asarray(v, float) for k, v in sk.zero_angles().items()}
        self.angles = {k: v.copy() for k, v in self.rest.items()}
        self._presets = self._make_presets()
        # one grid and camera for every pose: the box of the visible tissue over the ready keyframes (when the
        # skeleton has them) and every preset, as `workbench animate` fits its camera
        template = self.poser.template
        tf = transfer_function(transfer)
        lo, hi = robust_range(template.data)
        mask = content_mask(template.data, first_visible(tf.resolved(lo, hi)))
        wf = self.poser.weights_factor
        sweep = list(self._presets.values())
        sweep = sweep * 2 if len(sweep) == 1 else sweep  # keyframes need two
        kf = Keyframes(times=np.arange(len(sweep), dtype=float), angles=sweep, interpolation="linear")
        g = template.geometry
        margin = 2.0 * max(g.spacing)
        boxes = [motion_bounds(self.poser, sk, kf, mask[::wf, ::wf, ::wf], margin)]
        try:
            boxes.append(motion_bounds(self.poser, sk, builtin_keyframes(sk), mask[::wf, ::wf, ::wf], margin))
        except InputFileError:
            pass  # a skeleton without ready keyframes: the presets alone
        from workbench.viz.render import union_bounds

        self.bounds = union_bounds(boxes)
        self.grid = covering_grid(g, self.bounds)
        self.transfer = transfer
        self._render_args = dict(size=size, reference=template, bounds=self.bounds, mapper=mapper)
        self.renderer = VolumeRenderer(self.grid, transfer=tf, clip=clip, **self._render_args)
        self._image = None
        self.posed = None
        self.showing = "model"
        self._scans = {}
        self._sigmas = {}
        self.sigma_overlay = False  # the slices of a scan shown with its registration's expected error over it
        self.window_range = (float(lo), float(hi))
        self.last = {}
        self.keyframes: list[dict] = []
        self._talk = False

    # -- poses -------------------------------------------------------------------------------------------
    def _make_presets(self) -> dict[str, dict]:
        from workbench.io.volumes import read_image_geometry

        rest = self.rest
        out = {"rest (template)": {k: v.copy() for k, v in rest.items()}}
        scans = {}
        for sid in self.study.scan_ids:
            try:
                a = self.study.pose(sid).joint_angles
            except (OSError, KeyError, ValueError):
                continue  # the pose stage has not run for this scan
            if a:
                scans[sid] = {k: np.asarray(a.get(k, rest[k]), float) for k in rest}
        for sid in scans:  # the compare view reads them later: a broken header is said now, before serving
            read_image_geometry(self.study.scan_path(sid))
        out.update({f"scan {sid}": a for sid, a in scans.items()})
        if len(scans) >= 2:  # Rhee §6.2: the principal components of the scans' joint-angle vectors
            keys = [(k, i) for k in rest for i in range(min(3, rest[k].size))]  # rotations (degrees) only
            x = np.array([[a[k][i] for k, i in keys] for a in scans.values()])
            mean = x.mean(axis=0)
            _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
            sd = s / np.sqrt(max(1, len(x) - 1))
            for c in range(min(N_EIGEN, int(np.sum(s > 1e-9 * max(1.0, s[0]))))):
                for sign in (1, -1):
                    v = mean + sign * EIGEN_SIGMAS * sd[c] * vt[c]
                    a = {k: rest[k].copy() for k in rest}
                    for (k, i), val in zip(keys, v):
                        a[k][i] = val
                    out[f"eigenpose {c + 1} {'+' if sign > 0 else '−'}{EIGEN_SIGMAS:g}σ"] = self._clamped(a)
        return out

    def _clamped(self, angles: dict) -> dict:
        for d in self.dofs:
            angles[d.joint][d.index] = float(np.clip(angles[d.joint][d.index], d.low, d.high))
        return angles

    def presets(self) -> list[str]:
        """The poses' names: ``rest (template)``, ``scan ID`` for each scan, ``eigenpose C ±1.5σ``."""
        return list(self._presets)

    def use(self, name: str) -> None:
        """Set every angle to the preset ``name``."""
        if name not in self._presets:
            raise KeyError(f"no pose {name!r}; the poses: {self.presets()}")
        self.angles = {k: v.copy() for k, v in self._presets[name].items()}

    def set(self, joint: str, index: int, value: float) -> None:
        """One joint value (degrees, or mm), clamped to the joint's limits."""
        d = next((d for d in self.dofs if d.joint == joint and d.index == index), None)
        if d is None:
            raise KeyError(f"no degree of freedom {joint}[{index}]")
        self.angles[joint][index] = float(np.clip(float(value), d.low, d.high))

    def value(self, d: Dof) -> float:
        """The current value of one degree of freedom."""
        return float(self.angles[d.joint][d.index])

    # -- the work ----------------------------------------------------------------------------------------
    def update(self, *, exact: bool = True) -> np.ndarray:
        """Pose the template at the current angles and render it; returns the image ``(h, w, 3)`` uint8."""
        t0 = time.perf_counter()
        self._posed_at = self.skeleton.pose(self.angles)  # the pose self.posed was made for (its σ's)
        self.posed = self.poser.pose(
            self._posed_at,
            labels=self.bones,
            target=self.grid,
            map_factor=1 if exact else COARSE_FACTOR,
        )
        t1 = time.perf_counter()
        self.renderer.set_draft(not exact)  # a moving slider: a quarter of the rays too
        self.show("model")
        t2 = time.perf_counter()
        self.last = {"exact": exact, "deform_s": t1 - t0, "render_s": t2 - t1, "total_s": t2 - t0}
        return self._image

    def training_scans(self) -> list[str]:
        """The scans whose estimated pose is a preset (the compare view's)."""
        return [name[len("scan ") :] for name in self._presets if name.startswith("scan ")]

    def scan_on_grid(self, scan_id: str):
        """The scan resampled (linear, world mm) onto the view's grid, read once."""
        from workbench.viz.render import resampled_onto

        if scan_id not in self._scans:
            self._scans[scan_id] = resampled_onto(self.study.scan(scan_id), self.grid)
        return self._scans[scan_id]

    def model_uncertainty(self):
        """The posed model's expected error σ (mm) on the view's grid at the current pose (EVD's
        :meth:`~deformation.models.evd.ExampleVolumeDeformation.expected_error` pulled through the pose's backward
        map, as ``workbench deform --uncertainty-out``); None with VBD (no model) or before the first pose."""
        if self.posed is None or self.poser.model is None:
            return None
        if self.posed.uncertainty is None:
            from deformation.fields.resample import resample_forward
            from deformation.geometry import Volume

            err = self.poser.model.expected_error(self._posed_at)  # the posed volume's pose, not a newer slider's
            vol = Volume(err, self.poser.template.geometry)
            bm = self.posed.backward
            fill = float(err.max()) if err.size else 0.0
            self.posed.uncertainty = (
                bm.pull(vol, fill=fill) if hasattr(bm, "pull") else resample_forward(bm, vol, fill=fill)
            )
        return self.posed.uncertainty

    def uncertainty_on_grid(self, scan_id: str):
        """The scan's registration's expected error σ (mm, ``uncertainty.mha``) resampled onto the view's grid, read
        once; None when the registration wrote none (Rhee's Algorithm 1, or the posterior off)."""
        from workbench.viz.render import resampled_onto

        if scan_id not in self._sigmas:
            sigma = self.study.registration_uncertainty(scan_id) if self.study.has_registration(scan_id) else None
            self._sigmas[scan_id] = None if sigma is None else resampled_onto(sigma, self.grid)
        return self._sigmas[scan_id]

    def show(self, what: str = "model") -> np.ndarray:
        """Render the posed model (``"model"``, its bones as surfaces) or a scan (its id) with the same
        transfer function, camera and clipping: the report's validation view, live."""
        if self.posed is None:
            self.update(exact=True)
            if what == "model":
                return self._image
        r = self.renderer
        r.clear_surfaces()
        if what == "model":
            if self.bones and self.posed.labels is not None:
                r.add_labels(self.posed.labels)
            self._image = r.render(self.posed.volume)
        else:
            self._image = r.render(self.scan_on_grid(what))
        self.showing = what
        return self._image

    @property
    def image(self) -> np.ndarray:
        """The view as shown now, ``(h, w, 3)`` uint8 (rendered and read when the last update did not)."""
        if self.posed is None:
            self.update(exact=True)
        if self._image is None:
            self._image = self.renderer.capture()
        return self._image

    def set_camera(self, **change) -> None:
        """Turn or zoom the camera (``azimuth``, ``elevation`` degrees, ``zoom``: fields of
        :class:`~workbench.viz.view.Camera`), on the same anatomy box."""
        from dataclasses import replace

        self.renderer.set_camera(replace(self.renderer.camera, **change))
        self._image = None

    def set_clipping(self, on: bool) -> None:
        """Cut the view by the clipping plane (``on``) or show the whole volume."""
        self.renderer.set_clipping(on)
        self._image = None

    def move_clip(self, axis: str, fraction: float) -> None:
        """The clipping plane across world ``axis`` at ``fraction`` of the anatomy's extent, the side facing
        the camera cut away (``workbench render --clip AXIS:FRACTION``)."""
        from workbench.viz.view import ClipPlane

        on = self.renderer.clipping
        self.renderer.move_clip(ClipPlane(axis, float(fraction)))
        self.renderer.set_clipping(on)
        self._image = None

    def set_transfer(self, transfer) -> None:
        """Another transfer function (a preset name or a JSON file, ``workbench render --preset``): the
        renderer is made again with the same camera and clipping."""
        from workbench.viz.render import VolumeRenderer, transfer_function

        old = self.renderer
        new = VolumeRenderer(
            self.grid, transfer=transfer_function(transfer), clip=old.clip, camera=old.camera, **self._render_args
        )
        new.set_clipping(old.clipping)
        old.close()
        self.renderer, self.transfer, self._image = new, transfer, None
        if self.posed is not None:
            self.show(self.showing)

    def slices(self) -> dict[str, bytes]:
        """Three orthogonal planes (``xy``, ``xz``, ``yz``) of the shown volume through the grid's centre, as
        PNG bytes (grey, windowed to the template's robust range)."""
        from workbench.report.figures import colour_map, encode_png, grey, plane

        vol = self.posed.volume if self.showing == "model" else self.scan_on_grid(self.showing)
        data = np.asarray(vol.data)
        at = tuple(int(n // 2) for n in data.shape)
        sigma = None
        if self.sigma_overlay:
            sigma = self.model_uncertainty() if self.showing == "model" else self.uncertainty_on_grid(self.showing)
        out = {}
        for which in ("xy", "xz", "yz"):
            sl, px = plane(data, self.grid.spacing, which, at)
            if sigma is None:
                out[which] = encode_png(grey(sl, px, self.window_range))
                continue
            # σ over the scan where the scan shows tissue (the template's robust range's lower tenth and up)
            ss, _ = plane(np.asarray(sigma.data), self.grid.spacing, which, at)
            lo, hi = self.window_range
            smax = float(max(np.percentile(np.asarray(sigma.data), 99.5), 1e-3))
            tissue = sl > lo + 0.1 * (hi - lo)
            out[which] = encode_png(
                colour_map(ss, px, 0.0, smax, cmap="magma", mask=tissue, background=sl, window=self.window_range)
            )
        return out

    # -- keeping what was made ---------------------------------------------------------------------------
    def _path(self, stem: str, suffix: str) -> Path:
        self.out.mkdir(parents=True, exist_ok=True)
        n = 1
        while (self.out / f"{stem}-{n:03d}{suffix}").exists():
            n += 1
        return self.out / f"{stem}-{n:03d}{suffix}"

    def pose_document(self) -> dict:
        """The current angles as a pose file's content, ``{"angles": {joint: [values]}}``."""
        return {"angles": {k: [round(float(x), 4) for x in v] for k, v in self.angles.items()}}

    def save_pose(self, path=None) -> Path:
        """The current angles as a pose file ``workbench deform --pose`` reads (``{"angles": {...}}``)."""
        from workbench.io.jsonio import write_json

        path = Path(path) if path is not None else self._path("pose", ".json")
        write_json(self.pose_document(), path, overwrite=True)
        return path

    def save_png(self, path=None) -> Path:
        from workbench.viz.render import write_png

        path = Path(path) if path is not None else self._path("view", ".png")
        write_png(self.image, path, overwrite=True)
        return path

    def add_keyframe(self, seconds: float = 1.0) -> int:
        """The current angles as the next keyframe, ``seconds`` after the previous one; returns the count."""
        t = 0.0 if not self.keyframes else self.keyframes[-1]["time"] + float(seconds)
        self.keyframes.append({"time": t, "angles": self.pose_document()["angles"]})
        return len(self.keyframes)

    @property
    def keyframe_count(self) -> int:
        return len(self.keyframes)

    def keyframes_document(self) -> dict:
        """The keyframes added so far as an ``avw-keyframes`` document (``workbench animate --keyframes``)."""
        from workbench.viz.animate import KEYFRAMES_FORMAT

        return {
            "format": KEYFRAMES_FORMAT,
            "version": 1,
            "skeleton": self.skeleton.name,
            "interpolation": "smooth",
            "keyframes": self.keyframes,
        }

    def export_animation(self, out=None, *, fps: float = 24.0, progress=None) -> tuple[Path, Path]:
        """Write the keyframes (``keyframes-NNN.json``) and their animation through ``workbench animate``'s code
        (MP4, the view's size); returns both paths."""
        from workbench.io.jsonio import write_json
        from workbench.viz.animate import animate_study

        if len(self.keyframes) < 2:
            raise ValueError(f"an animation needs at least 2 keyframes; {len(self.keyframes)} added")
        kpath = self._path("keyframes", ".json")
        write_json(self.keyframes_document(), kpath, overwrite=True)
        out = Path(out) if out is not None else kpath.with_name(kpath.stem.replace("keyframes", "animation") + ".mp4")
        r = self.renderer
        animate_study(  # as the view looks: its transfer function, camera and clipping plane
            self.study.root,
            out,
            keyframes=kpath,
            method=self.method,
            fps=fps,
            size=r.size,
            transfer=self.transfer,
            camera=r.camera,
            clip=r.clip if r.clipping else None,
            bones=self.bones,
            progress=progress,
        )
        return kpath, out

    def close(self) -> None:
        self.renderer.close()
