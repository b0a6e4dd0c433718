"""`goi view`'s front end on viser: the scene as splats, the training cameras, a prompt box,
and the answers lit up in 3D while they refine.

Every page (browser tab) has its own controls, highlight, camera and answer on display; what a
page asks and is shown follows the answer protocol (`stages.view.answers`), which also keeps
the shared history; all answers and exports run on one worker (`stages.view.worker`). Every
value a page sends is checked before it is used, as a CLI option is: a bad one is refused with
a line in that page, which goes on. All text a user typed is escaped wherever it is shown.
viser is imported here and in `stages.view.server` only (the optional extra `goi[view]`).
"""

from __future__ import annotations

import dataclasses
import html
import math
import threading
import time
import traceback
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from stages.core.errors import GoiError
from stages.core.report import SILENT, Report
from stages.query.pointing import GRANULARITIES, BoxPrompt, Click
from stages.scene.cameras import Camera
from stages.view.answers import INTERNAL, SHOWN, Answers, Shown
from stages.view.cameras import MASK_SIDE, browser_camera, browser_pose, framing, render_size
from stages.view.pointed import ray_pixel, screen_box, screen_pixel
from stages.view.selections import stretched
from stages.view.session import ROUTE_NAMES, Answer, ViewSession
from stages.view.splats import MODES, Plan, pack, plan, scene_splats
from stages.view.worker import Job, Worker

#: The camera has rested when it has not moved for this long (seconds): then the mask at it
#: is rendered.
REST_S = 0.3
#: A page's mask at its camera is rendered at most this often (seconds) while its answer
#: refines; a final answer or a camera that rested gets its mask as soon as it can.
PREVIEW_MASK_S = 2.0
#: The side of the photos shown for a training camera.
PHOTO_SIDE = 480
TINT = np.array([1.0, 0.0, 0.55], np.float32)  # magenta: stands out in most scenes
#: A preview (a step before the final answer) is drawn in this colour whatever the tint, so
#: that it never looks like a final answer.
PREVIEW_TINT = np.array([1.0, 0.72, 0.0], np.float32)  # amber
EXPORT_BUTTONS = {
    "selection.h5": "selection",
    "PLY: the selection": "subset",
    "PLY: the scene without it": "invert",
    "PLY: the scene, it highlighted": "highlight",
    "masks of the test views": "masks",
}
NONE = "-"
NONE_POINTER = "orbit (clicks off)"
#: What a plain click (or drag) on the scene does, as the page offers it; Shift and Alt do the
#: same whatever the choice (POINTER_KEYS).
POINTER = {
    "orbit (clicks off)": "orbit",
    "click adds (+)": "add",
    "click removes (-)": "remove",
    "drag a box": "box",
}
POINTER_KEYS = "Shift+click adds, Alt+click removes, Shift+drag draws a box (in any mode)"
#: The operations of "Combine", as the page writes them.
OP_NAMES = {
    "A | B (union)": "union",
    "A & B (intersection)": "intersection",
    "A - B (difference)": "difference",
    "not A (invert)": "invert",
}
#: A click whose ray and canvas position disagree by more than this share of the long side
#: was made while the page's camera moved: refused (the pixel would be another).
RAY_SLACK = 0.02
#: The smallest box a drag makes (pixels of the page's camera, each side).
MIN_BOX = 4.0
HEAT_LEGEND = (
    "heat: grey no score, blue low, yellow the answer's cut, red certain (lifted: the vote "
    "share; the paper's routes: the plane's probability)"
)


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
        run = session.run
        self.answers = Answers(session, self.worker, self.log, run.history_mib << 20,
                               prompts_per_s=run.prompts_per_s,
                               undo_bytes=run.undo_mib << 20)  # fmt: skip
        self.pages: dict[int, Page] = {}
        self.gone: set[int] = set()  # tabs closed while their page was being built
        self.lock = threading.Lock()
        self.server: Any = None
        self._unquiet: Callable[[], None] = lambda: None
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
        from stages.view.server import Guard, quiet_libraries, servable_port, serve

        # a tab closed while its answer or mask was on the way: nothing is lost, say nothing
        warnings.filterwarnings("ignore", message="Queued a .* on a closed connection")

        run = self.session.run
        port = servable_port(run.host, run.port)
        self.access = Access(None if run.no_token else new_token(), server_names(run.host))
        guard = Guard(self.access, run.max_pages, run.max_message_bytes, self.log)
        self._unquiet = quiet_libraries(self.log)
        self.server = serve(run.host, port, guard, self._share_refused)
        srv = self.server
        srv.gui.configure_theme(
            control_width="medium", show_logo=False, show_share_button=False, dark_mode=False
        )
        srv.gui.main_panel.dock_right()  # beside the scene, not over it
        srv.scene.set_up_direction(tuple(self.up))
        first = (self.session.scene.views("train") or self.session.scene.cameras)[0]
        wxyz, pos, fov = browser_pose(first)
        # a little behind the first camera, so that its frustum is in view, not around it
        fwd = np.asarray(first.R, np.float64)[2]
        back = pos - fwd * 3.0 * self.frustum_scale
        srv.initial_camera.position = tuple(back)
        srv.initial_camera.look_at = tuple(back + fwd * 0.25 * self.extent)
        srv.initial_camera.up = tuple(self.up)
        srv.initial_camera.fov = fov
        srv.initial_camera.near = 0.002 * self.extent
        self._add_cameras()
        srv.on_client_connect(self._connect)
        srv.on_client_disconnect(self._disconnect)
        token = self.access.token
        host = _url_host(run.host)
        self.log(f"serving {self.session.scene.ply_path.parent.name} on {host}:{srv.get_port()}")
        return f"http://{host}:{srv.get_port()}/" + (f"?token={token}" if token else "")

    def stop(self) -> None:
        self.worker.stop()
        with self.lock:
            pages = list(self.pages.values())
        for p in pages:
            p.close()
        if self.server is not None:
            import contextlib
            import io

            with contextlib.redirect_stdout(io.StringIO()):
                self.server.stop()
        self._unquiet()

    def log(self, message: str) -> None:
        """One line in the viewer's log (the terminal): prompts, answers, exports, refusals."""
        self.report.log(f"view: {message}")

    def _share_refused(self) -> None:
        self.log("refused a page's request to publish the viewer on the internet (Share)")

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
            page.guarded(getattr(page, what), *args)

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
        else:
            self.log(f"page {page.id} opened")

    def _disconnect(self, client: Any) -> None:
        with self.lock:
            page = self.pages.pop(client.client_id, None)
            if page is None:  # still being built: _connect closes it
                self.gone.add(client.client_id)
        if page is not None:
            page.close()
            self.log(f"page {page.id} closed")

    def _job_failed(self, job: Job, e: BaseException) -> None:
        self.answers.failed(job, e)


