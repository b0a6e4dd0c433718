"""`goi view`'s front end on viser: the scene as splats, the training cameras, a prompt box,
and the answers lit up in 3D while they refine.

Every page (browser tab) has its own controls, highlight and answer on display; the answer
history, the exports and the worker are shared by all pages (`stages.view.worker`: one queue,
a new prompt from a page supersedes that page's unfinished one). All text a user typed is
escaped wherever it is shown. viser is imported here only (the optional extra `goi[view]`).
"""

from __future__ import annotations

import contextlib
import html
import io
import sys
import threading
import time
import traceback
import warnings
from typing import Any

import numpy as np

from stages.core.errors import GoiError
from stages.core.report import SILENT, Report
from stages.scene.cameras import Camera
from stages.view.cameras import MASK_SIDE, browser_camera, browser_pose, render_size
from stages.view.session import ROUTE_NAMES, ROUTES, Answer, Control, ViewSession
from stages.view.splats import MODES, Plan, pack, plan, scene_splats
from stages.view.worker import Job, Worker

#: The camera has rested when it has not moved for this long (seconds): then the mask at it
#: is rendered.
REST_S = 0.3
#: The side of the photos shown for a training camera.
PHOTO_SIDE = 480
TINT = np.array([1.0, 0.0, 0.55], np.float32)  # magenta: stands out in most scenes
EXPORT_BUTTONS = {
    "selection.h5": "selection",
    "PLY: the selection": "subset",
    "PLY: the scene without it": "invert",
    "PLY: the scene, it highlighted": "highlight",
    "masks of the test views": "masks",
}


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def scene_up(cams: list[Camera]) -> np.ndarray:
    """[3] the scene's up direction: the training cameras' mean up axis (-y in OpenCV axes)."""
    up = sum(-np.asarray(c.R, np.float64)[1] for c in cams)
    n = float(np.linalg.norm(up))
    return up / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


