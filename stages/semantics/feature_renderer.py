"""Rendering per-Gaussian features at chosen pixels of the cached views, differentiably.

Forward is a row-gathered CSR product (the rendered feature of each requested row), backward its
transpose (the gradient of each Gaussian's feature). Both are numba kernels over the stacked CSR
of all cached views, with the columns in Morton order so that the Gaussians a row touches sit
close in memory.
"""

from __future__ import annotations

import os

import numba
import numpy as np
import torch

from stages.core.artifacts import open_h5
from stages.core.errors import GoiError
from stages.core.hdf5 import read_h5
from stages.semantics.blend_cache import SCHEMA, BlendCache, read_order, read_view


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
def _sum_and_clear(bufs, idx, out):
    """out[idx[i]] = sum_b bufs[b, i] (out[i] with an empty idx), then bufs[:, i] = 0: the
    buffers are ready for the next step without a separate pass (or fresh pages) over
    [blocks, G, C]."""
    for i in numba.prange(bufs.shape[1]):
        j = np.int64(i) if idx.shape[0] == 0 else np.int64(idx[i])
        for c in range(out.shape[1]):
            out[j, c] = bufs[0, i, c]
            bufs[0, i, c] = 0.0
        for t in range(1, bufs.shape[0]):
            for c in range(out.shape[1]):
                out[j, c] += bufs[t, i, c]
                bufs[t, i, c] = 0.0


_IDENTITY = np.zeros(0, np.int32)


class GradBuffers:
    """The transpose's private block buffers [T_BLOCKS, G, C], kept zeroed between steps.

    A training loop passes one to every `render` call: at 3M Gaussians the buffers are 240 MB,
    and allocating them afresh each step (page faults, then zeroing) cost more than the
    transpose itself."""

    def __init__(self) -> None:
        self.blocks = np.zeros((0, 0, 0), np.float32)

    def get(self, n_gaussians: int, n_ch: int) -> np.ndarray:
        if self.blocks.shape != (T_BLOCKS, n_gaussians, n_ch):
            self.blocks = np.zeros((T_BLOCKS, n_gaussians, n_ch), np.float32)
        return self.blocks


