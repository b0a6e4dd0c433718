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


#: Pixels decoded together: their logits for one entry fill a few vector registers' worth.
DECODE_BLOCK = 256


@numba.njit(parallel=True, cache=True)
def _decode_kernel(f, wt, b, out):  # noqa: ANN001, ANN202
    # A block of pixels at a time, entry by entry: the block's features transposed to [S, B]
    # make every inner loop run over pixels, contiguous and branch-free, which the compiler
    # vectorises (2x the speed of a loop over entries per pixel). Each logit is still
    # b[k] + f[0] wt[0, k] + f[1] wt[1, k] + ..., in that order, and the running maximum keeps
    # the first entry that reaches it (strict >): the [M, N] logits are never materialised.
    m, s = f.shape
    n = wt.shape[1]
    blk_n = DECODE_BLOCK
    for blk in numba.prange((m + blk_n - 1) // blk_n):
        i0 = blk * blk_n
        nb = min(m, i0 + blk_n) - i0
        ft = np.zeros((s, blk_n), np.float32)  # [S, B]
        for j in range(s):
            for t in range(nb):
                ft[j, t] = f[i0 + t, j]
        logit = np.empty(blk_n, np.float32)
        best = np.empty(blk_n, np.float32)
        arg = np.zeros(blk_n, np.int32)
        for k in range(n):
            bk = b[k]
            for t in range(blk_n):
                logit[t] = bk
            for j in range(s):
                w = wt[j, k]
                for t in range(blk_n):
                    logit[t] += ft[j, t] * w
            if k == 0:
                best[:] = logit
            else:
                for t in range(blk_n):
                    x = logit[t]
                    gt = x > best[t]
                    best[t] = x if gt else best[t]
                    arg[t] = k if gt else arg[t]
        for t in range(nb):
            out[i0 + t] = arg[t]


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
