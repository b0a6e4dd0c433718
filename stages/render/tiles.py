"""Tile binning: which Gaussians touch each 16x16 tile, each tile's list front to back."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from stages.render.constants import TILE
from stages.render.projection import Projected, tile_rect


@dataclass
class Bins:
    """Gaussians per tile, each tile's list in front-to-back order."""

    tiles_x: int
    tiles_y: int
    offsets: np.ndarray  # [tiles + 1] int64 into `ids`
    ids: np.ndarray  # [pairs] int32


@numba.njit(cache=True)
def _bin_kernel(order, means2d, radii, tiles_x, tiles_y):
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, np.int64)
    for g in order:
        r = radii[g]
        if r == 0:
            continue
        x0, y0, x1, y1 = tile_rect(means2d[g, 0], means2d[g, 1], r, tiles_x, tiles_y)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    cursor = offsets[:-1].copy()
    ids = np.empty(offsets[-1], np.int32)
    for g in order:  # in depth order, so every tile's list comes out sorted front to back
        r = radii[g]
        if r == 0:
            continue
        x0, y0, x1, y1 = tile_rect(means2d[g, 0], means2d[g, 1], r, tiles_x, tiles_y)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                ids[cursor[ty * tiles_x + tx]] = g
                cursor[ty * tiles_x + tx] += 1
    return offsets, ids


def depth_order(proj: Projected) -> np.ndarray:
    """Visible Gaussians front to back; equal depths keep their index order."""
    vis = np.flatnonzero(proj.radii > 0).astype(np.int32)
    return vis[np.argsort(proj.depths[vis], kind="stable")]


def bin_tiles(proj: Projected, width: int, height: int) -> Bins:
    tx, ty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    offsets, ids = _bin_kernel(depth_order(proj), proj.means2d, proj.radii, tx, ty)
    return Bins(tx, ty, offsets, ids)
