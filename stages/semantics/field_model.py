"""The semantic field's model, losses and hyperparameters (paper section 3.4 and appendix).

Per Gaussian a low-dimensional feature f (zero at start), rendered by alpha blending to f_hat; a
linear decoder D: S -> N gives logits e; the decoded feature is T[argmax e] with T the codebook.
Losses (weights and schedule as the authors' code):
  L_ent   = entropy(softmax(tau cos(v_gt, T)))            x 0.3, tau 1 -> 2 after 2/3 of the run
  L_max   = 1 - cos(v_gt, T[d]), d = argmax cos(v_gt, T)   x 1
  L_joint = 50 MSE(softmax(e), onehot(d))                 x 1 (the authors' form of |e - 1_d|^2)
  L_e2e   = 1 - cos(v_gt, T[argmax e])                     x 1 (reaches the codebook only)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Annotated

import numpy as np
import torch
import torch.nn.functional as F

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


#: Names of the loss curve's columns, in order.
LOSS_NAMES = ("total", "ent", "max", "joint", "e2e")


class FieldModel(torch.nn.Module):
    """The trainable parts: per-Gaussian features [G, S], the decoder S -> N (direct: S -> D)
    and the codebook [N, D]."""

    def __init__(self, n_gaussians: int, sem_dim: int, codebook: np.ndarray, direct: bool):
        super().__init__()
        self.features = torch.nn.Parameter(torch.zeros(n_gaussians, sem_dim))
        self.decoder = torch.nn.Linear(sem_dim, codebook.shape[1 if direct else 0])
        self.codebook = torch.nn.Parameter(torch.from_numpy(codebook.copy()))

    def parameter_list(self) -> list[torch.Tensor]:
        """In the order of `PARAMETERS`."""
        return [self.features, self.decoder.weight, self.decoder.bias, self.codebook]


#: The model's tensors as the field and checkpoint artifacts name them.
PARAMETERS = ("features", "decoder_weight", "decoder_bias", "codebook")


def field_losses(
    model: FieldModel, f_hat: torch.Tensor, v_gt: torch.Tensor, tau: float, p: FieldParams
) -> tuple[torch.Tensor, list[float]]:
    """The weighted total and each term (LOSS_NAMES) for rendered features f_hat [B, S] and
    unit target features v_gt [B, D]."""
    e = model.decoder(f_hat)  # [B, N] (direct: [B, D])
    if p.no_tfcc:
        loss = 1 - (v_gt * F.normalize(e, dim=1)).sum(1).mean()
        return loss, [float(loss.detach()), 0.0, 0.0, 0.0, float(loss.detach())]
    t_unit = F.normalize(model.codebook, dim=1)  # [N, D]
    sim = v_gt @ t_unit.T  # [B, N] cosines (v_gt is unit)
    prob = torch.softmax(sim * tau, dim=1)
    l_ent = -(prob * torch.log(prob.clamp_min(1e-12))).sum(1).mean()
    s_max, d = sim.max(dim=1)
    l_max = 1 - s_max.mean()
    l_joint = 50 * F.mse_loss(torch.softmax(e, dim=1), F.one_hot(d, sim.shape[1]).float())
    v = t_unit[e.argmax(dim=1)]
    l_e2e = 1 - (v_gt * v).sum(1).mean()
    total = p.w_ent * l_ent + p.w_max * l_max + p.w_joint * l_joint + p.w_e2e * l_e2e
    return total, [float(x.detach()) for x in (total, l_ent, l_max, l_joint, l_e2e)]
