"""Keyframe animations of a study's template: pose, deform, render, encode (Rhee's "accompanying video").

A keyframe file (``avw-keyframes``, JSON) lists joint angles at times::

    {"format": "avw-keyframes", "version": 1, "skeleton": "knee",
     "interpolation": "smooth",            # or "linear"
     "fps": 24,                            # optional; --fps overrides
     "camera": {"view": "auto", "azimuth": 0, "elevation": 0, "zoom": 1.0, "orbit": 0},
     "keyframes": [{"time": 0.0, "angles": {"knee": [0, 0, 0]}},
                   {"time": 1.25, "angles": {"knee": [60, 0, 0]}}, ...]}

Joints a keyframe leaves out stay at 0 (the template's pose), as in ``workbench deform --pose``.  Between two
keyframes every angle moves with the smoothstep ``s = u²(3 − 2u)`` of the segment's time fraction ``u``
(``smooth``: the motion starts and stops gently at each keyframe) or linearly.  ``camera.orbit`` turns the camera
by that many degrees of azimuth over the animation.

Each frame: the pose by forward kinematics, the template deformed to it (EVD, Rhee Eq. 6–7, when the study has a
model; VBD, Rhee Eq. 2, otherwise), rendered by one reused :class:`workbench.viz.render.VolumeRenderer` whose
camera is fitted once to the anatomy over all keyframe poses, and encoded: MP4 (H.264 through the ffmpeg binary
imageio-ffmpeg ships), GIF, or numbered PNGs. Ready keyframes for the knee (bend and straighten) and the hand
(open, fist, point with the index finger) are in ``workbench/viz/keyframes/``.
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from deformation.geometry import covering_grid
from deformation.kinematics.skeleton import SkeletonError
from workbench.errors import InputFileError, OutputExistsError
from workbench.io.jsonio import read_json

__all__ = [
    "Keyframes",
    "read_keyframes",
    "builtin_keyframes",
    "camera_from",
    "animate_study",
    "FORMATS",
    "scan_keyframes",
    "motion_bounds",
]

KEYFRAMES_FORMAT = "avw-keyframes"
FORMATS = (".mp4", ".gif", ".png")
_INTERPOLATIONS = ("smooth", "linear")


@dataclass
class Keyframes:
    """Keyframe times (s, increasing) and full joint-angle dicts, with the interpolation and camera."""

    times: np.ndarray
    angles: list  #: one ``{joint: np.ndarray}`` per keyframe, every joint of the skeleton present
    interpolation: str = "smooth"
    fps: float | None = None
    camera: dict = field(default_factory=dict)
    names: list = field(default_factory=list)
    source: str = ""

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def at(self, t: float) -> dict:
        """Joint angles at time ``t`` (clamped to the first and last keyframe)."""
        ts = self.times
        t = min(max(float(t), float(ts[0])), float(ts[-1]))
        i = int(np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 2))
        span = float(ts[i + 1] - ts[i])
        u = 0.0 if span <= 0 else (t - float(ts[i])) / span
        s = u * u * (3.0 - 2.0 * u) if self.interpolation == "smooth" else u
        a, b = self.angles[i], self.angles[i + 1]
        return {k: (1.0 - s) * a[k] + s * b[k] for k in a}

    def frame_times(self, n_frames: int) -> np.ndarray:
        """``n_frames`` evenly spaced times from the first keyframe to the last, both included."""
        if n_frames < 2:
            raise ValueError(f"an animation needs at least 2 frames, got {n_frames}")
        return np.linspace(float(self.times[0]), float(self.times[-1]), int(n_frames))


def _keyframes_from_dict(d, skeleton, where: str, *, check_limits: bool = True, path=None) -> Keyframes:
    def bad(msg):
        p = path if path is not None else Path(where) if where and not where.startswith("<") else None
        return InputFileError(f"{where}: {msg}", p) if p is not None else ValueError(f"{where}: {msg}")

    if not isinstance(d, dict) or d.get("format") != KEYFRAMES_FORMAT:
        raise bad(f"not a keyframe file ('format' must be {KEYFRAMES_FORMAT!r}); see `workbench animate --help`")
    if d.get("skeleton") not in (None, skeleton.name):
        raise bad(f"keyframes for the skeleton {d.get('skeleton')!r}, but the study's skeleton is {skeleton.name!r}")
    interp = d.get("interpolation", "smooth")
    if interp not in _INTERPOLATIONS:
        raise bad(f"interpolation {interp!r}: expected one of {_INTERPOLATIONS}")
    kfs = d.get("keyframes")
    if not isinstance(kfs, list) or len(kfs) < 2:
        raise bad('needs a list \'keyframes\' of at least 2 entries {"time": s, "angles": {joint: [deg, ...]}}')
    times, angles, names = [], [], []
    zero = skeleton.zero_angles()
    for n, kf in enumerate(kfs):
        if not isinstance(kf, dict) or "time" not in kf or not isinstance(kf.get("angles", {}), dict):
            raise bad(f"keyframe {n} needs 'time' (s) and 'angles' {{joint: [degrees, ...]}}")
        if not _is_number(kf["time"]):
            raise bad(f"keyframe {n}: 'time' must be a number of seconds, got {kf['time']!r}")
        full = {k: np.asarray(v, float).copy() for k, v in zero.items()}
        for j, v in kf.get("angles", {}).items():
            if j not in full:
                raise bad(f"keyframe {n}: unknown joint {j!r}; the skeleton's joints are {sorted(full)}")
            if not isinstance(v, list) or not all(_is_number(x) for x in v):
                raise bad(f"keyframe {n}: joint {j!r} needs a list of numbers (degrees), got {v!r}")
            a = np.asarray(v, float)
            if a.shape != full[j].shape:
                raise bad(
                    f"keyframe {n}: joint {j!r} takes {full[j].size} values (degrees, then mm for a "
                    f"6-DOF joint), got {a.size}"
                )
            if not np.all(np.isfinite(a)):
                raise bad(f"keyframe {n}: joint {j!r} has a non-finite angle {v!r}")
            full[j] = a
        try:
            skeleton.pose(full)
        except (SkeletonError, ValueError) as e:
            raise bad(f"keyframe {n}: {e}") from e
        outside = skeleton.limit_problems(full) if check_limits else []
        if outside:
            raise bad(
                f"keyframe {n}: {outside[0]}"
                + (f" (and {len(outside) - 1} more)" if len(outside) > 1 else "")
                + (
                    ""
                    if "half a turn" in outside[0]
                    else ", the range of motion of the study's skeleton (skeleton.json, 'limits')"
                )
            )
        times.append(float(kf["time"]))
        angles.append(full)
        names.append(str(kf.get("name", f"keyframe {n}")))
    t = np.asarray(times)
    if np.any(np.diff(t) <= 0):
        raise bad(f"keyframe times must increase strictly, got {times}")
    fps = d.get("fps")
    if fps is not None and not (_is_number(fps) and fps > 0):
        raise bad(f"fps must be a positive number, got {fps!r}")
    cam = d.get("camera", {}) or {}
    if not isinstance(cam, dict):
        raise bad("'camera' must be an object {view, azimuth, elevation, zoom, orbit}")
    unknown = set(cam) - {"view", "azimuth", "elevation", "zoom", "orbit"}
    if unknown:
        raise bad(f"camera: unknown keys {sorted(unknown)} (expected view, azimuth, elevation, zoom, orbit)")
    for k in ("azimuth", "elevation", "zoom", "orbit"):
        if k in cam and not _is_number(cam[k]):
            raise bad(f"camera: {k} must be a number, got {cam[k]!r}")
    try:
        camera_from(cam)
    except ValueError as e:
        raise bad(f"camera: {e}") from e
    return Keyframes(t, angles, interp, None if fps is None else float(fps), dict(cam), names, where)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def camera_from(doc: dict, **override):
    """A :class:`workbench.viz.view.Camera` from a keyframe file's ``camera`` block (``override`` wins)."""
    from workbench.viz.render import Camera

    d = {"view": "auto", "azimuth": 0.0, "elevation": 0.0, "zoom": 1.0}
    d.update({k: doc[k] for k in ("view", "azimuth", "elevation", "zoom") if k in doc})
    d.update({k: v for k, v in override.items() if v is not None})
    return Camera(
        view=str(d["view"]), azimuth=float(d["azimuth"]), elevation=float(d["elevation"]), zoom=float(d["zoom"])
    )


