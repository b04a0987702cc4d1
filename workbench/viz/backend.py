"""The off-screen OpenGL context VTK renders in: EGL, else OSMesa, probed once per process.

On a software renderer (Mesa's llvmpipe, as on machines without a GPU) the
volume renderer uses the CPU ray caster ``vtkFixedPointVolumeRayCastMapper``
(faster there than the GPU ray caster run through Mesa: see
docs/measurements/library-choices.md, ``benchmarks/bench_rendering.py``); with a
hardware renderer ``vtkGPUVolumeRayCastMapper``.  ``AVW_OPENGL=egl`` or
``osmesa`` forces one context.
"""

from __future__ import annotations

import functools
import os
import re
from dataclasses import dataclass

from workbench.errors import WorkbenchError

__all__ = ["Backend", "RenderError", "opengl_backend", "offscreen_available"]

_SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "software rasterizer", "lavapipe")


class RenderError(WorkbenchError, RuntimeError):
    """No off-screen OpenGL, or a rendering request that cannot be met."""


# -- the OpenGL context --------------------------------------------------------------------------
@dataclass(frozen=True)
class Backend:
    name: str  #: "egl" or "osmesa"
    window_class: str  #: the VTK render-window class
    renderer: str  #: the OpenGL renderer string (e.g. "llvmpipe (LLVM 15.0.6, 256 bits)")
    software: bool  #: a software rasteriser (no GPU)

    @property
    def mapper(self) -> str:
        """The volume mapper ``auto`` picks: ``fixed`` (CPU ray cast) on software OpenGL, else ``gpu``."""
        return "fixed" if self.software else "gpu"

    def describe(self) -> str:
        kind = "software" if self.software else "hardware"
        return f"{self.name.upper()} ({self.window_class}), {kind} OpenGL: {self.renderer}"


_WINDOWS = {"egl": "vtkEGLRenderWindow", "osmesa": "vtkOSOpenGLRenderWindow"}


def _probe(name: str) -> Backend | None:
    import vtkmodules.vtkRenderingOpenGL2 as gl
    from vtkmodules.vtkCommonCore import vtkObject
    from vtkmodules.vtkRenderingCore import vtkRenderer

    cls = getattr(gl, _WINDOWS[name], None)
    if cls is None:
        return None
    warn = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()  # a failed probe prints VTK errors; we report our own
    win = None
    try:
        win = cls()
        win.SetOffScreenRendering(1)
        win.SetSize(8, 8)
        win.AddRenderer(vtkRenderer())
        win.Render()
        if not win.SupportsOpenGL():
            return None
        caps = win.ReportCapabilities() or ""
        m = re.search(r"OpenGL renderer string:\s*(.+)", caps)
        renderer = m.group(1).strip() if m else "unknown"
    except Exception:  # noqa: BLE001 - any failure means this backend is unusable here
        return None
    finally:
        if win is not None:
            try:
                win.Finalize()
            except Exception:  # noqa: BLE001 - releasing a context that never worked
                pass
        vtkObject.SetGlobalWarningDisplay(warn)
    software = any(s in renderer.lower() for s in _SOFTWARE_GL)
    return Backend(name, _WINDOWS[name], renderer, software)


@functools.cache
def _backend_cached(forced: str) -> Backend | None:
    for name in [forced] if forced else ["egl", "osmesa"]:
        b = _probe(name)
        if b is not None:
            return b
    return None


def opengl_backend() -> Backend:
    """The off-screen OpenGL context this machine offers: EGL, else OSMesa (probed once per process).

    ``AVW_OPENGL=egl`` or ``AVW_OPENGL=osmesa`` forces one.  Raises
    :class:`RenderError` naming the Debian packages to install when neither works.
    """
    forced = os.environ.get("AVW_OPENGL", "").strip().lower()
    if forced and forced not in _WINDOWS:
        raise RenderError(f"AVW_OPENGL={forced!r}: expected 'egl' or 'osmesa' (or unset it to probe both)")
    b = _backend_cached(forced)
    if b is None:
        tried = forced or "EGL and OSMesa"
        raise RenderError(
            f"no off-screen OpenGL context ({tried} tried): install the Debian packages libegl1 "
            "libegl-mesa0 libgl1-mesa-dri (EGL) or libosmesa6 (OSMesa) — `make venv` does it "
            "as root."
        )
    return b


def offscreen_available() -> bool:
    """Whether :func:`opengl_backend` finds a context (tests skip rendering when not)."""
    try:
        opengl_backend()
        return True
    except RenderError:
        return False
