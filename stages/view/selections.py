"""Selections combined, and their scores: arrays in, arrays out.

A page keeps answers under names and combines any two: union, intersection, difference, or
the invert of one. A selection's score (`[G]` float32 in [0, 1], what heat mode colours: a
lifted answer's vote share, the plane's probability, a pointed answer's last round's vote
share) combines with it as fuzzy sets do (union the larger score, intersection the smaller,
difference the smaller of A's and 1 - B's, invert 1 - A's), so a combined answer's heat still
shows what almost made it in. A selection without a score scores 1 where it selects and 0
elsewhere.
"""

from __future__ import annotations

import numpy as np

#: The operations, in the order the page offers them, and how the page writes them.
OPS = {"union": "|", "intersection": "&", "difference": "-", "invert": "not"}


def score_of(selected: np.ndarray, score: np.ndarray | None) -> np.ndarray:
    """[G] float32: `score` [G], or the selection [G] bool itself as 0 / 1 without one."""
    if score is None:
        return np.asarray(selected, np.float32)
    return np.asarray(score, np.float32)


def combine(
    op: str,
    a: np.ndarray,
    b: np.ndarray | None,
    a_score: np.ndarray | None = None,
    b_score: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(selected [G] bool, score [G] float32) of `op` on selections `a`, `b` [G] bool (b
    unused by invert) and their scores (see the module doc)."""
    if op not in OPS:
        raise ValueError(f"unknown operation {op!r}")
    sa = score_of(a, a_score)
    if op == "invert":
        return ~np.asarray(a, bool), (1.0 - sa).astype(np.float32)
    assert b is not None
    sb = score_of(b, b_score)
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if op == "union":
        return a | b, np.maximum(sa, sb)
    if op == "intersection":
        return a & b, np.minimum(sa, sb)
    return a & ~b, np.minimum(sa, 1.0 - sb).astype(np.float32)


def refined_score(
    base: np.ndarray | None,
    base_score: np.ndarray | None,
    share: np.ndarray,
    evident: np.ndarray,
    plus: bool,
) -> np.ndarray:
    """[G] float32: the score of an answer refined by a click or box whose last round voted
    `share` [G] (in [0, 1], read where `evident` [G] bool): added to the base (a plus click,
    a box) it is the union's score, taken out of it (a minus click) the difference's; the
    base None is an empty one."""
    n = share.shape[0]
    sb = np.zeros(n, np.float32) if base is None else score_of(base, base_score)
    s = np.where(evident, share, 0.0).astype(np.float32)
    if plus:
        return np.maximum(sb, s)
    return np.minimum(sb, np.where(evident, 1.0 - s, 1.0)).astype(np.float32)


def stretched(score: np.ndarray, cut: float = 0.5) -> np.ndarray:
    """[G] float32 in [0, 1]: `score` [G] stretched about its answer's `cut` to the whole
    range, the cut kept in the middle (a threshold plane's probabilities span 0.27..0.73;
    stretched, the Gaussians near the cut stay near the middle colour and the far ones reach
    the ends). Scores of 0 stay 0 (nothing claims them)."""
    s = np.asarray(score, np.float64)
    spread = float(np.abs(s[s > 0] - cut).max(initial=0.0))
    if spread <= 0:
        return s.astype(np.float32)
    out = np.clip(0.5 + 0.5 * (s - cut) / spread, 0.0, 1.0)
    return np.where(s > 0, out, 0.0).astype(np.float32)
