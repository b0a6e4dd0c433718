"""Rendering the semantic field at any camera and decoding it through the codebook.

A pixel's rendered low-dimensional feature f_hat = sum_i f_i alpha_i T_i decodes to the codebook
entry argmax(D f_hat). The RGB can ride along in the same tile walk (3 more channels), which is
how render-mask gets its overlay for little extra cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from stages.render.rasterizer import Rasterizer, RenderBackend, take_rows
from stages.scene.cameras import Camera
from stages.scene.gaussians import Gaussians
from stages.semantics.field import Field

#: A pixel counts as covered by the scene when its accumulated alpha exceeds this; elsewhere
#: f_hat is mostly empty space and decodes to noise, so it is never in a mask.
COVERED_ALPHA = 0.5


@numba.njit(cache=True)
def _max(a):  # noqa: ANN001, ANN202
    # Eight independent running maxima (no loop-carried dependency, so the compiler vectorises
    # it), then combined: the same value as a plain scan, as max is exact.
    n = a.shape[0]
    m = np.empty(8, np.float32)
    m[:] = a[0]
    for k0 in range(0, n - 7, 8):
        for q in range(8):
            x = a[k0 + q]
            m[q] = x if x > m[q] else m[q]
    best = m[0]
    for q in range(1, 8):
        best = m[q] if m[q] > best else best
    for k in range(n - n % 8, n):
        best = a[k] if a[k] > best else best
    return best


@numba.njit(parallel=True, cache=True)
def _decode_kernel(f, wt, b, out):  # noqa: ANN001, ANN202
    # Per pixel, the N logits go to a small buffer and the argmax is taken there: the [M, N]
    # logits matrix (370 MB at 640x480, N = 300) is never materialised. The inner loop runs
    # over entries with wt [S, N] contiguous, which the compiler vectorises. The argmax is the
    # first entry equal to the maximum (what a strict > scan keeps), the maximum found apart.
    m, s = f.shape
    n = wt.shape[1]
    block = 256
    for blk in numba.prange((m + block - 1) // block):
        acc = np.empty(n, np.float32)
        for i in range(blk * block, min(m, (blk + 1) * block)):
            for k in range(n):
                acc[k] = b[k]
            for j in range(s):
                fij = f[i, j]
                for k in range(n):
                    acc[k] += fij * wt[j, k]
            best = _max(acc)
            arg = 0
            while acc[arg] != best:
                arg += 1
            out[i] = arg


def decode_reference(f_hat: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """Plain numpy: argmax of the logits [M, N] (float64)."""
    logits = f_hat.astype(np.float64) @ weight.T.astype(np.float64) + bias
    return np.argmax(logits, axis=1).astype(np.int32)


@dataclass
class DecodedView:
    index: np.ndarray  # [H, W] int32, codebook entry per pixel
    covered: np.ndarray  # [H, W] bool
    rgb: np.ndarray | None  # [H, W, 3] float32 0..1, when asked for


class SemanticRenderer:
    def __init__(self, gaussians: Gaussians, field: Field, backend: RenderBackend | None = None):
        self.g = gaussians
        self.field = field
        self.rast = Rasterizer.from_gaussians(gaussians, backend)
        self._wt = np.ascontiguousarray(field.decoder_weight.T, np.float32)  # [S, N]
        self._b = np.ascontiguousarray(field.decoder_bias, np.float32)  # [N]

    def decode(self, f_hat: np.ndarray) -> np.ndarray:
        """[M, S] rendered features -> [M] int32 codebook entries."""
        out = np.empty(f_hat.shape[0], np.int32)
        _decode_kernel(np.ascontiguousarray(f_hat, np.float32), self._wt, self._b, out)
        return out

    def render(self, cam: Camera, with_rgb: bool = False) -> DecodedView:
        s = self.field.features.shape[1]
        if self.rast.backend is not None:
            feats = self.field.features  # [G, S]
            if with_rgb:
                feats = np.concatenate([feats, self.rast.colors(cam)], axis=1)
            out = self.rast.render_features(cam, np.ascontiguousarray(feats, np.float32))
        else:
            # Only the Gaussians the view sees: their features gathered, their colours evaluated.
            view = self.rast.view(cam)
            values = take_rows(self.field.features, view.gaussians)  # [V, S]
            if with_rgb:
                values = np.concatenate([values, self.rast.colors(cam, view.gaussians)], axis=1)
            out = self.rast.render_view(cam, view, values)
        img = out.image  # [H, W, C]
        covered = out.alpha > COVERED_ALPHA
        index = np.zeros(covered.shape, np.int32)  # uncovered pixels are in no mask anyway
        index[covered] = self.decode(img[:, :, :s][covered])
        color = np.clip(img[:, :, s:], 0, 1) if with_rgb else None
        return DecodedView(index, covered, color)
