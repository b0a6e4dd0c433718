"""The frozen-geometry blend cache and the feature renderer built on it.

GOI never moves the Gaussians while it fits semantics, so for a fixed view the rendered feature
map is linear in the per-Gaussian features: F_view = W_view f, with W_view a sparse
[pixels x Gaussians] matrix of blending weights alpha_i T_i. Rasterise every training view once,
keep W_view, and each training step is a sparse product (and its transpose for the gradient)
instead of a rasterisation.

Columns are stored in Morton (Z-curve) order of the Gaussian centres: Gaussians that meet at a
pixel sit close in memory, which is what makes the sparse products fast.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numba
import numpy as np
import torch

from stages.artifacts import open_h5, put, write_h5
from stages.cameras import Camera
from stages.errors import GoiError
from stages.progress import progress
from stages.rasterizer import Rasterizer, blend_weights

SCHEMA = "goi.blend_cache"


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


@dataclass
class ViewWeights:
    """One view's W as CSR [height * width, n_gaussians]; columns are positions in `order`."""

    width: int
    height: int
    indptr: np.ndarray  # [P + 1] int64
    indices: np.ndarray  # [nnz] int32
    weights: np.ndarray  # [nnz] float32
    mass_kept: float  # sum of kept weights / sum of all weights (1 without top-K)
    entries_total: int  # entries before top-K

    @property
    def nbytes(self) -> int:
        return self.indptr.nbytes + self.indices.nbytes + self.weights.nbytes


def view_weights(
    rast: Rasterizer,
    cam: Camera,
    position: np.ndarray,
    k: int = 0,
    size: tuple[int, int] | None = None,
) -> ViewWeights:
    """Rasterise `cam` once and keep its weights; `position` maps Gaussian id -> column.
    With `size` (width, height) smaller than the image, pixels are pooled into that grid."""
    proj, bins = rast.prepare(cam)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    total = float(vals.sum(dtype=np.float64))
    kp, ki, kv = top_k(indptr, position[ids], vals, k)
    kept = float(kv.sum(dtype=np.float64))
    w, h = size or (cam.width, cam.height)
    if (w, h) != (cam.width, cam.height):
        kp, ki, kv = pool(kp, ki, kv, cam.width, cam.height, w, h, len(position))
    return ViewWeights(w, h, kp, ki, kv, kept / total if total > 0 else 1.0, int(len(ids)))


@dataclass
class BlendCache:
    order: np.ndarray  # [G] int32: column j is Gaussian order[j]
    views: dict[str, ViewWeights]
    top_k: int
    ply_sha256: str
    cameras_sha256: str

    @property
    def n_gaussians(self) -> int:
        return int(len(self.order))

    def save(self, path: str | os.PathLike[str], force: bool = True) -> None:
        inputs = {"ply": self.ply_sha256, "cameras": self.cameras_sha256}
        with write_h5(path, SCHEMA, inputs, force=force) as f:
            f.attrs.update(
                n_gaussians=self.n_gaussians,
                top_k=self.top_k,
                ply_sha256=self.ply_sha256,
                cameras_sha256=self.cameras_sha256,
            )
            put(f, "order", self.order)
            views = f.create_group("views", track_order=True)
            for name, vw in self.views.items():
                grp = views.create_group(name)
                grp.attrs.update(
                    width=vw.width,
                    height=vw.height,
                    mass_kept=vw.mass_kept,
                    entries_total=vw.entries_total,
                )
                put(grp, "indptr", vw.indptr)
                put(grp, "indices", vw.indices)
                put(grp, "weights", vw.weights)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> BlendCache:
        with open_h5(path, SCHEMA) as f:
            views = {}
            for name, grp in f["views"].items():
                a = grp.attrs
                vw = ViewWeights(
                    int(a["width"]),
                    int(a["height"]),
                    grp["indptr"][()],
                    grp["indices"][()],
                    grp["weights"][()],
                    float(a["mass_kept"]),
                    int(a["entries_total"]),
                )
                if len(vw.indptr) != vw.width * vw.height + 1:
                    raise GoiError(
                        f"{path}: view '{name}' has {len(vw.indptr) - 1} pixel rows "
                        f"for a {vw.width}x{vw.height} image"
                    )
                views[name] = vw
            return cls(
                f["order"][()],
                views,
                int(f.attrs["top_k"]),
                str(f.attrs["ply_sha256"]),
                str(f.attrs["cameras_sha256"]),
            )

    def weight_stats(self) -> dict[str, float]:
        n_views = max(len(self.views), 1)
        return {
            "views": float(len(self.views)),
            "entries_per_pixel": sum(len(v.indices) for v in self.views.values())
            / max(sum(v.width * v.height for v in self.views.values()), 1),
            "mass_kept": sum(v.mass_kept for v in self.views.values()) / n_views,
            "mib_per_view": sum(v.nbytes for v in self.views.values()) / n_views / 2**20,
        }


def build_cache(
    rast: Rasterizer,
    cameras: list[Camera],
    k: int,
    ply_sha256: str,
    cameras_sha256: str,
    sizes: dict[str, tuple[int, int]] | None = None,
) -> BlendCache:
    order = morton_order(rast.means)
    position = np.empty_like(order)
    position[order] = np.arange(len(order), dtype=np.int32)
    views = {
        cam.name: view_weights(rast, cam, position, k, (sizes or {}).get(cam.name))
        for cam in progress(cameras, "blend cache", length=len(cameras))
    }
    return BlendCache(order, views, k, ply_sha256, cameras_sha256)


def build_or_load(
    path: str | os.PathLike[str],
    scene,  # noqa: ANN001 - stages.scene.Scene
    cameras: list[Camera],
    k: int = 0,
    sizes: dict[str, tuple[int, int]] | None = None,
) -> BlendCache:
    """The cache for these views, reused from `path` when it was built for the same PLY,
    cameras, top-K and view sizes, otherwise (re)built and written there. `sizes` gives a
    view's (width, height) when it is to be pooled below image resolution."""
    ply_sha, cam_sha = scene.ply_digest(), scene.cameras_digest()
    want = {c.name: (sizes or {}).get(c.name, (c.width, c.height)) for c in cameras}
    p = Path(path)
    if p.is_file() and _matches(p, ply_sha, cam_sha, k, want):
        cache = BlendCache.load(p)
        cache.views = {c.name: cache.views[c.name] for c in cameras}
        return cache
    rast = Rasterizer.from_gaussians(scene.gaussians)
    cache = build_cache(rast, cameras, k, ply_sha, cam_sha, want)
    cache.save(p, force=True)
    return cache


def _matches(p: Path, ply_sha: str, cam_sha: str, k: int, want: dict[str, tuple[int, int]]) -> bool:
    try:
        with h5py.File(p, "r") as f:
            a, views = f.attrs, f.get("views", {})
            return (
                a.get("schema") == SCHEMA
                and a.get("ply_sha256") == ply_sha
                and a.get("cameras_sha256") == cam_sha
                and int(a.get("top_k", -1)) == k
                and all(
                    v in views
                    and (int(views[v].attrs["width"]), int(views[v].attrs["height"])) == wh
                    for v, wh in want.items()
                )
            )
    except (OSError, KeyError):
        return False


# --- sparse feature rendering -------------------------------------------------------------


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
