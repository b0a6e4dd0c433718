"""Each public benchmark's metric against values computed by hand on tiny masks, and the fast
kernels against plain transcriptions of the reference code."""

import math

import cv2
import numpy as np
import pytest

from stages.core.errors import GoiError
from stages.evaluation.benchmarks.common import BenchmarkScene, Frame, Query, pil_nearest, read_grey
from stages.evaluation.benchmarks.protocols import (
    closed_set,
    goi_eval_seg_image,
    goi_resized,
    lerf_mask_scores,
    lerf_ovs_localised,
    lerf_ovs_mask,
    lerf_smooth,
    lerf_smooth_reference,
    mask_to_boundary,
    three_d_ovs_scores,
)
from stages.evaluation.benchmarks.scoring import protocol_scores
from tests.helpers import front_camera


def test_goi_eval_seg_per_image_by_hand():
    gt = np.array([[1, 1], [0, 0]], bool)
    iou, mpa, mp = goi_eval_seg_image(np.array([[1, 0], [0, 0]], bool), gt)
    # IoU 1/2; recalls 1/2 (fg) and 2/2 (bg); precisions 1/1 and 2/3
    assert (iou, mpa, mp) == pytest.approx((0.5, 0.75, (1 + 2 / 3) / 2))
    iou, mpa, mp = goi_eval_seg_image(np.zeros((2, 2), bool), gt)
    assert iou == 0 and mpa == 0.5 and math.isnan(mp)  # mP has no guard: 0/0 -> NaN
    iou, mpa, mp = goi_eval_seg_image(np.zeros((2, 2), bool), np.zeros((2, 2), bool))
    assert math.isnan(iou) and mpa == 0.5  # an absent class's recall counts 0, not left out


def test_goi_eval_seg_resizes_bilinear_then_above_zero():
    # cv2's bilinear 2x2 -> 4x4 of a 255 corner reaches 3 x 3 pixels (the last weight 1/16)
    pred = goi_resized(np.array([[1, 0], [0, 0]], bool), (4, 4))
    want = np.zeros((4, 4), bool)
    want[:3, :3] = True
    assert (pred == want).all()


def test_lerf_smooth_equals_the_reference_loop():
    rng = np.random.default_rng(0)
    for shape in ((2, 2), (5, 9), (17, 12)):
        for p in (0.2, 0.5, 0.8):
            m = (rng.random(shape) < p).astype(np.uint8)
            assert (lerf_smooth(m) == lerf_smooth_reference(m)).all()
    # by hand: a lone pixel is voted away; a tie (the last row and column never count) goes to 0
    m = np.zeros((8, 8), np.uint8)
    m[3, 3] = 1
    assert not lerf_smooth(m).any()
    m = np.zeros((2, 2), np.uint8)
    m[0, 0] = 1  # every window is the single pixel (0, 0)
    assert lerf_smooth(m).all()


def test_lerf_ovs_mask_and_localisation_of_a_binary_map():
    r = np.zeros((100, 120), np.float32)
    r[20:70, 30:90] = 1  # goi's mask as the relevancy map
    m = lerf_ovs_mask(r).astype(bool)
    assert m[45, 60] and not m[~(r > 0)].any()  # the core is kept, nothing outside the mask
    assert not lerf_ovs_mask(np.zeros((40, 40), np.float32)).any()
    box = np.array([[89, 69, 30, 20]])  # corners in either order, inclusive
    assert lerf_ovs_localised(r, box)
    assert not lerf_ovs_localised(r, np.array([[0, 0, 10, 10]]))
    assert lerf_ovs_localised(r, np.array([[0, 0, 10, 10], [50, 40, 70, 50]]))  # any box


def test_lerf_mask_iou_and_boundary_iou_by_hand():
    gt = np.zeros((10, 10), np.uint8)
    gt[2:8, 2:8] = 255
    pred = np.zeros((10, 10), np.uint8)
    pred[2:8, 2:7] = 255
    iou, biou = lerf_mask_scores(pred, gt)
    # d = max(1, round(0.02 * 14.1)) = 1: boundaries are the 1-px rings, 20 and 18 pixels;
    # 14 of the prediction's lie on the ground truth's ring (its right column is inside)
    assert iou == pytest.approx(30 / 36) and biou == pytest.approx(14 / 24)
    assert lerf_mask_scores(gt, gt) == (1.0, 1.0)
    # Python's round: 0.02 * 125 = 2.5 -> 2 erosions, a 2-px ring of a full 75 x 100 mask
    full = np.ones((75, 100), np.uint8)
    assert mask_to_boundary(full).sum() == 75 * 100 - 71 * 96


def test_pil_nearest_and_grey_equal_pillow(tmp_path):
    Image = pytest.importorskip("PIL.Image")
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (13, 17), dtype=np.uint8)
    for w, h in ((5, 4), (17, 13), (40, 31), (8, 13)):
        want = np.array(Image.fromarray(img).resize((w, h), resample=Image.NEAREST))
        assert (pil_nearest(img, w, h) == want).all()
    rgb = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "c.png"), rgb[:, :, ::-1])
    want = np.array(Image.open(tmp_path / "c.png").convert("L"))
    assert (read_grey(tmp_path / "c.png", "mask") == want).all()


