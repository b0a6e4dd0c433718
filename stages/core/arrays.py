"""Small array helpers shared by every layer."""

from __future__ import annotations

import numpy as np


def normalise(x: np.ndarray, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    """`x` scaled to unit L2 norm along `axis`; all-zero vectors stay zero (never NaN)."""
    n = np.linalg.norm(x, axis=axis, keepdims=True)
    return x / np.maximum(n, eps)
