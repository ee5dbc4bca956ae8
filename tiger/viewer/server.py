"""The web viewer: a viser server whose frames are drawn by TIGER's rasterizer.

Each browser tab reports its camera; one render thread draws the latest camera of every tab (a
camera that arrives while a frame is drawn replaces the waiting one: no queue of stale frames),
small while the camera moves and at the canvas size once it has rested for ``rest_s``, and sends
it as the page's background image (JPEG). The panels call :class:`~tiger.viewer.state.ViewerState`.
"""
from __future__ import annotations

import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np
import torch

from .camera import camera_from_pose, fit_size, pose_of
from .frames import MODES, render_frame
from .jobs import GUIDANCES, DeleteJob, EditJob, EditRequest, Job, guidance_availability
from .state import MAX_TEXT, SHOW, ViewerError, ViewerState

log = logging.getLogger(__name__)


class PortInUseError(OSError):
    """The port is taken by another program."""


def check_port(host: str, port: int) -> None:
    """Raise :class:`PortInUseError` when ``host:port`` cannot be bound (viser would silently move
    to the next port)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as e:
            raise PortInUseError(f"port {port} on {host} is in use ({e.strerror}); pass another --port") from None


@dataclass
class ClientView:
    """The render request of one browser tab: its latest camera and what it was last sent."""

    client: Any
    pose: Optional[tuple] = None  # (wxyz, position, fov, width, height)
    moved_at: float = 0.0
    sent_version: int = -1
    sent_full: bool = False
    dirty: bool = True
    stats: dict = field(default_factory=dict)


class ViewerServer:
    """Serve ``state`` on ``host:port``.

    Args:
        state: the viewer state (scene, selection, history).
        device: where edits run (the scene is already there).
        max_pixels: the largest frame drawn at rest (the canvas size, capped here).
        moving_pixels: the frame size while the camera moves.
        rest_s: seconds without a camera message before the full-size frame is drawn.
        jpeg_quality: JPEG quality of the frames (the resting frame; moving frames use 70).
    """

    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080, *,
                 device: Optional[torch.device] = None, max_pixels: int = 1920 * 1080,
                 moving_pixels: int = 480 * 270, rest_s: float = 0.15, jpeg_quality: int = 90) -> None:
        self.state, self.host, self.port = state, host, port
        self.device = device or state.scene.device
        self.max_pixels, self.moving_pixels, self.rest_s = max_pixels, moving_pixels, rest_s
        self.jpeg_quality = jpeg_quality
        self.views: dict[int, ClientView] = {}
        self.cond = threading.Condition()
        self.stopping = threading.Event()
        self.job: Optional[Job] = None
        self.frames_sent = 0
        self.server = None
        self._render_thread: Optional[threading.Thread] = None
        self._poll_thread: Optional[threading.Thread] = None
        self._boxes: list = []
        self._drawn_selection = None

    # -- life cycle ------------------------------------------------------------------------------
    def start(self) -> "ViewerServer":
        import viser

        check_port(self.host, self.port)
        if self.host not in ("127.0.0.1", "localhost", "::1"):
            log.warning("serving on %s: anyone who can reach this address can view, edit and delete "
                        "(and save into the output folder)", self.host)
        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
        self._initial_camera()
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._render_thread = threading.Thread(target=self._render_loop, name="tiger-viewer-render", daemon=True)
        self._render_thread.start()
        self._poll_thread = threading.Thread(target=self._poll_loop, name="tiger-viewer-status", daemon=True)
        self._poll_thread.start()
        log.info("tiger view: http://%s:%d", self.host, self.port)
        return self

    def stop(self) -> None:
        """Stop the threads and the server (a running job is cancelled first)."""
        self.stopping.set()
        if self.job is not None and not self.job.finished.is_set():
            self.job.cancel()
            self.job.wait(30)
        with self.cond:
            self.cond.notify_all()
        for t in (self._render_thread, self._poll_thread):
            if t is not None:
                t.join(timeout=10)
        if self.server is not None:
            self.server.stop()

    def serve_forever(self) -> None:
        """Block until Ctrl-C, then stop cleanly."""
        try:
            while not self.stopping.is_set():
                time.sleep(0.25)
        except KeyboardInterrupt:
            log.info("tiger view: stopping")
        finally:
            self.stop()

    # -- cameras ----------------------------------------------------------------------------------
    def start_camera(self):
        """The camera new tabs open with: the first capture camera, else an orbit view of the scene."""
        if self.state.cameras:
            return self.state.cameras[0]
        from tiger.render.views import orbit_cameras_around

        return orbit_cameras_around(self.state.scene.means, 1, 640, 480, elevation_deg=25.0, up=(0.0, -1.0, 0.0))[0]

    def _initial_camera(self) -> None:
        cam = self.start_camera()
        pose = pose_of(cam, distance=self._look_distance(cam))
        ic = self.server.initial_camera
        self.server.scene.set_up_direction(tuple(pose["up"]))
        ic.position, ic.look_at, ic.up, ic.fov = pose["position"], pose["look_at"], pose["up"], pose["fov"]

    def _look_distance(self, cam) -> float:
        centre = self.state.scene.means.detach().double().cpu().median(0).values
        return max(float((centre - cam.center.double().cpu()).norm()), 1e-3)

    def go_to(self, client, cam) -> None:
        """Move a tab's camera to ``cam`` (a capture camera)."""
        pose = pose_of(cam, distance=self._look_distance(cam))
        with client.atomic():
            client.camera.up_direction = pose["up"]
            client.camera.position = pose["position"]
            client.camera.look_at = pose["look_at"]
            client.camera.fov = pose["fov"]

    def _on_connect(self, client) -> None:
        view = ClientView(client)
        with self.cond:
            self.views[client.client_id] = view

        @client.camera.on_update
        def _(camera) -> None:
            pose = (tuple(camera.wxyz), tuple(camera.position), float(camera.fov), int(camera.image_width),
                    int(camera.image_height))
            with self.cond:
                view.pose, view.moved_at, view.dirty = pose, time.perf_counter(), True
                self.cond.notify_all()

    def _on_disconnect(self, client) -> None:
        with self.cond:
            self.views.pop(client.client_id, None)

    def browser_camera(self, view: ClientView, full: bool = True):
        """The :class:`Camera` of a tab's latest pose, at the canvas size (``full``) or small."""
        wxyz, pos, fov, w, h = view.pose
        w, h = fit_size(max(w, 16), max(h, 16), self.max_pixels if full else self.moving_pixels)
        return camera_from_pose(wxyz, pos, fov, w, h)

    # -- frames -----------------------------------------------------------------------------------
    def _next_request(self) -> Optional[tuple[ClientView, bool]]:
        """The tab to draw next and whether at full size (None: nothing to do)."""
        now = time.perf_counter()
        version = self.state.version
        best = None
        for view in self.views.values():
            if view.pose is None:
                continue
            resting = now - view.moved_at >= self.rest_s
            if view.dirty or view.sent_version != version:
                full = resting
            elif resting and not view.sent_full:
                full = True
            else:
                continue
            if best is None or view.moved_at < best[0].moved_at:  # the longest waiting first
                best = (view, full)
        return best

    def _render_loop(self) -> None:
        while not self.stopping.is_set():
            with self.cond:
                req = self._next_request()
                if req is None:
                    self.cond.wait(timeout=self.rest_s / 2)
                    continue
                view, full = req
                view.dirty = False
                version = self.state.version
            try:
                self.draw(view, full)
                view.sent_version, view.sent_full = version, full
            except Exception as e:  # a failed frame must not stop the viewer
                log.exception("frame failed")
                self._status(f"frame failed: {type(e).__name__}: {e}")
                view.sent_version, view.sent_full = version, True

    def draw(self, view: ClientView, full: bool = True) -> dict:
        """Render and send one frame to a tab; returns its timings (ms) and size."""
        cam = self.browser_camera(view, full)
        t0 = time.perf_counter()
        img = render_frame(self.state.frame_inputs(), cam.to(self.device))
        t1 = time.perf_counter()
        view.client.scene.set_background_image(img, format="jpeg", jpeg_quality=self.jpeg_quality if full else 70)
        t2 = time.perf_counter()
        self.frames_sent += 1
        view.stats = {"render_ms": 1e3 * (t1 - t0), "send_ms": 1e3 * (t2 - t1), "width": cam.width,
                      "height": cam.height, "full": full}
        if full and self.gui is not None:
            self.gui["frame"].content = (f"frame {cam.width}x{cam.height}: render {view.stats['render_ms']:.0f} ms "
                                         f"+ encode {view.stats['send_ms']:.0f} ms (#{self.frames_sent})")
        return view.stats

    # -- panels ---------------------------------------------------------------------------------
    gui: Optional[dict] = None

    def _status(self, text: str) -> None:
        if self.gui is not None:
            self.gui["status"].content = text[:2000]

    def _guard(self, fn: Callable) -> Callable:
        """A GUI callback whose errors are shown in the page (the scene stays as it was)."""

        def wrapped(event) -> None:
            try:
                fn(event)
            except ViewerError as e:
                self._status(f"⚠ {e}")
            except Exception as e:  # noqa: BLE001 - reported in the page
                log.exception("viewer action failed")
                self._status(f"⚠ {type(e).__name__}: {e}")

        return wrapped

    def _build_gui(self) -> None:
        gui, st = self.server.gui, self.state
        g: dict = {}
        self.gui = g
        lang_note = st.language_note()
        with gui.add_folder("View"):
            g["mode"] = gui.add_dropdown("Render", MODES, initial_value="RGB")
            g["background"] = gui.add_rgb("Background", tuple(int(255 * c) for c in st.background))
            g["fov"] = gui.add_slider("FOV (deg)", 10.0, 120.0, 1.0, round(math.degrees(self.start_camera().fov_y)))
            names = [c.image_name or f"camera {i}" for i, c in enumerate(st.cameras)] or ["(no cameras.json)"]
            g["cameras"] = gui.add_dropdown("Capture cameras", names, initial_value=names[0],
                                            disabled=not st.cameras)
            g["frame"] = gui.add_markdown("frame: waiting for the browser's camera")
        with gui.add_folder("Ask and select"):
            if lang_note or st.encoder is None:
                g["ask_note"] = gui.add_markdown(f"*{lang_note or st.encoder_note}*")
            g["query"] = gui.add_text("Query", "", hint="comma-separated, e.g. ball, mug")
            g["ask"] = gui.add_button("Ask")
            g["point"] = gui.add_button("Point prompt (then click the image)")
            g["show"] = gui.add_dropdown("Show selection", SHOW, initial_value=st.show)
            g["box"] = gui.add_checkbox("Draw box", True)
            g["auto"] = gui.add_checkbox("Threshold auto", True)
            g["tau"] = gui.add_slider("Threshold", -1.0, 1.0, 0.01, 0.5, disabled=True)
            g["clear"] = gui.add_button("Clear selection")
            g["count"] = gui.add_markdown("nothing selected")
            for k in ("query", "ask", "point", "show", "box", "auto", "clear"):
                g[k].disabled = bool(lang_note)
            if st.encoder is None:
                g["query"].disabled = g["ask"].disabled = True
        avail = guidance_availability(st.models)
        with gui.add_folder("Edit and delete"):
            g["instruction"] = gui.add_text("Instruction", "", hint="e.g. make it red")
            usable = [k for k in GUIDANCES if not avail[k]]
            g["guidance"] = gui.add_dropdown("Guidance", usable, initial_value=usable[0])
            notes = [f"{k}: {why}" for k, why in avail.items() if why]
            if notes:
                gui.add_markdown("*unavailable:* " + "; ".join(n[:160] for n in notes))
            g["steps"] = gui.add_number("Steps", 100, min=1, max=10_000, step=1)
            g["size"] = gui.add_number("Edit size (px)", 512 if self.device.type == "cuda" else 96, min=32,
                                       max=1024, step=16)
            g["preview"] = gui.add_number("Preview every", 10, min=0, max=1000, step=1)
            g["run"] = gui.add_button("Run edit")
            g["delete"] = gui.add_button("Delete selection")
            g["cancel"] = gui.add_button("Cancel", disabled=True)
            g["progress"] = gui.add_progress_bar(0.0)
            for k in ("instruction", "guidance", "steps", "size", "preview", "run", "delete"):
                g[k].disabled = bool(lang_note)
        with gui.add_folder("History"):
            g["undo"] = gui.add_button("Undo")
            g["redo"] = gui.add_button("Redo")
            g["save"] = gui.add_button("Save PLY")
            g["history"] = gui.add_markdown(self._history_text())
        g["status"] = gui.add_markdown(f"*{lang_note}*" if lang_note else "ready")
        self._wire(g)

    def _history_text(self) -> str:
        st = self.state
        return "  \n".join(("**→** " if i == st.index else "") + f"{i}. {label}"
                           for i, (label, _) in enumerate(st.history))

    def _wire(self, g: dict) -> None:
        st = self.state
        g["mode"].on_update(self._guard(lambda e: st.set_view(mode=g["mode"].value)))
        g["background"].on_update(self._guard(
            lambda e: st.set_view(background=tuple(c / 255.0 for c in g["background"].value))))
        g["show"].on_update(self._guard(lambda e: st.set_view(show=g["show"].value)))

        def set_fov(e) -> None:
            for client in self.server.get_clients().values():
                client.camera.fov = math.radians(float(g["fov"].value))

        g["fov"].on_update(self._guard(set_fov))

        def go_camera(e) -> None:
            names = [c.image_name or f"camera {i}" for i, c in enumerate(st.cameras)]
            cam = st.cameras[names.index(g["cameras"].value)]
            for client in ([e.client] if e.client is not None else self.server.get_clients().values()):
                self.go_to(client, cam)

        g["cameras"].on_update(self._guard(go_camera))

        def ask(e) -> None:
            text = str(g["query"].value)[:MAX_TEXT + 1]
            t0 = time.perf_counter()
            sel = st.ask(text)
            self._selection_changed(f"asked {sel.label!r} in {1e3 * (time.perf_counter() - t0):.0f} ms")

        g["ask"].on_click(self._guard(ask))

        def point(e) -> None:
            client = e.client
            if client is None:
                raise ViewerError("the point prompt needs a browser tab")
            self._status("point prompt: click on the object in the image")

            @client.scene.on_click()
            def on_click(ev) -> None:
                client.scene.remove_click_callback(on_click)
                self._guard(lambda _: self._point(client, ev.screen_pos))(ev)

        g["point"].on_click(self._guard(point))

        def set_tau(e) -> None:
            g["tau"].disabled = bool(g["auto"].value)
            st.set_tau("auto" if g["auto"].value else float(g["tau"].value))
            self._selection_changed("threshold " + ("auto" if g["auto"].value else f"{float(g['tau'].value):.2f}"))

        g["auto"].on_update(self._guard(set_tau))
        g["tau"].on_update(self._guard(set_tau))
        g["box"].on_update(self._guard(lambda e: self._draw_boxes()))
        g["clear"].on_click(self._guard(lambda e: (st.clear_selection(), self._selection_changed("cleared"))))

        def run(e) -> None:
            self._start_job(EditJob(st, EditRequest(
                instruction=str(g["instruction"].value)[:MAX_TEXT + 1], guidance=str(g["guidance"].value),
                steps=int(g["steps"].value), size=int(g["size"].value), preview_every=int(g["preview"].value)),
                self.device))

        g["run"].on_click(self._guard(run))
        g["delete"].on_click(self._guard(lambda e: self._start_job(DeleteJob(st, steps=int(g["steps"].value)))))
        g["cancel"].on_click(self._guard(lambda e: self.job.cancel() if self.job is not None else None))

        def history(action: Callable[[], str], verb: str) -> Callable:
            def fn(e) -> None:
                if self.job is not None and not self.job.finished.is_set():
                    raise ViewerError("wait for the running job (or cancel it)")
                label = action()
                self._selection_changed(f"{verb}: {label}")

            return fn

        g["undo"].on_click(self._guard(history(st.undo, "undone")))
        g["redo"].on_click(self._guard(history(st.redo, "redone")))
        g["save"].on_click(self._guard(lambda e: self._status(f"saved {st.save()}")))

    def _point(self, client, screen_pos) -> None:
        view = self.views.get(client.client_id)
        if view is None or view.pose is None:
            raise ViewerError("no camera from this tab yet")
        x, y = screen_pos
        cam = self.browser_camera(view, full=False)
        sel = self.state.point_prompt(cam.to(self.device), float(x), float(y))
        self._selection_changed(f"point prompt at ({x:.2f}, {y:.2f})")
        del sel

    def _start_job(self, job: Job) -> None:
        if self.job is not None and not self.job.finished.is_set():
            raise ViewerError(f"a {self.job.kind} is running; wait for it or press Cancel")
        self.job = job.start()
        self.gui["cancel"].disabled = False
        self._status(f"{job.kind}: started")

    def _selection_changed(self, message: str) -> None:
        sel = self.state.selection
        if sel is None:
            self.gui["count"].content = "nothing selected"
        else:
            taus = ", ".join(f"{r.tau:.3f}" for r in sel.retrievals)
            self.gui["count"].content = (f"**{sel.count}** of {len(self.state.scene)} Gaussians selected "
                                         f"({sel.label}; tau {taus})")
        self.gui["history"].content = self._history_text()
        self._draw_boxes()
        self._status(message)

    def _draw_boxes(self) -> None:
        for handle in self._boxes:
            handle.remove()
        self._boxes = []
        sel = self.state.selection
        if sel is None or not self.gui["box"].value:
            return
        for i, (lo, hi) in enumerate(sel.boxes()):
            lo, hi = np.asarray(lo), np.asarray(hi)
            self._boxes.append(self.server.scene.add_box(
                f"/selection/box{i}", color=(255, 128, 0), dimensions=tuple(np.maximum(hi - lo, 1e-4)),
                position=tuple((lo + hi) / 2), wireframe=True, cast_shadow=False, receive_shadow=False))

    def _poll_loop(self) -> None:
        """Job progress into the page (progress bar, status) and its end (history, selection)."""
        last = None
        while not self.stopping.wait(0.2):
            job = self.job
            if job is None:
                continue
            state = (job.outcome, round(job.progress, 3), job.message)
            if state == last:
                continue
            last = state
            self.gui["progress"].value = 100.0 * job.progress
            if job.finished.is_set():
                self.gui["cancel"].disabled = True
                self._selection_changed(f"{job.kind} {job.outcome}: {job.message}")
            else:
                self._status(f"{job.kind}: {job.message}")
