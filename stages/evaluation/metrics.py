"""The paper's 2D metrics (IoU, mPA, mP per image), our 3D IoU over Gaussians and the stray share.

Per image, over the two classes foreground and background:
- IoU is the foreground's; an image where neither prediction nor ground truth has foreground
  scores 1 (they agree that the target is absent).
- mPA is the mean of the classes' recalls. A class absent from the ground truth has no recall
  (there is nothing of it to find): it is left out of the mean, not counted 0 or 1.
- mP is the mean of the classes' precisions. A class absent from both prediction and ground
  truth has no precision and is left out; a class the ground truth has but the prediction
  lacks scores 0 (all of it was missed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.query.clean import near_any, scene_extent


@dataclass
class Scores:
    iou: float
    mpa: float  # mean of the defined class recalls
    mp: float  # mean of the defined class precisions

    def as_dict(self) -> dict[str, float]:
        return {"iou": self.iou, "mpa": self.mpa, "mp": self.mp}


def _mean_defined(values: list[float | None]) -> float:
    defined = [v for v in values if v is not None]
    return float(np.mean(defined))  # every image has at least one class in its ground truth


def image_scores(pred: np.ndarray, gt: np.ndarray) -> Scores:
    """[H, W] bool prediction (resized to the ground truth's size first) and ground truth."""
    if pred.shape != gt.shape:
        import cv2

        pred = cv2.resize(
            pred.astype(np.uint8), (gt.shape[1], gt.shape[0]), interpolation=cv2.INTER_NEAREST
        ).astype(bool)
    p, g = pred.astype(bool), gt.astype(bool)
    recalls: list[float | None] = []
    precisions: list[float | None] = []
    for pc, gc in ((p, g), (~p, ~g)):  # foreground, then background
        hit = float(np.sum(pc & gc))
        n_gt, n_pred = float(gc.sum()), float(pc.sum())
        recalls.append(hit / n_gt if n_gt else None)
        precisions.append(hit / n_pred if n_pred else (None if not n_gt else 0.0))
    union = float(np.sum(p | g))
    iou = float(np.sum(p & g)) / union if union else 1.0
    return Scores(iou, _mean_defined(recalls), _mean_defined(precisions))


def mean_scores(scores: list[Scores]) -> Scores:
    return Scores(
        float(np.mean([s.iou for s in scores])),
        float(np.mean([s.mpa for s in scores])),
        float(np.mean([s.mp for s in scores])),
    )


def iou_3d(selected: np.ndarray, target: np.ndarray, weight: np.ndarray | None = None) -> float:
    """IoU of two Gaussian sets ([G] bool), counting each Gaussian once or by `weight`; two
    empty sets agree (1)."""
    w = np.ones(selected.shape) if weight is None else weight
    union = float(w[selected | target].sum())
    return float(w[selected & target].sum()) / union if union > 0 else 1.0


#: `stray_share`'s distance, as a share of the scene's extent (the Gaussians' bounding box
#: diagonal; issue #52: 0.22 m on the demo scene).
STRAY_DISTANCE = 0.03


def stray_share(selected: np.ndarray, target: np.ndarray, means: np.ndarray) -> float:
    """The share of the selected Gaussians ([G] bool) farther than STRAY_DISTANCE of the scene's
    extent from every target Gaussian ([G] bool; centres means [G, 3]): what an exported PLY or
    an isolated answer shows floating away from the object, which test-view IoU hardly sees (a
    speck is a few pixels). 0 for an empty selection."""
    n = int(selected.sum())
    if n == 0:
        return 0.0
    r = STRAY_DISTANCE * scene_extent(means)
    near = near_any(means[selected], means[target], r)
    return float(n - int(near.sum())) / n
