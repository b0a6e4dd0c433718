"""`goi init-codebook`: the codebook (TFCC) artifact, initialised by spherical k-means over
sampled 2D features (see `kmeans`)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from stages.core.arrays import normalise, require_finite, require_nonzero_rows
from stages.core.artifacts import check_writable, input_digest, open_h5, put, write_h5
from stages.core.errors import GoiError
from stages.core.files import refuse_inputs
from stages.core.params import AT_LEAST_1, SEED, Range, check_params
from stages.core.report import SILENT, Report
from stages.semantics.features import load_features
from stages.semantics.kmeans import even_subset, sample_cells, spherical_kmeans

SCHEMA = "goi.codebook"


@dataclass
class CodebookParams:
    entries: Annotated[int, Range(ge=2)] = 300
    """N, the number of codebook entries (the paper's default)."""
    views: Annotated[int, AT_LEAST_1] = 40
    """Feature maps to sample from, evenly spaced over the training views (paper: 30-50)."""
    samples: Annotated[int, AT_LEAST_1] = 200_000
    """Feature cells drawn from those views for clustering."""
    iterations: Annotated[int, AT_LEAST_1] = 10
    """k-means iterations (the authors' code uses 10)."""
    two_stage: bool = False
    """The authors' variant: k-means(80) on every 8th view, then k-means(N) on those centres."""
    seed: Annotated[int, SEED] = 0
    """Random seed; the same seed and inputs give the same codebook."""


@dataclass
class CodebookRun:
    out: Path
    """Codebook artifact to write (HDF5, schema goi.codebook)."""
    force: bool = False
    """Replace an existing output."""


def init_codebook(
    features_path: Path, p: CodebookParams, run: CodebookRun, report: Report = SILENT
) -> Path:
    check_params(p)
    check_writable(run.out, run.force, "--out")
    refuse_inputs({"--out": run.out}, [features_path])
    fm = load_features(features_path)
    rng = np.random.default_rng(p.seed)
    if p.two_stage:
        firsts = []
        for i, v in enumerate(fm.views[::8]):
            cells = np.unique(fm.maps[v].reshape(-1, fm.dim), axis=0)
            k = min(80, len(cells))
            c, _ = spherical_kmeans(cells, k, p.iterations, p.seed + i, f"k-means {v}", report)
            firsts.append(c)
        x = np.concatenate(firsts)
        method = "two-stage spherical k-means (80 per 8th view, then N)"
    else:
        x = sample_cells(fm, even_subset(fm.views, p.views), p.samples, rng)
        method = "spherical k-means, k-means++ seeding"
    entries, counts = spherical_kmeans(normalise(x), p.entries, p.iterations, p.seed, report=report)
    with write_h5(run.out, SCHEMA, input_digest("features", features_path), run.force) as f:
        f.attrs.update(
            n_entries=p.entries, dim=fm.dim, seed=p.seed, method=method, samples=int(len(x))
        )
        put(f, "entries", entries.astype(np.float32))
        put(f, "counts", counts.astype(np.int64))
    return run.out


def load_codebook(path: str | os.PathLike[str]) -> np.ndarray:
    """[N, D] float32 unit entries."""
    with open_h5(path, SCHEMA) as f:
        entries = require_finite(f["entries"][()], f"{path}: dataset 'entries'")
    if entries.shape[0] < 2 or entries.shape[1] < 1:
        raise GoiError(f"{path}: a codebook needs at least 2 entries; it has {entries.shape}")
    return require_nonzero_rows(entries, f"{path}: dataset 'entries'")
