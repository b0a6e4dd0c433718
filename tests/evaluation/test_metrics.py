import numpy as np
import pytest

from stages.evaluation.metrics import image_scores, iou_3d, mean_scores, stray_share


def _m(rows):
    return np.array(rows, bool)


#: ground truth, prediction, (IoU, mPA, mP) worked out by hand
KNOWN = [
    # TP 1, FP 1, FN 1, TN 5
    ([[1, 1, 0, 0], [0, 0, 0, 0]], [[1, 0, 1, 0], [0, 0, 0, 0]],
     (1 / 3, (1 / 2 + 5 / 6) / 2, (1 / 2 + 5 / 6) / 2)),
    # TP 2, FP 1, FN 2, TN 3
    ([[1, 1, 1, 1], [0, 0, 0, 0]], [[1, 1, 0, 0], [1, 0, 0, 0]],
     (2 / 5, (2 / 4 + 3 / 4) / 2, (2 / 3 + 3 / 5) / 2)),
]  # fmt: skip


def test_known_values():
    scores = [image_scores(_m(pred), _m(gt)) for gt, pred, _ in KNOWN]
    for s, (_, _, want) in zip(scores, KNOWN, strict=True):
        assert (s.iou, s.mpa, s.mp) == pytest.approx(want)
    assert mean_scores(scores).iou == pytest.approx((1 / 3 + 2 / 5) / 2)


def test_empty_prediction_and_empty_ground_truth():
    gt = _m([[1, 0], [0, 0]])
    empty = np.zeros((2, 2), bool)
    s = image_scores(empty, gt)  # missed the object
    assert s.iou == 0 and s.mpa == pytest.approx(0.5) and s.mp == pytest.approx((0 + 3 / 4) / 2)
    s = image_scores(empty, empty)  # nothing there, nothing predicted: perfect
    assert (s.iou, s.mpa, s.mp) == (1.0, 1.0, 1.0)
    # A false alarm on an empty ground truth: the foreground has no recall to score (nothing
    # to find), so mPA is the background's recall alone; the false pixel costs precision.
    s = image_scores(gt, empty)
    assert s.iou == 0 and s.mpa == pytest.approx(3 / 4) and s.mp == pytest.approx((0 + 1) / 2)
    full = np.ones((2, 2), bool)
    assert image_scores(full, full).as_dict() == {"iou": 1.0, "mpa": 1.0, "mp": 1.0}


def test_a_class_absent_from_the_ground_truth_is_left_out_of_the_means():
    full = np.ones((2, 2), bool)
    pred = _m([[1, 1], [1, 0]])  # one pixel wrongly called background
    s = image_scores(pred, full)
    # background recall is undefined (no background to find): mPA is the foreground's recall
    assert s.mpa == pytest.approx(3 / 4)
    # foreground precision 3/3; background precision 0/1 (its one pixel is foreground)
    assert s.mp == pytest.approx((1 + 0) / 2)
    assert s.iou == pytest.approx(3 / 4)
    # a class the ground truth has but the prediction lacks: recall 0 and precision 0
    half = _m([[1, 1], [0, 0]])
    s = image_scores(full, half)
    assert s.mpa == pytest.approx((1 + 0) / 2)  # fg recall 2/2, bg recall 0/2
    assert s.mp == pytest.approx((2 / 4 + 0) / 2)  # fg precision 2/4, bg missed entirely
    # background absent from both: left out of both means
    s = image_scores(full, full)
    assert (s.mpa, s.mp) == (1.0, 1.0)


def test_prediction_is_resized_to_the_ground_truth():
    gt = np.zeros((4, 4), bool)
    gt[:2, :2] = True
    pred = np.zeros((2, 2), bool)
    pred[0, 0] = True
    assert image_scores(pred, gt).iou == 1.0


def test_iou_3d_counts_and_weights():
    sel = np.array([1, 1, 0, 0], bool)
    tgt = np.array([1, 0, 1, 0], bool)
    assert iou_3d(sel, tgt) == pytest.approx(1 / 3)
    assert iou_3d(sel, tgt, np.array([2.0, 1.0, 1.0, 5.0])) == pytest.approx(2 / 4)
    assert iou_3d(np.zeros(3, bool), np.zeros(3, bool)) == 1.0


def test_stray_share_counts_the_selection_far_from_every_target_gaussian():
    # the corners make the extent 10 (the bounding box diagonal): strays lie beyond 0.3
    means = np.array(
        [[0, 0, 0], [6, 8, 0], [1, 1, 0], [1.1, 1, 0], [1, 1.29, 0], [1, 1.31, 0], [3, 3, 0]],
        float,
    )
    target = np.array([0, 0, 1, 1, 0, 0, 0], bool)
    sel = np.array([0, 0, 1, 1, 1, 1, 1], bool)
    assert stray_share(sel, target, means) == pytest.approx(2 / 5)
    assert stray_share(target, target, means) == 0.0
    assert stray_share(np.zeros(7, bool), target, means) == 0.0  # nothing selected
    assert stray_share(sel, np.zeros(7, bool), means) == 1.0  # no target: all of it strays
