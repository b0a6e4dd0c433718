"""The compositing walk: the one numba kernel that applies the alpha/transmittance rules, per tile.

Parallel over tiles. Within a tile it loops Gaussians outside and pixels inside, and only over
the pixels where alpha can reach 1/255 (an exact bound: q <= 2 ln(255 o)), so work follows each
Gaussian's footprint instead of the tile's 256 pixels. `stages.render.reference` is the slow,
obviously correct twin the tests hold it to.
"""

from __future__ import annotations

import functools
import inspect
import math
from dataclasses import dataclass

import numba
import numpy as np

from stages.render.constants import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from stages.render.projection import Projected
from stages.render.tiles import Bins

# One walk serves every use of the weights w = alpha * T: compositing colours (RENDER),
# counting and recording them per pixel for the blend cache (COUNT, RECORD), pushing a
# gradient back to per-Gaussian values (BACKWARD, the naive design the cache replaces),
# summing them per Gaussian over the cells of a coarser grid (POOL, the pooled blend cache
# without its per-pixel CSR) and per Gaussian and mask label (LIFT, a 2D mask lifted onto the
# Gaussians: stages.render.lift). One kernel keeps the alpha / transmittance rules in one place;
# the mode branch is loop-invariant and costs nothing measurable.
RENDER, COUNT, RECORD, BACKWARD, POOL, LIFT = 0, 1, 2, 3, 4, 5


@numba.njit(cache=True, inline="always")
def _footprint(g, means2d, extent, x0, y0, x1, y1):
    """The pixels [gx0, gx1) x [gy0, gy1) of the tile [x0, x1) x [y0, y1) the walk visits for
    Gaussian g (empty when gx0 >= gx1 or gy0 >= gy1); the POOL bound counts the same rectangle."""
    mx, my = means2d[g, 0], means2d[g, 1]
    gx0 = max(x0, int(math.floor(mx - extent[g, 0])))
    gx1 = min(x1, int(math.ceil(mx + extent[g, 0])) + 1)
    gy0 = max(y0, int(math.floor(my - extent[g, 1])))
    gy1 = min(y1, int(math.ceil(my + extent[g, 1])) + 1)
    return gx0, gx1, gy0, gy1


