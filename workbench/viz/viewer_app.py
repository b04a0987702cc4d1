"""``workbench view``'s web page: trame (Kitware's framework for VTK applications in the browser) around a
:class:`workbench.viz.viewer.PoseSession`.

The server renders (off-screen VTK, as ``workbench render``) and sends each image to the page as a JPEG; the
page's client ships inside the trame packages, nothing is fetched at run time.  One slider (with a number
field) per degree of freedom, grouped by joint, within the skeleton's limits; a menu of poses; reset; the
camera's azimuth, elevation and zoom; the clipping plane; compare with a scan; three orthogonal slices; save
the pose, a PNG, keyframes and their animation.  While a slider moves each change is posed with the coarse
maps (every 2nd voxel); ``SETTLE_S`` after the last change the exact maps redo it.

The images go through the page's state, not trame-vtk's remote view: that view renders the window again when
its JPEG is not ready yet, half a second later (``delta_stale_time_before_render``), which made a slider
move's image arrive about 1 s after the move at the demo's size (docs: viewer measurements).
"""

from __future__ import annotations

import asyncio
import sys
import time

__all__ = ["build_app", "serve", "SETTLE_S"]

JPEG_QUALITY = 90  # the images sent to the page
COALESCE_S = 0.01  # a slider's changes arriving within this are posed once
SETTLE_S = 0.3  # seconds without a change after which the exact pose replaces the coarse one
SHOWN_DIGITS = 2  # the number fields show a preset's angles rounded to this many decimals
SHOWN_DIGITS_TOLERANCE = 0.6 * 10**-SHOWN_DIGITS  # a value within this of the pose's is its rounded echo
FLICKER_S = 0.8  # the compare view's flicker: seconds each of the model and the scan stays on screen


