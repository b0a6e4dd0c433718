"""The options of `goi fit-field`: the fit's hyperparameters and the run's files, in a module
without torch, so that every goi command can build its command line without importing it."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

from stages.core.params import AT_LEAST_1, FRACTION, NON_NEGATIVE, POSITIVE, SEED, Range


@dataclass
class FieldParams:
    """The hyperparameters of a fit; recorded in the field artifact as its `config`."""

    iterations: Annotated[int, AT_LEAST_1] = 1500
    """Training iterations (paper: 1500)."""
    sem_dim: Annotated[int, Range(ge=1, le=256)] = 10
    """Low-dimensional feature per Gaussian (paper: 10)."""
    views_per_step: Annotated[int, AT_LEAST_1] = 4
    """Training views drawn per iteration (the authors use 1 whole view)."""
    cells_per_view: Annotated[int, NON_NEGATIVE] = 4096
    """Feature cells drawn from each of those views per iteration (0: all of them)."""
    lr_features: Annotated[float, POSITIVE] = 0.005
    """Adam learning rate of the per-Gaussian features (authors: 0.005, eps 1e-15)."""
    lr_decoder: Annotated[float, POSITIVE] = 0.003
    """Adam learning rate of the decoder (authors: 0.003)."""
    lr_codebook: Annotated[float, POSITIVE] = 0.001
    """Adam learning rate of the codebook (authors: 0.001)."""
    w_ent: Annotated[float, NON_NEGATIVE] = 0.3
    """Weight of L_ent (paper: 0.3)."""
    w_max: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of L_max (paper: 1)."""
    w_joint: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of L_joint (paper: 1)."""
    w_e2e: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of L_e2e (paper: 1)."""
    tau_start: Annotated[float, POSITIVE] = 1.0
    """Annealing temperature of L_ent at the start (paper: 1)."""
    tau_end: Annotated[float, POSITIVE] = 2.0
    """... and after `anneal_at` of the run (paper: 2 after 1000 of 1500 iterations)."""
    anneal_at: Annotated[float, FRACTION] = 2 / 3
    """Fraction of the run after which tau_end applies."""
    top_k: Annotated[int, NON_NEGATIVE] = 0
    """Keep only the K largest blending weights per pixel in the cache (0: all)."""
    reference_losses: bool = False
    """The paper's losses as written in torch, differentiated by autograd, and torch's
    multi-tensor Adam: goi's path before the fused kernels, kept to reproduce its figures (a
    step takes about twice the CPU time). The default computes the same losses and gradients
    in fused kernels with torch's fused Adam, in another rounding order (dev-room `full` mIoU
    over six seeds: docs/performance.md)."""
    no_tfcc: bool = False
    """Ablation (paper's 'without TFCC'): decode the low-dimensional features straight to the
    feature space with a linear decoder and a cosine loss, without the codebook. goi query
    needs a TFCC field; goi eval uses this for its without_tfcc and baseline variants."""
    seed: Annotated[int, SEED] = 0
    """Random seed; the same seed and inputs give the same field."""

    def config(self) -> dict:
        return asdict(self)

    def tau(self, iteration: int) -> float:
        """L_ent's temperature at `iteration` (0-based)."""
        anneal = int(round(self.anneal_at * self.iterations))
        return self.tau_start if iteration < anneal else self.tau_end


@dataclass
class FieldRun:
    out: Path
    """Field artifact to write (HDF5, schema goi.field)."""
    cache: Path | None = None
    """Blend cache file; default blend_cache.h5 beside the output. Reused when it matches."""
    checkpoint_every: Annotated[int, NON_NEGATIVE] = 250
    """Write <out>.ckpt every this many iterations (0: never)."""
    resume: bool = False
    """Continue from <out>.ckpt when it exists (and was made from the same inputs)."""
    max_memory_gib: Annotated[float, NON_NEGATIVE] = 0.0
    """Memory the fit may use (GiB; 0: three quarters of this machine's). When the blend
    cache does not fit beside the rest, it is streamed from disk a step's views at a time; a
    budget below even that is refused before any work."""
    force: bool = False
    """Replace an existing output."""
    distributed: bool = False
    """Split the Gaussians across the ranks torchrun started (`torchrun --nproc-per-node N
    -m goi fit-field --distributed ...`): each rank keeps its Gaussians' features, Adam
    state and blend-cache columns, and one all_reduce per step sums the rendered features.
    Gives the single-process field within float rounding (docs/scaling.md)."""
    dist_timeout_s: Annotated[float, POSITIVE] = 600.0
    """--distributed: seconds the rendezvous and every collective (all_reduce, barrier) may
    wait for the other ranks before the run fails."""
    threads: Annotated[int, NON_NEGATIVE] = 0
    """--distributed: CPU threads per rank (0: this machine's cores divided by torchrun's
    local ranks, so that the ranks of a node do not oversubscribe its cores)."""

    @property
    def cache_path(self) -> Path:
        return self.cache or self.out.with_name("blend_cache.h5")

    @property
    def checkpoint(self) -> Path:
        return self.out.with_name(self.out.name + ".ckpt")
