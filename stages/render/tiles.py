"""Tile binning: which Gaussians touch each 16x16 tile, each tile's list front to back.

`compact_view` is what every render walks: the Gaussians a view sees, gathered into rows of
their own (ordered by the tile their centre falls in, so a tile's Gaussians lie close together
in memory and the walk reads them from cache instead of from all of the scene's [G, ...]
arrays), and each tile's list sorted by (depth, scene index). Counting, scattering and sorting
are parallel (over chunks of Gaussians, then over tiles); the result does not depend on the
number of threads. `bin_tiles` gives the same lists in scene indices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from stages.render.constants import TILE
from stages.render.projection import Projected, tile_rect

#: Chunks the counting sorts split the Gaussians into (fixed, so the output is too; enough for
#: the parallel loops to balance).
_CHUNKS = 32


@dataclass
class Bins:
    """Gaussians per tile, each tile's list in front-to-back order."""

    tiles_x: int
    tiles_y: int
    offsets: np.ndarray  # [tiles + 1] int64 into `ids`
    ids: np.ndarray  # [pairs] int32


@dataclass
class View:
    """A camera's visible Gaussians in rows of their own: `proj` and `bins` index the rows, and
    row r is the scene's Gaussian `gaussians[r]` (per-Gaussian values go in as
    values[gaussians])."""

    proj: Projected  # [V] rows, every one visible (radius > 0)
    bins: Bins  # ids are rows of `proj`
    gaussians: np.ndarray  # [V] int32 scene index of each row


