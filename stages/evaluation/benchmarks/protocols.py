"""Each benchmark's metric, exactly as its reference script computes it (arrays in, numbers
out; cv2 only where the reference calls cv2, so that borders and rounding agree).

Protocols (named as the report names them):
- `goi-eval-seg`: GOI's eval_seg.py. Per image: the prediction resized bilinear (cv2 default)
  to the ground truth, both > 0; IoU; mPA = mean of the two classes' recalls, a class absent
  from the ground truth counting 0; mP = mean of the two precisions with no guard (NaN when the
  prediction is all one class). Means: m360 image -> prompt -> scene -> overall; Replica
  prompt -> image -> scene -> overall.
- `lerf-ovs`: LangSplat's evaluate_iou_loc.py. A relevancy map r -> 0.5 (mean30(r) + r), min-max
  normalised, clip(2n - 1, 0, 1) > 0.4, a 7x7 majority filter (`lerf_smooth`); IoU per
  (frame, category), flat mean. Localisation: mean30(r)'s maximum pixels, a hit when one lies
  in a box of the category (inclusive); hits / (frame, category) pairs.
- `lerf-mask`: Gaussian Grouping's eval_lerf_mask.py. Masks grey > 128 (prediction resized
  PIL-nearest); IoU and boundary IoU (d = max(1, round(0.02 diagonal)), boundary = mask minus
  its d-times 3x3 erosion with a 1-px zero pad); mean per prompt over views, then over prompts.
- `3d-ovs`: 3D-OVS renderer.py. Closed set: a class per pixel; per image sklearn's jaccard per
  class (multilabel, a class absent from both scores 0) and accuracy (a pixel counts when its
  whole label row matches); mIoU = mean over (image, class), accuracy = mean over images.
"""

from __future__ import annotations

import math

import numpy as np

# -- GOI's eval_seg.py ---------------------------------------------------------------------


