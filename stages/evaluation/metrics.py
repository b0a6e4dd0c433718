"""The paper's 2D metrics (IoU, mPA, mP per image) and our 3D IoU over Gaussians.

A ratio whose denominator is empty (0/0) counts as 1 when prediction and ground truth agree that
the class is absent, and as 0 otherwise; so an empty prediction of an empty ground truth is
perfect, and an empty prediction of a present object scores 0 on the object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _ratio(num: float, den: float, both_empty: bool) -> float:
    if den > 0:
        return float(num / den)
    return 1.0 if both_empty else 0.0


@dataclass
class Scores:
    iou: float
    mpa: float  # mean of foreground and background recall
    mp: float  # mean of foreground and background precision

    def as_dict(self) -> dict[str, float]:
        return {"iou": self.iou, "mpa": self.mpa, "mp": self.mp}


def image_scores(pred: np.ndarray, gt: np.ndarray) -> Scores:
    """[H, W] bool prediction (resized to the ground truth's size first) and ground truth."""
    if pred.shape != gt.shape:
        import cv2

        pred = cv2.resize(
            pred.astype(np.uint8), (gt.shape[1], gt.shape[0]), interpolation=cv2.INTER_NEAREST
        ).astype(bool)
    p, g = pred.astype(bool), gt.astype(bool)
    tp = float(np.sum(p & g))
    fp = float(np.sum(p & ~g))
    fn = float(np.sum(~p & g))
    tn = float(np.sum(~p & ~g))
    fg_empty = bool(not p.any() and not g.any())
    bg_empty = bool(p.all() and g.all())
    iou = _ratio(tp, tp + fp + fn, fg_empty)
    recall_fg = _ratio(tp, tp + fn, fg_empty)
    recall_bg = _ratio(tn, tn + fp, bg_empty)
    prec_fg = _ratio(tp, tp + fp, fg_empty)
    prec_bg = _ratio(tn, tn + fn, bg_empty)
    return Scores(iou, (recall_fg + recall_bg) / 2, (prec_fg + prec_bg) / 2)


def mean_scores(scores: list[Scores]) -> Scores:
    return Scores(
        float(np.mean([s.iou for s in scores])),
        float(np.mean([s.mpa for s in scores])),
        float(np.mean([s.mp for s in scores])),
    )


def iou_3d(selected: np.ndarray, target: np.ndarray, weight: np.ndarray | None = None) -> float:
    """IoU of two Gaussian sets ([G] bool), counting each Gaussian once or by `weight`."""
    w = np.ones(selected.shape) if weight is None else weight
    union = float(w[selected | target].sum())
    return _ratio(float(w[selected & target].sum()), union, not selected.any() and not target.any())
