"""Lifting: a 2D mask pushed back onto the Gaussians through the view's blend weights.

With frozen geometry a rendered value is linear in the per-Gaussian values,
F(p) = sum_i w_i(p) f_i with w_i(p) = alpha_i(p) T_i(p), so the transpose of the render takes
an image back to the Gaussians. For a binary mask m this gives each Gaussian's evidence

    s1_i = sum_p w_i(p) m(p)          (blend weight it puts on mask pixels)
    s0_i = sum_p w_i(p) (1 - m(p))    (blend weight it puts on the other pixels)

at the image's full resolution, in one tile walk, without keeping the weights (a 640x480 view
holds ~100 MiB of them). `stages.render.reference.reference_lift` is the plain twin the tests
hold this kernel to.

Determinism: tiles are dealt round-robin to LIFT_BLOCKS private float32 buffers, each walked by
one thread in tile order, and the buffers are summed in block order. The order of every
addition is fixed by the image alone, never by thread scheduling or the core count, so the
same inputs give the same s1/s0 bit for bit on any machine.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from stages.render.composite import render
from stages.render.constants import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from stages.render.projection import Projected
from stages.render.tiles import Bins

#: Private accumulation buffers (see the module doc). 8 keeps 2-8 cores busy (tiles are many
#: and dealt round-robin, so blocks carry about equal work) and costs 8 x [G, 2] float32.
LIFT_BLOCKS = 8


# The walk applies the same rules as stages.render.composite._walk_kernel (alpha bound, skips,
# early stop); it is its own kernel because that one parallelises over tiles with per-thread
# buffers, whose addition order depends on scheduling.
@numba.njit(parallel=True, cache=True, fastmath=True)
def _lift_kernel(
    offsets,  # [tiles + 1] int64
    ids,  # [pairs] int32, front to back per tile
    means2d,  # [G, 2] f32
    conics,  # [G, 3] f32
    extent,  # [G, 2] f32
    opacities,  # [G] f32
    width,
    height,
    tiles_x,
    labels,  # [H, W] uint8: 1 in the mask, 0 outside
    out,  # [B, G, 2] f32: out[b, g, label] += w
):
    n_tiles = offsets.shape[0] - 1
    n_blocks = out.shape[0]
    for blk in numba.prange(n_blocks):
        T = np.empty(TILE * TILE, np.float32)
        done = np.empty(TILE * TILE, np.bool_)
        for tile in range(blk, n_tiles, n_blocks):
            x0 = (tile % tiles_x) * TILE
            y0 = (tile // tiles_x) * TILE
            x1 = min(x0 + TILE, width)
            y1 = min(y0 + TILE, height)
            T[:] = 1.0
            done[:] = False
            n_left = (x1 - x0) * (y1 - y0)
            for k in range(offsets[tile], offsets[tile + 1]):
                g = ids[k]
                mx, my = means2d[g, 0], means2d[g, 1]
                ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
                o = opacities[g]
                q_max = 2.0 * math.log(255.0 * o)
                gx0 = max(x0, int(math.floor(mx - extent[g, 0])))
                gx1 = min(x1, int(math.ceil(mx + extent[g, 0])) + 1)
                gy0 = max(y0, int(math.floor(my - extent[g, 1])))
                gy1 = min(y1, int(math.ceil(my + extent[g, 1])) + 1)
                for py in range(gy0, gy1):
                    dy = my - np.float32(py)
                    disc = cb * cb * dy * dy - ca * (cc * dy * dy - q_max)
                    if disc < 0.0:
                        continue
                    root = math.sqrt(disc)
                    sx0 = max(gx0, int(math.floor(mx - (root - cb * dy) / ca)) - 1)
                    sx1 = min(gx1, int(math.ceil(mx + (root + cb * dy) / ca)) + 2)
                    for px in range(sx0, sx1):
                        p = (py - y0) * TILE + (px - x0)
                        if done[p]:
                            continue
                        dx = mx - np.float32(px)
                        power = np.float32(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power > 0.0:
                            continue
                        alpha = min(np.float32(ALPHA_MAX), o * np.exp(power))
                        if alpha < ALPHA_MIN:
                            continue
                        test_t = T[p] * (np.float32(1.0) - alpha)
                        if test_t < T_MIN:
                            done[p] = True
                            n_left -= 1
                            continue
                        out[blk, g, labels[py, px]] += alpha * T[p]
                        T[p] = test_t
                if n_left == 0:
                    break


def lift_mask(proj: Projected, bins: Bins, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One view's evidence: s1, s0 [G] float64 (see the module doc). `mask` [H, W] bool at the
    view's resolution; an all-False mask is an empty mask (every Gaussian the view sees gets s0)."""
    h, w = mask.shape
    if (w + TILE - 1) // TILE != bins.tiles_x or (h + TILE - 1) // TILE != bins.tiles_y:
        raise ValueError(f"mask {w}x{h} != the view's {bins.tiles_x}x{bins.tiles_y} tiles")
    n = proj.means2d.shape[0]
    buf = np.zeros((LIFT_BLOCKS, n, 2), np.float32)  # [B, G, 2]
    _lift_kernel(
        bins.offsets,
        bins.ids,
        proj.means2d,
        proj.conics,
        proj.extent,
        proj.opacities,
        w,
        h,
        bins.tiles_x,
        np.ascontiguousarray(mask, np.uint8),
        buf,
    )
    acc = np.zeros((n, 2))
    for b in range(LIFT_BLOCKS):  # fixed order: the sum does not depend on the machine
        acc += buf[b]
    return acc[:, 1], acc[:, 0]


def selection_mask(proj: Projected, bins: Bins, selected: np.ndarray, width: int, height: int):
    """[H, W] bool: pixels where the selected Gaussians carry more than half of the pixel's
    blend weight (its alpha). The 2D answer is then the 3D selection seen from the view, so the
    two agree, and it has none of the per-pixel speckle of decoding the field."""
    r = render(proj, bins, np.asarray(selected, np.float32)[:, None], width, height)
    return r.image[:, :, 0] > 0.5 * r.alpha


def score_map(proj: Projected, bins: Bins, scores: np.ndarray, width: int, height: int):
    """[H, W] float32: a per-Gaussian score [G] composited like a colour, sum_i w_i s_i over the
    pixel's blend weights w_i (0 where nothing is drawn, so the background scores 0). With the
    0/1 selection as `scores` it is the map selection_mask compares against half the alpha;
    with a probability it is the continuous answer a relevancy-map protocol expects. Scores
    [G, K] (K queries at once: one tile walk for all) give [H, W, K]."""
    s = np.asarray(scores, np.float32)
    r = render(proj, bins, s[:, None] if s.ndim == 1 else s, width, height)
    return r.image[:, :, 0] if s.ndim == 1 else r.image
