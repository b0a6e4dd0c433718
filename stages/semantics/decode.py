"""Rendering the semantic field at any camera and decoding it through the codebook.

A pixel's rendered low-dimensional feature f_hat = sum_i f_i alpha_i T_i decodes to the codebook
entry argmax(D f_hat). The RGB can ride along in the same tile walk (3 more channels), which is
how render-mask gets its overlay for little extra cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from stages.render.rasterizer import Rasterizer, RenderBackend
from stages.render.sh import sh_to_rgb
from stages.scene.cameras import Camera
from stages.scene.gaussians import Gaussians
from stages.semantics.field import Field

#: A pixel counts as covered by the scene when its accumulated alpha exceeds this; elsewhere
#: f_hat is mostly empty space and decodes to noise, so it is never in a mask.
COVERED_ALPHA = 0.5


@numba.njit(parallel=True, cache=True)
def _decode_kernel(f, wt, b, out):  # noqa: ANN001, ANN202
    # Per pixel, the N logits go to a small buffer and the argmax is taken there: the [M, N]
    # logits matrix (370 MB at 640x480, N = 300) is never materialised. The inner loop runs
    # over entries with wt [S, N] contiguous, which the compiler vectorises.
    m, s = f.shape
    n = wt.shape[1]
    block = 256
    for blk in numba.prange((m + block - 1) // block):
        acc = np.empty(n, np.float32)
        for i in range(blk * block, min(m, (blk + 1) * block)):
            acc[:] = b
            for j in range(s):
                fij = f[i, j]
                for k in range(n):
                    acc[k] += fij * wt[j, k]
            arg = 0
            best = acc[0]
            for k in range(1, n):
                if acc[k] > best:
                    best = acc[k]
                    arg = k
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
        feats = self.field.features  # [G, S]
        s = feats.shape[1]
        if with_rgb:
            rgb = sh_to_rgb(self.g.sh, self.g.means, cam.center)  # [G, 3]
            feats = np.concatenate([feats, rgb], axis=1)
        out = self.rast.render_features(cam, np.ascontiguousarray(feats, np.float32))
        img = out.image  # [H, W, C]
        covered = out.alpha > COVERED_ALPHA
        index = np.zeros(covered.shape, np.int32)  # uncovered pixels are in no mask anyway
        index[covered] = self.decode(img[:, :, :s][covered])
        color = np.clip(img[:, :, s:], 0, 1) if with_rgb else None
        return DecodedView(index, covered, color)