def test_three_d_ovs_jaccard_and_accuracy_by_hand():
    pred = np.array([[0, 1], [1, 1]])
    gt = np.zeros((2, 2, 3), np.int8)
    gt[0, :, 0] = 1  # class 0: the top row
    gt[1, :, 1] = 1  # class 1: the bottom row; class 2 nowhere
    ious, acc = three_d_ovs_scores(pred, gt)
    assert ious == pytest.approx([1 / 2, 2 / 3, 0.0]) and acc == 0.75
    gt[0, 0, :] = 0  # a pixel of no class never matches a one-hot row
    assert three_d_ovs_scores(pred, gt)[1] == 0.5
    masks = np.array([[[0, 1]], [[1, 1]], [[0, 0]]], bool)  # [C, H, W]: ties to the first
    assert (closed_set(masks) == [[1, 0]]).all()


def _scene() -> tuple[BenchmarkScene, dict]:
    """Two queries: A on frames f1 (right) and f2 (wrong), B on f1 (right)."""
    gt = np.array([[1, 0], [0, 0]], bool)
    cam1, cam2 = front_camera(2, 2, "f1"), front_camera(2, 2, "f2")
    frames = [Frame("f1", cam1, None, {"A": gt, "B": gt}), Frame("f2", cam2, None, {"A": gt})]  # type: ignore[arg-type]
    scene = BenchmarkScene("s", None, [Query("A", "a"), Query("B", "b")], frames)  # type: ignore[arg-type]
    preds = {"A": {"f1": gt, "f2": ~gt}, "B": {"f1": gt}}
    return scene, preds


def test_aggregation_orders_differ_as_the_references_do():
    scene, preds = _scene()
    m360, _ = protocol_scores("goi-m360", scene, preds)
    replica, _ = protocol_scores("replica-goi", scene, preds)
    assert m360["miou"] == pytest.approx(0.75)  # images -> prompt: A 0.5, B 1 -> 0.75
    assert replica["miou"] == pytest.approx(0.5)  # prompts -> image: f1 1, f2 0 -> 0.5
    for f in scene.frames:  # LERF-Mask's ground truth is grey (> 128 is in)
        f.gts = {q: g.astype(np.uint8) * 255 for q, g in f.gts.items()}
    lm, _ = protocol_scores("lerf-mask", scene, preds)
    assert lm["miou"] == pytest.approx(0.75)  # per prompt over views, then over prompts


def test_a_prediction_of_another_size_is_refused_where_the_protocol_does_not_resize():
    scene, preds = _scene()
    preds["A"]["f1"] = np.zeros((3, 3), bool)
    for f in scene.frames:
        f.boxes = {q: np.array([[0, 0, 1, 1]]) for q in f.gts}
    with pytest.raises(GoiError, match="a prediction of 3x3 for the 2x2 ground truth of 'A'"):
        protocol_scores("lerf-ovs", scene, preds)
    assert protocol_scores("goi-m360", scene, preds)[0]["miou"] >= 0  # resized bilinear


def test_lerf_ovs_score_map_resolves_what_the_binary_map_cannot():
    """A 25x25 object (the box) and a 60x60 distractor both in goi's 0/1 mask: the 30x30 mean
    peaks on the distractor (a miss) and the distractor survives the threshold. The score map
    (object 1.0, distractor 0.5) peaks on the object (25*25/900 = 0.69 > 0.5) and its
    normalised distractor (about 0.5 / 0.85 < 0.7) falls under the 0.4 cut of 2n - 1."""
    gt = np.zeros((120, 160), bool)
    gt[20:45, 20:45] = True
    binary = gt.copy()
    binary[40:100, 80:140] = True
    score = np.where(gt, 1.0, np.where(binary, 0.5, 0.0)).astype(np.float32)
    cam = front_camera(160, 120, "f1")
    frame = Frame("f1", cam, None, {"A": gt}, {"A": np.array([[20, 20, 44, 44]])})  # type: ignore[arg-type]
    scene = BenchmarkScene("s", None, [Query("A", "a")], [frame])  # type: ignore[arg-type]
    figs, detail = protocol_scores("lerf-ovs", scene, {"A": {"f1": binary}}, {"A": {"f1": score}})
    assert figs["localisation_accuracy"] == 0 and figs["localisation_accuracy_score_map"] == 1
    assert figs["miou"] < 0.3 and figs["miou_score_map"] > 0.9
    assert figs["goi_binary_miou"] == pytest.approx(625 / (625 + 3600))  # no overlap
    assert detail["A"]["f1"]["localised_score_map"] and not detail["A"]["f1"]["localised"]
    assert "miou_score_map" not in protocol_scores("lerf-ovs", scene, {"A": {"f1": binary}})[0]


def test_three_d_ovs_argmax_over_score_maps_by_hand():
    """Both classes claim both pixels in 0/1 (ties go to the first class: accuracy 1/2, IoU
    1/2 and 0); their scores [0.9, 0.4] and [0.2, 0.7] split them (accuracy 1, IoU 1 and 1)."""
    cam = front_camera(2, 1, "f1")
    gts = {"A": np.array([[1, 0]], np.uint8), "B": np.array([[0, 1]], np.uint8)}
    frame = Frame("f1", cam, None, gts)  # type: ignore[arg-type]
    scene = BenchmarkScene("s", None, [Query("A", "a"), Query("B", "b")], [frame])  # type: ignore[arg-type]
    both = np.ones((1, 2), bool)
    maps = {"A": {"f1": np.array([[0.9, 0.4]])}, "B": {"f1": np.array([[0.2, 0.7]])}}
    figs, detail = protocol_scores("3d-ovs", scene, {"A": {"f1": both}, "B": {"f1": both}}, maps)
    assert figs["accuracy"] == 0.5 and figs["miou"] == pytest.approx(0.25)
    assert figs["accuracy_score_map"] == 1 and figs["miou_score_map"] == 1
    assert detail["B"]["f1"] == {"iou": 0.0, "iou_score_map": 1.0}
