"""Spherical harmonics: view-dependent colour of degree 0-3, evaluated as INRIA does."""

from __future__ import annotations

import numpy as np

from stages.core.arrays import normalise
from stages.scene.gaussians import SH_C0

SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_to_rgb(sh: np.ndarray, means: np.ndarray, center: np.ndarray) -> np.ndarray:
    """View-dependent colour [N, 3] from SH [N, K, 3] of degree 0-3, as INRIA evaluates it."""
    k = sh.shape[1]
    rgb = SH_C0 * sh[:, 0]
    if k > 1:
        d = means - center[None].astype(np.float32)
        d = normalise(d, axis=1)
        x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
        rgb = rgb - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
        if k > 4:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            rgb = (
                rgb
                + SH_C2[0] * xy * sh[:, 4]
                + SH_C2[1] * yz * sh[:, 5]
                + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
                + SH_C2[3] * xz * sh[:, 7]
                + SH_C2[4] * (xx - yy) * sh[:, 8]
            )
            if k > 9:
                rgb = (
                    rgb
                    + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9]
                    + SH_C3[1] * xy * z * sh[:, 10]
                    + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
                    + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
                    + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13]
                    + SH_C3[5] * z * (xx - yy) * sh[:, 14]
                    + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15]
                )
    return np.maximum(rgb + 0.5, 0.0).astype(np.float32)