class ViewerApp:
    """The server: one per `goi view`. `start()` serves, `stop()` ends it."""

    def __init__(self, session: ViewSession, report: Report = SILENT):
        self.session = session
        self.report = report
        g = session.scene.gaussians
        self.splats = scene_splats(g, session.run.max_splats)
        self.chunks = self.splats.chunks()
        s = self.splats
        self.buffers = [
            pack(s.centers[c], s.covariances[c], s.rgbs[c], s.opacities[c]) for c in self.chunks
        ]
        self.sent_bytes = int(sum(b.nbytes for b in self.buffers))
        self.worker = Worker(self._job_failed)
        self.pages: dict[int, Page] = {}
        self.gone: set[int] = set()  # tabs closed while their page was being built
        self.lock = threading.Lock()
        self.server: Any = None
        cams = session.scene.cameras
        self.up = scene_up(cams)
        means = np.asarray(g.means, np.float64)
        lo, hi = np.percentile(means, 2, axis=0), np.percentile(means, 98, axis=0)
        self.extent = float(np.linalg.norm(hi - lo)) or 1.0
        self.centre = 0.5 * (lo + hi)
        self.frustum_scale = 0.01 * self.extent

    # -- serving ------------------------------------------------------------------------------

    def start(self) -> str:
        """Serve; returns the page's address (with the run's token unless --no-token)."""
        from stages.view.access import Access, new_token, server_names
        from stages.view.server import Guard, servable_port, serve

        # a tab closed while its answer or mask was on the way: nothing is lost, say nothing
        warnings.filterwarnings("ignore", message="Queued a .* on a closed connection")

        run = self.session.run
        port = servable_port(run.host, run.port)
        self.access = Access(None if run.no_token else new_token(), server_names(run.host))
        guard = Guard(self.access, run.max_pages, run.max_message_bytes, self.log)
        self.server = serve(run.host, port, guard, self._share_refused)
        srv = self.server
        srv.gui.configure_theme(
            control_width="large", show_logo=False, show_share_button=False, dark_mode=False
        )
        srv.scene.set_up_direction(tuple(self.up))
        first = (self.session.scene.views("train") or self.session.scene.cameras)[0]
        wxyz, pos, fov = browser_pose(first)
        # a little behind the first camera, so that its frustum is in view, not around it
        fwd = np.asarray(first.R, np.float64)[2]
        back = pos - fwd * 3.0 * self.frustum_scale
        srv.initial_camera.position = tuple(back)
        srv.initial_camera.look_at = tuple(back + fwd * 0.25 * self.extent)
        srv.initial_camera.fov = fov
        self._add_cameras()
        srv.on_client_connect(self._connect)
        srv.on_client_disconnect(self._disconnect)
        token = self.access.token
        return f"http://{_url_host(run.host)}:{srv.get_port()}/" + (
            f"?token={token}" if token else ""
        )

    def log(self, message: str) -> None:
        """One line in the viewer's log (the terminal): prompts, answers, exports, refusals."""
        self.report.log(f"view: {message}")

    def _share_refused(self) -> None:
        self.log("refused a page's request to publish the viewer on the internet (Share)")

    def stop(self) -> None:
        self.worker.stop()
        with self.lock:
            pages = list(self.pages.values())
        for p in pages:
            p.close()
        if self.server is not None:
            with contextlib.redirect_stdout(io.StringIO()):
                self.server.stop()

    def _add_cameras(self) -> None:
        train = {c.name for c in self.session.scene.views("train")}
        scale = self.frustum_scale
        for cam in self.session.scene.cameras:
            wxyz, pos, fov = browser_pose(cam)
            h = self.server.scene.add_camera_frustum(
                f"/cameras/{_node_name(cam.name)}",
                fov=fov,
                aspect=cam.width / cam.height,
                scale=scale,
                thickness=1.5,
                thickness_units="screen",
                color=(30, 90, 200) if cam.name in train else (150, 150, 150),
                wxyz=wxyz,
                position=pos,
            )
            h.on_click(lambda ev, cam=cam: self._page_do(ev.client.client_id, "fly_to", cam))

    def _page_do(self, client_id: Any, what: str, *args: Any) -> None:
        with self.lock:
            page = self.pages.get(client_id)
        if page is not None:
            getattr(page, what)(*args)

    def _connect(self, client: Any) -> None:
        page = Page(self, client)
        try:
            page.build()
        except BaseException:
            page.close()
            raise
        # registered once built (history and answers reach only built pages), unless the tab
        # closed while it was being built
        with self.lock:
            gone = client.client_id in self.gone
            self.gone.discard(client.client_id)
            if not gone:
                self.pages[client.client_id] = page
        if gone:
            page.close()

    def _disconnect(self, client: Any) -> None:
        with self.lock:
            page = self.pages.pop(client.client_id, None)
            if page is None:  # still being built: _connect closes it
                self.gone.add(client.client_id)
        self.worker.cancel(client.client_id)
        if page is not None:
            page.close()

    def history_changed(self) -> None:
        with self.lock:
            pages = list(self.pages.values())
        for p in pages:
            p.refresh_history()

    def _job_failed(self, job: Job, e: BaseException) -> None:
        owner = job.owner[0] if isinstance(job.owner, tuple) else job.owner
        if isinstance(e, GoiError):
            message = str(e)
        else:
            traceback.print_exception(e, file=sys.stderr)
            message = f"internal error: {type(e).__name__}: {str(e)[:200]}"
        self._page_do(owner, "failed", message)