def read_keyframes(path, skeleton) -> Keyframes:
    """Read and check a keyframe file against ``skeleton`` (clear errors naming the file and keyframe)."""
    path = Path(path)
    return _keyframes_from_dict(read_json(path), skeleton, str(path))


def builtin_keyframes(skeleton) -> Keyframes:
    """The ready keyframes for the knee or hand skeleton (``workbench/viz/keyframes/<name>.json``)."""
    res = resources.files("workbench.viz") / "keyframes" / f"{skeleton.name}.json"
    if not res.is_file():
        have = sorted(
            p.name[:-5] for p in (resources.files("workbench.viz") / "keyframes").iterdir() if p.name.endswith(".json")
        )
        raise InputFileError(
            f"no ready keyframes for the skeleton {skeleton.name!r} (there are {have}); "
            "pass --keyframes FILE (see `workbench animate --help` for the format)."
        )
    import json

    return _keyframes_from_dict(
        json.loads(res.read_text(encoding="utf-8")), skeleton, f"<builtin {skeleton.name}.json>"
    )


def scan_keyframes(study, *, seconds_per_pose: float = 1.0) -> Keyframes:
    """Keyframes through the study's example poses (Kurihara Fig. 9: "Pose 1 ... transformed into Pose 5
    and then into Pose 3"): the template's rest pose, each scan's estimated joint angles in the study's
    order, and rest again, ``seconds_per_pose`` apart (``--keyframes scans``).  A joint the pose stage gave
    no angle (a flagged bone's) stays at rest."""
    sk = study.skeleton()
    zero = sk.zero_angles()
    frames = [
        {"time": 0.0, "name": "template (rest)", "angles": {k: np.asarray(v, float).tolist() for k, v in zero.items()}}
    ]
    for sid in study.scan_ids:
        a = study.pose(sid).joint_angles
        if not a:
            raise InputFileError(
                f"{study.root}: scan {sid!r} has no joint angles; run `workbench pose "
                f"{study.root} --force` first (--keyframes scans follows the scans' poses)",
                study.manifest_path,
            )
        frames.append(
            {
                "time": len(frames) * seconds_per_pose,
                "name": sid,
                "angles": {k: np.asarray(v, float).tolist() for k, v in a.items() if k in zero},
            }
        )
    frames.append({"time": len(frames) * seconds_per_pose, "name": "template (rest)", "angles": frames[0]["angles"]})
    # measured angles: a straight joint estimated at −1° is no user error (no range-of-motion check)
    return _keyframes_from_dict(
        {"format": KEYFRAMES_FORMAT, "skeleton": sk.name, "keyframes": frames},
        sk,
        f"<the scans of {study.root.name}>",
        check_limits=False,
        path=study.manifest_path,
    )


