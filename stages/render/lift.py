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

Given the view's visibility (each Gaussian's blend weight over the whole view: the lift of an
empty mask, which a process asking many masks of one view keeps), a mask's lift walks only the
tiles that the Gaussians drawn on the mask's tiles are drawn in: a small object's mask is a
tenth of the view's tiles instead of all of them (dev room clicks: 44 -> 8 ms a lift). A
Gaussian drawn on the mask's tiles has every tile of its own walked, each in the lane it has in
the whole walk, so its s1 and s0 are the whole walk's bit for bit; any other Gaussian has no
weight on the mask (s1 = 0) and all of its visibility outside it (s0 = the empty mask's s0,
again the same additions in the same order). So the answer does not depend on whether the
visibility was kept.

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
from stages.render.tiles import Bins, drawn_in, tiles_holding

#: Private accumulation buffers (see the module doc). 8 keeps 2-8 cores busy (tiles are many
#: and dealt round-robin, so blocks carry about equal work) and costs 8 x [G, 2] float32.
LIFT_BLOCKS = 8


#: With the visibility given, a lift whose walk would still cover more than this share of the
#: view's tiles walks them all (the subset costs its bookkeeping and saves little).
WHOLE_WALK_SHARE = 0.6


def lift_mask(
    proj: Projected, bins: Bins, mask: np.ndarray, visibility: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """One view's evidence: s1, s0 [G] float64 (see the module doc). `mask` [H, W] bool at the
    view's resolution; an all-False mask is an empty mask (every Gaussian the view sees gets s0).
    `visibility` [G] float64, the view's (`visibility`): the walk covers only the tiles that
    the Gaussians drawn on the mask's tiles are drawn in, with the same s1, s0 bit for bit."""
    h, w = mask.shape
    if (w + TILE - 1) // TILE != bins.tiles_x or (h + TILE - 1) // TILE != bins.tiles_y:
        raise ValueError(f"mask {w}x{h} != the view's {bins.tiles_x}x{bins.tiles_y} tiles")
    labels = np.asarray(mask, np.uint8)
    n = proj.means2d.shape[0]
    tiles = on_mask = None
    if visibility is not None:
        if visibility.shape != (n,):
            raise ValueError(f"visibility {visibility.shape} != the view's ({n},) Gaussians")
        on_mask = drawn_in(bins, _mask_tiles(mask, bins), n)  # [G]
        tiles = tiles_holding(bins, on_mask)
        if len(tiles) > WHOLE_WALK_SHARE * bins.tiles_x * bins.tiles_y:
            tiles = on_mask = None
    buf = label_sums(proj, bins, labels, 2, LIFT_BLOCKS, tiles)  # [B, G, 2]
    acc = np.zeros(buf.shape[1:])
    for b in range(LIFT_BLOCKS):  # fixed order: the sum does not depend on the machine
        acc += buf[b]
    if on_mask is None:
        return acc[:, 1], acc[:, 0]
    assert visibility is not None
    return acc[:, 1], np.where(on_mask, acc[:, 0], visibility)


def visibility(proj: Projected, bins: Bins, width: int, height: int) -> np.ndarray:
    """[G] float64: each Gaussian's blend weight summed over the view (the s0 of an empty mask;
    0 for the Gaussians it does not see)."""
    # a copy: the lift's s0 is a view of its [G, 2] sums, and a kept visibility should hold
    # only its own 8 bytes a Gaussian
    return np.ascontiguousarray(lift_mask(proj, bins, np.zeros((height, width), bool))[1])


def _mask_tiles(mask: np.ndarray, bins: Bins) -> np.ndarray:
    """[k] int64: the tiles holding a pixel of `mask` [H, W], ascending."""
    h, w = mask.shape
    ty, tx = bins.tiles_y, bins.tiles_x
    padded = np.zeros((ty * TILE, tx * TILE), bool)
    padded[:h, :w] = mask
    return np.flatnonzero(padded.reshape(ty, TILE, tx, TILE).any(axis=(1, 3)))


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