class FeatureRenderer:
    """Renders per-Gaussian features at any pixels of the cached views, differentiably.

    The chosen views' matrices are stacked into one CSR so that a training step only names
    rows: no per-step copying of weights.
    """

    def __init__(
        self,
        order: np.ndarray,  # [G] int32: column j holds Gaussian order[j]
        sizes: dict[str, tuple[int, int]],  # view -> (width, height), in stacking order
        indptr: np.ndarray,  # [rows + 1] int64, the views' rows one after another
        indices: np.ndarray,  # [nnz] int32
        weights: np.ndarray,  # [nnz] float32
    ):
        self.views = list(sizes)
        self.sizes = sizes
        self.row_offset: dict[str, int] = {}
        row = 0
        for v, (w, h) in sizes.items():
            self.row_offset[v] = row
            row += w * h
        self.indptr, self.indices, self.weights = indptr, indices, weights
        self.order = order
        self.n_gaussians = int(len(order))

    @classmethod
    def from_cache(cls, cache: BlendCache, views: list[str] | None = None) -> FeatureRenderer:
        names = list(cache.views) if views is None else views
        missing = [v for v in names if v not in cache.views]
        if missing:
            raise GoiError(f"view(s) {', '.join(missing[:5])} are not in the blend cache")
        parts = [cache.views[v] for v in names]
        ptrs, base = [np.zeros(1, np.int64)], 0
        for p in parts:
            ptrs.append(p.indptr[1:] + base)
            base += int(p.indptr[-1])
        return cls(
            cache.order,
            {v: (p.width, p.height) for v, p in zip(names, parts, strict=True)},
            np.concatenate(ptrs),
            np.concatenate([p.indices for p in parts]),
            np.concatenate([p.weights for p in parts]),
        )

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike[str],
        views: list[str],
        order: np.ndarray | None = None,
        check: bool = True,
        schema: str = SCHEMA,
    ) -> FeatureRenderer:
        """The views' weights read from the cache file straight into the stacked arrays, so
        that memory holds them once. A fit that streams the cache calls this every step for
        that step's views, with the `order` it read once and `check` off (it checked every
        view once before, so the per-step read skips the schema validation of the whole file
        as well). A distributed fit reads its shard of the cache (`schema`
        goi.blend_cache_shard, with its columns' `order`) the same way."""
        opened = open_h5(path, schema) if check else read_h5(path)
        with opened as f:
            n = int(f.attrs["n_gaussians"])
            order = read_order(f, path) if order is None else order
            missing = [v for v in views if v not in f["views"]]
            if missing:
                raise GoiError(f"{path}: view(s) {', '.join(missing[:5])} are not in the cache")
            groups = [f["views"][v] for v in views]
            sizes = {
                v: (int(g.attrs["width"]), int(g.attrs["height"]))
                for v, g in zip(views, groups, strict=True)
            }
            nnz = [g["indices"].shape[0] for g in groups]
            indptr = np.zeros(sum(w * h for w, h in sizes.values()) + 1, np.int64)
            indices = np.empty(sum(nnz), np.int32)
            weights = np.empty(sum(nnz), np.float32)
            row = base = 0
            for v, g, m in zip(views, groups, nnz, strict=True):
                w, h = sizes[v]
                vw = read_view(
                    g,
                    n,
                    f"{path}: view '{v}'",
                    check,
                    indices[base : base + m],
                    weights[base : base + m],
                )
                indptr[row + 1 : row + w * h + 1] = vw.indptr[1:] + base
                row, base = row + w * h, base + m
        return cls(order, sizes, indptr, indices, weights)

    def rows(self, view: str, pixels: np.ndarray | None = None) -> np.ndarray:
        """Global row ids [R] int64 of a view's pixels (row-major ids; None = all)."""
        w, h = self.sizes[view]
        off = self.row_offset[view]
        if pixels is None:
            return np.arange(off, off + w * h, dtype=np.int64)
        return np.asarray(pixels, np.int64) + off

    def render(
        self,
        features: torch.Tensor,
        rows: np.ndarray,
        in_columns: bool = False,
        buffers: GradBuffers | None = None,
    ) -> torch.Tensor:
        """Rendered features [R, C] at `rows` from per-Gaussian features [G, C], differentiable
        with respect to `features`. These are in PLY order, or with `in_columns` in the
        cache's column order (`order`): a fit keeps them so, which spares a [G, C] gather each
        step and a scatter each backward. `buffers` are reused by the backward."""
        rows = np.ascontiguousarray(rows)
        return _SparseRender.apply(features, self, rows, in_columns, buffers or GradBuffers())


class _SparseRender(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx,
        features: torch.Tensor,  # [G, C]
        fr: FeatureRenderer,
        rows: np.ndarray,  # [R]
        in_columns: bool,
        buffers: GradBuffers,
    ) -> torch.Tensor:
        ctx.fr, ctx.rows, ctx.in_columns, ctx.buffers = fr, rows, in_columns, buffers  # type: ignore[attr-defined]
        f = src = features.detach().numpy()
        if not in_columns:
            f = np.empty_like(src)
            _gather(src, fr.order, f)  # to cache column order
        out = np.empty((len(rows), f.shape[1]), np.float32)
        _spmm_rows(fr.indptr, fr.indices, fr.weights, rows, f, out)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]  # noqa: ANN001, ANN205
        fr: FeatureRenderer = ctx.fr
        g = grad.detach().contiguous().numpy()
        buf = ctx.buffers.get(fr.n_gaussians, g.shape[1])
        _spmm_rows_t(fr.indptr, fr.indices, fr.weights, ctx.rows, g, buf)
        grad_f = np.empty_like(buf[0])
        # summed straight into PLY order unless the caller holds the features in columns
        _sum_and_clear(buf, _IDENTITY if ctx.in_columns else fr.order, grad_f)
        return torch.from_numpy(grad_f), None, None, None, None