# -- output ----------------------------------------------------------------------------------------------
class _Writer:
    """Frames to MP4 / GIF / numbered PNGs, written to a temporary name and moved into place at the end."""

    def __init__(self, out: Path, fps: float, overwrite: bool):
        import secrets

        self.out, self.fps, self.kind = out, fps, out.suffix.lower()
        self.check(out, overwrite)
        self.token = secrets.token_hex(4)
        self.n = 0
        self._gif = []
        if self.kind == ".png":
            self.staging = out.parent / f".{out.stem}.frames-{self.token}"
        else:
            self.staging = out.parent / f".{out.stem}.tmp-{self.token}{self.kind}"
        self.overwrite = overwrite
        self._w = None
        if self.kind == ".png":
            self.staging.mkdir()
        elif self.kind == ".mp4":
            import imageio.v2 as iio2

            # H.264 in yuv420p (what players and slide software accept); even sizes are checked by parse_size;
            # macro_block_size=1: no silent resize to multiples of 16
            self._w = iio2.get_writer(
                str(self.staging),
                format="FFMPEG",
                fps=fps,
                codec="libx264",
                pixelformat="yuv420p",
                quality=8,
                macro_block_size=1,
                ffmpeg_log_level="error",
                output_params=["-threads", "1"],
            )

    @staticmethod
    def check(out: Path, overwrite: bool) -> None:
        """The target's format, folder (missing or read-only) and clash, before any work."""
        from workbench.io.atomic import check_output_folder

        if out.suffix.lower() not in FORMATS:
            raise ValueError(
                f"{out}: the animation format is chosen by the extension: .mp4 (H.264), .gif, or "
                ".png (numbered frames <name>_0000.png, ...)"
            )
        check_output_folder(out, "--out")
        if not overwrite:
            clash = _Writer._existing_files(out)
            if clash:
                raise OutputExistsError(clash[0], f"{clash[0]} exists; pass --force to replace it.")

    @staticmethod
    def _existing_files(out: Path) -> list:
        if out.suffix.lower() == ".png":
            return sorted(out.parent.glob(f"{out.stem}_[0-9][0-9][0-9][0-9].png"))
        return [out] if out.exists() else []

    def _existing(self):
        return self._existing_files(self.out)

    def frame_name(self, i: int) -> str:
        return f"{self.out.stem}_{i:04d}.png"

    def add(self, img: np.ndarray) -> None:
        from workbench.io.atomic import naming_failures

        with naming_failures(self.out):  # a full disk or a file-size limit: one line naming the output
            self._add(img)

    def _add(self, img: np.ndarray) -> None:
        if self.kind == ".mp4":
            self._w.append_data(img)
        elif self.kind == ".gif":
            self._gif.append(img)
        else:
            import imageio.v3 as iio

            (self.staging / self.frame_name(self.n)).write_bytes(iio.imwrite("<bytes>", img, extension=".png"))
        self.n += 1

    def commit(self) -> list[Path]:
        from workbench.io.atomic import naming_failures

        with naming_failures(self.out):
            return self._commit()

    def _commit(self) -> list[Path]:
        if self.kind == ".mp4":
            self._w.close()
            self._w = None
            _check_video(self.staging, self.n)
        elif self.kind == ".gif":
            import imageio.v3 as iio

            # the GIF frame delay is in whole hundredths of a second: 24 fps plays at 25
            self.staging.write_bytes(
                iio.imwrite("<bytes>", np.stack(self._gif), extension=".gif", duration=1000.0 / self.fps, loop=0)
            )
        from workbench.io.atomic import commit_file

        if self.kind == ".png":
            # A set of files cannot be swapped in one step: every frame is complete in the
            # staging folder first (each flushed as it is moved), then the old frames (with --force) are removed
            # and the new ones moved
            # in, without clobbering a frame that appeared meanwhile unless --force.
            names = [self.frame_name(i) for i in range(self.n)]
            stale = self._existing()
            if stale and not self.overwrite:
                raise OutputExistsError(stale[0], f"{stale[0]} appeared while rendering; pass --force to replace it.")
            for p in stale:
                if p.name not in names:
                    p.unlink()
            done = []
            for name in names:
                commit_file(self.staging / name, self.out.parent / name, overwrite=self.overwrite)
                done.append(self.out.parent / name)
            self.staging.rmdir()
            return done
        commit_file(
            self.staging, self.out, overwrite=self.overwrite
        )  # no clobber without --force, even at the last moment
        return [self.out]

    def abort(self) -> None:
        if self._w is not None:
            try:
                self._w.close()
            except Exception:  # noqa: BLE001 - cleaning up after a failure
                pass
        if self.staging.is_dir():
            shutil.rmtree(self.staging, ignore_errors=True)
        elif self.staging.exists():
            self.staging.unlink()


