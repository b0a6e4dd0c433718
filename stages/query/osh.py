"""The Optimizable Semantic-space Hyperplane (OSH, paper section 3.5), as pure math.

A pixel or Gaussian is of interest when its decoded feature x satisfies W x + b > 0. W starts as
the prompt's text embedding and b as minus the fixed cosine threshold, which is exactly the
fixed-threshold query (the baseline); the plane is then fitted against RES masks with the
paper's weighted logistic loss (or the authors' hinge loss), full-batch SGD, and an early stop
once the plane's mask agrees with the RES mask.

Why it is cheap: a decoded feature is always one of the N codebook entries, so the loss over all
pixels only depends on how many positive and negative RES pixels decode to each entry. Fitting
works on those N weighted points (`Counts`), and the plane's decision is one score per entry.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Annotated

import numpy as np

from stages.core.params import AT_LEAST_1, COSINE, FRACTION, NON_NEGATIVE, POSITIVE, Choice

#: The fixed cosine threshold between a decoded feature and the prompt's embedding: the
#: baseline's cut and the hyperplane's starting bias. One value for every prompt and scene,
#: chosen before any evaluation (between the cosines of unrelated texts, ~0.1-0.3, and of a text
#: and its own object's feature, ~0.6-0.9, for sentence-model embeddings); never tuned on test
#: masks.
THRESHOLD = 0.5
LOSSES = ("logistic", "hinge")


@dataclass
class HyperplaneParams:
    """How a prompt's plane is fitted; recorded with the plane (and part of its cache key)."""

    loss: Annotated[str, Choice(LOSSES)] = "logistic"
    """logistic: the paper's weighted logistic regression; hinge: the authors' code."""
    positive_weight: Annotated[float, POSITIVE] = 0.1
    """w on the positive (target) term of the logistic loss (paper: 1/10)."""
    threshold: Annotated[float, COSINE] = THRESHOLD
    """Fixed cosine threshold: the starting bias b = -threshold, and the baseline's cut."""
    lr: Annotated[float, POSITIVE] = 0.01
    """SGD learning rate (authors: 0.01)."""
    steps: Annotated[int, NON_NEGATIVE] = 8000
    """At most this many full-batch steps (authors: 8000)."""
    target_iou: Annotated[float, FRACTION] = 0.9
    """Stop once the plane's mask reaches this IoU with the RES mask (authors: 0.9)."""
    fit_views: Annotated[int, AT_LEAST_1] = 1
    """Number of views to fit on (paper: 1): those whose RES mask is largest."""
    fit_on: str | None = None
    """Comma-separated views to fit on, instead of choosing them."""

    def config(self) -> dict:
        return asdict(self)


@dataclass
class Hyperplane:
    prompt: str
    W: np.ndarray  # [D]
    b: float
    scores: np.ndarray  # [N] W T_k + b for each unit codebook entry
    text: np.ndarray  # [D] the prompt's unit embedding
    info: dict = field(default_factory=dict)

    @property
    def positive(self) -> np.ndarray:
        """[N] bool: the codebook entries on the positive side."""
        return self.scores > 0


def probability(z: np.ndarray) -> np.ndarray:
    """s(z) = 1 / (1 + e^-z) as float32: the logistic model the OSH is fitted with, read as each
    point's probability of being of interest (above 0.5 exactly where W x + b > 0)."""
    return (0.5 * (1.0 + np.tanh(0.5 * np.asarray(z, np.float64)))).astype(np.float32)


def threshold_plane(
    prompt: str, text: np.ndarray, unit_codebook: np.ndarray, threshold: float
) -> Hyperplane:
    """The fixed-threshold query as a plane: cos(T_k, t) > threshold."""
    W = text.astype(np.float64)
    b = -float(threshold)
    scores = unit_codebook.astype(np.float64) @ W + b
    return Hyperplane(prompt, W.astype(np.float32), b, scores.astype(np.float32), text, {})


@dataclass
class Counts:
    """RES pixels per codebook entry: how many decode to entry k inside / outside the mask."""

    pos: np.ndarray  # [N] float64
    neg: np.ndarray  # [N] float64

    def iou(self, decision: np.ndarray) -> float:
        tp = self.pos[decision].sum()
        fp = self.neg[decision].sum()
        fn = self.pos[~decision].sum()
        return float(tp / max(tp + fp + fn, 1))


def count_pixels(index: np.ndarray, covered: np.ndarray, mask: np.ndarray, n: int) -> Counts:
    """Counts over the covered pixels of one view ([H, W] each)."""
    idx = index[covered]
    m = mask[covered]
    return Counts(
        np.bincount(idx[m], minlength=n).astype(np.float64),
        np.bincount(idx[~m], minlength=n).astype(np.float64),
    )


def loss_gradient(counts: Counts, z: np.ndarray, p: HyperplaneParams) -> np.ndarray:
    """dL/dz_k [N] of the loss summed per entry, z_k = W T_k + b (see fit_osh)."""
    P = max(counts.pos.sum() + counts.neg.sum(), 1.0)
    if p.loss == "logistic":
        s = 1.0 / (1.0 + np.exp(-z))
        return (-p.positive_weight * counts.pos * (1 - s) + counts.neg * s) / P
    return (-counts.pos * (z < 1) + counts.neg * (z > -1)) / P


def fit_osh(
    counts: Counts, unit_codebook: np.ndarray, text: np.ndarray, p: HyperplaneParams
) -> tuple[np.ndarray, float, dict]:
    """Full-batch SGD on the N weighted codebook points; returns W [D], b and a record.

    The per-pixel loss of the paper,
        -(1/P) sum_i [w m_i log s(z_i) + (1 - m_i) log(1 - s(z_i))],
    summed by entry is (1/P) sum_k [w pos_k softplus(-z_k) + neg_k softplus(z_k)] with
    z_k = W T_k + b, which has the same value and gradient. The hinge loss likewise:
    (1/P) sum_k [pos_k max(0, 1 - z_k) + neg_k max(0, 1 + z_k)].
    The best plane seen (by IoU with the RES mask) is kept, as the early stop would keep it.
    """
    T = unit_codebook.astype(np.float64)  # [N, D]
    W = text.astype(np.float64).copy()
    b = -float(p.threshold)
    z = T @ W + b
    iou0 = counts.iou(z > 0)
    best = (iou0, W.copy(), b, 0)
    step = 0
    while step < p.steps and best[0] < p.target_iou:
        g = loss_gradient(counts, z, p)
        W -= p.lr * (T.T @ g)
        b -= p.lr * float(g.sum())
        z = T @ W + b
        step += 1
        iou = counts.iou(z > 0)
        if iou > best[0]:
            best = (iou, W.copy(), b, step)
    iou, W, b, at = best
    return W, b, {"res_iou_init": iou0, "res_iou": iou, "steps_run": step, "best_step": at}