# fastmath: about 10% faster; no NaN reaches here (the PLY reader refuses them).
@numba.njit(parallel=True, cache=True, fastmath=True)
def _walk_kernel(
    mode,
    offsets,  # [tiles + 1] int64: each tile's run of `ids`
    ids,  # [pairs] int32: Gaussians front to back per tile
    means2d,  # [N, 2] f32
    conics,  # [N, 3] f32
    extent,  # [N, 2] f32: the footprint's half width and height
    opacities,  # [N] f32
    depths,  # [N] f32
    colors,  # [N, C] f32: RENDER's values
    width,
    height,
    tiles_x,
    out,  # [H, W, C] f32: RENDER's image
    alpha_out,  # [H, W] f32: RENDER's 1 - T
    depth_out,  # [H, W] f32: RENDER's sum of w z
    counts,  # COUNT: [H * W] weights per pixel; POOL: [tiles] entries, or -(room needed) - 1
    row_ptr,  # [H * W + 1] int64: RECORD's CSR rows
    w_ids,  # [nnz] int32: RECORD's Gaussians
    w_vals,  # [nnz] f32: RECORD's weights
    grad_out,  # [H, W, C] f32: BACKWARD's d loss / d image
    labels,  # [H, W] uint8: LIFT's label of each pixel
    sums,  # [buffers, N, C] f32: BACKWARD's per-thread, LIFT's per-lane per-Gaussian sums
    tile_list,  # [n] int64: the tiles to walk (default: all, in order)
    lane_ptr,  # [lanes + 1] int64: lane l walks tile_list[lane_ptr[l]:lane_ptr[l + 1]] in order
    cell_x,  # [W] int64: POOL's cell column of each pixel column
    cell_y,  # [H] int64: POOL's cell row of each pixel row
    cell_x_end,  # [cells_w] int64: the pixel column after each cell column
    columns,  # [N] int32: POOL's column of each Gaussian
    seg_base,  # [tiles + 1] int64: each tile's first segment (one a cell it covers)
    seg_start,  # [segments] int64: where a segment's pairs start in pool_cols / pool_vals
    seg_len,  # [segments] int64
    cursor,  # [threads, 2] int64: [next free, region end] of each thread's region
    pool_cols,  # [room] int32
    pool_vals,  # [room] f32
):
    # A lane is one thread's run of tiles, walked in order: by default every tile is a lane of
    # its own. LIFT deals the tiles to a few lanes with a buffer each, so that the order of
    # every addition is fixed by the image, never by the threads (stages.render.lift).
    n_tiles = offsets.shape[0] - 1 if tile_list.shape[0] == 0 else tile_list.shape[0]
    n_lanes = n_tiles if lane_ptr.shape[0] == 0 else lane_ptr.shape[0] - 1
    n_ch = colors.shape[1]
    for lane in numba.prange(n_lanes):
        first, stop = np.int64(lane), np.int64(lane + 1)
        if lane_ptr.shape[0] > 0:
            first, stop = lane_ptr[lane], lane_ptr[lane + 1]
        for i_tile in range(first, stop):
            tile = np.int64(i_tile)
            if tile_list.shape[0] > 0:
                tile = tile_list[i_tile]
            x0 = (tile % tiles_x) * TILE
            y0 = (tile // tiles_x) * TILE
            x1 = min(x0 + TILE, width)
            y1 = min(y0 + TILE, height)
            T = np.ones(TILE * TILE, np.float32)
            acc = np.zeros((TILE * TILE, n_ch), np.float32)
            dacc = np.zeros(TILE * TILE, np.float32)
            n_rec = np.zeros(TILE * TILE, np.int64)
            done = np.zeros(TILE * TILE, np.bool_)
            n_left = (x1 - x0) * (y1 - y0)
            # Each row's live pixels lie in [lo, hi): where a row's pixels stop, its span
            # shrinks, so they are not visited again (about half the visits at 3M Gaussians).
            lo = np.full(TILE, x0, np.int64)
            hi = np.full(TILE, x1, np.int64)
            tid = numba.get_thread_id()
            # POOL: the tile's cells have local index (cy - lcy0) * n_lcx + (cx - lcx0).
            # `cell_sum` holds the current Gaussian's weights summed per cell (`hit`: the cells
            # it reached so far), `stage_*` the tile's (column, sum) pairs per cell.
            n_lc, lcx0, lcy0, n_lcx, n_stage = 0, 0, 0, 0, 0
            n_hit, n_entries, row_lc, cx = 0, 0, 0, 0
            if mode == POOL:
                lcx0, lcy0 = cell_x[x0], cell_y[y0]
                n_lcx = cell_x[x1 - 1] - lcx0 + 1
                n_lc = n_lcx * (cell_y[y1 - 1] - lcy0 + 1)
                n_stage = offsets[tile + 1] - offsets[tile]
            cell_sum = np.zeros(n_lc, np.float32)
            hit = np.empty(n_lc, np.int64)
            stage_n = np.zeros(n_lc, np.int64)
            stage_cols = np.empty((n_lc, n_stage), np.int32)
            stage_vals = np.empty((n_lc, n_stage), np.float32)
            for k in range(offsets[tile], offsets[tile + 1]):
                g = ids[k]
                mx, my = means2d[g, 0], means2d[g, 1]
                ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
                o = opacities[g]
                q_max = 2.0 * math.log(255.0 * o)
                # Below this power alpha < 1/255 for certain (by a margin far above float32
                # rounding): those pixels skip the exp; the exact test below decides the rest.
                power_min = np.float32(-0.5 * q_max - 1e-3)
                gx0, gx1, gy0, gy1 = _footprint(g, means2d, extent, x0, y0, x1, y1)
                for py in range(gy0, gy1):
                    r = py - y0
                    if lo[r] >= hi[r]:
                        continue
                    dy = my - np.float32(py)
                    # This row's span of the ellipse q <= q_max, widened by a pixel for rounding.
                    disc = cb * cb * dy * dy - ca * (cc * dy * dy - q_max)
                    if disc < 0.0:
                        continue
                    root = math.sqrt(disc)
                    sx0 = max(gx0, int(math.floor(mx - (root - cb * dy) / ca)) - 1)
                    sx1 = min(gx1, int(math.ceil(mx + (root + cb * dy) / ca)) + 2)
                    sx0 = max(sx0, lo[r])
                    sx1 = min(sx1, hi[r])
                    if mode == POOL:
                        row_lc = (cell_y[py] - lcy0) * n_lcx - lcx0
                    # The span in pieces: POOL cuts it at cell edges and sums each piece's
                    # weights in a register; every other mode takes it whole.
                    pa = sx0
                    while pa < sx1:
                        pb = sx1
                        if mode == POOL:
                            cx = cell_x[pa]
                            pb = min(sx1, cell_x_end[cx])
                        w_sum = np.float32(0.0)
                        for px in range(pa, pb):
                            p = r * TILE + (px - x0)
                            if done[p]:
                                continue
                            dx = mx - np.float32(px)
                            power = np.float32(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                            if power > 0.0 or power < power_min:
                                continue
                            alpha = min(np.float32(ALPHA_MAX), o * np.exp(power))
                            if alpha < ALPHA_MIN:
                                continue
                            test_t = T[p] * (np.float32(1.0) - alpha)
                            if test_t < T_MIN:
                                done[p] = True
                                n_left -= 1
                                while lo[r] < hi[r] and done[r * TILE + lo[r] - x0]:
                                    lo[r] += 1
                                while hi[r] > lo[r] and done[r * TILE + hi[r] - 1 - x0]:
                                    hi[r] -= 1
                                continue
                            if mode == LIFT:
                                # alpha * T[p] used once, so fastmath may fuse it into the
                                # addition: one rounding, the bits the lift has always had.
                                sums[lane, g, labels[py, px]] += alpha * T[p]
                                T[p] = test_t
                                continue
                            w = alpha * T[p]
                            if mode == RENDER:
                                for c in range(n_ch):
                                    acc[p, c] += w * colors[g, c]
                                dacc[p] += w * depths[g]
                            elif mode == COUNT:
                                n_rec[p] += 1
                            elif mode == RECORD:
                                j = row_ptr[py * width + px] + n_rec[p]
                                w_ids[j] = g
                                w_vals[j] = w
                                n_rec[p] += 1
                            elif mode == POOL:
                                w_sum += w
                                n_entries += 1
                            else:
                                for c in range(n_ch):
                                    sums[tid, g, c] += w * grad_out[py, px, c]
                            T[p] = test_t
                        # Every weight is > 0 (alpha >= 1/255, T >= T_MIN): a sum > 0 is a hit.
                        if mode == POOL and w_sum > 0.0:
                            lc = row_lc + cx
                            if cell_sum[lc] == 0.0:
                                hit[n_hit] = lc
                                n_hit += 1
                            cell_sum[lc] += w_sum
                        pa = pb
                if n_hit > 0:
                    col = columns[g]
                    for h in range(n_hit):
                        lc = hit[h]
                        stage_cols[lc, stage_n[lc]] = col
                        stage_vals[lc, stage_n[lc]] = cell_sum[lc]
                        stage_n[lc] += 1
                        cell_sum[lc] = 0.0
                    n_hit = 0
                if n_left == 0:
                    break
            for py in range(y0, y1):
                for px in range(x0, x1):
                    p = (py - y0) * TILE + (px - x0)
                    if mode == RENDER:
                        for c in range(n_ch):
                            out[py, px, c] = acc[p, c]
                        alpha_out[py, px] = 1.0 - T[p]
                        depth_out[py, px] = dacc[p]
                    elif mode == COUNT:
                        counts[py * width + px] = n_rec[p]
            if mode == POOL:
                # The tile's segments, one per cell, go to the end of this thread's region of
                # pool_cols / pool_vals (cursor[tid] = [next free, region end]); a tile that
                # does not fit says how much room it needs, -(need) - 1, and is walked again.
                need = stage_n.sum()
                at = cursor[tid, 0]
                if at + need > cursor[tid, 1]:
                    counts[tile] = -need - 1
                else:
                    for lc in range(n_lc):
                        seg_start[seg_base[tile] + lc] = at
                        seg_len[seg_base[tile] + lc] = stage_n[lc]
                        for j in range(stage_n[lc]):
                            pool_cols[at + j] = stage_cols[lc, j]
                            pool_vals[at + j] = stage_vals[lc, j]
                        at += stage_n[lc]
                    cursor[tid, 0] = at
                    counts[tile] = n_entries


_NO_F = np.zeros((0, 0), np.float32)
_NO_F1 = np.zeros(0, np.float32)
_NO_F3 = np.zeros((0, 0, 0), np.float32)
_NO_I = np.zeros(0, np.int64)
_NO_I2 = np.zeros((0, 0), np.int64)
_NO_I32 = np.zeros(0, np.int32)
_NO_U8 = np.zeros((0, 0), np.uint8)
# What a mode does not use: empty arrays of the types the kernel is compiled for.
_UNUSED = {
    "colors": _NO_F,
    "out": _NO_F3,
    "alpha_out": _NO_F,
    "depth_out": _NO_F,
    "counts": _NO_I,
    "row_ptr": _NO_I,
    "w_ids": _NO_I32,
    "w_vals": _NO_F1,
    "grad_out": _NO_F3,
    "labels": _NO_U8,
    "sums": _NO_F3,
    "tile_list": _NO_I,
    "lane_ptr": _NO_I,
    "cell_x": _NO_I,
    "cell_y": _NO_I,
    "cell_x_end": _NO_I,
    "columns": _NO_I32,
    "seg_base": _NO_I,
    "seg_start": _NO_I,
    "seg_len": _NO_I,
    "cursor": _NO_I2,
    "pool_cols": _NO_I32,
    "pool_vals": _NO_F1,
}
_PARAMS = tuple(inspect.signature(_walk_kernel.py_func).parameters)


def _walk(mode: int, proj: Projected, bins: Bins, width: int, height: int, **arrays) -> None:
    """The walk in `mode` over the view's tiles; `arrays` are the mode's own (by the kernel's
    parameter names), every other array is empty."""
    unknown = set(arrays) - set(_UNUSED)
    if unknown:
        raise TypeError(f"_walk: unknown arrays {sorted(unknown)}")
    if "tile_list" in arrays and len(arrays["tile_list"]) == 0:
        return  # the kernel reads an empty list as every tile; a list given empty is none
    args = {
        **_UNUSED,
        **arrays,
        "mode": mode,
        "offsets": bins.offsets,
        "ids": bins.ids,
        "means2d": proj.means2d,
        "conics": proj.conics,
        "extent": proj.extent,
        "opacities": proj.opacities,
        "depths": proj.depths,
        "width": width,
        "height": height,
        "tiles_x": bins.tiles_x,
    }
    _walk_kernel(*(args[name] for name in _PARAMS))


def blend_weights(
    proj: Projected, bins: Bins, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The view's blending weights as CSR (indptr [P + 1], Gaussian ids [nnz], w [nnz]).

    Rows are pixels in row-major order; within a row the entries are front to back.
    """
    counts = np.zeros(width * height, np.int64)
    _walk(COUNT, proj, bins, width, height, counts=counts)
    indptr = np.zeros(width * height + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    ids = np.empty(indptr[-1], np.int32)
    vals = np.empty(indptr[-1], np.float32)
    _walk(RECORD, proj, bins, width, height, row_ptr=indptr, w_ids=ids, w_vals=vals)
    return indptr, ids, vals


@numba.njit(parallel=True, cache=True)
def _pool_merge_kernel(
    order, cell_segs, seg_start, seg_len, cols, vals, n_pix, acc, row_at, row_cols, row_vals
):
    """Each cell's row: its tiles' partial sums merged per column (added in segment order,
    so the bits do not depend on the threads), sorted by column, divided by its pixel count,
    written from row_at[c] on. Returns each row's length."""
    n_cells = cell_segs.shape[0] - 1
    n_out = np.zeros(n_cells, np.int64)
    # acc [threads, columns]: one dense accumulator per thread, back to zeros after each cell;
    # a partial sum is > 0, so 0 means "not seen yet".
    for c in numba.prange(n_cells):
        a = acc[numba.get_thread_id()]
        r0 = row_at[c]
        n_t = 0
        for s in range(cell_segs[c], cell_segs[c + 1]):
            sg = order[s]
            for j in range(seg_start[sg], seg_start[sg] + seg_len[sg]):
                col = cols[j]
                if a[col] == 0.0:
                    row_cols[r0 + n_t] = col
                    n_t += 1
                a[col] += vals[j]
        row_cols[r0 : r0 + n_t].sort()
        for i in range(n_t):
            col = row_cols[r0 + i]
            row_vals[r0 + i] = a[col] / n_pix[c]
            a[col] = 0.0
        n_out[c] = n_t
    return n_out


@numba.njit(parallel=True, cache=True)
def _pool_compact_kernel(cols, vals, starts, indptr, out_cols, out_vals):
    for c in numba.prange(indptr.shape[0] - 1):
        r0 = starts[c]
        for i in range(indptr[c + 1] - indptr[c]):
            out_cols[indptr[c] + i] = cols[r0 + i]
            out_vals[indptr[c] + i] = vals[r0 + i]


def pooled_blend_weights(
    proj: Projected,
    bins: Bins,
    width: int,
    height: int,
    cell_x: np.ndarray,
    cell_y: np.ndarray,
    columns: np.ndarray,
    room: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The blending weights averaged over the cells of a coarser grid, as CSR, in one walk and
    without the per-pixel CSR `blend_weights` holds (what pooling that CSR gives, up to float32
    summation order; the tests hold the two equal).

    `cell_x` [width] and `cell_y` [height] give each pixel column's and row's cell (from 0,
    non-decreasing, no cell empty); `columns` [N] maps Gaussian id -> column. Rows are cells in
    row-major order; within a row, columns ascend and a column's weight is the sum of its
    pixels' weights / the cell's pixel count. Also returns how many per-pixel weights there were.

    The walk sums each Gaussian's weights over every (tile, cell) it reaches into a segment of
    its own; a second pass merges each cell's segments in a fixed order, so the output is the
    same bytes whatever the thread count. `room`: (column, sum) pairs each thread has room for
    before a tile is walked again with more (default: twice as many as the tiles hold
    Gaussians, shared out)."""
    cell_x = np.ascontiguousarray(cell_x, np.int64)
    cell_y = np.ascontiguousarray(cell_y, np.int64)
    cells_w, cells_h = int(cell_x[-1]) + 1, int(cell_y[-1]) + 1
    n_tiles = bins.tiles_x * bins.tiles_y
    tile = np.arange(n_tiles)
    x0 = (tile % bins.tiles_x) * TILE
    y0 = (tile // bins.tiles_x) * TILE
    lcx0, lcy0 = cell_x[x0], cell_y[y0]
    n_lcx = cell_x[np.minimum(x0 + TILE, width) - 1] - lcx0 + 1
    n_lcy = cell_y[np.minimum(y0 + TILE, height) - 1] - lcy0 + 1
    seg_base = np.zeros(n_tiles + 1, np.int64)
    np.cumsum(n_lcx * n_lcy, out=seg_base[1:])
    seg_tile = np.repeat(tile, n_lcx * n_lcy)
    local = np.arange(seg_base[-1]) - seg_base[seg_tile]
    seg_cell = (lcy0[seg_tile] + local // n_lcx[seg_tile]) * cells_w + (
        lcx0[seg_tile] + local % n_lcx[seg_tile]
    )
    seg_start = np.zeros(seg_base[-1], np.int64)
    seg_len = np.zeros(seg_base[-1], np.int64)
    per_tile = np.zeros(n_tiles, np.int64)
    kw = dict(
        counts=per_tile,
        cell_x=cell_x,
        cell_y=cell_y,
        cell_x_end=np.searchsorted(cell_x, np.arange(cells_w), side="right").astype(np.int64),
        columns=np.ascontiguousarray(columns, np.int32),
        seg_base=seg_base,
        seg_start=seg_start,
        seg_len=seg_len,
    )
    n_thr = numba.get_num_threads()
    # About 1.1 pairs per tile entry at 3M Gaussians and 8 px cells: twice that, shared out.
    room = (2 * len(bins.ids) + 1024) // n_thr + 1024 if room is None else room
    cols, vals, cursor = _pool_buffers(n_thr, room)
    # Tile rows dealt out in turn: a split of the loop into one run per thread (numba's
    # default) gives each thread rows from all over the image, not the top or the bottom.
    rows = np.arange(n_tiles) // bins.tiles_x
    dealt = np.argsort(rows % n_thr, kind="stable")
    walk = functools.partial(_walk, POOL, proj, bins, width, height, **kw)
    walk(tile_list=dealt, cursor=cursor, pool_cols=cols, pool_vals=vals)
    again = np.flatnonzero(per_tile < 0)
    if len(again):
        # Room enough for all of them in every thread's region, so one more walk does.
        more, more_vals, more_cursor = _pool_buffers(n_thr, int(-(per_tile[again] + 1).sum()))
        more_cursor += len(cols)
        cols, vals = np.concatenate([cols, more]), np.concatenate([vals, more_vals])
        walk(tile_list=again, cursor=more_cursor, pool_cols=cols, pool_vals=vals)
    # Segments cell by cell, each cell's tiles in tile order: the merge's fixed order.
    order = np.argsort(seg_cell, kind="stable")
    cell_segs = np.zeros(cells_w * cells_h + 1, np.int64)
    np.cumsum(np.bincount(seg_cell, minlength=cells_w * cells_h), out=cell_segs[1:])
    row_at = np.zeros(cells_w * cells_h + 1, np.int64)
    np.cumsum(np.add.reduceat(seg_len[order], cell_segs[:-1]), out=row_at[1:])
    row_cols = np.empty(row_at[-1], np.int32)
    row_vals = np.empty(row_at[-1], np.float32)
    n_pix = np.outer(np.bincount(cell_y), np.bincount(cell_x)).ravel()
    acc = np.zeros((n_thr, len(columns)), np.float32)
    n_out = _pool_merge_kernel(
        order, cell_segs, seg_start, seg_len, cols, vals, n_pix, acc, row_at, row_cols, row_vals
    )
    indptr = np.zeros(len(n_out) + 1, np.int64)
    np.cumsum(n_out, out=indptr[1:])
    out_cols = np.empty(indptr[-1], np.int32)
    out_vals = np.empty(indptr[-1], np.float32)
    _pool_compact_kernel(row_cols, row_vals, row_at, indptr, out_cols, out_vals)
    return indptr, out_cols, out_vals, int(per_tile.sum())


def _pool_buffers(n_threads: int, room: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Columns and sums for `n_threads` regions of `room` pairs, and each region's cursor."""
    cursor = np.zeros((n_threads, 2), np.int64)
    cursor[:, 0] = np.arange(n_threads) * room
    cursor[:, 1] = cursor[:, 0] + room
    return np.empty(n_threads * room, np.int32), np.empty(n_threads * room, np.float32), cursor


def render_backward(
    proj: Projected, bins: Bins, grad_image: np.ndarray, n_gaussians: int
) -> np.ndarray:
    """d loss / d colors [N, C] given d loss / d image [H, W, C], by walking the tiles again."""
    height, width, n_ch = grad_image.shape
    buf = np.zeros((numba.get_num_threads(), n_gaussians, n_ch), np.float32)
    _walk(
        BACKWARD,
        proj,
        bins,
        width,
        height,
        colors=np.zeros((0, n_ch), np.float32),
        grad_out=np.ascontiguousarray(grad_image, np.float32),
        sums=buf,
    )
    return buf.sum(axis=0)


def label_sums(
    proj: Projected,
    bins: Bins,
    labels: np.ndarray,
    n_labels: int,
    lanes: int,
    tiles: np.ndarray | None = None,
):
    """[lanes, N, n_labels] float32: each Gaussian's weights summed over the pixels of each label
    (`labels` [H, W] uint8, each < n_labels), one sum per lane. The tiles are dealt round-robin
    to the lanes, each walked by one thread in tile order into its own sums, so the order of
    every addition depends on the image alone, never on the threads (stages.render.lift).
    `tiles` [n] int64 (ascending): walk only these, each in the lane it has in the walk of
    every tile, so a Gaussian drawn in none of the others gets the same sums bit for bit."""
    height, width = labels.shape
    n_tiles = bins.tiles_x * bins.tiles_y
    if tiles is None:
        dealt = [np.arange(lane, n_tiles, lanes) for lane in range(lanes)]
    else:
        tiles = np.asarray(tiles, np.int64)
        dealt = [tiles[tiles % lanes == lane] for lane in range(lanes)]
    lane_ptr = np.zeros(lanes + 1, np.int64)
    np.cumsum([len(d) for d in dealt], out=lane_ptr[1:])
    sums = np.zeros((lanes, proj.means2d.shape[0], n_labels), np.float32)
    _walk(
        LIFT,
        proj,
        bins,
        width,
        height,
        labels=np.ascontiguousarray(labels, np.uint8),
        sums=sums,
        tile_list=np.concatenate(dealt).astype(np.int64),
        lane_ptr=lane_ptr,
    )
    return sums


@dataclass
class Rendered:
    image: np.ndarray  # [H, W, C] float32: RGB (with background) or features (without)
    alpha: np.ndarray  # [H, W] float32, 1 - final transmittance
    depth: np.ndarray  # [H, W] float32, expected depth sum(w z) / alpha (0 where alpha = 0)


def render(
    proj: Projected,
    bins: Bins,
    colors: np.ndarray,
    width: int,
    height: int,
    background: np.ndarray | None = None,
    tiles: np.ndarray | None = None,
) -> Rendered:
    """Composite per-Gaussian values `colors` [N, C] (RGB or features) into an image.
    `tiles` [n] int64: walk only these tiles; the others are left 0 (no weight, no value)."""
    colors = np.ascontiguousarray(colors, np.float32)
    alloc = np.empty if tiles is None else np.zeros
    out = alloc((height, width, colors.shape[1]), np.float32)
    alpha = alloc((height, width), np.float32)
    depth = alloc((height, width), np.float32)
    more = {} if tiles is None else {"tile_list": np.ascontiguousarray(tiles, np.int64)}
    _walk(
        RENDER, proj, bins, width, height, colors=colors, out=out, alpha_out=alpha,
        depth_out=depth, **more,
    )  # fmt: skip
    if background is not None:
        out += (1.0 - alpha)[:, :, None] * np.asarray(background, np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(alpha > 0, depth / alpha, 0.0).astype(np.float32)
    return Rendered(out, alpha, depth)