def build_app(session, *, name: str = "workbench view"):
    """The trame server of ``session`` (not started)."""
    from PIL import Image
    from trame.app import get_server
    from trame.ui.vuetify3 import SinglePageWithDrawerLayout
    from trame.widgets import html
    from trame.widgets import vuetify3 as v3

    from workbench.report.figures import encode_jpeg
    from workbench.report.html import data_uri
    from workbench.viz.render import PRESETS

    server = get_server(name, client_type="vue3")
    state = server.state
    dofs = session.dofs
    keys = [d.key for d in dofs]
    for d in dofs:
        state[d.key] = session.value(d)
    poses = session.presets()
    state.update(
        {
            "pose_choice": poses[0],
            "status": "",
            "saved": "",
            "n_keyframes": 0,
            "method_line": (
                "EVD (Rhee Eq. 6–7): the study's example-based model"
                if session.method == "evd"
                else "VBD (Rhee Eq. 2): the study has no EVD model (workbench model builds one)"
            ),
        }
    )
    state.update(
        {
            "clip_on": session.renderer.clipping,
            "clip_axis": (session.renderer.clip.axis if session.renderer.clip is not None else "z"),
            "clip_fraction": (session.renderer.clip.fraction if session.renderer.clip is not None else 0.5),
            "preset": str(session.transfer),
            "compare": "model",
            "sigma_overlay": False,
            "has_model": session.method == "evd",  # the posed model has an expected error to overlay
            "compare_scan": "",
            "showing": "model",
            "image": "",
            "azimuth": session.renderer.camera.azimuth,
            "elevation": session.renderer.camera.elevation,
            "zoom": session.renderer.camera.zoom,
            "slice_xy": "",
            "slice_xz": "",
            "slice_yz": "",
        }
    )
    pending = {"generation": 0, "flicker": None, "scheduled": False}

    def push_image() -> None:
        state.image = data_uri(encode_jpeg(Image.fromarray(session.image), quality=JPEG_QUALITY), "image/jpeg")

    @state.change("azimuth", "elevation", "zoom")
    def on_camera(azimuth, elevation, zoom, **_):
        try:
            session.set_camera(azimuth=float(azimuth), elevation=float(elevation), zoom=float(zoom))
        except (TypeError, ValueError):
            return  # a field being typed into
        session.show(session.showing)
        push_image()

    def refresh_slices() -> None:
        with state:  # its own flush: the image has gone to the page first
            for which, png in session.slices().items():
                state[f"slice_{which}"] = data_uri(png, "image/png")

    def slices_next() -> None:
        asyncio.get_event_loop().call_soon(refresh_slices)

    def show(exact: bool) -> None:
        if state.compare != "model":
            state.compare = "model"  # a new pose: the model again
        session.update(exact=exact)
        t = session.last
        state.showing = "model"
        state.status = f"{'exact' if exact else 'coarse (every 2nd voxel)'} map: deform {t['deform_s']:.2f} s"
        push_image()
        if exact:
            slices_next()

    def show_what(what: str) -> None:
        try:
            session.show(what)
        except Exception as e:  # noqa: BLE001 - said on the page; the server goes on
            state.saved = f"could not show {what}: {e}"
            return
        state.showing = "model" if what == "model" else f"scan {what}"
        push_image()
        slices_next()

    async def flicker() -> None:
        try:
            while state.compare == "flicker" and state.compare_scan:
                with state:  # the scan chosen now (the menu may have changed it since the last pass)
                    show_what(state.compare_scan if session.showing == "model" else "model")
                await asyncio.sleep(FLICKER_S)
        finally:
            pending["flicker"] = None

    @state.change("sigma_overlay")
    def on_sigma_overlay(sigma_overlay, **_):
        session.sigma_overlay = bool(sigma_overlay)
        slices_next()

    @state.change("compare")
    def on_compare(compare, **_):
        if compare == "flicker":
            if pending["flicker"] is None:
                pending["flicker"] = asyncio.ensure_future(flicker())
        elif compare in ("model", "scan"):
            want = "model" if compare == "model" or not state.compare_scan else state.compare_scan
            if session.showing != want:
                show_what(want)

    @state.change("clip_on", "clip_axis", "clip_fraction")
    def on_clip(clip_on, clip_axis, clip_fraction, **_):
        try:
            fraction = min(max(float(clip_fraction), 0.0), 1.0)
        except (TypeError, ValueError):
            return
        if session.renderer.clip is None or (session.renderer.clip.axis, session.renderer.clip.fraction) != (
            clip_axis,
            fraction,
        ):
            session.move_clip(clip_axis, fraction)
        session.set_clipping(bool(clip_on))
        show_what(session.showing)

    @state.change("preset")
    def on_preset(preset, **_):
        if preset and preset != str(session.transfer):
            session.set_transfer(preset)
            show_what(session.showing)

    def settle(generation: int) -> None:
        if generation == pending["generation"]:  # no change since: the exact pose
            with state:
                show(True)

    @state.change(*keys)
    def on_angles(**values):
        changed = False
        for d in dofs:
            v = values.get(d.key)
            try:
                v = float(v)
            except (TypeError, ValueError):
                continue  # a number field being typed into
            if abs(v - session.value(d)) > SHOWN_DIGITS_TOLERANCE:  # not the echo of a preset shown rounded
                session.set(d.joint, d.index, v)
                changed = True
                if session.value(d) != v:  # beyond the joint's limits: show where it stopped
                    state[d.key] = session.value(d)
        if not changed:
            return
        pending["generation"] += 1
        state.compare_scan = ""
        state.pose_choice = None  # no longer the menu's pose: choosing it again applies it
        if not pending["scheduled"]:  # the changes that arrive meanwhile (a drag) are posed once, the latest
            pending["scheduled"] = True
            asyncio.get_event_loop().call_later(COALESCE_S, coarse)

    def coarse() -> None:
        pending["scheduled"] = False
        generation = pending["generation"]
        with state:
            show(False)
        asyncio.get_event_loop().call_later(SETTLE_S, settle, generation)

    def sync_sliders() -> None:
        # their change handler sees the values as the pose's own (within SHOWN_DIGITS_TOLERANCE) and does nothing
        for d in dofs:
            state[d.key] = round(session.value(d), SHOWN_DIGITS)

    @state.change("pose_choice")
    def on_pose(pose_choice, **_):
        if pose_choice not in poses:
            return
        session.use(pose_choice)
        state.compare_scan = pose_choice[len("scan ") :] if pose_choice.startswith("scan ") else ""
        sync_sliders()
        show(True)

    def reset():
        state.pose_choice = poses[0]  # its change handler poses it (after a slider moved, the menu is empty)

    def report(what: str, fn):
        try:
            state.saved = f"{what}: {fn()}"
        except Exception as e:  # noqa: BLE001 - shown on the page, the server goes on
            state.saved = f"{what} failed: {e}"

    def save_pose():
        report("pose saved", session.save_pose)

    def save_png():
        report("PNG saved", session.save_png)

    def add_keyframe():
        state.n_keyframes = session.add_keyframe()
        state.saved = f"keyframe {state.n_keyframes} added"

    async def export():
        # in a worker thread (its own render window): the page stays live while the frames are made
        state.saved = f"exporting {session.keyframe_count} keyframes ..."
        state.flush()
        t0 = time.perf_counter()
        try:
            k, a = await asyncio.get_event_loop().run_in_executor(None, session.export_animation)
            state.saved = f"animation written: {k} and {a} ({time.perf_counter() - t0:.0f} s)"
        except Exception as e:  # noqa: BLE001 - said on the page; the server goes on
            state.saved = f"animation failed: {e}"
        state.flush()

    state.trame__title = f"workbench view: {session.study.root.name}"
    with SinglePageWithDrawerLayout(server) as layout:
        layout.title.set_text(f"{session.study.root.name} — {session.method.upper()}")
        with layout.drawer as drawer:
            drawer.width = 380
            with v3.VContainer(classes="pa-2"):
                html.Div("{{ method_line }}", classes="text-caption mb-2", id="method")
                v3.VSelect(
                    label="pose", items=("poses", poses), v_model=("pose_choice",), density="compact", id="pose-menu"
                )
                v3.VBtn("reset to rest", click=reset, size="small", classes="mb-2", id="reset")
                presets = sorted({*PRESETS, str(session.transfer)})
                v3.VSelect(
                    label="transfer function",
                    items=("presets", presets),
                    v_model=("preset",),
                    density="compact",
                    hide_details=True,
                    id="preset",
                )
                with v3.VRow(dense=True, align="center", classes="ma-0"):
                    v3.VCheckbox(
                        v_model=("clip_on",),
                        label="cut open",
                        density="compact",
                        hide_details=True,
                        id="clip",
                        style="flex: 2",
                    )
                    v3.VSelect(
                        items=("clip_axes", ["x", "y", "z"]),
                        v_model=("clip_axis",),
                        density="compact",
                        hide_details=True,
                        id="clip-axis",
                        style="flex: 1",
                    )
                v3.VSlider(
                    v_model=("clip_fraction",),
                    min=0.05,
                    max=0.95,
                    step=0.05,
                    label="cut at",
                    hide_details=True,
                    density="compact",
                    thumb_label=True,
                    id="clip-fraction",
                )
                html.Div("camera", classes="text-subtitle-2 mt-2")
                for key, label, lo, hi, step in (
                    ("azimuth", "azimuth °", -180, 180, 5),
                    ("elevation", "elevation °", -85, 85, 5),
                    ("zoom", "zoom", 0.5, 4.0, 0.1),
                ):
                    v3.VSlider(
                        v_model=(key,),
                        min=lo,
                        max=hi,
                        step=step,
                        label=label,
                        hide_details=True,
                        density="compact",
                        thumb_label=True,
                        id=f"camera-{key}",
                    )
                html.Div("compare with the scan (at a scan's pose):", classes="text-caption mt-1")
                with v3.VBtnToggle(
                    v_model=("compare",),
                    mandatory=True,
                    density="compact",
                    disabled=("!compare_scan",),
                    id="compare",
                ):
                    v3.VBtn("model", value="model", size="small", id="compare-model")
                    v3.VBtn("scan", value="scan", size="small", id="compare-scan")
                    v3.VBtn("flicker", value="flicker", size="small", id="compare-flicker")
                v3.VCheckbox(
                    v_model=("sigma_overlay",),
                    label="the slices: the expected error σ over them (the posed model's, or a scan's registration's)",
                    density="compact",
                    hide_details=True,
                    disabled=("!compare_scan && !has_model",),
                    id="sigma-overlay",
                )
                joints = []
                for d in dofs:
                    if d.joint not in joints:
                        joints.append(d.joint)
                for j in joints:
                    html.Div(j, classes="text-subtitle-2 mt-2")
                    for d in (d for d in dofs if d.joint == j):
                        with v3.VRow(dense=True, align="center", classes="ma-0"):
                            v3.VSlider(
                                v_model=(d.key,),
                                min=d.low,
                                max=d.high,
                                step=0.5,
                                label=d.label,
                                hide_details=True,
                                density="compact",
                                id=f"slider-{d.key}",
                                style="flex: 3",
                            )
                            v3.VTextField(
                                v_model_number=(d.key,),
                                type="number",
                                step=0.5,
                                hide_details=True,
                                density="compact",
                                id=f"value-{d.key}",
                                style="flex: 1; min-width: 70px",
                            )
                with v3.VRow(dense=True, classes="mt-3 ma-0"):
                    v3.VBtn("save pose", click=save_pose, size="small", id="save-pose", classes="mr-1 mb-1")
                    v3.VBtn("save PNG", click=save_png, size="small", id="save-png", classes="mr-1 mb-1")
                    v3.VBtn("add keyframe", click=add_keyframe, size="small", id="add-keyframe", classes="mr-1 mb-1")
                    v3.VBtn(
                        "export animation",
                        click=export,
                        size="small",
                        id="export",
                        disabled=("n_keyframes < 2",),
                        classes="mb-1",
                    )
                html.Div("{{ saved }}", classes="text-caption mt-2", id="saved")
                html.Div("{{ status }}", classes="text-caption mt-1", id="status")
        with layout.content:
            with html.Div(style="display: flex; flex-direction: column; height: 100%"):
                html.Div("showing: {{ showing }}", classes="text-caption px-2", id="showing")
                with html.Div(style="flex: 1; position: relative; min-height: 300px"):
                    with html.Div(id="view", style="position: absolute; inset: 0; background: #000"):
                        html.Img(src=("image",), style="width: 100%; height: 100%; object-fit: contain")
                with html.Div(style="display: flex; gap: 4px; height: 180px; background: #000", id="slices"):
                    for which in ("xy", "xz", "yz"):
                        html.Img(
                            src=(f"slice_{which}",),
                            title=f"{which} plane through the grid's centre",
                            style="height: 100%; object-fit: contain; flex: 1",
                            id=f"slice-{which}",
                        )
    show(True)
    return server


def serve(server, *, host: str, port: int, open_browser: bool) -> None:
    """Run ``server`` until Ctrl-C (trame's own command-line parsing kept away from the workbench's)."""
    argv = sys.argv
    sys.argv = argv[:1]
    try:
        server.start(host=host, port=port, open_browser=open_browser, show_connection_info=False, timeout=0)
    finally:
        sys.argv = argv
