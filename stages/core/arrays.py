"""Small array helpers shared by every layer."""

from __future__ import annotations

import numpy as np

from stages.core.errors import GoiError


def normalise(x: np.ndarray, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    """`x` scaled to unit L2 norm along `axis`; all-zero vectors stay zero (never NaN)."""
    n = np.linalg.norm(x, axis=axis, keepdims=True)
    return x / np.maximum(n, eps)


def require_finite(x: np.ndarray, where: str) -> np.ndarray:
    """`x` when every value is finite, else a GoiError saying where and how many are not."""
    bad = ~np.isfinite(x)
    if bad.any():
        raise GoiError(f"{where} holds {int(bad.sum())} NaN/inf values")
    return x