def goi_resized(pred: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """[H, W] bool: a 0/255 prediction resized bilinear (cv2.resize's default) to the ground
    truth's size, then > 0, as eval_seg.py reads the rendered mask PNG."""
    import cv2

    img: np.ndarray = pred.astype(np.uint8) * 255
    if img.shape != shape:
        img = np.asarray(cv2.resize(img, (shape[1], shape[0])))
    return np.asarray(img > 0)


def goi_eval_seg_image(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    """(IoU, mPA, mP) of one image as eval_seg.py has them: pred [h, w] bool (any size), gt
    [H, W] bool. 0/0 is NaN, as numpy and torch give it."""
    p = goi_resized(pred, gt.shape)
    g = gt.astype(bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.float64(np.sum(g & p)) / np.float64(np.sum(g | p))
        recalls, precisions = [], []
        for pc, gc in ((p, g), (~p, ~g)):  # class 1, then class 0
            hit = np.float64(np.sum(pc & gc))
            n_gt = np.float64(gc.sum())
            recalls.append(hit / n_gt if n_gt > 0 else 0.0)  # the reference's guard
            precisions.append(hit / np.float64(pc.sum()))  # no guard: NaN
    return float(iou), float(np.mean(recalls)), float(np.mean(precisions))


def nanless(x: float) -> float | None:
    """A figure for JSON: NaN (what the reference's 0/0 gives) becomes null."""
    return None if x is None or math.isnan(x) else float(x)


# -- LangSplat's evaluate_iou_loc.py (LERF-OVS) --------------------------------------------

#: the box filter of the relevancy map (30 x 30 mean, cv2.filter2D's default border)
LERF_FILTER = 30
#: the mask threshold on the normalised relevancy (the script's --mask_thresh default)
LERF_THRESHOLD = 0.4


def _mean30(r: np.ndarray) -> np.ndarray:
    import cv2

    kernel = np.ones((LERF_FILTER, LERF_FILTER)) / (LERF_FILTER**2)
    return np.asarray(cv2.filter2D(r, -1, kernel))


def lerf_smooth_reference(mask: np.ndarray) -> np.ndarray:
    """LangSplat's `smooth`, loop for loop: each pixel takes the majority (ties to 0) of the
    window rows max(0, i-3) .. min(i+4, h-1) (exclusive) and the same in x: the last row and
    column never enter a window."""
    h, w = mask.shape
    out = mask.copy()
    for i in range(h):
        for j in range(w):
            sq = mask[max(0, i - 3) : min(i + 4, h - 1), max(0, j - 3) : min(j + 4, w - 1)]
            out[i, j] = np.argmax(np.bincount(sq.reshape(-1)))
    return out


def lerf_smooth(mask: np.ndarray) -> np.ndarray:
    """`lerf_smooth_reference` through an integral image: [H, W] uint8 0/1 -> the same."""
    h, w = mask.shape
    ii = np.zeros((h + 1, w + 1), np.int64)
    ii[1:, 1:] = np.cumsum(np.cumsum(mask.astype(np.int64), 0), 1)
    r0 = np.maximum(np.arange(h) - 3, 0)
    r1 = np.minimum(np.arange(h) + 4, h - 1)
    c0 = np.maximum(np.arange(w) - 3, 0)
    c1 = np.minimum(np.arange(w) + 4, w - 1)
    ones = ii[r1][:, c1] - ii[r0][:, c1] - ii[r1][:, c0] + ii[r0][:, c0]  # [H, W]
    size = (r1 - r0)[:, None] * (c1 - c0)[None, :]
    return (2 * ones > size).astype(mask.dtype)  # argmax of the bincount: ties go to 0


def lerf_ovs_mask(relevancy: np.ndarray) -> np.ndarray:
    """[H, W] float32 relevancy -> [H, W] uint8 0/1 mask as activate_stream makes it."""
    r = relevancy.astype(np.float32)
    r = (0.5 * (_mean30(r) + r)).astype(np.float32)
    out = r - r.min()
    out = out / (out.max() + np.float32(1e-9))
    out = np.clip(out * np.float32(2.0) - np.float32(1.0), 0, 1)
    return lerf_smooth((out > np.float32(LERF_THRESHOLD)).astype(np.uint8))


def binary_iou(pred: np.ndarray, gt: np.ndarray) -> float:
    """|pred & gt| / |pred | gt| as the scripts compute it (NaN when both are empty)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(np.float64(np.sum(pred.astype(bool) & gt.astype(bool))) / np.sum(pred | gt))


def lerf_ovs_localised(relevancy: np.ndarray, boxes: np.ndarray) -> bool:
    """Whether a maximum pixel of mean30(relevancy) lies in one of the boxes ([K, 4] x1 y1 x2 y2,
    corners in any order, edges inclusive)."""
    avg = _mean30(relevancy.astype(np.float32))
    ys, xs = np.nonzero(avg == avg.max())
    for x1, y1, x2, y2 in boxes.reshape(-1, 4):
        inside = (
            (xs >= min(x1, x2)) & (xs <= max(x1, x2)) & (ys >= min(y1, y2)) & (ys <= max(y1, y2))
        )
        if inside.any():
            return True
    return False


# -- Gaussian Grouping's eval_lerf_mask.py (LERF-Mask) -------------------------------------


def mask_to_boundary(mask: np.ndarray, dilation_ratio: float = 0.02) -> np.ndarray:
    """[H, W] uint8 0/1 -> its boundary band (uint8 0/1), as the reference's gist has it."""
    import cv2

    h, w = mask.shape
    dilation = max(1, int(round(dilation_ratio * math.sqrt(h**2 + w**2))))  # Python's round
    padded = cv2.copyMakeBorder(mask, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    eroded = cv2.erode(padded, np.ones((3, 3), np.uint8), iterations=dilation)[1 : h + 1, 1 : w + 1]
    return mask - eroded


def lerf_mask_scores(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """(IoU, boundary IoU) of a prediction and a ground truth, both [.., ..] uint8 grey (> 128
    is in); the prediction is resized PIL-nearest to the ground truth first."""
    from stages.evaluation.benchmarks.common import pil_nearest

    if pred.shape != gt.shape:
        pred = pil_nearest(pred, gt.shape[1], gt.shape[0])
    p, g = (pred > 128).astype(np.uint8), (gt > 128).astype(np.uint8)
    iou = binary_iou(p.astype(bool), g.astype(bool))
    gb, pb = mask_to_boundary(g), mask_to_boundary(p)
    with np.errstate(invalid="ignore", divide="ignore"):
        biou = float(np.float64(((gb * pb) > 0).sum()) / ((gb + pb) > 0).sum())
    return iou, biou


# -- 3D-OVS renderer.py --------------------------------------------------------------------


def three_d_ovs_scores(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, float]:
    """pred [H, W] class index, gt [H, W, C] 0/1 (several or no classes per pixel) -> (per-class
    jaccard [C], subset accuracy), as sklearn's jaccard_score(average=None) and
    accuracy_score give them on the one-hot rows."""
    c = gt.shape[-1]
    onehot = np.eye(c, dtype=bool)[pred]  # [H, W, C]
    g = gt.astype(bool)
    inter = np.sum(onehot & g, axis=(0, 1)).astype(np.float64)
    union = np.sum(onehot | g, axis=(0, 1)).astype(np.float64)
    ious = np.divide(inter, union, out=np.zeros(c), where=union > 0)  # zero_division: 0
    accuracy = float(np.mean(np.all(onehot == g, axis=-1)))
    return ious, accuracy


def closed_set(masks: np.ndarray) -> np.ndarray:
    """goi's binary answers [C, H, W] (classes in sorted order) -> a class per pixel: the
    argmax over the classes as the reference takes it over their similarities, here over 0/1
    (a pixel claimed by several classes, or by none, goes to the first of them in the order)."""
    return np.argmax(masks, axis=0)