@numba.njit(cache=True, inline="always")
def _centre_tile(mx, my, tiles_x, tiles_y):
    tx = min(tiles_x - 1, max(0, int(mx // TILE)))
    ty = min(tiles_y - 1, max(0, int(my // TILE)))
    return ty * tiles_x + tx


@numba.njit(parallel=True, cache=True)
def _gather_visible(radii, means2d, conics, extent, depths, opacities, tiles_x, tiles_y):
    """The visible Gaussians in rows, by centre tile, then by scene index: a stable counting
    sort (per-chunk counts, one prefix sum over (tile, chunk), a per-chunk scatter). The scatter
    reads the scene's arrays in order and writes each row where it goes (scattered stores are
    cheap, scattered loads are not).

    With the rows come their depth keys and tile rectangles. A key orders as (depth, scene
    index) does: depths are > NEAR > 0, so their float32 bit patterns order as the depths do,
    and the scene index below them breaks ties as `depth_order` does (a stable sort of the
    visible Gaussians in index order)."""
    n = radii.shape[0]
    n_tiles = tiles_x * tiles_y
    size = (n + _CHUNKS - 1) // _CHUNKS
    counts = np.zeros((_CHUNKS, n_tiles), np.int64)
    tile_of = np.empty(n, np.int32)
    for c in numba.prange(_CHUNKS):
        for i in range(c * size, min(n, (c + 1) * size)):
            if radii[i] > 0:
                t = _centre_tile(means2d[i, 0], means2d[i, 1], tiles_x, tiles_y)
                tile_of[i] = t
                counts[c, t] += 1
            else:
                tile_of[i] = -1
    v = 0
    for t in range(n_tiles):
        for c in range(_CHUNKS):
            k = counts[c, t]
            counts[c, t] = v
            v += k
    rows = np.empty(v, np.int32)
    m2 = np.empty((v, 2), np.float32)
    co = np.empty((v, 3), np.float32)
    ex = np.empty((v, 2), np.float32)
    de = np.empty(v, np.float32)
    ra = np.empty(v, np.int32)
    op = np.empty(v, np.float32)
    keys = np.empty(v, np.int64)
    rect = np.empty((v, 4), np.int32)
    bits = depths.view(np.int32)
    for c in numba.prange(_CHUNKS):
        for g in range(c * size, min(n, (c + 1) * size)):
            t = tile_of[g]
            if t < 0:
                continue
            r = counts[c, t]
            counts[c, t] += 1
            rows[r] = g
            m2[r, 0] = means2d[g, 0]
            m2[r, 1] = means2d[g, 1]
            co[r, 0] = conics[g, 0]
            co[r, 1] = conics[g, 1]
            co[r, 2] = conics[g, 2]
            ex[r, 0] = extent[g, 0]
            ex[r, 1] = extent[g, 1]
            de[r] = depths[g]
            ra[r] = radii[g]
            op[r] = opacities[g]
            keys[r] = (np.int64(bits[g]) << 32) | np.int64(g)
            x0, y0, x1, y1 = tile_rect(means2d[g, 0], means2d[g, 1], radii[g], tiles_x, tiles_y)
            rect[r, 0] = x0
            rect[r, 1] = y0
            rect[r, 2] = x1
            rect[r, 3] = y1
    return rows, (m2, co, ex, de, ra, op), keys, rect


@numba.njit(parallel=True, cache=True)
def _depth_ordered(keys, rows, rect, n):
    """The rows of sorted `keys` (scene indices mapped back to rows) and their rectangles."""
    row_of = np.empty(n, np.int32)
    for r in numba.prange(rows.shape[0]):
        row_of[rows[r]] = r
    by_depth = np.empty(keys.shape[0], np.int32)
    rect_d = np.empty((keys.shape[0], 4), np.int32)
    for k in numba.prange(keys.shape[0]):
        r = row_of[keys[k] & 0xFFFFFFFF]
        by_depth[k] = r
        for j in range(4):
            rect_d[k, j] = rect[r, j]
    return by_depth, rect_d


@numba.njit(parallel=True, cache=True)
def _bin_rows(by_depth, rect, tiles_x, tiles_y):
    """Per tile, the rows whose rectangle covers it: visited front to back (`by_depth`, with
    their rectangles `rect` in that order) in chunks, each chunk scattering after the ones
    before it, so every list comes out sorted."""
    v = by_depth.shape[0]
    n_tiles = tiles_x * tiles_y
    size = (v + _CHUNKS - 1) // _CHUNKS
    counts = np.zeros((_CHUNKS, n_tiles), np.int64)
    for c in numba.prange(_CHUNKS):
        for k in range(c * size, min(v, (c + 1) * size)):
            for ty in range(rect[k, 1], rect[k, 3]):
                for tx in range(rect[k, 0], rect[k, 2]):
                    counts[c, ty * tiles_x + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    total = 0
    for t in range(n_tiles):
        offsets[t] = total
        for c in range(_CHUNKS):
            k = counts[c, t]
            counts[c, t] = total
            total += k
    offsets[n_tiles] = total
    ids = np.empty(total, np.int32)
    for c in numba.prange(_CHUNKS):
        for k in range(c * size, min(v, (c + 1) * size)):
            r = by_depth[k]
            for ty in range(rect[k, 1], rect[k, 3]):
                for tx in range(rect[k, 0], rect[k, 2]):
                    t = ty * tiles_x + tx
                    ids[counts[c, t]] = r
                    counts[c, t] += 1
    return offsets, ids


def compact_view(proj: Projected, width: int, height: int) -> View:
    """The visible Gaussians of `proj` (scene-sized) in rows of their own, binned."""
    tx, ty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    rows, parts, keys, rect = _gather_visible(
        proj.radii, proj.means2d, proj.conics, proj.extent, proj.depths, proj.opacities, tx, ty
    )
    keys.sort()  # numpy's sort of int64 (vectorised): ~10 ms for a million keys
    by_depth, rect_d = _depth_ordered(keys, rows, rect, proj.radii.shape[0])
    offsets, ids = _bin_rows(by_depth, rect_d, tx, ty)
    return View(Projected(*parts), Bins(tx, ty, offsets, ids), rows)


def depth_order(proj: Projected) -> np.ndarray:
    """Visible Gaussians front to back; equal depths keep their index order."""
    vis = np.flatnonzero(proj.radii > 0).astype(np.int32)
    return vis[np.argsort(proj.depths[vis], kind="stable")]


def bin_tiles(proj: Projected, width: int, height: int) -> Bins:
    """Per tile, the scene indices of the Gaussians touching it, front to back."""
    view = compact_view(proj, width, height)
    return Bins(
        view.bins.tiles_x, view.bins.tiles_y, view.bins.offsets, view.gaussians[view.bins.ids]
    )


@numba.njit(parallel=True, cache=True)
def _holding(offsets, ids, chosen):
    n = offsets.shape[0] - 1
    out = np.zeros(n, np.bool_)
    for t in numba.prange(n):
        for k in range(offsets[t], offsets[t + 1]):
            if chosen[ids[k]]:
                out[t] = True
                break
    return out


def tiles_holding(bins: Bins, chosen: np.ndarray) -> np.ndarray:
    """[n] int64: the tiles whose list holds at least one `chosen` [N] bool Gaussian, in order.
    A render of values that are 0 on every other Gaussian is 0 outside them."""
    return np.flatnonzero(_holding(bins.offsets, bins.ids, np.ascontiguousarray(chosen, np.bool_)))


@numba.njit(cache=True)
def _drawn_in(offsets, ids, tiles, n):
    out = np.zeros(n, np.bool_)
    for t in tiles:
        for k in range(offsets[t], offsets[t + 1]):
            out[ids[k]] = True
    return out


def drawn_in(bins: Bins, tiles: np.ndarray, n: int) -> np.ndarray:
    """[n] bool: the Gaussians whose footprint is listed in any of `tiles` [k] (the reverse of
    tiles_holding)."""
    tiles = np.ascontiguousarray(tiles, np.int64)
    return _drawn_in(bins.offsets, bins.ids, tiles, n)