class Page:
    """One browser tab: its controls, its highlight and the answer it shows."""

    def __init__(self, app: ViewerApp, client: Any):
        self.app = app
        self.client = client
        self.id: int = client.client_id
        self.lock = threading.RLock()
        self.answer: Answer | None = None
        self.mode = "tint"
        self.color = TINT.copy()
        self.route = app.session.default_route()
        self.shown: list[bytes] = [b"base"] * len(app.chunks)
        self.scene_visible = True
        self.chunk_nodes: list[Any] = []
        self.overlay_node: Any = None
        self.closed = threading.Event()
        self.built = threading.Event()  # its controls and splats exist: answers can be shown
        self.camera_moved = threading.Event()
        self.last_move = 0.0
        self.history_keys: dict[str, tuple[str, str]] = {}
        #: (time.perf_counter(), answer) of every answer shown, once its messages were flushed
        #: to the page (the benchmarks time Enter to highlight from it)
        self.timeline: list[tuple[float, Answer]] = []
        self.mask_thread = threading.Thread(target=self._mask_loop, daemon=True)

    # -- building the page --------------------------------------------------------------------

    def build(self) -> None:
        gui, s = self.client.gui, self.app.session
        g = s.scene.gaussians
        sent = self.app.splats.count
        size = f"{g.count:,} Gaussians" + (
            f" ({sent:,} drawn: the most visible)" if sent < g.count else ""
        )
        name = _e(s.scene.ply_path.parent.name)
        gui.add_html(
            f"<div style='font-size:0.85em'><b>goi view</b> &middot; {name} &middot; {size} "
            f"&middot; {len(s.scene.cameras)} cameras</div>"
        )
        with gui.add_form(None) as form:
            self.prompt_box = gui.add_text("Prompt", "", hint="Type a prompt and press Enter")
            ask = gui.add_button("Ask", hint="Answer the prompt (or press Enter)")
        ask.on_click(lambda _: form.submit())
        form.on_submit(lambda _: self.ask(self.prompt_box.value))
        if s.suggestions():
            self.suggest = gui.add_dropdown("Examples", ["-", *s.suggestions()], initial_value="-")
            self.suggest.on_update(lambda _: self._suggested())
        allowed = [r for r, why in s.routes().items() if why is None]
        self.route_box = gui.add_dropdown(
            "Route", [ROUTE_NAMES[r] for r in allowed], initial_value=ROUTE_NAMES[self.route]
        )
        self.route_box.on_update(lambda _: self._route_changed())
        closed = [(r, why) for r, why in s.routes().items() if why is not None]
        if closed:
            rows = "".join(
                f"<div style='color:#999'>{_e(ROUTE_NAMES[r])}: {_e(why)}</div>"
                for r, why in closed
            )
            gui.add_html(f"<div style='font-size:0.8em'>{rows}</div>")
        self.mode_box = gui.add_button_group("Highlight", list(MODES))
        self.mode_box.on_click(lambda ev: self.set_mode(ev.target.value))
        self.color_box = gui.add_rgb("Tint", tuple(int(255 * c) for c in TINT))
        self.color_box.on_update(lambda _: self._color_changed())
        self.status = gui.add_html(self._status_html("Ask a prompt to light up its Gaussians."))
        self.bar = gui.add_progress_bar(0.0, visible=False)
        self.history_box = gui.add_dropdown("History", ["-"], initial_value="-")
        self.history_box.on_update(lambda _: self._history_picked())
        with gui.add_folder("At this camera (goi's renderer)"):
            blank = np.zeros((*render_size(4, 3)[::-1], 3), np.uint8)
            self.mask_image = gui.add_image(blank, format="jpeg", jpeg_quality=85)
            self.mask_note = gui.add_html(self._small("Rest the camera to render the mask here."))
            save = gui.add_button("Save camera", hint="Write this camera as a camera file "
                                  "for goi render-mask --camera-file")  # fmt: skip
            save.on_click(lambda _: self.save_camera())
        with gui.add_folder("Export the answer", expand_by_default=False):
            for label, what in EXPORT_BUTTONS.items():
                b = gui.add_button(label)
                b.on_click(lambda _, what=what: self.export(what))
            self.export_note = gui.add_html(self._small(f"Into {_e(s.out)}/"))
        with gui.add_folder("Training photo", expand_by_default=False) as self.photo_folder:
            self.photo = gui.add_image(blank, format="jpeg", jpeg_quality=85)
            self.photo_note = gui.add_html(self._small("Click a camera in the scene."))
        self._send_scene()
        self.client.camera.on_update(lambda _: self._camera_moved())
        self.mask_thread.start()
        self.built.set()
        self.refresh_history()

    def _send_scene(self) -> None:
        app = self.app
        s = app.splats
        for i, c in enumerate(app.chunks):
            self.chunk_nodes.append(
                self.client.scene.add_gaussian_splats(
                    f"/scene/chunk-{i:04d}",
                    centers=s.centers[c],
                    covariances=s.covariances[c],
                    rgbs=s.rgbs[c],
                    opacities=s.opacities[c],
                )
            )

    @staticmethod
    def _small(text: str) -> str:
        return f"<div style='font-size:0.8em;color:#555'>{text}</div>"

    @staticmethod
    def _status_html(text: str, error: bool = False) -> str:
        color = "#b00020" if error else "#222"
        return f"<div style='font-size:0.85em;color:{color}'>{text}</div>"

    def close(self) -> None:
        self.closed.set()
        self.camera_moved.set()
        self.built.set()  # an answer waiting for the page to be built sees it closed

    # -- asking ---------------------------------------------------------------------------------

    def ask(self, text: str) -> None:
        s = self.app.session
        try:
            prompt = s.check_prompt(text)
        except GoiError as e:
            self.failed(str(e))
            return
        route = self.route
        cached = s.cached(prompt, route)
        if cached is not None:
            self.app.worker.cancel(self.id)
            self.show(cached, note=" (from the history)")
            return
        self._say(f"answering <i>{_e(prompt)}</i> ({_e(ROUTE_NAMES[route])})...")
        self._progress(0, 1)
        control = Control()
        control.partial = self.show
        control.progress = lambda done, total, what: self._progress(done, total)

        def job(control: Control) -> None:
            if route not in ("threshold", "lifted_fieldless"):  # (threshold is the field's)
                first = s.field_answer(prompt)
                if first is not None:
                    label = f"the field, first: {first.label}"
                    self.show(
                        Answer(first.prompt, first.route, first.selected, label, False, first.plane)
                    )
            ans = s.answer(prompt, route, control)
            control.check()
            self.show(ans)
            self.app.history_changed()

        self.app.worker.submit(self.id, job, control)

    def _suggested(self) -> None:
        value = self.suggest.value
        if value != "-":
            self.prompt_box.value = value
            self.ask(value)

    def _route_changed(self) -> None:
        by_name = {ROUTE_NAMES[r]: r for r in ROUTES}
        self.route = by_name.get(self.route_box.value, self.route)

    def _history_picked(self) -> None:
        key = self.history_keys.get(self.history_box.value)
        if key is None:
            return
        ans = self.app.session.cached(*key)
        if ans is not None and ans is not self.answer:
            self.app.worker.cancel(self.id)
            self.show(ans, note=" (from the history)")

    def refresh_history(self) -> None:
        answers = self.app.session.history()
        keys = {}
        for a in answers:
            keys[f"{a.prompt.text} · {ROUTE_NAMES[a.route]} · {a.count:,}"] = a.key
        with self.lock:
            self.history_keys = keys
            current = self.history_box.value
            self.history_box.options = ["-", *keys]
            if current in keys:
                self.history_box.value = current

    # -- showing --------------------------------------------------------------------------------

    def show(self, ans: Answer, note: str = "") -> None:
        """Light the answer up in 3D and say what answered it (a partial or final answer)."""
        self.built.wait()
        with self.lock:
            if self.closed.is_set():
                return
            self.answer = ans
            self._apply(ans.selected)
            done = note if ans.final else " (refining...)"
            self._say(
                f"<b>{ans.count:,}</b> Gaussians &middot; <span>{_e(ans.label)}</span>{done}<br>"
                f"<i>{_e(ans.prompt.text)}</i> &middot; {ans.seconds:.2f} s"
            )
            if ans.final:
                self.bar.visible = False
        self.client.flush()
        self.timeline.append((time.perf_counter(), ans))
        self.camera_moved.set()  # the mask at the camera shows the new answer

    def _apply(self, selected: np.ndarray | None) -> None:
        app = self.app
        p: Plan = plan(app.splats, app.chunks, self.shown, selected, self.mode, self.color)
        with self.client.atomic():
            for i, words in p.chunk_words.items():
                buf = app.buffers[i].copy()
                buf[:, 7] = words
                self.chunk_nodes[i].buffer = buf
            if p.scene_visible != self.scene_visible:
                for node in self.chunk_nodes:
                    node.visible = p.scene_visible
                self.scene_visible = p.scene_visible
            if self.overlay_node is not None:
                self.overlay_node.remove()
                self.overlay_node = None
            if p.overlay.size:
                self.overlay_node = self._overlay(p.overlay, p.overlay_tinted)
        self.shown = p.chunk_keys

    def _overlay(self, idx: np.ndarray, tinted: bool) -> Any:
        from stages.view.splats import covariances, highlighted

        g = self.app.session.scene.gaussians
        rgb = g.colors_dc()[idx].astype(np.float32)
        op = np.asarray(g.opacities[idx], np.float32)[:, None]
        if tinted:
            rgb, op = highlighted(rgb, op, np.ones(idx.size, bool), "tint", self.color)
        covs = covariances(g.quats[idx], g.scales[idx])
        return self.client.scene.add_gaussian_splats(
            "/selection", centers=g.means[idx], covariances=covs, rgbs=rgb, opacities=op
        )

    def set_mode(self, mode: str) -> None:
        with self.lock:
            self.mode = mode
            self._apply(self.answer.selected if self.answer else None)

    def _color_changed(self) -> None:
        with self.lock:
            self.color = np.asarray(self.color_box.value, np.float32) / 255.0
            self._apply(self.answer.selected if self.answer else None)

    def _say(self, text: str, error: bool = False) -> None:
        self.status.content = self._status_html(text, error)

    def _progress(self, done: int, total: int) -> None:
        self.bar.visible = True
        self.bar.value = 100.0 * done / max(total, 1)

    def failed(self, message: str) -> None:
        with self.lock:
            self.bar.visible = False
            self._say(_e(message), error=True)

    # -- the mask at the browser's camera -------------------------------------------------------

    def _camera_moved(self) -> None:
        self.last_move = time.monotonic()
        self.camera_moved.set()

    def browser_camera(self, name: str = "browser") -> Camera | None:
        cam = self.client.camera
        try:
            w, h = render_size(cam.image_width, cam.image_height, MASK_SIDE)
            return browser_camera(name, cam.wxyz, cam.position, cam.fov, w, h)
        except (AssertionError, GoiError):  # no camera reported yet
            return None

    def _mask_loop(self) -> None:
        while not self.closed.is_set():
            self.camera_moved.wait()
            self.camera_moved.clear()
            if self.closed.is_set():
                return
            while time.monotonic() - self.last_move < REST_S:
                time.sleep(REST_S / 3)
            cam = self.browser_camera()
            if cam is None:
                continue
            try:
                self.render_mask(cam)
            except Exception as e:  # shown, never fatal to the page
                self.mask_note.content = self._small(f"could not render: {_e(e)}")

    def render_mask(self, cam: Camera) -> None:
        s = self.app.session
        answer = self.answer
        t0 = time.perf_counter()
        with self.app.worker.gate.urgent():
            mv = s.mask_at(answer, cam)
        dt = time.perf_counter() - t0
        self.mask_image.image = mv.overlay
        what = "no answer yet" if answer is None else f"{int(mv.mask.sum()):,} pixels of the mask"
        self.mask_note.content = self._small(
            f"{cam.width}x{cam.height}, {what}, rendered in {dt:.2f} s: what goi render-mask "
            "--camera-file writes for this camera (Save camera)."
        )

    # -- cameras, exports -----------------------------------------------------------------------

    def fly_to(self, cam: Camera) -> None:
        wxyz, pos, fov = browser_pose(cam)
        with self.client.atomic():
            self.client.camera.position = pos
            self.client.camera.wxyz = wxyz
            self.client.camera.fov = fov
        try:
            rgb = self.app.session.scene.load_image(cam)
        except GoiError as e:
            self.photo_note.content = self._small(_e(e))
            return
        self.photo.image = _fit(rgb, PHOTO_SIDE)
        self.photo_folder.expand_by_default = True
        self.photo_note.content = self._small(f"{_e(cam.name)} ({cam.width}x{cam.height})")

    def save_camera(self) -> None:
        cam = self.browser_camera()
        if cam is None:
            self.mask_note.content = self._small("the browser has not reported its camera yet")
            return
        try:
            path = self.app.session.save_camera(cam)
        except GoiError as e:
            self.mask_note.content = self._small(_e(e))
            return
        self.mask_note.content = self._small(
            f"camera saved: {_e(path)} (goi render-mask --camera-file {_e(path)})"
        )

    def export(self, what: str) -> None:
        ans = self.answer
        if ans is None or not ans.final:
            self.export_note.content = self._small("ask a prompt and wait for its answer first")
            return
        color = "#" + "".join(f"{int(round(255 * c)):02x}" for c in self.color)
        self.export_note.content = self._small(f"writing {_e(what)}...")

        def job(control: Control) -> None:
            try:
                files = self.app.session.export(ans, what, color)
            except GoiError as e:
                self.export_note.content = self._small(_e(e))
                return
            where = files[0] if len(files) == 1 else f"{files[0].parent}/ ({len(files)} files)"
            self.export_note.content = self._small(f"wrote {_e(where)}")

        self.app.worker.submit((self.id, "export"), job, Control())


def _fit(rgb: np.ndarray, side: int) -> np.ndarray:
    import cv2

    h, w = rgb.shape[:2]
    s = side / max(h, w)
    if s >= 1:
        return rgb
    return cv2.resize(
        rgb, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA
    )


def _node_name(name: str) -> str:
    """A camera's name as a scene-node name (no '/', which nests nodes)."""
    return name.replace("/", "_") or "_"


def _url_host(host: str) -> str:
    if host in ("0.0.0.0", ""):
        return "127.0.0.1"
    if host == "::":
        return "[::1]"
    return f"[{host}]" if ":" in host else host
