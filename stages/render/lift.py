"""Lifting: a 2D mask pushed back onto the Gaussians through the view's blend weights.

With frozen geometry a rendered value is linear in the per-Gaussian values,
F(p) = sum_i w_i(p) f_i with w_i(p) = alpha_i(p) T_i(p), so the transpose of the render takes
an image back to the Gaussians. For a binary mask m this gives each Gaussian's evidence

    s1_i = sum_p w_i(p) m(p)          (blend weight it puts on mask pixels)
    s0_i = sum_p w_i(p) (1 - m(p))    (blend weight it puts on the other pixels)

at the image's full resolution, in one tile walk (the compositing walk's LIFT mode,
`stages.render.composite.label_sums`), without keeping the weights (a 640x480 view holds
~100 MiB of them). `stages.render.reference.reference_lift` is the plain twin the tests hold
it to.

Determinism: tiles are dealt round-robin to LIFT_BLOCKS private float32 buffers, each walked by
one thread in tile order, and the buffers are summed in block order. The order of every
addition is fixed by the image alone, never by thread scheduling or the core count, so the
same inputs give the same s1/s0 bit for bit on any machine.
"""

from __future__ import annotations

import numpy as np

from stages.render.composite import label_sums, render
from stages.render.constants import TILE
from stages.render.projection import Projected
from stages.render.tiles import Bins, tiles_holding

#: Private accumulation buffers (see the module doc). 8 keeps 2-8 cores busy (tiles are many
#: and dealt round-robin, so blocks carry about equal work) and costs 8 x [G, 2] float32.
LIFT_BLOCKS = 8


def lift_mask(proj: Projected, bins: Bins, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One view's evidence: s1, s0 [G] float64 (see the module doc). `mask` [H, W] bool at the
    view's resolution; an all-False mask is an empty mask (every Gaussian the view sees gets s0)."""
    h, w = mask.shape
    if (w + TILE - 1) // TILE != bins.tiles_x or (h + TILE - 1) // TILE != bins.tiles_y:
        raise ValueError(f"mask {w}x{h} != the view's {bins.tiles_x}x{bins.tiles_y} tiles")
    buf = label_sums(proj, bins, np.asarray(mask, np.uint8), 2, LIFT_BLOCKS)  # [B, G, 2]
    acc = np.zeros(buf.shape[1:])
    for b in range(LIFT_BLOCKS):  # fixed order: the sum does not depend on the machine
        acc += buf[b]
    return acc[:, 1], acc[:, 0]


def selection_mask(proj: Projected, bins: Bins, selected: np.ndarray, width: int, height: int):
    """[H, W] bool: pixels where the selected Gaussians carry more than half of the pixel's
    blend weight (its alpha). The 2D answer is then the 3D selection seen from the view, so the
    two agree, and it has none of the per-pixel speckle of decoding the field."""
    sel = np.asarray(selected, bool)
    # only the tiles where a selected Gaussian is drawn: elsewhere the selection carries no
    # weight and the mask is False, so the walk there decides nothing (a cup: a few tiles)
    r = render(proj, bins, sel.astype(np.float32)[:, None], width, height,
               tiles=tiles_holding(bins, sel))  # fmt: skip
    return r.image[:, :, 0] > 0.5 * r.alpha


def selection_masks(
    proj: Projected, bins: Bins, selections: np.ndarray, width: int, height: int
) -> np.ndarray:
    """[H, W, K] bool: selection_mask of each of K selections ([G, K] bool) in one tile walk
    (each channel is composited alone, so each equals its own selection_mask bit for bit)."""
    sel = np.asarray(selections, bool)
    r = render(proj, bins, sel.astype(np.float32), width, height,
               tiles=tiles_holding(bins, np.any(sel, axis=1)))  # fmt: skip
    return r.image > 0.5 * r.alpha[:, :, None]


def score_map(proj: Projected, bins: Bins, scores: np.ndarray, width: int, height: int):
    """[H, W] float32: a per-Gaussian score [G] composited like a colour, sum_i w_i s_i over the
    pixel's blend weights w_i (0 where nothing is drawn, so the background scores 0). With the
    0/1 selection as `scores` it is the map selection_mask compares against half the alpha;
    with a probability it is the continuous answer a relevancy-map protocol expects. Scores
    [G, K] (K queries at once: one tile walk for all) give [H, W, K]."""
    s = np.asarray(scores, np.float32)
    r = render(proj, bins, s[:, None] if s.ndim == 1 else s, width, height)
    return r.image[:, :, 0] if s.ndim == 1 else r.image
