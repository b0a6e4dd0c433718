"""Rendering per-Gaussian features at chosen pixels of the cached views, differentiably.

Forward is a row-gathered CSR product (the rendered feature of each requested row), backward its
transpose (the gradient of each Gaussian's feature). Both are numba kernels over the stacked CSR
of all cached views, with the columns in Morton order so that the Gaussians a row touches sit
close in memory.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from stages.core.errors import GoiError
from stages.semantics.blend_cache import BlendCache


@numba.njit(parallel=True, cache=True)
def _spmm_rows(indptr, indices, weights, rows, f, out):
    """out[i] = sum_j w[rows[i], j] f[j]: the rendered feature of each requested pixel."""
    n_ch = f.shape[1]
    for i in numba.prange(rows.shape[0]):
        r = rows[i]
        for c in range(n_ch):
            out[i, c] = 0.0
        for j in range(indptr[r], indptr[r + 1]):
            w = weights[j]
            g = indices[j]
            for c in range(n_ch):
                out[i, c] += w * f[g, c]


#: The transpose sums into this many private buffers, each over a fixed block of rows, so the
#: order of the float additions never depends on thread scheduling or on the machine's core
#: count: the same inputs give the same gradients, bit for bit, everywhere.
T_BLOCKS = 2


@numba.njit(parallel=True, cache=True)
def _spmm_rows_t(indptr, indices, weights, rows, grad, buf):
    """buf[b, j] += w[rows[i], j] grad[i] for the rows i of block b: the transpose."""
    n_ch = grad.shape[1]
    n_blocks = buf.shape[0]
    n = rows.shape[0]
    for b in numba.prange(n_blocks):
        for i in range(n * b // n_blocks, n * (b + 1) // n_blocks):
            r = rows[i]
            for j in range(indptr[r], indptr[r + 1]):
                w = weights[j]
                g = indices[j]
                for c in range(n_ch):
                    buf[b, g, c] += w * grad[i, c]


@numba.njit(parallel=True, cache=True)
def _gather(src, idx, out):
    """out[i] = src[idx[i]] (numpy's fancy indexing is single-threaded and 10x slower)."""
    for i in numba.prange(idx.shape[0]):
        out[i] = src[idx[i]]


@numba.njit(parallel=True, cache=True)
def _scatter_sum(bufs, idx, out):
    """out[idx[i]] = sum_b bufs[b, i]: reduce the block buffers straight into PLY order."""
    for i in numba.prange(idx.shape[0]):
        out[idx[i]] = bufs[0, i]
        for t in range(1, bufs.shape[0]):
            out[idx[i]] += bufs[t, i]


class FeatureRenderer:
    """Renders per-Gaussian features at any pixels of the cached views, differentiably.

    All views' matrices are stacked once into one CSR so that a training step only names
    rows: no per-step copying of weights.
    """

    def __init__(self, cache: BlendCache, views: list[str] | None = None):
        names = list(cache.views) if views is None else views
        missing = [v for v in names if v not in cache.views]
        if missing:
            raise GoiError(f"view(s) {', '.join(missing[:5])} are not in the blend cache")
        parts = [cache.views[v] for v in names]
        self.views = names
        self.sizes = {v: (p.width, p.height) for v, p in zip(names, parts, strict=True)}
        self.row_offset: dict[str, int] = {}
        ptrs, base, row = [np.zeros(1, np.int64)], 0, 0
        for v, p in zip(names, parts, strict=True):
            self.row_offset[v] = row
            ptrs.append(p.indptr[1:] + base)
            base += int(p.indptr[-1])
            row += p.width * p.height
        self.indptr = np.concatenate(ptrs)  # [rows + 1] int64
        self.indices = np.concatenate([p.indices for p in parts])  # [nnz] int32
        self.weights = np.concatenate([p.weights for p in parts])  # [nnz] float32
        self.order = cache.order  # [G] int32: column j holds Gaussian order[j]
        self.n_gaussians = cache.n_gaussians

    def rows(self, view: str, pixels: np.ndarray | None = None) -> np.ndarray:
        """Global row ids [R] int64 of a view's pixels (row-major ids; None = all)."""
        w, h = self.sizes[view]
        off = self.row_offset[view]
        if pixels is None:
            return np.arange(off, off + w * h, dtype=np.int64)
        return np.asarray(pixels, np.int64) + off

    def render(self, features: torch.Tensor, rows: np.ndarray) -> torch.Tensor:
        """Rendered features [R, C] at `rows` from per-Gaussian features [G, C] in PLY order;
        differentiable with respect to `features`."""
        return _SparseRender.apply(features, self, np.ascontiguousarray(rows))


class _SparseRender(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        features: torch.Tensor,
        fr: FeatureRenderer,
        rows: np.ndarray,  # noqa: ANN001
    ) -> torch.Tensor:
        ctx.fr, ctx.rows = fr, rows
        src = features.detach().numpy()
        f = np.empty_like(src)
        _gather(src, fr.order, f)  # to cache column order
        out = np.empty((len(rows), f.shape[1]), np.float32)
        _spmm_rows(fr.indptr, fr.indices, fr.weights, rows, f, out)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # noqa: ANN001, ANN205
        fr: FeatureRenderer = ctx.fr
        g = grad.detach().contiguous().numpy()
        buf = np.zeros((T_BLOCKS, fr.n_gaussians, g.shape[1]), np.float32)
        _spmm_rows_t(fr.indptr, fr.indices, fr.weights, ctx.rows, g, buf)
        grad_f = np.empty_like(buf[0])
        _scatter_sum(buf, fr.order, grad_f)  # back to PLY order
        return torch.from_numpy(grad_f), None, None
