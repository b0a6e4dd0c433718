"""Spherical k-means (pure math): the TFCC's initial entries.

Spherical: features and centres are unit vectors, a sample joins the centre of highest dot
product, and a centre is the normalised mean of its samples. Seeding is k-means++ on 1 - cos;
an emptied cluster is re-seeded with the sample its centre explains worst.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from stages.core.errors import GoiError
from stages.core.report import SILENT, Report
from stages.core.torch_numerics import settle_vml
from stages.semantics.features import FeatureMaps

if TYPE_CHECKING:  # torch is imported where k-means runs: every goi command imports this module
    import torch


def _assign(
    x: torch.Tensor, c: torch.Tensor, chunk: int = 65536
) -> tuple[torch.Tensor, torch.Tensor]:
    """Best centre [M] and its cosine [M] for unit rows x [M, D] against unit centres c [K, D]."""
    import torch

    best, sims = [], []
    for s in range(0, x.shape[0], chunk):
        v, i = (x[s : s + chunk] @ c.T).max(dim=1)
        best.append(i)
        sims.append(v)
    return torch.cat(best), torch.cat(sims)


def spherical_kmeans(
    x: np.ndarray,
    k: int,
    iterations: int,
    seed: int,
    label: str = "k-means",
    report: Report = SILENT,
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster unit rows x [M, D] into k unit centres [k, D]; returns centres and counts [k]."""
    import torch

    settle_vml()
    if x.shape[0] < k:
        raise GoiError(
            f"--entries: only {x.shape[0]} feature samples for {k} codebook entries: lower "
            "--entries, or raise --samples or --views"
        )
    rng = np.random.default_rng(seed)
    xt = torch.from_numpy(np.ascontiguousarray(x, np.float32))
    m = xt.shape[0]
    # k-means++ seeding on 1 - cos, over a subsample: seeding is sequential in k.
    pool = xt[torch.from_numpy(rng.choice(m, min(m, 20 * k + 1000), replace=False))]
    centres = torch.empty(k, xt.shape[1])
    centres[0] = pool[int(rng.integers(len(pool)))]
    dist = (1 - pool @ centres[0]).clamp_min(0)
    for j in range(1, k):
        p = dist.double().numpy()
        total = p.sum()
        idx = int(rng.choice(len(pool), p=p / total)) if total > 0 else int(rng.integers(len(pool)))
        centres[j] = pool[idx]
        dist = torch.minimum(dist, (1 - pool @ centres[j]).clamp_min(0))
    counts = torch.zeros(k, dtype=torch.int64)
    for _ in report.progress(range(iterations), label, length=iterations):
        assign, sim = _assign(xt, centres)
        counts = torch.bincount(assign, minlength=k)
        sums = torch.zeros_like(centres).index_add_(0, assign, xt)
        empty = torch.nonzero(counts == 0).flatten()
        if len(empty):
            worst = torch.argsort(sim)[: len(empty)]  # the samples explained worst
            sums[empty] = xt[worst]
        centres = torch.nn.functional.normalize(sums, dim=1)
    assign, _ = _assign(xt, centres)
    counts = torch.bincount(assign, minlength=k)
    return centres.numpy(), counts.numpy()


def sample_cells(fm: FeatureMaps, views: list[str], n: int, rng: np.random.Generator) -> np.ndarray:
    """Up to n unit feature vectors [n, D], drawn evenly from the given views' non-zero cells."""
    per = max(1, n // max(len(views), 1))
    out = []
    for v in views:
        cells = fm.maps[v].reshape(-1, fm.dim)
        cells = cells[np.linalg.norm(cells, axis=1) > 0.5]
        take = min(per, len(cells))
        out.append(cells[rng.choice(len(cells), take, replace=False)])
    return np.concatenate(out)


def even_subset(names: list[str], n: int) -> list[str]:
    if n >= len(names):
        return list(names)
    return [names[int(i)] for i in np.linspace(0, len(names) - 1, n).round()]
