"""Pure math on blend weights stored as CSR (rows = pixels or feature cells, columns = Gaussians):
Morton ordering of the columns, keeping the top-K weights of each row, and pooling pixel rows
into the cells of a coarser feature grid."""

from __future__ import annotations

import numba
import numpy as np


def morton_order(means: np.ndarray) -> np.ndarray:
    """[N] int32 permutation sorting Gaussian centres [N, 3] along a 3D Z-curve (10 bits/axis)."""
    lo, hi = means.min(0), means.max(0)
    q = ((means - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.uint64)
    code = np.zeros(len(means), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable").astype(np.int32)


@numba.njit(parallel=True, cache=True)
def _top_k_kernel(indptr, ids, vals, k, new_ptr, new_ids, new_vals):
    rows = indptr.shape[0] - 1
    for r in numba.prange(rows):
        a, b = indptr[r], indptr[r + 1]
        o = new_ptr[r]
        if b - a <= k:
            for j in range(b - a):
                new_ids[o + j] = ids[a + j]
                new_vals[o + j] = vals[a + j]
            continue
        # Keep the k largest weights, in their front-to-back order.
        cut = np.sort(vals[a:b])[b - a - k]
        n_above = 0
        for j in range(a, b):
            if vals[j] > cut:
                n_above += 1
        ties = k - n_above
        m = 0
        for j in range(a, b):
            v = vals[j]
            if v > cut or (v == cut and ties > 0):
                if v == cut:
                    ties -= 1
                new_ids[o + m] = ids[j]
                new_vals[o + m] = v
                m += 1


def top_k(
    indptr: np.ndarray, ids: np.ndarray, vals: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the k largest weights of every row (k = 0 keeps everything)."""
    if k <= 0:
        return indptr, ids, vals
    counts = np.minimum(np.diff(indptr), k)
    new_ptr = np.zeros_like(indptr)
    np.cumsum(counts, out=new_ptr[1:])
    new_ids = np.empty(new_ptr[-1], np.int32)
    new_vals = np.empty(new_ptr[-1], np.float32)
    _top_k_kernel(indptr, ids, vals, k, new_ptr, new_ids, new_vals)
    return new_ptr, new_ids, new_vals


@numba.njit(cache=True)
def _pool_kernel(
    indptr,
    indices,
    weights,
    width,
    cell_y0,
    cell_y1,
    cell_x0,
    cell_x1,
    n_gauss,
    out_ptr,
    out_ids,
    out_w,
):
    """Each cell's row = the mean of its pixels' rows (entries of one Gaussian merged)."""
    acc = np.zeros(n_gauss, np.float32)
    seen = np.zeros(n_gauss, np.bool_)
    touched = np.empty(n_gauss, np.int32)
    pos = 0
    cell = 0
    for cy in range(cell_y0.shape[0]):
        for cx in range(cell_x0.shape[0]):
            n_t = 0
            n_pix = (cell_y1[cy] - cell_y0[cy]) * (cell_x1[cx] - cell_x0[cx])
            for y in range(cell_y0[cy], cell_y1[cy]):
                for x in range(cell_x0[cx], cell_x1[cx]):
                    r = y * width + x
                    for j in range(indptr[r], indptr[r + 1]):
                        g = indices[j]
                        if not seen[g]:
                            seen[g] = True
                            touched[n_t] = g
                            n_t += 1
                        acc[g] += weights[j]
            ids = np.sort(touched[:n_t])
            for g in ids:
                out_ids[pos] = g
                out_w[pos] = acc[g] / n_pix
                pos += 1
                acc[g] = 0.0
                seen[g] = False
            cell += 1
            out_ptr[cell] = pos
    return pos


def _cell_bounds(n_pix: int, n_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel ranges [start, end) per cell; pixel y is in cell floor((y + .5) n_cells / n_pix)."""
    cell = ((np.arange(n_pix) + 0.5) * n_cells / n_pix).astype(np.int64)
    start = np.searchsorted(cell, np.arange(n_cells), side="left")
    end = np.searchsorted(cell, np.arange(n_cells), side="right")
    return start, end


def pixel_cells(n_pix: int, n_cells: int) -> np.ndarray:
    """[n_pix] int64: the cell of each pixel (row or column), as `_cell_bounds` draws them."""
    start, end = _cell_bounds(n_pix, n_cells)
    return np.repeat(np.arange(n_cells, dtype=np.int64), end - start)


def pool(
    indptr: np.ndarray,
    ids: np.ndarray,
    vals: np.ndarray,
    width: int,
    height: int,
    cells_w: int,
    cells_h: int,
    n_gaussians: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average a [height * width] pixel CSR into a [cells_h * cells_w] cell CSR: since a render
    is linear in the weights, a cell's row renders the mean of its pixels' features, which is
    what an area-downsampled feature map holds."""
    y0, y1 = _cell_bounds(height, cells_h)
    x0, x1 = _cell_bounds(width, cells_w)
    out_ptr = np.zeros(cells_w * cells_h + 1, np.int64)
    out_ids = np.empty(len(ids), np.int32)
    out_w = np.empty(len(ids), np.float32)
    n = _pool_kernel(indptr, ids, vals, width, y0, y1, x0, x1, n_gaussians, out_ptr, out_ids, out_w)
    return out_ptr, out_ids[:n].copy(), out_w[:n].copy()