def _check_video(path: Path, n_frames: int) -> None:
    """Raise :class:`OSError` unless the video at ``path`` decodes to ``n_frames`` frames: ffmpeg ends normally
    when the disk fills or a file-size limit cuts its output short (the container's index is then missing)."""
    import imageio_ffmpeg

    try:
        n, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    except RuntimeError as e:
        raise OSError("the video is incomplete: ffmpeg cannot read it back") from e
    if n != n_frames:
        raise OSError(f"the video holds {n} of its {n_frames} frames")


# -- the animation -----------------------------------------------------------------------------------------
def _sweep_times(keyframes: Keyframes, per_segment: int = 4) -> np.ndarray:
    """Every keyframe's time and ``per_segment − 1`` times between each two: a curling finger sweeps beyond
    both its open and its closed position."""
    ts = keyframes.times
    return np.unique(np.concatenate([np.linspace(a, b, per_segment + 1) for a, b in zip(ts, ts[1:])]))


def motion_bounds(poser, skeleton, keyframes: Keyframes, mask: np.ndarray, margin_mm: float) -> tuple:
    """World box of the visible template tissue over the motion (forward maps only, no resampling), sampled
    at ``_sweep_times``."""
    from workbench.viz.render import points_bounds, union_bounds

    return union_bounds(
        [points_bounds(poser.forward(skeleton.pose(keyframes.at(t)))[mask], margin_mm) for t in _sweep_times(keyframes)]
    )


