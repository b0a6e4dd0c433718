"""Small array helpers shared by every layer."""

from __future__ import annotations

import numpy as np

from stages.core.errors import GoiError


def unit_norms(
    x: np.ndarray, axis: int = -1, eps: float = 1e-12, keepdims: bool = False
) -> np.ndarray:
    """The L2 norms along `axis` that `normalise` divides by (clamped below at `eps`)."""
    return np.maximum(np.linalg.norm(x, axis=axis, keepdims=keepdims), eps)


def normalise(x: np.ndarray, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    """`x` scaled to unit L2 norm along `axis`; all-zero vectors stay zero (never NaN)."""
    return x / unit_norms(x, axis, eps, keepdims=True)


def require_finite(x: np.ndarray, where: str) -> np.ndarray:
    """`x` when every value is finite, else a GoiError saying where and how many are not."""
    bad = ~np.isfinite(x)
    if bad.any():
        raise GoiError(f"{where} holds {int(bad.sum())} NaN/inf values")
    return x


def require_nonzero_rows(x: np.ndarray, where: str) -> np.ndarray:
    """`x` [N, D] when no row is all zeros (a direction is needed: a zero codebook entry has
    a cosine of 0 with everything and would silently never be chosen), else a GoiError."""
    zero = ~np.any(x != 0, axis=1)
    if zero.any():
        raise GoiError(
            f"{where}: {int(zero.sum())} of {len(x)} rows are all zeros (first: row "
            f"{int(np.argmax(zero))}); each entry must be a direction"
        )
    return x
