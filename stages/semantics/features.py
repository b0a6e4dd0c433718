"""The features artifact: per training view a dense [h, w, D] map of language-aligned features.

Readers get float32, L2-normalised per cell (GOI only ever compares features by cosine), or,
for a fit that holds every view at once, the stored float16 as it is (`unit=False`: half the
memory; the caller normalises the cells it draws, which gives the same float32 values).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.core.arrays import normalise
from stages.core.artifacts import open_h5
from stages.core.errors import GoiError

SCHEMA = "goi.features"


@dataclass
class FeatureMaps:
    dim: int
    maps: dict[str, np.ndarray]  # view -> [h, w, D] float32 unit norm (zero cells stay zero),
    # or float16 as stored with unit=False

    @property
    def views(self) -> list[str]:
        return list(self.maps)


def feature_views(path: str | os.PathLike[str]) -> tuple[int, list[str]]:
    """The features' dimension and views, without reading the maps (for early checks)."""
    with open_h5(path, SCHEMA) as f:
        dim = int(f.attrs["dim"])
        names = list(f["views"])
    if dim < 1 or not names:
        raise GoiError(f"{path}: holds no views (dimension {dim}); re-run goi extract")
    return dim, names


def feature_grid(path: str | os.PathLike[str], views: list[str]) -> dict[str, tuple[int, int]]:
    """Each view's feature grid (width, height), read from the dataset shapes alone."""
    feature_views(path)
    with open_h5(path, SCHEMA) as f:
        missing = [v for v in views if v not in f["views"]]
        if missing:
            raise GoiError(
                f"{path}: no features for view(s) {', '.join(missing[:5])}"
                f"{' ...' if len(missing) > 5 else ''}; re-run goi extract"
            )
        return {v: (f["views"][v]["features"].shape[1], f["views"][v]["features"].shape[0])
                for v in views}  # fmt: skip


def load_features(
    path: str | os.PathLike[str], views: list[str] | None = None, unit: bool = True
) -> FeatureMaps:
    p = Path(path)
    feature_views(p)
    with open_h5(p, SCHEMA) as f:
        dim = int(f.attrs["dim"])
        names = list(f["views"]) if views is None else views
        missing = [v for v in names if v not in f["views"]]
        if missing:
            raise GoiError(
                f"{p}: no features for view(s) {', '.join(missing[:5])}"
                f"{' ...' if len(missing) > 5 else ''}; re-run goi extract"
            )
        maps = {}
        for v in names:
            m = f["views"][v]["features"][()]
            if not np.isfinite(m).all():
                raise GoiError(f"{p}: features of view '{v}' contain NaN/inf")
            maps[v] = normalise(m.astype(np.float32)) if unit else m.astype(np.float16)
    return FeatureMaps(dim, maps)