def animate_study(
    folder,
    out,
    *,
    keyframes=None,
    method: str = "auto",
    weighting: str = "psd",
    fps=None,
    size=(640, 480),
    n_frames: int | None = None,
    transfer="mri",
    camera=None,
    orbit=None,
    clip=None,
    bones: bool = False,
    background=(0.0, 0.0, 0.0),
    mapper: str = "auto",
    skin: str | None = None,
    overwrite: bool = False,
    map_factor: int = 1,
    progress=None,
) -> dict:
    """Render the study's template moving through ``keyframes`` and write ``out`` (.mp4, .gif or .png frames).

    ``skin`` ("ssd", "psd" or "wpsd"): instead of the volume, Kurihara's surface model (``workbench
    surface``) posed by that method at every frame and rendered as a mesh, through the same keyframes.

    ``keyframes``: a file, a :class:`Keyframes`, or ``None`` for the ready
    ones of the study's skeleton.  ``fps`` (default: the file's, else 24) and
    ``n_frames`` (default: duration × fps + 1) set the timing; ``camera``
    (:class:`workbench.viz.view.Camera`) and ``orbit`` (degrees of azimuth over
    the animation) default to the file's ``camera``.  Returns a summary with
    the frame count and the time spent deforming, rendering and encoding.
    """
    from workbench.deform import study_poser
    from workbench.study import read_study
    from workbench.viz.render import VolumeRenderer, content_mask, first_visible, robust_range, transfer_function

    say = progress or (lambda line: None)
    t_start = time.perf_counter()
    study = read_study(folder)
    out = Path(out)
    _Writer.check(out, overwrite)  # format, folder, clash: before the deformation model is built
    if skin is not None:
        from deformation.models.surface_model import SURFACE_METHODS

        if skin not in SURFACE_METHODS:
            raise ValueError(f"--skin must be one of {', '.join(SURFACE_METHODS)}, got {skin!r}")
        if bones:
            raise ValueError("--bones draws posed bone labels on a volume animation; leave it out with --skin")
        if int(map_factor) != 1:
            raise ValueError(
                "--map-factor sets how a volume animation's maps are solved; a --skin animation poses "
                "a mesh: leave it out"
            )
        model = study.surface_model()  # a clear "run `workbench surface` first" before any work
        poser = None
    else:
        from workbench.deform import say_if_compiling

        say_if_compiling(say)
        poser = study_poser(study, method=method, weighting=weighting, progress=say)
    sk = study.skeleton()
    if keyframes is None:
        kf = builtin_keyframes(sk)
    elif isinstance(keyframes, Keyframes):
        kf = keyframes
    else:
        kf = read_keyframes(keyframes, sk)
    fps = float(fps if fps is not None else (kf.fps or 24.0))
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    n = int(n_frames) if n_frames is not None else int(round(kf.duration * fps)) + 1
    if n < 2:
        raise ValueError(f"an animation needs at least 2 frames, got {n} (duration {kf.duration:g} s at {fps:g} fps)")
    cam_doc = kf.camera
    if camera is None:
        camera = camera_from(cam_doc)
    orbit = float(cam_doc.get("orbit", 0.0) if orbit is None else orbit)
    writer = _Writer(out, fps, overwrite)
    try:
        if skin is not None:  # the surface model's mesh, posed frame by frame
            from workbench.viz.render import points_bounds, union_bounds

            def deform(pose):
                return model.deform(pose, skin)

            bounds = union_bounds([points_bounds(deform(sk.pose(kf.at(t))).vertices, 2.0) for t in _sweep_times(kf)])
            g = None
            renderer = VolumeRenderer(
                None, size=size, camera=camera, clip=clip, background=background, bounds=bounds, mapper=mapper
            )
            what = f"Kurihara's surface model ({model.base.n_triangles} triangles) by {skin.upper()}"
        else:
            template = poser.template
            g = template.geometry
            tf = transfer_function(transfer)
            lo, hi = robust_range(template.data)
            thr = first_visible(tf.resolved(lo, hi))
            mask = content_mask(template.data, thr)
            wf = poser.weights_factor  # the forward map lies on the weights' grid
            bounds = motion_bounds(poser, sk, kf, mask[::wf, ::wf, ::wf], 2.0 * max(g.spacing))
            # frames on a grid the whole motion fits in: curling fingers pass below a flat hand's slab
            g = covering_grid(g, bounds)
            renderer = VolumeRenderer(
                g,
                size=size,
                transfer=tf,
                reference=template,
                camera=camera,
                clip=clip,
                background=background,
                bounds=bounds,
                mapper=mapper,
            )
            what = f"{poser.method.upper()} deformation"
        say(
            f"{n} frames at {fps:g} fps ({kf.duration:g} s, {len(kf.times)} keyframes, {kf.interpolation}); "
            f"{what}; {renderer.backend.describe()}, {renderer.mapper_name} mapper"
        )
        t_deform = t_render = t_encode = 0.0
        base_az = camera.azimuth
        last_say = time.perf_counter()
        with renderer:
            for i, t in enumerate(kf.frame_times(n)):
                t0 = time.perf_counter()
                if skin is not None:
                    mesh = deform(sk.pose(kf.at(t)))
                else:
                    posed = poser.pose(sk.pose(kf.at(t)), labels=bones, target=g, map_factor=map_factor)
                t1 = time.perf_counter()
                if orbit:
                    renderer.set_camera(replace(camera, azimuth=base_az + orbit * i / (n - 1)))
                if skin is not None:
                    renderer.clear_surfaces()
                    renderer.add_mesh(mesh)
                    img = renderer.render()
                else:
                    if bones and posed.labels is not None:
                        renderer.clear_surfaces()
                        renderer.add_labels(posed.labels)
                    img = renderer.render(posed.volume)
                t2 = time.perf_counter()
                writer.add(img)
                t3 = time.perf_counter()
                t_deform, t_render, t_encode = t_deform + t1 - t0, t_render + t2 - t1, t_encode + t3 - t2
                done = i + 1
                now = time.perf_counter()
                if done in (1, n) or now - last_say >= 2.0:  # a line every ~2 s, not one per frame
                    last_say = now
                    left = (t_deform + t_render + t_encode) / done * (n - done)
                    say(
                        f"frame {done}/{n}  t={t:.2f} s  deform {t1 - t0:.2f} s  render {t2 - t1:.2f} s  "
                        f"elapsed {now - t_start:.0f} s  ~{left:.0f} s left"
                    )
        t4 = time.perf_counter()
        files = writer.commit()
        t_encode += time.perf_counter() - t4
    except BaseException:
        writer.abort()
        raise
    return {
        "out": str(out),
        "files": len(files),
        "frames": n,
        "fps": fps,
        "size": list(size),
        "method": poser.method if skin is None else f"surface {skin}",
        "keyframes": kf.source,
        "backend": renderer.backend.describe(),
        "mapper": renderer.mapper_name,
        "deform_seconds": t_deform,
        "render_seconds": t_render,
        "encode_seconds": t_encode,
        "total_seconds": time.perf_counter() - t_start,
        "render_seconds_per_frame": t_render / n,
        "deform_seconds_per_frame": t_deform / n,
        "bounds_mm": [round(v, 2) for v in bounds],
        "grid": None if g is None else list(g.size),
    }