class Page:
    """One browser tab: its controls, its highlight and the answer it shows (a `Display` of
    the answer protocol)."""

    def __init__(self, app: ViewerApp, client: Any):
        self.app = app
        self.client = client
        self.id: int = client.client_id
        self.lock = threading.RLock()
        self.shown: Shown | None = None
        self.shown_at = 0.0  # time.perf_counter() when the answer on display was sent
        self.mode = "tint"
        self.color = TINT.copy()
        self.route = app.session.default_route()
        self.drawn: list[bytes] = [b"base"] * len(app.chunks)
        self.scene_visible = True
        self.chunk_nodes: list[Any] = []
        self.overlay_node: Any = None
        self.closed = threading.Event()
        self.built = threading.Event()  # its controls and splats exist: answers can be shown
        self.wake = threading.Event()  # the mask loop has something to look at
        self.last_move = 0.0
        self.mask_key: tuple = ()  # the camera and answer of the mask on display
        self.history_keys: dict[str, tuple] = {}
        self.route_names: dict[str, str] = {}
        self.pointer = "orbit"
        self.granularity = app.session.point_params.granularity
        self.cameras = 0  # the page's cameras a click or box was made at, so far
        self.evidence_views: dict[str, str] = {}  # the evidence dropdown's entries -> views
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
        self.prompt_box = None
        self.suggest = None
        if self.route is not None:
            with gui.add_form(None) as form:
                self.prompt_box = gui.add_text("Prompt", "", hint="Type a prompt and press Enter")
                ask = gui.add_button("Ask", hint="Answer the prompt (or press Enter)")
            ask.on_click(lambda _: form.submit())
            form.on_submit(lambda _: self.guarded(self.ask, self._prompt_text()))
            if s.suggestions():
                self.suggest = gui.add_dropdown(
                    "Examples", [NONE, *s.suggestions()], initial_value=NONE
                )
                self.suggest.on_update(lambda _: self.guarded(self._suggested))
            allowed = [r for r, why in s.routes().items() if why is None]
            self.route_names = {ROUTE_NAMES[r]: r for r in allowed}
            self.route_box = gui.add_dropdown(
                "Route", list(self.route_names), initial_value=ROUTE_NAMES[self.route]
            )
            self.route_box.on_update(lambda _: self.guarded(self._route_changed))
        closed = [(r, why) for r, why in s.routes().items() if why is not None]
        if closed and self.route is not None:
            rows = "".join(
                f"<div style='color:#999'>{_e(ROUTE_NAMES[r])}: {_e(why)}</div>"
                for r, why in closed
            )
            gui.add_html(f"<div style='font-size:0.8em'>{rows}</div>")
        first = "Ask a prompt to light up its Gaussians."
        if s.sam is not None:
            first = (
                "Ask a prompt, or point at something: pick what a click does below."
                if self.route is not None
                else "Point at something to light up its Gaussians: pick what a click does "
                "below (the bundle is a SAM alone: no text prompts)."
            )
        self.status = gui.add_html(self._status_html(first))
        self.bar = gui.add_progress_bar(0.0, visible=False)
        self.fly_button = gui.add_button(
            "Fly to the answer", hint="Frame the answer on display", visible=False
        )
        self.fly_button.on_click(lambda _: self.guarded(self.fly_to_answer))
        if s.sam is not None:
            self._build_pointer(gui)
        undo = gui.add_button("Undo", hint="Show the step before (text, click, box, combine)")
        undo.on_click(lambda _: self.guarded(self.app.answers.undo, self.id))
        redo = gui.add_button("Redo", hint="Show the step after (after an undo)")
        redo.on_click(lambda _: self.guarded(self.app.answers.redo, self.id))
        self.steps_html = gui.add_html(self._small("Steps: none yet."))
        self.mode_box = gui.add_dropdown("Highlight", list(MODES), initial_value=self.mode)
        self.mode_box.on_update(lambda _: self.guarded(self._mode_changed))
        self.color_box = gui.add_rgb("Tint", tuple(int(255 * c) for c in TINT))
        self.color_box.on_update(lambda _: self.guarded(self._color_changed))
        self.history_box = gui.add_dropdown("History", [NONE], initial_value=NONE)
        self.history_box.on_update(lambda _: self.guarded(self._history_picked))
        self._build_named(gui)
        blank = np.zeros((*render_size(4, 3)[::-1], 3), np.uint8)
        with gui.add_folder("Evidence of the answer shown"):
            self.evidence_note = gui.add_html(self._small("No answer yet."))
            self.evidence_box = gui.add_dropdown("View", [NONE], initial_value=NONE)
            self.evidence_box.on_update(lambda _: self.guarded(self._evidence_picked))
            self.evidence_image = gui.add_image(blank, format="jpeg", jpeg_quality=85,
                                                visible=False)  # fmt: skip
        # the photo of the camera last clicked: near the top, shown once there is one
        self.photo_note = gui.add_html(self._small("Click a camera in the scene for its photo."))
        self.photo = gui.add_image(blank, format="jpeg", jpeg_quality=85, visible=False)
        with gui.add_folder("At this camera (goi's renderer)"):
            self.mask_image = gui.add_image(blank, format="jpeg", jpeg_quality=85)
            self.mask_note = gui.add_html(self._small("Rest the camera to render the mask here."))
            save = gui.add_button("Save camera", hint="Write this camera as a camera file "
                                  "for goi render-mask --camera-file")  # fmt: skip
            save.on_click(lambda _: self.guarded(self.save_camera))
        with gui.add_folder("Export the answer", expand_by_default=False):
            for label, what in EXPORT_BUTTONS.items():
                b = gui.add_button(label)
                b.on_click(lambda _, what=what: self.guarded(self.export, what))
            labels = gui.add_button(
                "PLY: the scene, named answers as labels",
                hint="The scene's PLY with a label and a score per Gaussian (OUT/labels/)",
            )
            labels.on_click(lambda _: self.guarded(self.export_labels))
            self.export_note = gui.add_html(self._small(f"Into {_e(s.out.root)}/"))
        self._send_scene()
        self.client.camera.on_update(lambda _: self._camera_moved())
        self._keep_in_the_room()
        self.app.answers.open(self.id, self)
        self.mask_thread.start()
        self.built.set()
        self.history_changed()

    def _build_pointer(self, gui: Any) -> None:
        """The pointer's controls: what a plain click or drag does, and the granularity."""
        sam = self.app.session.sam
        assert sam is not None
        modes = {k: v for k, v in POINTER.items() if sam.takes_points or v in ("orbit", "box")}
        self.pointer_names = modes
        self.pointer_box = gui.add_dropdown("Pointer", list(modes), initial_value=NONE_POINTER)
        self.pointer_box.on_update(lambda _: self.guarded(self._pointer_changed))
        self.grow_box = gui.add_dropdown(
            "Grow to", list(GRANULARITIES), initial_value=self.granularity,
            hint="plus clicks and boxes: object grows from the part clicked to the whole "
            "object, part keeps what was clicked (a minus click takes out the part it hit)",
        )  # fmt: skip
        self.grow_box.on_update(lambda _: self.guarded(self._grow_changed))
        self.pointer_keys = POINTER_KEYS if sam.takes_points else (
            f"Shift+drag draws a box (in any mode); this SAM ({sam.layout}) takes boxes only"
        )  # fmt: skip
        self.pointer_note = gui.add_html("")
        self._register_pointer()

    def _register_pointer(self) -> None:
        """viser's scene pointer callbacks for the page's pointer mode: Shift and Alt always;
        a plain click in the click modes; a plain drag only in box mode (viser holds the
        camera still while a box is dragged, so the orbit needs a mode of its own)."""
        sam = self.app.session.sam
        if sam is None:
            return
        sc = self.client.scene
        sc.remove_click_callback("all")
        sc.remove_rect_select_callback("all")
        if sam.takes_points:
            sc.on_click(modifier="shift")(lambda ev: self.guarded(self._clicked, ev, True))
            sc.on_click(modifier="alt")(lambda ev: self.guarded(self._clicked, ev, False))
            if self.pointer in ("add", "remove"):
                plus = self.pointer == "add"
                sc.on_click()(lambda ev: self.guarded(self._clicked, ev, plus))
        sc.on_rect_select(modifier="shift")(lambda ev: self.guarded(self._boxed, ev))
        if self.pointer == "box":
            sc.on_rect_select()(lambda ev: self.guarded(self._boxed, ev))
        # said after the callbacks are registered: a page that shows it has them (viser's
        # messages reach a page in order)
        now = {
            "orbit": "Now a drag orbits.",
            "add": "Now a click adds (+).",
            "remove": "Now a click removes (-).",
            "box": "Now a drag draws a box (the camera holds still: orbit to move it).",
        }[self.pointer]
        self.pointer_note.content = self._small(f"<b>{_e(now)}</b> {_e(self.pointer_keys)}")

    def _build_named(self, gui: Any) -> None:
        """Named answers: keep the answer shown under a name, combine any two, forget one."""
        with gui.add_folder("Named answers"):
            self.name_box = gui.add_text("Name", "", hint="A name for the answer shown")
            keep = gui.add_button("Keep the answer shown", hint="Under the name typed above")
            keep.on_click(lambda _: self.guarded(self.keep))
            self.named_html = gui.add_html(self._small("None kept yet."))
            self.a_box = gui.add_dropdown("A", [SHOWN], initial_value=SHOWN)
            self.op_box = gui.add_dropdown("Operation", list(OP_NAMES))
            self.b_box = gui.add_dropdown("B", [SHOWN], initial_value=SHOWN)
            combine = gui.add_button("Combine", hint="Show A and B combined (a step of its own)")
            combine.on_click(lambda _: self.guarded(self.combine))
            forget = gui.add_button("Forget A", hint="Drop the name chosen as A")
            forget.on_click(lambda _: self.guarded(self.forget))

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

    def _keep_in_the_room(self) -> None:
        """The orbit stays at the scene's scale: the camera is never dollied further from the
        point it orbits than a third of the scene, nor closer than a thousandth of it."""
        cam, extent = self.client.camera, self.app.extent
        try:
            cam.max_orbit_distance = max(0.35 * extent, 1e-6)
            cam.min_orbit_distance = max(1e-3 * extent, 1e-9)
        except (AssertionError, ValueError):  # no camera reported yet: the defaults stay
            pass

    @staticmethod
    def _small(text: str) -> str:
        return f"<div style='font-size:0.8em;color:#555'>{text}</div>"

    @staticmethod
    def _status_html(text: str, error: bool = False) -> str:
        color = "#b00020" if error else "#222"
        return f"<div style='font-size:0.85em;color:{color}'>{text}</div>"

    def close(self) -> None:
        self.closed.set()
        self.wake.set()
        self.built.set()  # an answer waiting for the page to be built sees it closed
        self.app.answers.close(self.id)

    def guarded(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run a page's callback: a GoiError is a refusal (a line in the page); anything else
        is a bug, logged with its traceback, and the page says so and goes on."""
        if self.closed.is_set():
            return
        try:
            fn(*args)
        except GoiError as e:
            self.app.answers.refuse(self.id, str(e))
        except Exception as e:
            self.app.log(f"page {self.id}: {type(e).__name__}: {str(e)[:200]}")
            self.app.log("".join(traceback.format_exception(e)).rstrip())
            self.failed(INTERNAL)

    # -- what the page sends, checked ---------------------------------------------------------

    def _prompt_text(self) -> object:
        return self.prompt_box.value if self.prompt_box is not None else None

    def ask(self, text: object) -> None:
        if not isinstance(text, str):
            raise GoiError("prompt: not text")
        if self.route is None:
            raise GoiError("prompt: this viewer answers clicks and boxes only (no text route)")
        self.app.answers.ask(self.id, text, self.route)

    def _suggested(self) -> None:
        assert self.suggest is not None
        value = self.suggest.value
        if value == NONE:
            return
        if value not in self.app.session.suggestions():
            self.suggest.value = NONE
            raise GoiError("examples: not one of the examples")
        assert self.prompt_box is not None
        self.prompt_box.value = value
        self.suggest.value = NONE  # picking the same example again asks it again
        self.ask(value)

    def _route_changed(self) -> None:
        route = self.route_names.get(self.route_box.value)
        if route is None:
            self.route_box.value = ROUTE_NAMES[self.route] if self.route else NONE
            raise GoiError("route: not one of the routes this viewer offers")
        self.route = route

    # -- pointing -----------------------------------------------------------------------------

    def _pointer_changed(self) -> None:
        mode = self.pointer_names.get(self.pointer_box.value)
        if mode is None:
            back = {v: k for k, v in self.pointer_names.items()}
            self.pointer_box.value = back[self.pointer]
            raise GoiError("pointer: not one of the pointer modes")
        with self.lock:
            self.pointer = mode
            self._register_pointer()

    def _grow_changed(self) -> None:
        value = self.grow_box.value
        if value not in GRANULARITIES:
            self.grow_box.value = self.granularity
            raise GoiError(f"grow to: one of {', '.join(GRANULARITIES)}")
        self.granularity = value

    def _page_camera(self, what: str) -> Camera:
        """The page's camera as a camera of its own (a click or box is made at it)."""
        cam = self.browser_camera()
        if cam is None:
            raise GoiError(f"{what}: the browser has not reported its camera yet")
        self.cameras += 1
        return dataclasses.replace(cam, name=f"page{self.id}-view{self.cameras}")

    def _clicked(self, event: Any, positive: bool) -> None:
        """A click on the scene: a pixel of the page's camera, + or -, refining the answer
        shown (checked: the canvas position, and the ray through it from the camera)."""
        screen: Any = getattr(event, "screen_pos", None)
        if not _unit_pair(screen):
            raise GoiError("click: the position is not a point of the canvas")
        cam = self._page_camera("click")
        u, v = screen_pixel(screen, cam)
        ray = None
        if _finite3(event):
            origin = np.asarray(event.ray_origin, np.float64)
            direction = np.asarray(event.ray_direction, np.float64)
            ray = ray_pixel(origin, direction, cam, self.app.extent)
        if ray is None or max(abs(ray[0] - u), abs(ray[1] - v)) > RAY_SLACK * max(
            cam.width, cam.height
        ):
            raise GoiError("click: the view moved while you clicked; click again once it rests")
        click = Click(cam.name, u, v, positive)
        self.app.log(f"page {self.id} clicked {click.text()}")
        self.app.answers.point(self.id, [click], [], {cam.name: cam}, self.granularity)

    def _boxed(self, event: Any) -> None:
        """A box dragged on the scene: a rectangle at the page's camera."""
        lo: Any = getattr(event, "screen_min", None)
        hi: Any = getattr(event, "screen_max", None)
        if not (_unit_pair(lo) and _unit_pair(hi)):
            raise GoiError("box: the corners are not points of the canvas")
        cam = self._page_camera("box")
        x0, y0, x1, y1 = screen_box(lo, hi, cam)
        if x1 - x0 < MIN_BOX or y1 - y0 < MIN_BOX:
            raise GoiError("box: drag a larger box around what you mean")
        box = BoxPrompt(cam.name, (x0, y0, x1, y1))
        self.app.log(f"page {self.id} drew a box {box.text()}")
        self.app.answers.point(self.id, [], [box], {cam.name: cam}, self.granularity)

    # -- named answers --------------------------------------------------------------------------

    def keep(self) -> None:
        if self.app.answers.keep(self.id, self.name_box.value):
            self.name_box.value = ""

    def combine(self) -> None:
        op = OP_NAMES.get(self.op_box.value)
        if op is None:
            raise GoiError(f"combine: the operation is one of {', '.join(OP_NAMES)}")
        self.app.answers.combine(self.id, op, self.a_box.value, self.b_box.value)

    def forget(self) -> None:
        if self.a_box.value == SHOWN:
            raise GoiError("forget: choose a named answer as A")
        self.app.answers.forget(self.id, self.a_box.value)

    def export_labels(self) -> None:
        if self.app.answers.export_labels(self.id):
            self.export_note.content = self._small("writing the labels...")

    def _mode_changed(self) -> None:
        mode = self.mode_box.value
        if mode not in MODES:
            self.mode_box.value = self.mode
            raise GoiError(f"highlight: one of {', '.join(MODES)}")
        with self.lock:
            self.mode = mode
            self._redraw()
            self._describe()

    def _color_changed(self) -> None:
        value = self.color_box.value
        ok = (
            isinstance(value, tuple)
            and len(value) == 3
            and all(isinstance(v, int) and 0 <= v <= 255 for v in value)
        )
        if not ok:
            self.color_box.value = tuple(int(round(255 * c)) for c in self.color)
            raise GoiError("tint: three integers from 0 to 255")
        with self.lock:
            self.color = np.asarray(value, np.float32) / 255.0
            self._redraw()

    def _history_picked(self) -> None:
        value = self.history_box.value
        if value == NONE:
            return
        key = self.history_keys.get(value)
        self.history_box.value = NONE  # picking the same entry again shows it again
        if key is None:
            raise GoiError("history: not one of the answers in the history")
        ans = self.app.answers.history.get(key)
        if ans is not None and ans.kind == "text" and self.prompt_box is not None:
            self.prompt_box.value = ans.prompt.text
        self.app.answers.pick(self.id, key)

    # -- what the answer protocol tells the page (a Display) ----------------------------------

    def show(self, shown: Shown) -> None:
        """Light the answer up in 3D and say what it is (a preview, or the final answer)."""
        self.built.wait()
        ans = shown.answer
        with self.lock:
            if self.closed.is_set():
                return
            first = self.shown is None or self.shown.request != shown.request
            self.shown = shown
            self._redraw()
            self._describe()
            self.fly_button.visible = ans.count > 0
            if not shown.preview:
                self._show_evidence(ans)
        self.client.flush()
        self.shown_at = time.perf_counter()
        if ans.count and (first or not shown.preview) and not self._in_view(ans.selected):
            self.fly_to_answer()  # nothing of it in view: frame it
        self._mask_wanted()

    def _describe(self) -> None:
        """The status line of the answer on display: its prompt, its count, whether it is a
        preview or the answer, and the highlight mode."""
        shown = self.shown
        if shown is None:
            return
        ans = shown.answer
        if shown.preview:
            what = (
                f"<span style='background:#ffe7a3;padding:0 3px'><b>preview</b></span> "
                f"{_e(ans.label)}: not the answer yet"
            )
        else:
            src = {"history": " (from the history)", "step": " (undo/redo)"}
            what = f"<b>answer</b>: {_e(ans.label)}{src.get(shown.source, '')}"
        legend = f"<br>{_e(HEAT_LEGEND)}" if self.mode == "heat" else ""
        self._say(
            f"<i>{_e(ans.prompt.text)}</i><br><b>{ans.count:,}</b> Gaussians &middot; {what}"
            f"<br><span style='color:#555'>highlight: {_e(self.mode)} &middot; "
            f"{ans.seconds:.2f} s{legend}</span>"
        )

    def progress(self, done: int, total: int, what: str) -> None:
        self.bar.visible = True
        self.bar.value = 100.0 * done / max(total, 1)

    def note(self, text: str) -> None:
        self._say(_e(text))

    def failed(self, message: str) -> None:
        with self.lock:
            self._say(_e(message), error=True)

    def idle(self) -> None:
        self.bar.visible = False

    def exported(self, message: str, error: bool) -> None:
        color = "#b00020" if error else "#555"
        self.export_note.content = f"<div style='font-size:0.8em;color:{color}'>{_e(message)}</div>"

    def history_changed(self) -> None:
        keys = {}
        for a in self.app.answers.history.answers():
            keys[f"{a.prompt.text} · {ROUTE_NAMES[a.route]} · {a.count:,}"] = a.key
        named = self.app.answers.named()
        with self.lock:
            self.history_keys = keys
            self.history_box.options = [NONE, *keys]
            self.history_box.value = NONE
            names = [SHOWN, *(n for n, _ in named)]
            for box in (self.a_box, self.b_box):
                keep = box.value if box.value in names else SHOWN
                box.options = names
                box.value = keep
            rows = "".join(
                f"<div><b>{_e(n)}</b>: {a.count:,} Gaussians ({_e(_kind(a))})</div>"
                for n, a in named
            )
            self.named_html.content = self._small(rows or "None kept yet.")

    def clear(self) -> None:
        """No answer on display (undone back to the first step)."""
        with self.lock:
            if self.closed.is_set():
                return
            self.shown = None
            self._redraw()
            self.fly_button.visible = False
            self._say("Nothing selected (the first step).")
            self._show_evidence(None)
        self._mask_wanted()

    def steps(self, items: list[str], at: int) -> None:
        """The page's steps, the one on display marked."""
        rows = []
        for i, line in enumerate(items):
            text = f"{i}. {_e(line)}"
            rows.append(f"<div><b>&#9656; {text}</b></div>" if i == at else f"<div>{text}</div>")
        recent = rows[-8:] if at >= len(rows) - 8 else rows[max(0, at - 4) : at + 4]
        more = f"<div>({len(rows)} steps)</div>" if len(rows) > len(recent) else ""
        self.steps_html.content = self._small("Steps:" + "".join(recent) + more)

    # -- the evidence -----------------------------------------------------------------------------

    def _show_evidence(self, ans: Answer | None) -> None:
        """The views behind the answer shown, with their weights, and the heaviest one's photo
        with its mask over it."""
        s = self.app.session
        views = s.evidence(ans) if ans is not None else []
        self.evidence_views = {f"{v} · weight {w:.2f}": v for v, w in views}
        self.evidence_box.options = [NONE, *self.evidence_views]
        if not views:
            why = "No answer yet." if ans is None else (
                "No view's mask is behind this answer (the fixed threshold, or answers combined)."
            )  # fmt: skip
            self.evidence_note.content = self._small(why)
            self.evidence_box.value = NONE
            self.evidence_image.visible = False
            return
        weights = ", ".join(f"{_e(v)} {w:.2f}" for v, w in views[:24])
        more = f", ... ({len(views)} views)" if len(views) > 24 else ""
        self.evidence_note.content = self._small(
            f"<b>{len(views)}</b> views voted, by weight: {weights}{more}"
        )
        first = next(iter(self.evidence_views))
        self.evidence_box.value = first
        self._draw_evidence(ans, views[0][0])

    def _evidence_picked(self) -> None:
        value = self.evidence_box.value
        if value == NONE:
            return
        view = self.evidence_views.get(value)
        if view is None:
            raise GoiError("view: not one of the views behind the answer shown")
        shown = self.shown
        if shown is not None:
            self._draw_evidence(shown.answer, view)

    def _draw_evidence(self, ans: Answer | None, view: str) -> None:
        """The training photo of `view` with the mask it gave `ans` over it."""
        if ans is None:
            return
        s = self.app.session
        cam = s.scene.by_name.get(view)
        if cam is None:
            return
        try:
            photo = _fit(s.scene.load_image(cam), PHOTO_SIDE)
        except GoiError as e:
            self.evidence_note.content = self._small(_e(e))
            return
        mask = s.evidence_mask(ans, view)
        if mask is not None:
            import cv2

            from stages.query.masks import overlay

            h, w = photo.shape[:2]
            if mask.shape != (h, w):
                small = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
                mask = small > 0
            photo = overlay(photo.astype(np.float32) / 255.0, mask)
        self.evidence_image.image = photo
        self.evidence_image.visible = True

    # -- drawing ------------------------------------------------------------------------------

    def _redraw(self) -> None:
        shown = self.shown
        selected = shown.answer.selected if shown is not None else None
        color = PREVIEW_TINT if shown is not None and shown.preview else self.color
        heat = None
        if self.mode == "heat" and shown is not None:
            score = self.app.session.heat(shown.answer)
            heat = None if score is None else stretched(score)
        self._apply(selected, color, heat)

    def _apply(
        self, selected: np.ndarray | None, color: np.ndarray, heat: np.ndarray | None = None
    ) -> None:
        app = self.app
        p: Plan = plan(app.splats, app.chunks, self.drawn, selected, self.mode, color, heat)
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
                self.overlay_node = self._overlay(p.overlay, p.overlay_tinted, color)
        self.drawn = p.chunk_keys

    def _overlay(self, idx: np.ndarray, tinted: bool, color: np.ndarray) -> Any:
        from stages.view.splats import covariances, highlighted

        g = self.app.session.scene.gaussians
        rgb = g.colors_dc()[idx].astype(np.float32)
        op = np.asarray(g.opacities[idx], np.float32)[:, None]
        if tinted:
            rgb, op = highlighted(rgb, op, np.ones(idx.size, bool), "tint", color)
        covs = covariances(g.quats[idx], g.scales[idx])
        return self.client.scene.add_gaussian_splats(
            "/selection", centers=g.means[idx], covariances=covs, rgbs=rgb, opacities=op
        )

    def _say(self, text: str, error: bool = False) -> None:
        self.status.content = self._status_html(text, error)

    # -- the camera ---------------------------------------------------------------------------

    def browser_camera(self, name: str = "browser") -> Camera | None:
        cam = self.client.camera
        try:
            w, h = render_size(cam.image_width, cam.image_height, MASK_SIDE)
            return browser_camera(name, cam.wxyz, cam.position, cam.fov, w, h)
        except (AssertionError, GoiError):  # no camera reported yet, or not a camera
            return None

    def _in_view(self, selected: np.ndarray) -> bool:
        """Whether any selected Gaussian's centre is in the page's view."""
        cam = self.browser_camera()
        if cam is None:
            return True  # no camera yet: the page's first camera decides
        means = self.app.session.scene.gaussians.means[selected]
        with np.errstate(divide="ignore", invalid="ignore"):  # a centre at the eye's depth
            uv, z = cam.project(np.asarray(means, np.float64))
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width)
        inside &= (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        return bool(inside.any())

    def fly_to_answer(self) -> None:
        shown = self.shown
        if shown is None or not shown.answer.count:
            raise GoiError("there is no answer on display to fly to")
        s = self.app.session
        cams = s.scene.views("train") or s.scene.cameras
        position, middle = framing(
            shown.answer.selected, s.scene.gaussians.means, cams, self.app.up,
            float(self.client.camera.fov),
        )  # fmt: skip
        self._fly(position, middle)

    def _fly(self, position: np.ndarray, look_at: np.ndarray, fov: float | None = None) -> None:
        with self.client.atomic():
            self.client.camera.up_direction = tuple(self.app.up)
            if fov is not None:
                self.client.camera.fov = fov
            self.client.camera.position = tuple(position)
            self.client.camera.look_at = tuple(look_at)

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
        self.photo.visible = True
        self.photo_note.content = self._small(
            f"Photo of training camera <b>{_e(cam.name)}</b> ({cam.width}x{cam.height}); the "
            "page now looks from it"
        )

    # -- the mask at the page's camera ----------------------------------------------------------

    def _camera_moved(self) -> None:
        self.last_move = time.monotonic()
        self.wake.set()

    def _mask_wanted(self) -> None:
        self.wake.set()

    def _mask_loop(self) -> None:
        """One render in flight for the page at most; the latest camera and answer win; a
        camera and answer whose mask is on display already cost nothing."""
        last_render = 0.0
        while not self.closed.is_set():
            self.wake.wait()
            self.wake.clear()
            while not self.closed.is_set() and time.monotonic() - self.last_move < REST_S:
                self.closed.wait(REST_S / 3)  # the camera is moving: wait for it to rest
            if self.closed.is_set():
                return
            shown = self.shown
            preview = shown is not None and shown.preview
            if preview and time.monotonic() - last_render < PREVIEW_MASK_S:
                self.closed.wait(PREVIEW_MASK_S - (time.monotonic() - last_render))
                self.wake.set()  # look again then: the newest answer and camera
                continue
            cam = self.browser_camera()
            if cam is None:
                continue
            key = (_pose_key(cam), id(shown.answer) if shown else None)
            if key == self.mask_key:
                continue
            try:
                self.render_mask(cam, shown)
            except GoiError as e:
                self.mask_note.content = self._small(f"could not render: {_e(e)}")
            except Exception as e:  # a bug: logged, the page goes on
                self.app.log(f"page {self.id}: the mask: {type(e).__name__}: {str(e)[:200]}")
                self.mask_note.content = self._small(_e(INTERNAL))
            self.mask_key = key
            last_render = time.monotonic()

    def render_mask(self, cam: Camera, shown: Shown | None) -> None:
        s = self.app.session
        answer = shown.answer if shown is not None else None
        t0 = time.perf_counter()
        with self.app.worker.gate.urgent():
            mv = s.mask_at(answer, cam)
        dt = time.perf_counter() - t0
        self.mask_image.image = mv.overlay
        what = "no answer yet" if answer is None else f"{int(mv.mask.sum()):,} pixels of the mask"
        if answer is not None:
            what += f" of <i>{_e(answer.prompt.text)}</i>" + (
                " (preview)" if shown and shown.preview else ""
            )
        self.mask_note.content = self._small(
            f"{cam.width}x{cam.height}, {what}, rendered in {dt:.2f} s: what goi render-mask "
            "--camera-file writes for this camera (Save camera)."
        )

    # -- saving ---------------------------------------------------------------------------------

    def save_camera(self) -> None:
        cam = self.browser_camera()
        if cam is None:
            raise GoiError("the browser has not reported its camera yet")
        try:
            path = self.app.session.save_camera(cam)
        except GoiError as e:
            self.mask_note.content = self._small(_e(e))
            self.app.log(f"refused a camera of page {self.id}: {e}")
            return
        self.app.log(f"page {self.id} saved a camera: {path}")
        self.mask_note.content = self._small(
            f"camera saved: {_e(path)} (goi render-mask --camera-file {_e(path)})"
        )

    def export(self, what: str) -> None:
        color = "#" + "".join(f"{int(round(255 * c)):02x}" for c in self.color)
        if self.app.answers.export(self.id, what, color):
            self.export_note.content = self._small(f"writing {_e(what)}...")


def _unit_pair(value: object) -> bool:
    """`value` is a canvas position: two finite numbers (viser's page sends 0..1; a little
    outside is clamped)."""
    return (
        isinstance(value, list | tuple)
        and len(value) == 2
        and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value)
        and all(math.isfinite(x) and -1.0 <= x <= 2.0 for x in value)
    )


def _finite3(event: Any) -> bool:
    """The click event's ray is two triples of finite numbers."""
    for name in ("ray_origin", "ray_direction"):
        v: Any = getattr(event, name, None)
        if not (isinstance(v, list | tuple) and len(v) == 3):
            return False
        if not all(isinstance(x, int | float) and math.isfinite(x) for x in v):
            return False
    return True


def _kind(ans: Answer) -> str:
    return {"text": ROUTE_NAMES.get(ans.route, ans.route), "combine": "combined"}.get(
        ans.kind, ans.kind
    )


def _pose_key(cam: Camera) -> tuple:
    return (cam.width, cam.height, round(cam.fx, 6), *np.round(cam.R, 6).ravel(),
            *np.round(cam.t, 6))  # fmt: skip


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
