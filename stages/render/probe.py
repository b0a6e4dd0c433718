"""What a view shows at a few pixels: the composite walk of one pixel at a time.

A click names a pixel; goi needs the surface under it (its depth, for the 3D point) and whether
another view sees that point or something in front of it (the depth at the point's projection).
Rendering whole views for that costs a full tile walk each (about 0.1 s a view at 400 x 300);
a probe walks only the one tile list of each pixel it is asked about, with the rules of
`stages.render.composite` (alpha = min(0.99, o exp(power)), alpha < 1/255 skipped, stop before T
would fall below 1e-4), so its alpha and depth equal the render's at those pixels (tested).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from stages.render.constants import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from stages.render.projection import Projected
from stages.render.tiles import Bins


@dataclass
class Probed:
    """The composite at K pixels."""

    alpha: np.ndarray  # [K] float32, 1 - final transmittance (0 off the image)
    depth: np.ndarray  # [K] float32, expected depth sum(w z) / alpha (0 where alpha = 0)
    top: np.ndarray  # [K] int32, the Gaussian with the largest blend weight there (-1: none)


@numba.njit(cache=True)
def _probe_kernel(xy, offsets, ids, means2d, conics, opacities, depths, width, height, tiles_x,
                  alpha_out, depth_out, top_out):  # fmt: skip
    for k in range(xy.shape[0]):
        px, py = xy[k, 0], xy[k, 1]
        alpha_out[k] = 0.0
        depth_out[k] = 0.0
        top_out[k] = -1
        if px < 0 or py < 0 or px >= width or py >= height:
            continue
        tile = (py // TILE) * tiles_x + px // TILE
        T = np.float32(1.0)
        acc = np.float32(0.0)
        best = np.float32(0.0)
        for j in range(offsets[tile], offsets[tile + 1]):
            g = ids[j]
            dx = means2d[g, 0] - np.float32(px)
            dy = means2d[g, 1] - np.float32(py)
            ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
            power = np.float32(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
            if power > 0.0:
                continue
            alpha = min(np.float32(ALPHA_MAX), opacities[g] * np.exp(power))
            if alpha < ALPHA_MIN:
                continue
            test_t = T * (np.float32(1.0) - alpha)
            if test_t < T_MIN:
                break
            w = alpha * T
            acc += w * depths[g]
            if w > best:
                best = w
                top_out[k] = g
            T = test_t
        alpha_out[k] = 1.0 - T
        depth_out[k] = acc / (1.0 - T) if T < 1.0 else 0.0


def probe(proj: Projected, bins: Bins, xy: np.ndarray, width: int, height: int) -> Probed:
    """The composite at integer pixels `xy` [K, 2] (column, row; pixel-index coordinates, as
    `Projected.means2d`): alpha, depth and the Gaussian that carries the most of the pixel."""
    xy = np.ascontiguousarray(np.asarray(xy, np.int64).reshape(-1, 2))
    k = xy.shape[0]
    alpha = np.empty(k, np.float32)
    depth = np.empty(k, np.float32)
    top = np.empty(k, np.int32)
    _probe_kernel(xy, bins.offsets, bins.ids, proj.means2d, proj.conics, proj.opacities,
                  proj.depths, width, height, bins.tiles_x, alpha, depth, top)  # fmt: skip
    return Probed(alpha, depth, top)
